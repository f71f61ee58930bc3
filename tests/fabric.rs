//! The cluster fabric on real processes over loopback: registration of the `tiny` and
//! `magg` topologies, routing of one-to-one and broadcast frames, refusal of wrong secrets
//! and versions, and hostile bytes on every listening port.

mod common;

use std::{
    collections::HashMap,
    io::{Read, Write},
    net::TcpStream,
    path::Path,
    process::Command,
    sync::atomic::AtomicBool,
    time::Duration,
};

use fabric::{Delivery, Topology, Via};
use host::cluster::{Cluster, ClusterConfig, ClusterMode, bind, start, start_on};
use protocol::{Frame, Message, NodeId, Secret};

fn config(topology: &str, mode: ClusterMode) -> ClusterConfig {
    // The host runs in this test process, the nodes in the binaries: the same build.
    magg::stamp_build_id();
    ClusterConfig {
        mode,
        topology: Topology::resolve(topology).unwrap(),
        secret: Secret::new("fabric test secret").unwrap(),
        join_timeout: Duration::from_secs(120),
        node_log: "error".into(),
        node_program: env!("CARGO_BIN_EXE_magg-host").into(),
        write_secret: None,
    }
}

/// Collects `Seen` reports for ping `id` for a while: node -> (from, count).
async fn collect_seen(
    cluster: &mut Cluster,
    id: u32,
    expect: usize,
) -> HashMap<NodeId, Vec<NodeId>> {
    let mut seen: HashMap<NodeId, Vec<NodeId>> = HashMap::new();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    let mut total = 0;
    loop {
        let wait = if total >= expect {
            Duration::from_millis(300)
        } else {
            deadline - tokio::time::Instant::now()
        };
        match tokio::time::timeout(wait, cluster.formed.inbox.recv()).await {
            Ok(Some(Delivery::Frame { frame, .. })) => match frame.message() {
                Ok(Message::Seen {
                    id: i, from, node, ..
                }) if i == id => {
                    seen.entry(node).or_default().push(from);
                    total += 1;
                }
                Ok(Message::Ping { id: i }) if i == id => {
                    seen.entry(0).or_default().push(frame.header.sender);
                    total += 1;
                }
                _ => {}
            },
            Ok(Some(_)) => {}
            _ => break,
        }
    }
    seen
}

