//! Faults during a render, with real processes killed by signal: a lost render node's work
//! moves to the others, a lost fork node's share of the scene is rebuilt on the other cards
//! and its render nodes served by another, and either way the image is the same bytes as one
//! process makes; losing the only fork node or the host ends everything cleanly and writes
//! no image; strangers and late joiners are refused without disturbing the render.
//!
//! The clusters here are started by hand (`--listen` plus node processes the test starts),
//! as a user on a LAN would, so the test knows each process and its node id.

mod common;
use common::*;

use std::ffi::OsStr;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

const SECRET: &str = "fault test secret";

fn bin(name: &str) -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_magg-host"))
        .parent()
        .unwrap()
        .join(name)
}

struct Cluster {
    host: Logged,
    /// Node id to process.
    nodes: Vec<(u32, Logged)>,
    out: PathBuf,
    stats: PathBuf,
}

fn cornell() -> PathBuf {
    data().join("scenes/cornell/cornell.gltf")
}

/// Starts a listen-mode host rendering `args` for `topology`, then its nodes, all on
/// 127.0.0.1, and waits until the render has begun.
fn start_cluster<S: AsRef<OsStr>>(dir: &Path, topology: &str, args: &[S]) -> Cluster {
    start_cluster_on(dir, "127.0.0.1", topology, args, &|_| "127.0.0.1".into())
}

/// The same with the host on `host_ip` and node `i` (in start order) on `node_ip(i)`.
fn start_cluster_on<S: AsRef<OsStr>>(
    dir: &Path,
    host_ip: &str,
    topology: &str,
    args: &[S],
    node_ip: &dyn Fn(u32) -> String,
) -> Cluster {
    let out = dir.join("cluster.png");
    let stats = dir.join("stats.json");
    // Every render node at work, as in the paper, whatever the machine's CPUs (these tests
    // kill or cut off particular nodes mid-render), unless the test says otherwise.
    let every_node =
        (!args.iter().any(|a| a.as_ref() == "--at-work")).then_some(["--at-work", "all"]);
    let host = Logged::start(
        host()
            .args([
                "--log",
                "info,magg::event=debug",
                "render",
                "--quiet",
                "--topology",
                topology,
            ])
            .args(every_node.iter().flatten())
            .arg("--listen")
            .arg(format!("{host_ip}:0"))
            .args(args)
            .arg("-o")
            .arg(&out)
            .arg("--stats")
            .arg(&stats)
            .env("MAGG_SECRET", SECRET),
    );
    let addr = host.join_address();
    let t = fabric::Topology::preset(topology).unwrap();
    let (forks, renders) = t.counts();
    let mut started = Vec::new();
    for (name, n) in [("magg-fork-node", forks), ("magg-render-node", renders)] {
        for _ in 0..n {
            let ip = node_ip(started.len() as u32);
            started.push(Logged::start(
                Command::new(bin(name))
                    .args(["--log", "info", "--join", &addr])
                    .arg("--listen")
                    .arg(format!("{ip}:0"))
                    .env("MAGG_SECRET", SECRET),
            ));
        }
    }
    let mut nodes = Vec::new();
    for p in started {
        let line = p
            .wait_for("joined as ", Duration::from_secs(30))
            .unwrap_or_else(|| panic!("a node did not join: {}", p.log()));
        let id: u32 = line
            .split("joined as ")
            .nth(1)
            .and_then(|r| r.split(';').next())
            .and_then(|r| r.split_whitespace().last())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no node id in {line:?}"));
        nodes.push((id, p));
    }
    host.wait_for("subscreens on", Duration::from_secs(60))
        .unwrap_or_else(|| panic!("the render did not begin: {}", host.log()));
    Cluster {
        host,
        nodes,
        out,
        stats,
    }
}

