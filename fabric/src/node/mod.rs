//! The network runtime of one process: its connections, forwarding, and delivery.
//!
//! Every process has one listening port. Connections to it start with the handshake, whose
//! identity says what they are: a mesh link from a neighbour, a direct (DMA or G-bus)
//! connection, or (at the host) a node's control connection. Each connection gets a reader
//! task and a writer task; frames for other nodes are forwarded at once, store-and-forward,
//! on this runtime, which never runs rendering, so rendering never starves forwarding (the
//! paper's high-priority communication process).
//!
//! The delay model is applied here and only here: a frame's header carries the model times
//! at which its first and last packets are ready at the far end of the last link crossed;
//! each link crossed advances them by that link's own model clock ([`LinkClock`]), and the
//! final receiver holds the frame until its last packet's time has come. Real forwarding
//! costs hide inside the modelled times instead of adding to them.
//!
//! The runtime has five jobs, one submodule each:
//! * `links`: the connections themselves (reader and writer tasks, heartbeats, the link
//!   model applied on each mesh link crossed, model times on the wire), and which links a
//!   node has in a topology.
//! * `accept`: taking connections (handshake, checking the caller's claim) and opening them.
//! * `forward`: sending, forwarding and broadcasting frames around the mesh, routing around
//!   dead nodes, and handing frames to the role code when their model time comes.
//! * `requests`: requests that wait for their answer, and sending them again when routes
//!   change.
//! * this file: the types they share and the [`Fabric`] handle.

mod accept;
mod forward;
mod links;
mod requests;

use std::{
    collections::HashMap,
    sync::{
        Arc, Mutex, RwLock,
        atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering},
    },
    time::Duration,
};

use protocol::{ConnectionKind, Frame, FrameReader, FrameWriter, Identity, NodeId, Role, Secret};
use tokio::sync::mpsc;

pub use accept::DialError;
pub use links::{dials, expected_direct};

use crate::{
    clock::PreciseTimer,
    model::{LinkClock, Model},
    routing::Routes,
    topology::Topology,
};

/// Header flag: the model times are relative to the frame's arrival (the link crosses
/// machines whose monotonic clocks differ).
pub const FLAG_RELATIVE_TIMES: u8 = 2;
/// Header flag: this frame answers the request with the same tag.
pub const FLAG_REPLY: u8 = 4;

/// Most connections a process lets sit in the handshake at once, in a cluster of up to as
/// many nodes; a larger one allows one per node (see [`pending_handshakes_allowed`]).
pub const MAX_PENDING_HANDSHAKES: usize = 256;

/// How many connections may be in the host's handshake at once in a cluster of `nodes` nodes. At
/// formation every node calls the host at about the same time: `magg1000`'s 1051 processes,
/// spawned on a loaded 2-core machine, had more than 256 handshakes waiting there, and the
/// host closed the rest, which ended the render ("a spawned render node exited before the
/// cluster formed"). Unauthenticated connections stay bounded, by the cluster's own size.
pub fn pending_handshakes_allowed(nodes: usize) -> usize {
    MAX_PENDING_HANDSHAKES.max(nodes.saturating_add(1))
}

/// A connection with nothing to send for this long sends a heartbeat, so the far end can
/// tell a quiet peer from a vanished one (a machine switched off or cut from the network
/// closes nothing).
pub const HEARTBEAT_INTERVAL: Duration = Duration::from_secs(1);
/// A control connection silent for this long is lost: the host declares the node dead, a
/// node declares the host gone. Generous against a busy machine's scheduling delays, short
/// enough that a vanished host lets its nodes exit within 10 seconds.
pub const CONTROL_SILENCE_LIMIT: Duration = Duration::from_secs(5);
/// A mesh or direct connection silent for this long is dropped. Only the host decides that
/// a node is dead, so this is longer: it only bounds what a silent peer can hold.
pub const LINK_SILENCE_LIMIT: Duration = Duration::from_secs(10);
/// Which way a frame travels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Route {
    /// Hop by hop through the mesh (serial links).
    Mesh,
    /// Over the direct connection to the peer (DMA or G-bus).
    Direct,
    /// Over the control connection between a node and the host (no model time: what travels
    /// there is outside the paper's machine, or chosen to bypass it).
    Control,
}

