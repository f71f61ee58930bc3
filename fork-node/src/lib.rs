//! The fork node role (the paper's FP): one per card.
//!
//! The first fork node (the paper's FP (0,-1)) receives the scene from the host, prepares it
//! (chunks, both BVH levels, lights, texture tiles), places the chunks and tiles across all
//! fork nodes' shared memories and sends every fork node the header and address table; the
//! shares of the cards on its own machine it writes as their shared-memory segments itself.
//! Each fork node then gives the render nodes of its card the scene minus shape and texture data,
//! by DMA; serves their demand requests by serial link or DMA, reading other cards' memories
//! over the G-bus; and writes the pixel rows they send into the host's frame buffer. The
//! first fork node also arbitrates the two G-buses for everyone.
//!
//! When a fork node is lost, the host sends the live ones the items it held and a new
//! address table (as more `Hold`s and a `Header`); the first live fork node arbitrates the
//! buses, and each serves, besides its own card, the render nodes of lost cards that
//! [`fabric::Topology::serving_fork`] gives it.
//!
//! The node's life (joining, stopping, losing the host) is [`fabric::role::run_role`]'s.
//! What is left is split by job, each with the state only it locks:
//!
//! * `assembly`: the first fork node's scene parts, their preparation and placement.
//! * `memory`: this card's shared memory, as the header and held items arrive.
//! * `handout`: giving the card's render nodes the header, and for a batch job all data.
//! * `serving`: demand requests, and the card's DMA bus timing.
//! * `gbus`: reads from other cards' memories and, on the first fork node, bus arbitration.
//! * `segment`: the card's memory published as a shared-memory segment for render nodes on
//!   this machine (on the first fork node, every card's on its machine), and other cards'
//!   announcements passed on.
//!
//! Pixel rows need no state: they are passed on to the host as they come.

mod assembly;
mod gbus;
mod handout;
mod memory;
mod segment;
mod serving;

use std::sync::{Arc, Mutex, atomic::Ordering};

use fabric::{
    Fabric, Route, Via,
    cluster::JoinConfig,
    role::{RoleError, RoleHandler, run_role},
};
use protocol::{Frame, Message, NodeStats, Role, words_to_bytes};

use assembly::SceneAssembly;
use gbus::GBus;
use handout::Handout;
use memory::SharedMemory;
use segment::{Announced, SegmentSlot, SharesInSegments};
use serving::Serving;

pub struct Config {
    pub join: JoinConfig,
}

/// Runs a fork node until the host says stop or goes away.
pub async fn run(config: Config) -> Result<(), RoleError> {
    let segment = SegmentSlot::default();
    let slot = segment.clone();
    let ended = run_role(config.join, |fabric| Handler {
        node: Arc::new(ForkNode::new(fabric.clone(), slot)),
    })
    .await;
    // The segments this node wrote go with it; render nodes keep their mappings.
    segment.lock().expect("segment lock").clear();
    ended
}

/// A fork node's state, one part per job. It is shared with the tasks that serve requests
/// and place the scene, so each part locks only what its own job touches.
struct ForkNode {
    fabric: Fabric,
    assembly: Mutex<SceneAssembly>,
    memory: Mutex<SharedMemory>,
    handout: Handout,
    serving: Serving,
    gbus: GBus,
    /// The shared-memory segments this node wrote: its card's memory, and on the first fork
    /// node the other cards' on its machine.
    segment: SegmentSlot,
    /// What this card's render nodes are told of segments.
    announced: Mutex<Announced>,
    /// On the first fork node: segments written for other cards, until their fork nodes
    /// answer.
    shares: Mutex<SharesInSegments>,
}

impl ForkNode {
    fn new(fabric: Fabric, segment: SegmentSlot) -> ForkNode {
        ForkNode {
            segment,
            announced: Mutex::default(),
            shares: Mutex::default(),
            assembly: Mutex::default(),
            memory: Mutex::default(),
            handout: Handout::default(),
            serving: Serving::default(),
            gbus: GBus::new(fabric.model().params.gbus_count),
            fabric,
        }
    }
}

/// The role's side of the shared loop: hands each message to the job it belongs to.
struct Handler {
    node: Arc<ForkNode>,
}

