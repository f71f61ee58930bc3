//! The cluster fabric: the network the roles talk over.
//!
//! * [`topology`]: which nodes exist and which are linked (a TOML file, or a preset).
//! * [`routing`]: dimension-ordered next hops and broadcast spanning trees.
//! * [`model`]: the paper's serial-link, DMA and G-bus timings, applied exactly once, here.
//! * [`clock`]: the shared monotonic clock and a timer precise well below a millisecond.
//! * [`node`]: the runtime every process runs: links, forwarding, delivery.
//! * [`registry`]: the decisions of forming a cluster (slots, refusals, completion, timeout), with no I/O.
//! * [`cluster`]: forming a cluster: registration with the host, addresses, links up.
//! * [`role`]: the life every node role shares: join, take deliveries, obey the host, leave.
//! * [`shm`]: a card's memory as a shared-memory segment, published and mapped, checked.
//! * [`pages`]: memory in large pages, for the walking forms rays read.

pub mod clock;
pub mod cluster;
pub mod diag;
pub mod model;
pub mod node;
pub mod pages;
pub mod registry;
pub mod role;
pub mod routing;
pub mod shm;
pub mod topology;

pub use model::Model;
pub use node::{Delivery, Fabric, RequestError, Route, SendError, Via};
pub use topology::Topology;

/// Peak resident memory of this process (Linux `VmHWM`), in bytes; 0 where it cannot be read.
/// Every role reports it in its stats. It counts pages of shared mappings too.
pub fn peak_rss_bytes() -> u64 {
    status_bytes("VmHWM:")
}

/// Resident memory of this process's own (Linux `RssAnon`: not files, not shared-memory
/// segments it maps), in bytes now; 0 where it cannot be read.
pub fn private_rss_bytes() -> u64 {
    status_bytes("RssAnon:")
}

fn status_bytes(key: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with(key))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}
