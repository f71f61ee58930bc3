//! Diagnostics every node answers, whatever its role: routing checks (pings reported to the
//! host) and timing probes (echoed to their sender), used by tests and experiments.

use protocol::{BROADCAST, Frame, Message};

use crate::{Fabric, Route, clock::now_ns};

/// Handles `message` if it is a diagnostic; returns whether it was.
pub fn handle(fabric: &Fabric, frame: &Frame, message: &Message) -> bool {
    match message {
        Message::Probe { id, .. } => {
            let echo = Message::ProbeEcho {
                id: *id,
                received_ns: now_ns(),
            };
            let _ = fabric.reply(frame, &echo, Box::new([]), Route::Mesh, 0);
            true
        }
        Message::Ping { id } => {
            let seen = Message::Seen {
                id: *id,
                from: frame.header.sender,
                node: fabric.me(),
                hops: frame.header.hops,
            };
            if fabric.me() == 0 {
                // The host notes its own pings through its inbox like any control report.
                let _ = fabric.send(0, &seen, Box::new([]), 0);
            } else {
                let _ = fabric.send_control(0, &seen);
            }
            true
        }
        Message::RunPings { id, to, broadcast } => {
            if *broadcast {
                let _ = fabric.send(BROADCAST, &Message::Ping { id: *id }, Box::new([]), 0);
            }
            for &t in to {
                if let Err(e) = fabric.send(t, &Message::Ping { id: *id }, Box::new([]), 0) {
                    tracing::warn!("ping to node {t}: {e}");
                }
            }
            true
        }
        _ => false,
    }
}
