//! Hostile traffic on every listening port of a cluster while it renders: random bytes,
//! truncated frames, oversized lengths, valid frames of the wrong kind and silent
//! connections. Each is refused, and the render completes with the correct image.

mod common;
use common::*;

use std::{
    io::Write,
    net::{TcpListener, TcpStream},
    path::Path,
    process::Command,
    sync::{
        Arc,
        atomic::{AtomicBool, Ordering},
    },
    time::Duration,
};

use protocol::{Frame, Message};

/// `count` distinct ports free now, below the kernel's ephemeral range. A port from that
/// range (what binding port 0 gives) can be taken before its node binds it: the attackers'
/// own connections use ephemeral ports, and one of them, open or in TIME_WAIT for a
/// minute, makes the node's bind fail (this test once lost a render node that way).
fn free_ports(count: usize) -> Vec<u16> {
    let ephemeral_low = std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .ok()
        .and_then(|r| r.split_whitespace().next()?.parse::<u16>().ok())
        .unwrap_or(32768);
    let low = 10_000u16.min(ephemeral_low / 2);
    let span = u32::from(ephemeral_low - low);
    let mut state = (std::process::id()
        ^ std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos()))
        | 1;
    let mut ports = Vec::new();
    for _ in 0..10_000 {
        if ports.len() == count {
            return ports;
        }
        // xorshift: different runs (and test binaries running at once) try different ports.
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        let port = low + (state % span) as u16;
        if !ports.contains(&port) && TcpListener::bind(("127.0.0.1", port)).is_ok() {
            ports.push(port);
        }
    }
    panic!("fewer than {count} free ports in {low}..{ephemeral_low}");
}

fn bin(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_BIN_EXE_magg-host"))
        .parent()
        .unwrap()
        .join(name)
}

fn attacks() -> Vec<Vec<u8>> {
    let shutdown = Frame::new(
        0,
        1,
        &Message::Shutdown {
            reason: "attack".into(),
        },
        Box::new([]),
    );
    let mut wrong_kind = shutdown.header.encode().to_vec();
    wrong_kind.extend_from_slice(&shutdown.meta);
    let mut oversized = Frame::new(1, 2, &Message::Go, Box::new([])).header;
    oversized.meta_len = u32::MAX;
    let mut truncated = Frame::new(1, 2, &Message::Go, Box::new([])).header;
    truncated.meta_len = 1000;
    vec![
        (0..8192u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 11) as u8)
            .collect(),
        wrong_kind,
        oversized.encode().to_vec(),
        truncated.encode()[..30].to_vec(),
        [&truncated.encode()[..], &[1, 2, 3]].concat(),
    ]
}

#[test]
fn a_render_under_attack_completes_with_the_right_image() {
    let dir = scratch("attacks");
    let size = ["--width", "96", "--height", "72", "--spp", "24"];
    let reference = dir.join("ref.pfm");
    let o = run(host()
        .arg("render")
        .arg("--in-process")
        .args(size)
        .arg("-o")
        .arg(&reference));
    assert!(o.status.success(), "{}", stderr(&o));

    // One port for the host, then one for each node: the fork node, then four render nodes.
    let ports = free_ports(6);
    let host_port = ports[0];
    let host_addr = format!("127.0.0.1:{host_port}");
    let out = dir.join("attacked.pfm");
    let mut host_proc = Logged::start(
        host()
            .arg("render")
            .args(size)
            .args([
                "--listen",
                &host_addr,
                "--topology",
                "tiny",
                "--subscreens",
                "60",
                "--quiet",
                "-o",
            ])
            .arg(&out)
            .env("MAGG_SECRET", "attack test secret"),
    );
    let mut node_ports = ports[1..].iter();
    let mut nodes = Vec::new();
    for (role, count) in [("magg-fork-node", 1), ("magg-render-node", 4)] {
        for _ in 0..count {
            let port = node_ports.next().unwrap();
            let node = Logged::start(
                Command::new(bin(role))
                    .args([
                        "--join",
                        &host_addr,
                        "--listen",
                        &format!("127.0.0.1:{port}"),
                        "--log",
                        "error",
                    ])
                    .env("MAGG_SECRET", "attack test secret"),
            );
            nodes.push((role, port, node));
        }
    }
    // Attack every port, over and over, until the render is over.
    let stop = Arc::new(AtomicBool::new(false));
    let attackers: Vec<_> = ports
        .iter()
        .map(|&port| {
            let stop = stop.clone();
            std::thread::spawn(move || {
                let mut silent = Vec::new();
                let mut rounds = 0;
                while !stop.load(Ordering::Relaxed) {
                    for a in attacks() {
                        if let Ok(mut s) = TcpStream::connect(("127.0.0.1", port)) {
                            let _ = s.write_all(&a);
                        }
                    }
                    if silent.len() < 20
                        && let Ok(s) = TcpStream::connect(("127.0.0.1", port))
                    {
                        silent.push(s);
                    }
                    rounds += 1;
                    std::thread::sleep(Duration::from_millis(20));
                }
                rounds
            })
        })
        .collect();
    // The host's log is read as it is written (every refused attack is a line of it): a
    // pipe left unread would fill and stall the host.
    let code = host_proc.wait_exit(Duration::from_secs(600));
    stop.store(true, Ordering::Relaxed);
    let rounds: usize = attackers.into_iter().map(|t| t.join().unwrap()).sum();
    if code != Some(Some(0)) {
        // The host logs every refused attack; what else it and the nodes said is the story.
        let host_log: Vec<_> = host_proc
            .log()
            .lines()
            .filter(|l| !l.contains("refused a connection from"))
            .map(str::to_string)
            .collect();
        let node_logs: Vec<_> = nodes
            .iter()
            .map(|(role, port, n)| format!("{role} at port {port}:\n{}", n.log()))
            .collect();
        panic!(
            "the render failed under attack (exit {code:?}); the host, less refused attacks:\n{}\n{}",
            host_log.join("\n"),
            node_logs.join("\n")
        );
    }
    assert!(rounds > 6, "the attacks should have run during the render");
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(&reference).unwrap(),
        "the attacked render differs"
    );
    for (_, _, mut n) in nodes {
        let _ = n.child.wait();
    }
}