impl Cluster {
    /// Waits until pixels rendered by render node `node` (any node: `None`) reach the host:
    /// the render is under way there, so a kill lands in its middle whatever the machine's
    /// speed.
    /// Waits until `node` (any render node, with `None`) has sent pixels; which node did.
    fn wait_for_pixels_from(&self, node: Option<u32>) -> u32 {
        let needle = match node {
            Some(n) => format!("MAGG_EVENT pixels node={n} "),
            None => "MAGG_EVENT pixels node=".to_string(),
        };
        let line = self
            .host
            .wait_for(&needle, Duration::from_secs(60))
            .unwrap_or_else(|| panic!("no pixels from {node:?}: {}", self.host.log()));
        line.split("MAGG_EVENT pixels node=")
            .nth(1)
            .and_then(|r| r.split_whitespace().next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no node in {line:?}"))
    }

    /// The host exits with success within `limit`, every node within ten seconds after it;
    /// the render's stats.
    fn finishes(&mut self, limit: Duration) -> serde_json::Value {
        let code = self.host.wait_exit(limit);
        assert_eq!(code, Some(Some(0)), "host: {}", self.host.log());
        self.nodes_exit(Duration::from_secs(10));
        self.stats()
    }

    fn node(&mut self, id: u32) -> &mut Logged {
        &mut self
            .nodes
            .iter_mut()
            .find(|(n, _)| *n == id)
            .unwrap_or_else(|| panic!("no node {id}"))
            .1
    }

    /// Every node process has exited within `limit`.
    fn nodes_exit(&mut self, limit: Duration) {
        for (id, p) in &mut self.nodes {
            assert!(
                p.wait_exit(limit).is_some(),
                "node {id} (pid {}) is still running: {}",
                p.pid(),
                p.log()
            );
        }
    }

    fn stats(&self) -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(&self.stats).unwrap()).unwrap()
    }
}

/// The Cornell box, rendered long enough (several seconds on two cores) that a kill lands in
/// its middle.
fn long_render() -> Vec<String> {
    let scene = cornell().display().to_string();
    [&scene, "--width", "96", "--height", "96", "--spp", "300"]
        .map(String::from)
        .to_vec()
}

#[test]
fn a_killed_render_node_is_routed_around_and_the_image_is_unchanged() {
    let _serial = serial();
    let dir = scratch("fault-render-node");
    let args = long_render();
    // grid:1x3x3: host 0, fork node 1 linked to render node 2; render nodes 2..=10 in a 3x3
    // mesh. Node 6 is the middle one: routes between its neighbours must go around it.
    let mut c = start_cluster(&dir, "grid:1x3x3", &args);
    c.wait_for_pixels_from(Some(6));
    let killed_at = Instant::now();
    let victim_pid = c.node(6).pid();
    c.node(6).kill9();
    let line = c
        .host
        .wait_for("lost render node 6", Duration::from_secs(10))
        .unwrap_or_else(|| panic!("the host did not report the loss: {}", c.host.log()));
    let noticed = killed_at.elapsed();
    assert!(
        noticed < Duration::from_secs(5),
        "the loss took {noticed:?} to notice"
    );
    assert!(
        line.contains(&format!("pid {victim_pid}")),
        "the message should name the process: {line}"
    );
    let stats = c.finishes(Duration::from_secs(120));
    let lost = stats["lost_nodes"].as_array().unwrap();
    assert_eq!(lost.len(), 1, "{stats}");
    assert_eq!(lost[0]["node"], 6);
    assert_eq!(lost[0]["pid"], victim_pid);
    assert!(
        lost[0]["subscreens_reassigned"].as_u64().unwrap() >= 1,
        "a node killed mid-render had work to hand on: {stats}"
    );
    same_bytes(&c.out, &in_process(&dir, &args));
}