async fn check_routing(cluster: &mut Cluster, t: &Topology, base_id: u32) {
    let others: Vec<NodeId> = (1..t.len() as NodeId).collect();
    let f = cluster.formed.fabric.clone();
    // Host to everyone, one-to-one through the mesh.
    for &n in &others {
        f.send(n, &Message::Ping { id: base_id }, Box::new([]), 0)
            .unwrap();
    }
    let seen = collect_seen(cluster, base_id, others.len()).await;
    for &n in &others {
        assert_eq!(
            seen.get(&n),
            Some(&vec![0]),
            "node {n} should see the host's ping once"
        );
    }
    // The farthest render node to everyone else, one-to-one.
    let far = *t.render_nodes().last().unwrap();
    let targets: Vec<NodeId> = (0..t.len() as NodeId).filter(|&n| n != far).collect();
    f.send_control(
        far,
        &Message::RunPings {
            id: base_id + 1,
            to: targets.clone(),
            broadcast: false,
        },
    )
    .unwrap();
    let seen = collect_seen(cluster, base_id + 1, targets.len()).await;
    for &n in &targets {
        assert_eq!(
            seen.get(&n),
            Some(&vec![far]),
            "node {n} should see node {far}'s ping once"
        );
    }
    // Broadcasts from a render node and from the host reach every other node exactly once.
    for (root, id) in [(far, base_id + 2), (0, base_id + 3)] {
        if root == 0 {
            f.broadcast(&Message::Ping { id }, Box::new([]));
        } else {
            f.send_control(
                root,
                &Message::RunPings {
                    id,
                    to: vec![],
                    broadcast: true,
                },
            )
            .unwrap();
        }
        let seen = collect_seen(cluster, id, t.len() - 1).await;
        for n in (0..t.len() as NodeId).filter(|&n| n != root) {
            assert_eq!(
                seen.get(&n).map(Vec::len),
                Some(1),
                "node {n} should get the broadcast from {root} exactly once: {seen:?}"
            );
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiny_and_magg_register_route_and_stop() {
    for preset in ["tiny", "magg"] {
        let cfg = config(preset, ClusterMode::Spawn);
        let t = cfg.topology.clone();
        let mut cluster = start(&cfg, &|_, _| {}, &AtomicBool::new(false))
            .await
            .unwrap();
        assert_eq!(cluster.formed.members.len(), t.len() - 1);
        let pids = cluster.local.as_ref().unwrap().pids();
        check_routing(&mut cluster, &t, 100).await;
        assert!(
            cluster.shutdown("test done").await,
            "{preset}: every node should exit when told"
        );
        for pid in pids {
            assert!(
                !Path::new(&format!("/proc/{pid}")).exists() || is_zombie(pid),
                "{preset}: process {pid} outlived the cluster"
            );
        }
    }
}

fn is_zombie(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .map(|s| s.contains(") Z "))
        .unwrap_or(true)
}

/// Starts the node processes of a topology by hand, joining `addr`.
fn start_nodes(t: &Topology, addr: &str, secret: &str) -> Vec<std::process::Child> {
    let (f, r) = t.counts();
    let mut v = Vec::new();
    for (bin, n) in [
        (env!("CARGO_BIN_EXE_magg-fork-node"), f),
        (env!("CARGO_BIN_EXE_magg-render-node"), r),
    ] {
        for _ in 0..n {
            v.push(
                Command::new(bin)
                    .args(["--join", addr, "--listen", "127.0.0.1:0", "--log", "error"])
                    .env("MAGG_SECRET", secret)
                    .spawn()
                    .unwrap(),
            );
        }
    }
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_secret_and_wrong_version_are_refused() {
    let cfg = config("tiny", ClusterMode::Listen("127.0.0.1:0".into()));
    let t = cfg.topology.clone();
    let listener = bind(&cfg).await.unwrap();
    let addr = listener.local_addr().unwrap().to_string();

    // An impostor with the wrong secret: refused, with a message saying why.
    let impostor = Command::new(env!("CARGO_BIN_EXE_magg-render-node"))
        .args([
            "--join",
            &addr,
            "--listen",
            "127.0.0.1:0",
            "--timeout",
            "30",
        ])
        .env("MAGG_SECRET", "not the right one")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // A peer speaking another protocol version, by hand.
    let version_addr = addr.clone();
    let version = std::thread::spawn(move || {
        let mut s = TcpStream::connect(&version_addr).unwrap();
        let hello = Message::Hello {
            version: 99,
            cluster_id: "magg".into(),
            nonce: [7; 32],
            identity: protocol::Identity {
                role: protocol::Role::Render,
                node: None,
                kind: protocol::ConnectionKind::Control,
            },
            build: magg::BUILD_ID.into(),
        };
        let f = Frame::new(0, 0, &hello, Box::new([]));
        let mut bytes = f.header.encode().to_vec();
        bytes.extend_from_slice(&f.meta);
        s.write_all(&bytes).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut buf = Vec::new();
        let _ = s.read_to_end(&mut buf);
        buf
    });
    let nodes = start_nodes(&t, &addr, "fabric test secret");
    let cluster = start_on(listener, &cfg, &|_, _| {}, &AtomicBool::new(false))
        .await
        .unwrap();
    let out = tokio::task::spawn_blocking(move || impostor.wait_with_output().unwrap())
        .await
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("secret"),
        "the impostor should be told about the secret: {err}"
    );
    let reply = version.join().unwrap();
    let header: [u8; protocol::HEADER_LEN] = reply[..protocol::HEADER_LEN].try_into().unwrap();
    let h = protocol::FrameHeader::decode(&header).unwrap();
    let m =
        Message::decode(&reply[protocol::HEADER_LEN..protocol::HEADER_LEN + h.meta_len as usize])
            .unwrap();
    match m {
        Message::Refused { reason } => assert!(reason.contains("version"), "{reason}"),
        other => panic!("expected a refusal, got {other:?}"),
    }
    assert!(cluster.formed.fabric.counters().connections_refused >= 2);
    assert!(cluster.shutdown("test done").await);
    for mut n in nodes {
        let _ = n.wait();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_bytes_on_every_port_leave_the_cluster_working() {
    let cfg = config("tiny", ClusterMode::Spawn);
    let t = cfg.topology.clone();
    let mut cluster = start(&cfg, &|_, _| {}, &AtomicBool::new(false))
        .await
        .unwrap();
    let addrs: Vec<String> = cluster
        .formed
        .members
        .iter()
        .map(|m| m.advertise.clone())
        .collect();
    let attacks: Vec<Vec<u8>> = vec![
        (0..4096u32)
            .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
            .collect(),
        {
            // A valid header claiming an enormous frame.
            let mut h = Frame::new(1, 2, &Message::Go, Box::new([])).header;
            h.data_len = u32::MAX - 3;
            h.encode().to_vec()
        },
        {
            // A frame of the wrong kind before any handshake.
            let f = Frame::new(
                1,
                2,
                &Message::Shutdown {
                    reason: "pwned".into(),
                },
                Box::new([]),
            );
            let mut b = f.header.encode().to_vec();
            b.extend_from_slice(&f.meta);
            b
        },
        b"MAGG\x01".to_vec(),
    ];
    let mut silent = Vec::new();
    for addr in &addrs {
        for a in &attacks {
            if let Ok(mut s) = TcpStream::connect(addr) {
                let _ = s.write_all(a);
            }
        }
        // Slow loris: connect, say nothing, keep the socket open.
        silent.push(TcpStream::connect(addr).unwrap());
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    check_routing(&mut cluster, &t, 200).await;
    let alive = cluster.local.as_mut().unwrap().pids().len();
    assert_eq!(alive, t.len() - 1);
    assert!(
        cluster.shutdown("test done").await,
        "every node still answers"
    );
    drop(silent);
    let _ = Via::Control(0);
}

/// Fork and render nodes run under valgrind, as callgrind needs them to: `bench/
/// cluster_counts.py` counts a cluster render's instructions that way, the one measure of
/// its cost that the shared machine's noise leaves alone. Reading the monotonic clock
/// through rustix crashed every node process there (rustix parses the vDSO itself, and
/// valgrind does not give it one to parse); through the C library it works.
#[test]
fn nodes_run_under_valgrind() {
    if Command::new("valgrind").arg("--version").output().is_err() {
        eprintln!("SKIPPED: nodes_run_under_valgrind (valgrind is not installed)");
        return;
    }
    const SECRET: &str = "valgrind test secret";
    let dir = common::scratch("valgrind-nodes");
    let out = dir.join("cluster.png");
    let mut host = common::Logged::start(
        common::host()
            .args(["render", "--quiet"])
            .arg(common::data().join("scenes/cornell/cornell.gltf"))
            .args(["--width", "8", "--height", "8", "--spp", "1"])
            .args(["--topology", "grid:1x1x1", "--listen", "127.0.0.1:0"])
            .arg("-o")
            .arg(&out)
            .env("MAGG_LOG", "info")
            .env("MAGG_SECRET", SECRET),
    );
    let addr = host.join_address();
    let nodes = common::join_one_of_each(
        &addr,
        |args| {
            let mut c = Command::new("valgrind");
            c.args(["--tool=none", "-q"]).args(args);
            c
        },
        |c| c.env("MAGG_SECRET", SECRET),
    );
    let code = host.wait_exit(Duration::from_secs(120));
    let logs: Vec<String> = nodes.iter().map(common::Logged::log).collect();
    assert_eq!(
        code,
        Some(Some(0)),
        "the render with its nodes under valgrind did not finish: host {}\nnodes {logs:?}",
        host.log()
    );
    assert!(out.exists(), "no image: {}", host.log());
    let _ = std::fs::remove_dir_all(&dir);
}
