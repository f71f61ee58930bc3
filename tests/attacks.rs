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

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
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

    let host_port = free_port();
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
    let mut ports = vec![host_port];
    let mut nodes = Vec::new();
    for (role, count) in [("magg-fork-node", 1), ("magg-render-node", 4)] {
        for _ in 0..count {
            let port = free_port();
            ports.push(port);
            nodes.push(
                Command::new(bin(role))
                    .args([
                        "--join",
                        &host_addr,
                        "--listen",
                        &format!("127.0.0.1:{port}"),
                        "--log",
                        "error",
                    ])
                    .env("MAGG_SECRET", "attack test secret")
                    .spawn()
                    .unwrap(),
            );
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
    assert_eq!(
        code,
        Some(Some(0)),
        "the render failed under attack: {}",
        host_proc.log()
    );
    assert!(rounds > 6, "the attacks should have run during the render");
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(&reference).unwrap(),
        "the attacked render differs"
    );
    for mut n in nodes {
        let _ = n.wait();
    }
}
