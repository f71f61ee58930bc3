//! The discrete-event simulator: what a render would take on a machine this one cannot run.
//!
//! A 2-core machine cannot show an 80-node speedup by wall time, let alone a 1000-node one.
//! The simulator replays what a real render recorded (per subscreen: CPU time, the chunks and
//! tiles touched; see [`workload`]) on any topology, under the same rules the real cluster
//! follows, and predicts the total time `T(n)` and each render node's busy, waiting (for
//! data) and idle time. It does no I/O, starts no runtime and reads no clock: the same input
//! gives the same output, to the nanosecond.
//!
//! What it models, and from where:
//!
//! * **Links**: the topology's routes (`fabric::routing`) and the paper's link model
//!   (`fabric::model`: `T = 310 + 234 d_row + 300 d_col` us for an 84-byte packet, longer
//!   messages in 1 KB packets of 640 data bytes, store-and-forward, scaled by `time_scale`).
//!   Bulk transfers are **flows**: a message books every link of its route when it is sent,
//!   FIFO per link, its packets pipelined (`LinkClock::cross`, the real fabric's own
//!   booking); see [`network`]. Every message that crosses the mesh in the real system does
//!   here: requests for work and their answers (render node to host and back), demand
//!   requests (render node to its fork node), serial-link data replies, and every scan line
//!   of pixels (render node to its fork node, which passes it to the host outside the model).
//! * **Scheduling** (as `host::schedule`): subscreens in the host's plain order, handed to
//!   whoever asks first, nodes that have rendered before first; a node asks again when it
//!   has sent its last row. Render nodes sharing a machine ([`SimConfig::machines`], the
//!   host's `--at-work` limit) are handed work only while fewer than the machine lets work
//!   hold some. With `adaptive`, a request that finds the queue empty makes the host ask the
//!   node with the most rows still missing to give back the unbegun half of them (the
//!   render node's `give_back`), if a node waiting could take them.
//! * **Data** (as `fork-node` and `render-node`): items placed round-robin on the fork nodes;
//!   batch transfer sends every item to every render node by DMA before it starts (each
//!   card's DMA bus one at a time, items from other cards over the G-bus first); demand
//!   transfer keeps an LRU cache of a byte budget per render node, and a miss sends a request
//!   through the mesh to the node's fork node, which reads the item over the G-bus if another
//!   card holds it and sends it back by DMA (queued on the card's one DMA bus) or through the
//!   mesh. The node waits, as its rendering thread blocks on a miss.
//! * **Rendering**: one rendering thread per render node. A subscreen is rendered band by
//!   band ([`workload::Band`]); at a band's first row the node makes sure it holds the band's
//!   items (fetching the missing ones in id order, one at a time), then renders its rows,
//!   each taking its share of the band's CPU time times `cpu_scale`.
//!
//! `T` runs from the moment the job reaches the nodes (the render nodes ask for work, or the
//! fork nodes begin a batch handout) to the moment the last scan line reaches its fork node:
//! what the host measures as its render time, without scene preparation or the start of the
//! processes.

pub mod cache;
mod engine;
pub mod network;
pub mod workload;

use fabric::{
    Topology,
    model::{LinkModelKind, ModelError},
};
use protocol::NodeId;
use serde::{Deserialize, Serialize};

pub use host::schedule::Machine;
pub use network::hops;
pub use workload::{Band, Subscreen, Workload, WorkloadError};

/// How scene data reaches the render nodes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Transfer {
    /// Every render node receives every chunk and tile by DMA before it renders.
    Batch,
    /// Fetched on a miss into an LRU cache of `cache_bytes` per render node.
    Demand {
        cache_bytes: u64,
        via: protocol::Transfer,
    },
}

impl Transfer {
    /// Demand transfer with a cache of `percent` of the scene's bytes, rounded up as the
    /// host rounds it.
    pub fn demand_percent(workload: &Workload, percent: f64, via: protocol::Transfer) -> Transfer {
        Transfer::Demand {
            cache_bytes: (percent / 100.0 * workload.scene_bytes() as f64).ceil() as u64,
            via,
        }
    }
}

/// Which subscreens there are.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Balance {
    /// The workload's own subscreens.
    AsRecorded,
    /// One subscreen per render node (the paper's static division).
    Static,
    /// About this many subscreens, handed out on request.
    Dynamic { subscreens: u32 },
}

/// Everything a simulation depends on besides the workload.
#[derive(Clone, Debug)]
pub struct SimConfig {
    /// The machine; its `model` section gives the link, DMA and G-bus constants.
    pub topology: Topology,
    /// Overrides the topology's link model kind and time scale.
    pub link: LinkModelKind,
    pub time_scale: f64,
    pub transfer: Transfer,
    pub balance: Balance,
    /// Adaptive redivision: a node that would wait makes the busiest give back half.
    pub adaptive: bool,
    /// Multiplies every recorded CPU time (a slower or faster processor than the recording's).
    pub cpu_scale: f64,
    /// Real costs the link, DMA and G-bus models leave out; zero models none.
    pub overheads: Overheads,
    /// Render nodes that share a machine, and how many of them the host lets hold work at
    /// once (`host::schedule::machines`, from `--at-work`); a render node on none has a
    /// processor of its own, as the paper's did. A recorded render's are in its stats'
    /// `machine_limits`.
    pub machines: Vec<Machine>,
}

