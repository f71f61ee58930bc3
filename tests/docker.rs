//! The container deployment, for real: the image built from nothing by
//! `deploy/build-images.sh`, the cluster brought up by `deploy/docker-compose.yml`, node
//! containers killed, cut off the network or impersonated mid-render, and the same compose
//! file deployed on a single-node Docker Swarm.
//!
//! These tests need a Docker daemon, so they are `#[ignore]`d: `scripts/test.sh` runs them
//! (one at a time) when `docker info` answers, and says in one line that they were skipped
//! when it does not.

mod common;
use common::*;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn docker(args: &[&str]) -> Output {
    Command::new("docker")
        .args(args)
        .output()
        .expect("run docker")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// Builds the image once for every test here, with the project's own script.
fn image() {
    static BUILT: OnceLock<Result<(), String>> = OnceLock::new();
    let r = BUILT.get_or_init(|| {
        let o = run(&mut Command::new(repo().join("deploy/build-images.sh")));
        if o.status.success() {
            eprintln!("{}", text(&o).trim());
            Ok(())
        } else {
            Err(text(&o))
        }
    });
    if let Err(e) = r {
        panic!("deploy/build-images.sh failed: {e}");
    }
}

/// One compose project: its own name, network, folders and secret.
struct Project {
    name: String,
    dir: PathBuf,
    files: Vec<PathBuf>,
    env: Vec<(String, String)>,
}

/// Compose as this host has it: the v2 plugin (`docker compose`) when it answers, else the
/// v1 program (`docker-compose`).
fn compose_command() -> Command {
    static V2: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let v2 = *V2.get_or_init(|| {
        Command::new("docker")
            .args(["compose", "version"])
            .output()
            .is_ok_and(|o| o.status.success())
    });
    if v2 {
        let mut c = Command::new("docker");
        c.arg("compose");
        c
    } else {
        Command::new("docker-compose")
    }
}

impl Project {
    fn new(name: &str, small: bool, render_args: &str) -> Project {
        image();
        let dir = scratch(&format!("docker-{name}"));
        let out = dir.join("out");
        let secrets = dir.join("secrets");
        std::fs::create_dir_all(&out).unwrap();
        std::fs::create_dir_all(&secrets).unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&out, std::fs::Permissions::from_mode(0o777)).unwrap();
        std::fs::set_permissions(&secrets, std::fs::Permissions::from_mode(0o700)).unwrap();
        let secret = secrets.join("magg_secret");
        std::fs::write(&secret, format!("docker test secret {name}")).unwrap();
        std::fs::set_permissions(&secret, std::fs::Permissions::from_mode(0o644)).unwrap();
        let mut files = vec![repo().join("deploy/docker-compose.yml")];
        if small {
            files.push(repo().join("deploy/docker-compose.small.yml"));
        }
        let env = vec![
            (
                "MAGG_INPUT".into(),
                data().join("scenes").display().to_string(),
            ),
            ("MAGG_OUT".into(), out.display().to_string()),
            ("MAGG_SECRET_FILE".into(), secret.display().to_string()),
            ("MAGG_RENDER_ARGS".into(), render_args.into()),
        ];
        let p = Project {
            name: format!("maggtest{name}"),
            dir,
            files,
            env,
        };
        p.down();
        p
    }

    fn compose(&self, args: &[&str]) -> Output {
        let mut c = compose_command();
        c.arg("-p").arg(&self.name);
        for f in &self.files {
            c.arg("-f").arg(f);
        }
        c.args(args).envs(self.env.iter().map(|(k, v)| (k, v)));
        c.output().expect("run docker compose")
    }

    fn down(&self) {
        let _ = self.compose(&["down", "--volumes", "--remove-orphans", "--timeout", "2"]);
    }

    fn out(&self) -> PathBuf {
        self.dir.join("out/magg.png")
    }

    fn stats(&self) -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(self.dir.join("out/magg.png.stats.json")).unwrap())
            .unwrap()
    }

    fn network(&self) -> String {
        format!("{}_magg", self.name)
    }

    /// Container ids of a service.
    fn containers(&self, service: &str) -> Vec<String> {
        let o = self.compose(&["ps", "-q", service]);
        String::from_utf8_lossy(&o.stdout)
            .split_whitespace()
            .map(str::to_string)
            .collect()
    }

    fn host_log(&self) -> String {
        text(&self.compose(&["logs", "--no-color", "magg-host"]))
    }

    /// Starts the cluster in the background and waits until the render has begun.
    fn start(&self) {
        self.start_with(&[]);
    }

    fn start_with(&self, up_args: &[&str]) {
        let mut args = vec!["up", "-d"];
        args.extend_from_slice(up_args);
        let o = self.compose(&args);
        assert!(o.status.success(), "compose up: {}", text(&o));
        self.wait_log("subscreens on", Duration::from_secs(180));
    }

    fn wait_log(&self, needle: &str, limit: Duration) -> String {
        let deadline = Instant::now() + limit;
        loop {
            let log = self.host_log();
            if log.contains(needle) {
                return log;
            }
            assert!(
                Instant::now() < deadline,
                "no {needle:?} in the host's log within {limit:?}: {log}"
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// The host container's exit code, waiting up to `limit`.
    fn host_exit(&self, limit: Duration) -> Option<i64> {
        let id = self
            .containers("magg-host")
            .pop()
            .expect("a host container");
        wait_exit(&id, limit)
    }

    /// Every container of the project has stopped within `limit`.
    fn all_stopped(&self, limit: Duration) {
        for service in ["magg-host", "fork-node", "render-node"] {
            for id in self.containers(service) {
                assert!(
                    wait_exit(&id, limit).is_some(),
                    "{service} container {id} still runs: {}",
                    text(&docker(&["logs", &id]))
                );
            }
        }
    }
}

impl Drop for Project {
    fn drop(&mut self) {
        self.down();
    }
}

/// A container's exit code once it has stopped, waiting up to `limit`.
fn wait_exit(id: &str, limit: Duration) -> Option<i64> {
    let deadline = Instant::now() + limit;
    loop {
        let o = docker(&[
            "inspect",
            "--format",
            "{{.State.Status}} {{.State.ExitCode}}",
            id,
        ]);
        let s = String::from_utf8_lossy(&o.stdout).trim().to_string();
        if let Some(code) = s.strip_prefix("exited ") {
            return code.parse().ok();
        }
        if Instant::now() > deadline {
            return None;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// What the same settings give in one process here (`/input/` is `tests/data/scenes`).
fn in_process_here(dir: &Path, args: &[&str]) -> PathBuf {
    let scenes = data().join("scenes");
    let args: Vec<String> = args
        .iter()
        .map(|a| match a.strip_prefix("/input/") {
            Some(rest) => scenes.join(rest).display().to_string(),
            None => a.to_string(),
        })
        .collect();
    in_process(dir, &args)
}

/// With a cache smaller than the scene, so that render nodes fetch on demand: the compose
/// file gives every container a /dev/shm of its own, so those fetches cross sockets.
const SMALL_RENDER: &[&str] = &[
    "/input/cornell/cornell.gltf",
    "--width",
    "64",
    "--height",
    "64",
    "--spp",
    "16",
    "--cache",
    "50",
];

/// Long enough that a fault lands in the middle of it, and that a node cut off the network is
/// found silent (5 s after its last heartbeat) before the render ends: at 400 spp, with two
/// of the small cluster's four render nodes at work on two cores, the render took 4.4 s and
/// ended before the host noticed the silent node.
const LONG_RENDER: &[&str] = &[
    "/input/cornell/cornell.gltf",
    "--width",
    "96",
    "--height",
    "96",
    "--spp",
    "1000",
];

#[test]
#[ignore = "needs a Docker daemon: scripts/test.sh runs it when one answers"]
fn the_magg_topology_in_containers_matches_one_process() {
    let _serial = serial();
    let p = Project::new("magg", false, &SMALL_RENDER.join(" "));
    let t0 = Instant::now();
    let o = p.compose(&["up", "--exit-code-from", "magg-host"]);
    assert!(o.status.success(), "compose up: {}", text(&o));
    eprintln!(
        "86 containers: up, render and stop in {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    let stats = p.stats();
    let members = stats["members"].as_array().unwrap();
    assert_eq!(members.len(), 85, "{stats}");
    let ips: std::collections::HashSet<&str> = members
        .iter()
        .map(|m| m["advertise"].as_str().unwrap().split(':').next().unwrap())
        .collect();
    assert_eq!(ips.len(), 85, "every node in its own container: {ips:?}");
    // One machine, but no container sees another's shared memory: `--at-work auto` lets
    // every render node work, as across machines, rather than as many as the CPUs.
    let domains: std::collections::HashSet<&str> = members
        .iter()
        .map(|m| m["shm_domain"].as_str().unwrap())
        .collect();
    assert_eq!(domains.len(), 85, "a /dev/shm per container: {domains:?}");
    // The first fork node writes the shares of the cards on its machine (one boot) as
    // segments, but only its own card can map its segment: the other fork nodes refuse
    // theirs and get their shares over sockets.
    let shares: Vec<(u64, u64)> = (stats["nodes"].as_array().unwrap().iter())
        .filter(|n| n["role"] == "Fork")
        .map(|n| {
            let items = n["share_items_in_segment"].as_u64().unwrap();
            (n["node"].as_u64().unwrap(), items)
        })
        .collect();
    assert_eq!(shares.len(), 5, "{shares:?}");
    for &(node, items) in &shares {
        assert_eq!(items > 0, node == 1, "items by fork node: {shares:?}");
    }
    assert_eq!(stats["at_work"], "auto", "{stats}");
    assert_eq!(stats["machine_limits"], serde_json::json!([]), "{stats}");
    same_bytes(&p.out(), &in_process_here(&p.dir, SMALL_RENDER));
    p.all_stopped(Duration::from_secs(10));
}

#[test]
#[ignore = "needs a Docker daemon: scripts/test.sh runs it when one answers"]
fn a_killed_and_a_disconnected_render_node_leave_the_image_unchanged() {
    let _serial = serial();
    // Every render node at work: with `--at-work auto` two of the four wait for work, and one
    // cut off the network while it waits holds nothing the render needs, so the render can
    // end before the host finds it silent (clean-clone CI: the render took 4.15 s, the node
    // was found silent after it, and the test saw one lost node of two). A node at work
    // holds subscreens that only it can finish until the host finds it lost.
    let args: Vec<&str> = LONG_RENDER
        .iter()
        .copied()
        .chain(["--at-work", "all"])
        .collect();
    let p = Project::new("rendernode", true, &args.join(" "));
    p.start();
    std::thread::sleep(Duration::from_millis(500));
    let renders = p.containers("render-node");
    assert_eq!(renders.len(), 4);
    // One killed outright, one cut off the network (only missed heartbeats tell).
    let o = docker(&["kill", &renders[0]]);
    assert!(o.status.success(), "{}", text(&o));
    let o = docker(&[
        "network",
        "disconnect",
        "--force",
        &p.network(),
        &renders[1],
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let code = p.host_exit(Duration::from_secs(180));
    let log = p.host_log();
    assert_eq!(code, Some(0), "host: {log}");
    assert_eq!(
        log.lines()
            .filter(|l| l.contains("lost render node") && l.contains("WARN"))
            .count(),
        2,
        "{log}"
    );
    let stats = p.stats();
    let lost = stats["lost_nodes"].as_array().unwrap();
    assert_eq!(lost.len(), 2, "{stats}");
    same_bytes(&p.out(), &in_process_here(&p.dir, &args));
}

#[test]
#[ignore = "needs a Docker daemon: scripts/test.sh runs it when one answers"]
fn a_killed_fork_node_container_leaves_the_image_unchanged() {
    let _serial = serial();
    // Two cards, so that a fork node has another to stand in for it; every DMA read over TCP
    // (the base file shares no memory between containers). Eight render nodes finish the
    // long render sooner than four: more samples keep it going past the kill.
    let args: Vec<&str> = LONG_RENDER
        .iter()
        .map(|&a| if a == "400" { "2000" } else { a })
        .chain(["--chunk-triangles", "16"])
        .collect();
    let mut p = Project::new("forknode", false, &args.join(" "));
    p.env.push(("MAGG_TOPOLOGY".into(), "grid:2x2x2".into()));
    p.env
        .push(("MAGG_HOST_LOG".into(), "info,magg::event=debug".into()));
    p.start_with(&["--scale", "fork-node=2", "--scale", "render-node=8"]);
    p.wait_log("MAGG_EVENT pixels", Duration::from_secs(60));
    let fork = p.containers("fork-node").pop().unwrap();
    let o = docker(&["kill", &fork]);
    assert!(o.status.success(), "{}", text(&o));
    let code = p.host_exit(Duration::from_secs(300));
    let log = p.host_log();
    assert_eq!(code, Some(0), "host: {log}");
    assert!(log.contains("lost fork node"), "{log}");
    let stats = p.stats();
    let lost = stats["lost_nodes"].as_array().unwrap();
    assert_eq!(lost.len(), 1, "{stats}");
    assert_eq!(lost[0]["role"], "fork node", "{stats}");
    assert!(lost[0]["items_moved"].as_u64().unwrap() >= 1, "{stats}");
    // The time from the kill to the render going on, for the summary (not asserted).
    eprintln!(
        "fork node container killed: lost {:.2} s into the render, rendering went on {:.3} s after the loss (its render nodes' pixels again after {} s), {} items rebuilt, {} subscreens queued again",
        lost[0]["after_s"].as_f64().unwrap(),
        lost[0]["recovered_after_s"].as_f64().unwrap(),
        lost[0]["served_rows_after_s"],
        lost[0]["items_moved"],
        lost[0]["subscreens_reassigned"]
    );
    same_bytes(&p.out(), &in_process_here(&p.dir, &args));
    p.all_stopped(Duration::from_secs(10));
}

#[test]
#[ignore = "needs a Docker daemon: scripts/test.sh runs it when one answers"]
fn a_killed_host_container_stops_every_node() {
    let _serial = serial();
    // Sized by hand this time: the base file, a topology, and --scale to match it.
    let mut p = Project::new("host", false, &LONG_RENDER.join(" "));
    p.env.push(("MAGG_TOPOLOGY".into(), "grid:1x1x3".into()));
    p.start_with(&["--scale", "fork-node=1", "--scale", "render-node=3"]);
    assert_eq!(p.containers("render-node").len(), 3);
    let host = p.containers("magg-host").pop().unwrap();
    assert!(docker(&["kill", &host]).status.success());
    p.all_stopped(Duration::from_secs(10));
    for id in p.containers("render-node") {
        let log = text(&docker(&["logs", &id]));
        assert!(log.contains("lost the host"), "{log}");
    }
    assert!(!p.out().exists());
}

#[test]
#[ignore = "needs a Docker daemon: scripts/test.sh runs it when one answers"]
fn a_container_with_the_wrong_secret_is_refused_and_the_render_goes_on() {
    let _serial = serial();
    let p = Project::new("secret", true, &LONG_RENDER.join(" "));
    p.start();
    let o = docker(&[
        "run",
        "--rm",
        "--network",
        &p.network(),
        "--entrypoint",
        "/bin/magg-render-node",
        "magg:latest",
        "--join",
        "magg-host:7000",
        "--secret",
        "not the cluster secret",
        "--timeout",
        "20",
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("secret"), "{}", text(&o));
    let code = p.host_exit(Duration::from_secs(180));
    let log = p.host_log();
    assert_eq!(code, Some(0), "{log}");
    assert!(
        log.contains("refused"),
        "the host should log the refusal: {log}"
    );
    same_bytes(&p.out(), &in_process_here(&p.dir, LONG_RENDER));
}

#[test]
#[ignore = "needs a Docker daemon: scripts/test.sh runs it when one answers"]
fn the_compose_file_deploys_on_a_single_node_swarm() {
    let _serial = serial();
    let p = Project::new("swarm", true, &SMALL_RENDER.join(" "));
    let state = docker(&["info", "--format", "{{.Swarm.LocalNodeState}}"]);
    let ours = String::from_utf8_lossy(&state.stdout).trim() != "active";
    if ours {
        let o = docker(&["swarm", "init", "--advertise-addr", "127.0.0.1"]);
        assert!(o.status.success(), "swarm init: {}", text(&o));
    }
    struct Leave(bool, &'static str);
    impl Drop for Leave {
        fn drop(&mut self) {
            let _ = docker(&["stack", "rm", self.1]);
            std::thread::sleep(Duration::from_secs(2));
            if self.0 {
                let _ = docker(&["swarm", "leave", "--force"]);
            }
        }
    }
    let stack = "maggswarmtest";
    let _leave = Leave(ours, stack);
    let mut cmd = Command::new("docker");
    cmd.args(["stack", "deploy"]);
    let mut files = p.files.clone();
    files.insert(1, repo().join("deploy/docker-compose.swarm.yml"));
    for f in &files {
        cmd.arg("-c").arg(f);
    }
    cmd.arg(stack).envs(p.env.iter().map(|(k, v)| (k, v)));
    let o = run(&mut cmd);
    assert!(o.status.success(), "stack deploy: {}", text(&o));
    // The host's task ends when the image is written.
    let deadline = Instant::now() + Duration::from_secs(240);
    let state = loop {
        let o = docker(&[
            "service",
            "ps",
            "--no-trunc",
            "--format",
            "{{.CurrentState}} {{.Error}}",
            &format!("{stack}_magg-host"),
        ]);
        let s = String::from_utf8_lossy(&o.stdout).trim().to_string();
        if s.starts_with("Complete") || s.starts_with("Failed") || s.starts_with("Rejected") {
            break s;
        }
        assert!(
            Instant::now() < deadline,
            "the swarm render did not end: {s}"
        );
        std::thread::sleep(Duration::from_secs(1));
    };
    let logs = text(&docker(&["service", "logs", &format!("{stack}_magg-host")]));
    assert!(state.starts_with("Complete"), "{state}: {logs}");
    same_bytes(&p.out(), &in_process_here(&p.dir, SMALL_RENDER));
}