impl Route {
    /// The route that answers a request that came `via` this way: a request over a control
    /// connection is answered there, any other through the mesh.
    pub fn back(via: Via) -> Route {
        match via {
            Via::Control(_) => Route::Control,
            Via::Mesh(_) | Via::Direct(_) => Route::Mesh,
        }
    }
}

/// How a frame reached this process.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Via {
    Mesh(NodeId),
    Direct(NodeId),
    Control(NodeId),
}

/// What the runtime hands to the role code.
pub enum Delivery {
    Frame {
        frame: Frame,
        via: Via,
    },
    /// A connection to a peer broke (`reason` says how: closed, silent, an error).
    Lost {
        peer: NodeId,
        kind: ConnectionKind,
        reason: String,
    },
    /// A new connection of `kind` from a peer without a node id yet (the host's
    /// registrations), with its halves.
    Incoming {
        identity: Identity,
        reader: FrameReader<tokio::net::tcp::OwnedReadHalf>,
        writer: FrameWriter<tokio::net::tcp::OwnedWriteHalf>,
    },
}

impl std::fmt::Debug for Delivery {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Delivery::Frame { frame, via } => write!(
                f,
                "Frame(kind {} from {} via {via:?})",
                frame.header.kind, frame.header.sender
            ),
            Delivery::Lost { peer, kind, reason } => write!(f, "Lost({peer}, {kind:?}: {reason})"),
            Delivery::Incoming { identity, .. } => write!(f, "Incoming({identity:?})"),
        }
    }
}