impl RoleHandler for Handler {
    const NAME: &'static str = "fork node";

    fn on_message(&mut self, frame: Frame, message: Message, via: Via) {
        self.node.clone().dispatch(frame, message, via);
    }
}

impl ForkNode {
    fn dispatch(self: Arc<ForkNode>, frame: Frame, msg: Message, via: Via) {
        let f = self.fabric.clone();
        match msg {
            // Only the host sends the scene, and only to the first fork node.
            Message::ScenePart {
                part,
                parts,
                total,
                len,
                chunk_triangles,
            } if via == Via::Direct(0) => {
                let of = assembly::PartOf {
                    parts,
                    total,
                    chunk_triangles,
                };
                self.on_scene_part(frame, part, of, len)
            }
            Message::Header {
                len,
                chunk_owner,
                tile_owner,
            } => {
                let Some(bytes) = words_to_bytes(&frame.data, len as usize) else {
                    tracing::warn!("short scene header from node {}", frame.header.sender);
                    return;
                };
                self.on_header(bytes.to_vec(), chunk_owner, tile_owner);
            }
            Message::Hold { id } => self.on_hold(id, frame.data),
            Message::HoldDone { count } => {
                self.memory.lock().expect("memory lock").expected = Some(count);
                self.maybe_ready();
            }
            Message::Job(job) => {
                self.handout.set_job(*job);
                self.maybe_ready();
            }
            Message::DataRequest {
                id,
                transfer,
                owner,
            } => {
                tokio::spawn(
                    async move { self.serve_request(frame, id, transfer, owner, true).await },
                );
            }
            // The render node reads the bytes from a shared segment; it needs only the time.
            Message::SharedRead { id, owner } => {
                tokio::spawn(async move {
                    self.serve_request(frame, id, protocol::Transfer::Dma, owner, false)
                        .await
                });
            }
            Message::ShareInSegment { count, segments } => {
                if let Via::Direct(from) = via {
                    self.on_share_in_segment(from, count, segments);
                }
            }
            Message::ShareAnswer { adopted } => {
                if let Via::Direct(from) = via {
                    self.on_share_answer(from, adopted);
                }
            }
            Message::SharedSegment(_) => {
                if let Via::Direct(from) = via {
                    self.relay_segment(from, &msg);
                }
            }
            Message::RemoteRead { id, .. } => {
                tokio::spawn(async move {
                    let deadline = std::time::Instant::now() + serving::REBUILD_WAIT;
                    let data = self.held(id, deadline).await.unwrap_or_default();
                    let _ = f.reply(
                        &frame,
                        &Message::RemoteData { id, done_ns: 0 },
                        data,
                        Route::Direct,
                        0,
                    );
                });
            }
            Message::BusRequest { bytes, ready_ns } => {
                let done_ns = self.gbus.book(f.model(), bytes as u64, ready_ns);
                let _ = f.reply(
                    &frame,
                    &Message::BusGrant { done_ns },
                    Box::new([]),
                    Route::Direct,
                    0,
                );
            }
            Message::Pixels { .. } => {
                // Into the frame buffer, which the host holds, over the G-bus.
                let _ = f.send_direct(0, &msg, frame.data, 0, 0);
            }
            Message::StatsRequest => {
                let _ = f.send_control(0, &Message::NodeStats(Box::new(self.stats())));
            }
            other => tracing::debug!("fork node {} ignores {}", f.me(), other.name()),
        }
    }

    fn stats(&self) -> NodeStats {
        let c = self.fabric.counters();
        NodeStats {
            node: self.fabric.me(),
            role: Some(Role::Fork),
            bytes_served: self.serving.bytes_served.load(Ordering::Relaxed),
            bytes_gbus: self.gbus.bytes_read.load(Ordering::Relaxed),
            frames_forwarded: c.frames_forwarded,
            frames_around_mesh: c.frames_around_mesh,
            bytes_forwarded: c.bytes_forwarded,
            peak_rss_bytes: fabric::peak_rss_bytes(),
            peak_private_bytes: fabric::private_rss_bytes(),
            share_items_in_segment: self.memory.lock().expect("memory lock").adopted_items() as u64,
            ..NodeStats::default()
        }
    }
}