/// What a real render pays beyond the modelled hardware: the processes' own work. The
/// models give link, DMA and G-bus times of the 1991 machine; the processes that stand in for
/// it also spend real time on each message (waking up, copying, the host's handling of a
/// request, the fork node passing a scan line on) and before the first request (the job
/// reaching every node, the scene header, the processes' start). Neither is a constant of
/// the paper's machine, so neither has a default: they are measured on the machine whose
/// render is replayed (`lab::simulate::measure_overheads` reads them off a recorded render),
/// and zero leaves them out.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Overheads {
    /// Before any render node may begin (and before a batch handout begins).
    pub start_ns: u64,
    /// Added for every hop of a message through the mesh (each process on the way wakes up,
    /// reads, copies and writes it), and once for each demand reply by DMA and each scan
    /// line the fork node passes on to the host.
    pub hop_ns: u64,
    /// The host sends the job to the nodes one after another: the k-th render node (in id
    /// order) may begin `k * job_stagger_ns` after the first.
    pub job_stagger_ns: u64,
}

impl SimConfig {
    /// No link delays, demand transfer with a cache holding the whole scene, the recorded
    /// subscreens.
    pub fn new(topology: Topology) -> SimConfig {
        SimConfig {
            topology,
            link: LinkModelKind::None,
            time_scale: 1.0,
            transfer: Transfer::Demand {
                cache_bytes: u64::MAX,
                via: protocol::Transfer::Dma,
            },
            balance: Balance::AsRecorded,
            adaptive: false,
            cpu_scale: 1.0,
            overheads: Overheads::default(),
            machines: Vec::new(),
        }
    }
}

/// Why a simulation cannot run.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    Workload(#[from] WorkloadError),
    #[error("invalid link model: {0}")]
    Model(#[from] ModelError),
    #[error("cpu_scale must be a positive number, not {0}")]
    CpuScale(f64),
    #[error("the number of subscreens must be at least 1")]
    NoSubscreens,
    #[error(
        "a cache of {cache_bytes} bytes cannot hold the largest item ({largest} bytes); the real render refuses it too"
    )]
    CacheTooSmall { cache_bytes: u64, largest: u64 },
    #[error("a machine limit names node {0}, which is not a render node of the topology")]
    NotARenderNode(NodeId),
    #[error("render node {0} is on two machines")]
    TwoMachines(NodeId),
    #[error("a machine that lets none of its render nodes work at once would never finish")]
    NoneAtWork,
}

/// One render node's time, split three ways; they add up to the total time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NodeTimes {
    pub node: NodeId,
    /// Rendering.
    pub busy_s: f64,
    /// Blocked on data: a cache miss, or the batch handout before it starts.
    pub waiting_s: f64,
    /// Waiting for the host's answer, or for the end once there is no more work.
    pub idle_s: f64,
    pub subscreens: u32,
    pub rows: u64,
    pub fetches: u64,
    pub fetched_bytes: u64,
    pub evictions: u64,
}

/// Bytes of scene data moved, by the path they took.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BytesByPath {
    /// Demand misses answered by DMA from the card's fork node.
    pub dma: u64,
    /// Demand misses answered through the mesh.
    pub mesh: u64,
    /// Between cards' memories over the G-bus (demand misses and batch handout).
    pub gbus: u64,
    /// The batch handout's DMA to every render node.
    pub batch: u64,
}

/// The prediction.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SimResult {
    pub total_s: f64,
    pub total_ns: u64,
    pub render_nodes: usize,
    /// Subscreens handed out, counting those split off by adaptive redivision.
    pub subscreens: u32,
    pub subscreens_split: u32,
    /// Demand fetches (cache misses served).
    pub transfers: u64,
    pub bytes: BytesByPath,
    /// Messages through the mesh and their wire bytes (requests, answers, data, pixels).
    pub messages: u64,
    pub mesh_wire_bytes: u64,
    /// Events processed: a measure of the simulation's own work.
    pub events: u64,
    pub nodes: Vec<NodeTimes>,
    /// Per subscreen handed out, in id order (the workload's, then those split off): when the
    /// host handed it out and when its last row reached the fork node, in ns.
    pub spans_ns: Vec<(u64, u64)>,
}

/// Predicts the render of `workload` under `config`, event by event.
pub fn simulate(workload: &Workload, config: &SimConfig) -> Result<SimResult, SimError> {
    workload.check()?;
    if !(config.cpu_scale.is_finite() && config.cpu_scale > 0.0) {
        return Err(SimError::CpuScale(config.cpu_scale));
    }
    let params = fabric::model::ModelParams {
        link: config.link,
        time_scale: config.time_scale,
        ..config.topology.model.clone()
    };
    params.check()?;
    if let Transfer::Demand { cache_bytes, .. } = config.transfer {
        let largest = workload.largest_item();
        if cache_bytes < largest {
            return Err(SimError::CacheTooSmall {
                cache_bytes,
                largest,
            });
        }
    }
    let mut on_machine = std::collections::HashSet::new();
    for m in &config.machines {
        if m.at_work == 0 {
            return Err(SimError::NoneAtWork);
        }
        for &node in &m.nodes {
            if (node as usize) >= config.topology.len()
                || config.topology.role(node) != protocol::Role::Render
            {
                return Err(SimError::NotARenderNode(node));
            }
            if !on_machine.insert(node) {
                return Err(SimError::TwoMachines(node));
            }
        }
    }
    let render_nodes = config.topology.render_nodes().len() as u32;
    let divided;
    let work = match config.balance {
        Balance::AsRecorded => workload,
        Balance::Static => {
            divided = workload.divided(render_nodes)?;
            &divided
        }
        Balance::Dynamic { subscreens: 0 } => return Err(SimError::NoSubscreens),
        Balance::Dynamic { subscreens } => {
            divided = workload.divided(subscreens)?;
            &divided
        }
    };
    Ok(engine::run(work, config, fabric::Model::new(params)))
}