/// Declares the counters once: the live atomic set (`Counters`), its plain copy
/// (`CounterSnapshot`) and the copying between them, so a counter cannot be added to one
/// and forgotten in the other.
macro_rules! counters {
    ($($(#[$doc:meta])* $name:ident,)*) => {
        /// Counters of what passed through this process.
        #[derive(Default, Debug)]
        pub struct Counters {
            $($(#[$doc])* pub $name: AtomicU64,)*
        }

        /// The counters at one moment.
        #[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
        pub struct CounterSnapshot {
            $($(#[$doc])* pub $name: u64,)*
        }

        impl Counters {
            fn snapshot(&self) -> CounterSnapshot {
                CounterSnapshot {
                    $($name: self.$name.load(Ordering::Relaxed),)*
                }
            }
        }
    };
}

counters! {
    frames_sent,
    frames_forwarded,
    bytes_forwarded,
    frames_delivered,
    bytes_mesh_out,
    bytes_direct_out,
    frames_dropped,
    connections_refused,
    /// Frames sent on a direct or control connection because the mesh had no route.
    frames_around_mesh,
}

/// One connection's sending end, as the rest of the runtime sees it.
struct Peer {
    tx: mpsc::UnboundedSender<Frame>,
    clock: Mutex<LinkClock>,
    /// Same machine (shared monotonic clock) or not.
    same_clock: bool,
}

pub(crate) struct Inner {
    pub me: NodeId,
    pub role: Role,
    pub topology: Arc<Topology>,
    pub model: Model,
    pub timer: PreciseTimer,
    pub secret: Secret,
    pub cluster_id: String,
    routes: RwLock<Routes>,
    mesh: Mutex<HashMap<NodeId, Arc<Peer>>>,
    direct: Mutex<HashMap<NodeId, Arc<Peer>>>,
    control: Mutex<HashMap<NodeId, Arc<Peer>>>,
    same_machine: Mutex<HashMap<NodeId, bool>>,
    inbox: mpsc::UnboundedSender<Delivery>,
    pub counters: Counters,
    closing: AtomicBool,
    pending: Mutex<HashMap<u32, requests::Pending>>,
    next_tag: AtomicU32,
}

impl Inner {
    /// The open connections of `kind`, by peer.
    fn table(&self, kind: ConnectionKind) -> &Mutex<HashMap<NodeId, Arc<Peer>>> {
        match kind {
            ConnectionKind::Mesh => &self.mesh,
            ConnectionKind::Direct => &self.direct,
            ConnectionKind::Control => &self.control,
        }
    }

    /// Adds one to a counter.
    fn count(&self, counter: impl Fn(&Counters) -> &AtomicU64) {
        counter(&self.counters).fetch_add(1, Ordering::Relaxed);
    }
}

/// A handle on this process's fabric runtime. Cheap to clone.
#[derive(Clone)]
pub struct Fabric {
    pub(crate) inner: Arc<Inner>,
}

#[derive(Debug, thiserror::Error)]
pub enum RequestError {
    #[error("{0}")]
    Send(#[from] SendError),
    #[error("no answer from node {peer} within {seconds} s")]
    Timeout { peer: NodeId, seconds: u64 },
    #[error("the connection to node {0} closed before it answered")]
    Closed(NodeId),
}

#[derive(Debug, thiserror::Error)]
pub enum SendError {
    #[error("no route from node {from} to node {to}")]
    NoRoute { from: NodeId, to: NodeId },
    #[error("no {kind:?} connection to node {peer}")]
    NotConnected { peer: NodeId, kind: ConnectionKind },
}

impl Fabric {
    pub(crate) fn new(
        me: NodeId,
        role: Role,
        topology: Arc<Topology>,
        secret: Secret,
        cluster_id: String,
    ) -> (Fabric, mpsc::UnboundedReceiver<Delivery>) {
        let (tx, rx) = mpsc::unbounded_channel();
        let routes = Routes::all_alive(&topology);
        let model = Model::new(topology.model.clone());
        let inner = Inner {
            me,
            role,
            topology,
            model,
            timer: PreciseTimer::new(),
            secret,
            cluster_id,
            routes: RwLock::new(routes),
            mesh: Mutex::new(HashMap::new()),
            direct: Mutex::new(HashMap::new()),
            control: Mutex::new(HashMap::new()),
            same_machine: Mutex::new(HashMap::new()),
            inbox: tx,
            counters: Counters::default(),
            closing: AtomicBool::new(false),
            pending: Mutex::new(HashMap::new()),
            next_tag: AtomicU32::new(1),
        };
        (
            Fabric {
                inner: Arc::new(inner),
            },
            rx,
        )
    }

    pub fn me(&self) -> NodeId {
        self.inner.me
    }

    pub fn role(&self) -> Role {
        self.inner.role
    }

    pub fn topology(&self) -> &Topology {
        &self.inner.topology
    }

    pub fn model(&self) -> &Model {
        &self.inner.model
    }

    pub fn timer(&self) -> &PreciseTimer {
        &self.inner.timer
    }

    pub fn counters(&self) -> CounterSnapshot {
        self.inner.counters.snapshot()
    }

    /// Stops reporting lost connections (the process is shutting down on purpose).
    pub fn begin_shutdown(&self) {
        self.inner.closing.store(true, Ordering::Relaxed);
        self.inner.timer.stop();
    }

    /// Closes and drops every connection: peers see each one end once the frames queued on
    /// it are written.
    pub fn hang_up(&self) {
        self.begin_shutdown();
        self.inner.mesh.lock().expect("lock").clear();
        self.inner.direct.lock().expect("lock").clear();
        self.inner.control.lock().expect("lock").clear();
    }

    pub fn is_closing(&self) -> bool {
        self.inner.closing.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every node of a cluster may be in its handshake with the host at once: the largest
    /// preset's too (it had 256 places for 1051 nodes), and small clusters keep the floor.
    #[test]
    fn every_node_of_a_cluster_may_handshake_at_once() {
        for name in ["tiny", "magg", "magg1000"] {
            let t = crate::Topology::preset(name).unwrap();
            let allowed = pending_handshakes_allowed(t.len());
            assert!(allowed > t.len(), "{name}: {allowed} for {} nodes", t.len());
            assert!(allowed >= MAX_PENDING_HANDSHAKES, "{name}");
        }
        assert_eq!(pending_handshakes_allowed(usize::MAX), usize::MAX);
    }
}