/// With two of nine render nodes at work (the others waiting, as on a machine of two CPUs),
/// killing one at work hands its unfinished subscreens to another and its place at work to
/// a node that waited; the image is unchanged.
#[test]
fn a_killed_render_node_at_work_gives_its_place_to_one_that_waited() {
    let _serial = serial();
    let dir = scratch("fault-at-work");
    let mut args = long_render();
    args.extend(["--at-work", "2"].map(String::from));
    let mut c = start_cluster(&dir, "grid:1x3x3", &args);
    let victim = c.wait_for_pixels_from(None);
    c.node(victim).kill9();
    c.host
        .wait_for(
            &format!("lost render node {victim}"),
            Duration::from_secs(10),
        )
        .unwrap_or_else(|| panic!("the host did not report the loss: {}", c.host.log()));
    let stats = c.finishes(Duration::from_secs(180));
    assert_eq!(stats["at_work"], "2", "{stats}");
    let lost = stats["lost_nodes"].as_array().unwrap();
    assert_eq!(lost.len(), 1, "{stats}");
    assert_eq!(lost[0]["node"], victim, "{stats}");
    assert!(
        lost[0]["subscreens_reassigned"].as_u64().unwrap() >= 1,
        "{stats}"
    );
    // The survivors that rendered: the other one at work and the one that took the lost
    // node's place, no more (the lost node reports nothing).
    let rendered: Vec<u64> = stats["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|n| n["role"] == "Render" && n["subscreens"].as_u64().unwrap() > 0)
        .map(|n| n["node"].as_u64().unwrap())
        .collect();
    assert_eq!(rendered.len(), 2, "{rendered:?}: {stats}");
    same_bytes(&c.out, &in_process(&dir, &args));
}

#[test]
fn a_render_node_cut_off_from_the_mesh_works_on_over_its_direct_connections() {
    let _serial = serial();
    let dir = scratch("fault-cut-off");
    let args = long_render();
    // grid:1x1x3: fork node 1 - render 2 - render 3 - render 4, a chain. Losing node 3
    // leaves node 4 with no mesh path to anyone: its requests for work and data go over
    // its direct connections to the host and the fork node instead.
    let mut c = start_cluster(&dir, "grid:1x1x3", &args);
    c.wait_for_pixels_from(Some(3));
    c.node(3).kill9();
    c.host
        .wait_for("lost render node 3", Duration::from_secs(10))
        .unwrap_or_else(|| panic!("{}", c.host.log()));
    let stats = c.finishes(Duration::from_secs(180));
    let lost: Vec<u64> = stats["lost_nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["node"].as_u64().unwrap())
        .collect();
    assert_eq!(lost, vec![3], "{stats}");
    let node4 = stats["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|n| n["node"] == 4)
        .unwrap_or_else(|| panic!("node 4 should have reported: {stats}"));
    assert!(
        node4["frames_around_mesh"].as_u64().unwrap() > 0,
        "node 4 should have gone around the mesh: {node4}"
    );
    same_bytes(&c.out, &in_process(&dir, &args));
}

/// The long render with the scene cut into eight chunks, spread over both cards, and every
/// DMA read over TCP, through the fork nodes (no shared memory).
fn long_render_fetching() -> Vec<String> {
    let mut args = long_render();
    args.extend(["--chunk-triangles", "16", "--dma-transport", "tcp"].map(String::from));
    args
}

/// Kills fork node `fork` of a grid:2x2x2 cluster (fork nodes 1 and 2; render nodes 3, 4, 7
/// and 8 on card 0, 5, 6, 9 and 10 on card 1) once render node `watch` of its card renders,
/// and checks that the render finishes with the bytes of one process.
fn fork_node_killed_mid_render(name: &str, fork: u32, watch: u32, extra: &[&str]) {
    let _serial = serial();
    let dir = scratch(name);
    let mut args = long_render_fetching();
    args.extend(extra.iter().map(|a| a.to_string()));
    let mut c = start_cluster(&dir, "grid:2x2x2", &args);
    c.wait_for_pixels_from(Some(watch));
    let fork_pid = c.node(fork).pid();
    c.node(fork).kill9();
    c.host
        .wait_for(
            &format!("MAGG_EVENT recovered node={fork}"),
            Duration::from_secs(60),
        )
        .unwrap_or_else(|| panic!("no recovery: {}", c.host.log()));
    let stats = c.finishes(Duration::from_secs(300));
    let lost = stats["lost_nodes"].as_array().unwrap();
    assert_eq!(lost.len(), 1, "{stats}");
    assert_eq!(lost[0]["node"], fork, "{stats}");
    assert_eq!(lost[0]["role"], "fork node", "{stats}");
    assert_eq!(lost[0]["pid"], fork_pid, "{stats}");
    assert!(
        lost[0]["items_moved"].as_u64().unwrap() >= 1,
        "a card holds a share of the scene: {stats}"
    );
    // Every render node served to the end, the lost card's through the other fork node.
    let rendered: Vec<u64> = stats["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|n| n["role"] == "Render")
        .map(|n| n["node"].as_u64().unwrap())
        .collect();
    assert_eq!(rendered, [3, 4, 5, 6, 7, 8, 9, 10], "{stats}");
    same_bytes(&c.out, &in_process(&dir, &args));
}

#[test]
fn a_killed_fork_node_has_its_share_rebuilt_and_the_image_is_unchanged() {
    fork_node_killed_mid_render("fault-fork-node", 2, 5, &[]);
}

#[test]
fn a_killed_fork_node_in_batch_mode_has_its_share_rebuilt_and_the_image_is_unchanged() {
    // Batch transfer: every render node holds the whole scene before it renders, so what the
    // loss costs is the card's routes and the rows on their way through it.
    fork_node_killed_mid_render("fault-fork-node-batch", 2, 5, &["--transfer", "batch"]);
}

#[test]
fn a_killed_first_fork_node_is_replaced_and_the_image_is_unchanged() {
    // The first fork node prepared the scene, arbitrates the G-buses and is the host's
    // only mesh link.
    fork_node_killed_mid_render("fault-first-fork-node", 1, 3, &[]);
}

#[test]
fn a_killed_only_fork_node_ends_the_render_with_no_image() {
    let _serial = serial();
    let dir = scratch("fault-only-fork-node");
    let args = long_render();
    let mut c = start_cluster(&dir, "tiny", &args);
    c.wait_for_pixels_from(None);
    let fork_pid = c.node(1).pid();
    c.node(1).kill9();
    let code = c.host.wait_exit(Duration::from_secs(10));
    assert!(
        matches!(code, Some(Some(c)) if c != 0),
        "the host should fail within 10 s, got {code:?}: {}",
        c.host.log()
    );
    let log = c.host.log();
    assert!(
        log.contains("lost fork node 1") && log.contains(&format!("pid {fork_pid}")),
        "the error should name the fork node and its process: {log}"
    );
    assert!(
        log.contains("no fork node is left") && log.contains("no image is written"),
        "{log}"
    );
    assert!(!c.out.exists(), "no image after a failed render");
    c.nodes_exit(Duration::from_secs(10));
}

#[test]
fn a_killed_host_stops_every_node() {
    let _serial = serial();
    let dir = scratch("fault-host");
    let args = long_render();
    let mut c = start_cluster(&dir, "tiny", &args);
    c.wait_for_pixels_from(None);
    c.host.kill9();
    let killed_at = Instant::now();
    c.nodes_exit(Duration::from_secs(10));
    assert!(killed_at.elapsed() < Duration::from_secs(10));
    for (id, p) in &c.nodes {
        assert!(
            p.log().contains("lost the host"),
            "node {id} should say why it stopped: {}",
            p.log()
        );
    }
    assert!(!c.out.exists());
}

#[test]
fn strangers_and_late_joiners_are_refused_while_the_render_goes_on() {
    let _serial = serial();
    let dir = scratch("fault-strangers");
    let args = long_render();
    let mut c = start_cluster(&dir, "tiny", &args);
    let line = c.host.wait_for("to join at ", Duration::ZERO).unwrap();
    let addr = line
        .rsplit("to join at ")
        .next()
        .unwrap()
        .trim()
        .to_string();

    let join = |secret: &str| {
        run(Command::new(bin("magg-render-node"))
            .args([
                "--join",
                &addr,
                "--listen",
                "127.0.0.1:0",
                "--timeout",
                "20",
            ])
            .env("MAGG_SECRET", secret))
    };
    // The wrong secret.
    let o = join("not the secret");
    assert!(!o.status.success());
    assert!(stderr(&o).contains("secret"), "{}", stderr(&o));
    // The right secret, but the cluster is full and busy.
    let o = join(SECRET);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("full"), "{}", stderr(&o));
    // Another protocol version, and another build of this version, by hand.
    let refusal = |version: u32, build: &str| {
        let mut s = std::net::TcpStream::connect(&addr).unwrap();
        let hello = protocol::Message::Hello {
            version,
            cluster_id: "magg".into(),
            nonce: [7; 32],
            identity: protocol::Identity {
                role: protocol::Role::Render,
                node: None,
                kind: protocol::ConnectionKind::Control,
            },
            build: build.into(),
        };
        let f = protocol::Frame::new(0, 0, &hello, Box::new([]));
        let mut bytes = f.header.encode().to_vec();
        bytes.extend_from_slice(&f.meta);
        s.write_all(&bytes).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut reply = Vec::new();
        let _ = s.read_to_end(&mut reply);
        String::from_utf8_lossy(&reply).into_owned()
    };
    let text = refusal(99, magg::BUILD_ID);
    assert!(
        text.contains("version"),
        "the refusal should say why: {text:?}"
    );
    let text = refusal(protocol::PROTOCOL_VERSION, "magg 0.0.9 src 000000000000");
    assert!(
        text.contains("same build") && text.contains(magg::BUILD_ID),
        "the refusal should name both builds: {text:?}"
    );
    assert!(
        c.host
            .wait_for("same build", Duration::from_secs(10))
            .is_some(),
        "the host should log the refusal: {}",
        c.host.log()
    );

    assert!(
        c.finishes(Duration::from_secs(120))["lost_nodes"]
            .as_array()
            .unwrap()
            .is_empty()
    );
    same_bytes(&c.out, &in_process(&dir, &args));
}

/// A cluster by hand on several addresses, as on a LAN: the host and every node on its own
/// loopback address (127.0.0.0/8 is all local on Linux), each found by the address it
/// advertises.
#[test]
fn a_cluster_by_hand_on_separate_addresses() {
    let _serial = serial();
    let dir = scratch("lan");
    let scene = cornell();
    let args = [
        scene.to_str().unwrap(),
        "--width",
        "48",
        "--height",
        "48",
        "--spp",
        "16",
    ];
    let ip = |i: u32| format!("127.0.1.{}", 10 + i);
    let mut c = start_cluster_on(&dir, "127.0.0.2", "tiny", &args, &ip);
    assert_eq!(
        c.host.wait_exit(Duration::from_secs(120)),
        Some(Some(0)),
        "{}",
        c.host.log()
    );
    c.nodes_exit(Duration::from_secs(10));
    let stats = c.stats();
    let mut seen = std::collections::HashSet::new();
    for m in stats["members"].as_array().unwrap() {
        let a = m["advertise"].as_str().unwrap();
        assert!(
            a.starts_with("127.0.1."),
            "{a} is not the address the node listened on"
        );
        assert!(
            seen.insert(a.split(':').next().unwrap().to_string()),
            "{a} twice"
        );
    }
    assert_eq!(seen.len(), 5);
    same_bytes(&c.out, &in_process(&dir, &args));
}

/// The default way to render, a cluster the host spawns itself: a child render node killed
/// mid-render is handed over like any other.
#[test]
fn a_killed_child_of_a_spawning_host_is_handed_over() {
    let _serial = serial();
    let dir = scratch("fault-spawned");
    let args = long_render();
    let out = dir.join("cluster.png");
    let mut host = Logged::start(render_on_spawned_tiny().args(&args).arg("-o").arg(&out));
    host.wait_for("MAGG_EVENT pixels node=", Duration::from_secs(60))
        .unwrap_or_else(|| panic!("the render did not begin: {}", host.log()));
    let render_child = render_node_child(host.pid()).expect("a render node child");
    signal(render_child, rustix::process::Signal::KILL);
    let line = host
        .wait_for("lost render node", Duration::from_secs(10))
        .unwrap_or_else(|| panic!("{}", host.log()));
    assert!(line.contains(&format!("pid {render_child}")), "{line}");
    assert_eq!(
        host.wait_exit(Duration::from_secs(120)),
        Some(Some(0)),
        "{}",
        host.log()
    );
    same_bytes(&out, &in_process(&dir, &args));
}

/// A spawned render node that hangs (SIGSTOP) mid-render is declared lost after its silence,
/// and once the image is written the host kills it and exits: it waited 10 s for the lost
/// node to obey the shutdown, then killed it and said "some nodes did not exit when told".
#[test]
fn a_hung_child_of_a_spawning_host_does_not_delay_its_exit() {
    let _serial = serial();
    let dir = scratch("fault-spawned-hung");
    let out = dir.join("cluster.png");
    let mut host = Logged::start(
        render_on_spawned_tiny()
            // Every render node holds work when it is stopped, so the image waits for its
            // loss.
            .args(["--at-work", "all"])
            .args(long_render())
            .arg("-o")
            .arg(&out),
    );
    host.wait_for("MAGG_EVENT pixels node=", Duration::from_secs(60))
        .unwrap_or_else(|| panic!("the render did not begin: {}", host.log()));
    let mut held = Held(Vec::new());
    let hung = render_node_child(host.pid()).expect("a render node child");
    held.hold(hung);
    let line = host
        .wait_for("lost render node", Duration::from_secs(30))
        .unwrap_or_else(|| panic!("the hung node was not declared lost: {}", host.log()));
    assert!(line.contains(&format!("pid {hung}")), "{line}");
    let until = Instant::now() + Duration::from_secs(120);
    while !out.exists() && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(out.exists(), "no image: {}", host.log());
    let written = Instant::now();
    assert_eq!(
        host.wait_exit(Duration::from_secs(60)),
        Some(Some(0)),
        "{}",
        host.log()
    );
    let exit_after_image = written.elapsed();
    assert!(
        exit_after_image < Duration::from_secs(6),
        "the host exited {exit_after_image:?} after writing the image: {}",
        host.log()
    );
    assert!(exited(hung), "the hung node {hung} outlived the host");
    assert!(
        !host.log().contains("did not exit when told"),
        "{}",
        host.log()
    );
}

/// Ctrl-C or SIGTERM while a host waits for its nodes to join ends the wait at once, with
/// the signal's exit status, and the nodes that had joined stop cleanly at once. It waited
/// for the join timeout and failed with status 1; its nodes saw only the connection end and
/// said they lost the host.
#[test]
fn a_host_stopped_while_its_nodes_join_stops_those_that_joined() {
    let _serial = serial();
    for (stop, name, code) in [
        (rustix::process::Signal::INT, "SIGINT", 130),
        (rustix::process::Signal::TERM, "SIGTERM", 143),
    ] {
        let dir = scratch(&format!("stopped-forming-{code}"));
        let mut host = Logged::start(
            host()
                .args(["--log", "info", "render", "--quiet", "--topology", "tiny"])
                .args(["--listen", "127.0.0.1:0", "--join-timeout", "120", "-o"])
                .arg(dir.join("never.png"))
                .arg(cornell())
                .env("MAGG_SECRET", SECRET),
        );
        let addr = host.join_address();
        let mut node = Logged::start(
            Command::new(bin("magg-render-node"))
                .args(["--log", "info", "--join", &addr, "--listen", "127.0.0.1:0"])
                .env("MAGG_SECRET", SECRET),
        );
        host.wait_for(" joined from ", Duration::from_secs(30))
            .unwrap_or_else(|| panic!("the node did not join: {}", host.log()));
        signal(host.pid() as u64, stop);
        assert_eq!(
            host.wait_exit(Duration::from_secs(20)),
            Some(Some(code)),
            "{name}: {}",
            host.log()
        );
        let log = host.log();
        assert!(
            log.contains(&format!("{name}: stopping the cluster")),
            "{log}"
        );
        assert!(
            log.contains("interrupted; the cluster was stopped and no image was written"),
            "{log}"
        );
        assert_eq!(
            node.wait_exit(Duration::from_secs(10)),
            Some(Some(0)),
            "{name}: {}",
            node.log()
        );
        assert!(
            node.log().contains("stopping: the host was stopped"),
            "{name}: {}",
            node.log()
        );
        let left: Vec<_> = std::fs::read_dir(&dir).unwrap().flatten().collect();
        assert!(left.is_empty(), "{name} left files: {left:?}");
    }
}
