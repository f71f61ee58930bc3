//! Measurements the host's experiments ask a render node for: mesh probes (latency between
//! two nodes) and demand transfers (what a chunk fetch costs by serial link or DMA). They
//! live apart from rendering because they use the fabric alone, never the scene or cache.

use std::time::Duration;

use fabric::{Fabric, Route, clock::now_ns};
use protocol::{DataId, Frame, Message, NodeId, Transfer};

const TIMEOUT: Duration = Duration::from_secs(120);

/// Samples made room for at once: the count comes in a message, and a count of four billion
/// took 34 GB before the first probe.
const PREALLOCATED: u32 = 4096;

/// Sends `count` probes of about `bytes` to `to`, one at a time, and reports their one-way
/// times (sender and receiver share CLOCK_MONOTONIC on one machine), or round trips.
pub(crate) async fn run_probes(f: Fabric, to: NodeId, bytes: u32, count: u32, round_trip: bool) {
    let mut samples = Vec::with_capacity(count.min(PREALLOCATED) as usize);
    for id in 0..count {
        let sent = now_ns();
        let probe = Message::Probe { id, sent_ns: sent };
        // Pad the frame to the requested size (the paper's figure is for 84-byte packets).
        let bare = Frame::new(f.me(), to, &probe, Box::new([])).wire_len();
        let pad = (bytes as usize).saturating_sub(bare).div_ceil(4);
        match f
            .request(
                to,
                &probe,
                vec![0u32; pad].into_boxed_slice(),
                Route::Mesh,
                TIMEOUT,
            )
            .await
        {
            Ok(reply) => {
                if let Ok(Message::ProbeEcho { received_ns, .. }) = reply.message() {
                    samples.push(if round_trip {
                        now_ns() - sent
                    } else {
                        received_ns.saturating_sub(sent)
                    });
                }
            }
            Err(e) => {
                tracing::warn!("probe {id} to node {to} failed: {e}");
                break;
            }
        }
    }
    report(&f, samples);
}

/// Measures `count` demand transfers of `bytes` from this card's fork node, the data held
/// by card `owner_card`, starting together with the other nodes at `start_ns`.
pub(crate) async fn run_transfers(
    f: Fabric,
    transfer: Transfer,
    bytes: u32,
    count: u32,
    owner_card: u16,
    start_ns: u64,
) {
    let t = f.topology();
    let (Some(fork), Some(owner)) = (t.fork_of(f.me()), t.fork_of_card(owner_card)) else {
        // The host waits for one report from every node it asked, empty or not.
        report(&f, Vec::new());
        return;
    };
    f.timer().sleep_until(start_ns).await;
    let mut samples = Vec::with_capacity(count.min(PREALLOCATED) as usize);
    for _ in 0..count {
        let t0 = now_ns();
        let request = Message::DataRequest {
            id: DataId::Synthetic { bytes },
            transfer,
            owner,
        };
        match f
            .request(fork, &request, Box::new([]), Route::Mesh, TIMEOUT)
            .await
        {
            Ok(reply) if reply.data.len() * 4 >= bytes as usize => samples.push(now_ns() - t0),
            Ok(_) => tracing::warn!("short reply to a transfer of {bytes} bytes"),
            Err(e) => {
                tracing::warn!("transfer of {bytes} bytes failed: {e}");
                break;
            }
        }
    }
    report(&f, samples);
}

fn report(f: &Fabric, samples_ns: Vec<u64>) {
    let _ = f.send_control(
        0,
        &Message::Measured {
            node: f.me(),
            samples_ns,
        },
    );
}
