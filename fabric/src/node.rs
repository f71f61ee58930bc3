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

use std::{
    collections::HashMap,
    net::SocketAddr,
    sync::{
        Arc, Mutex, RwLock,
        atomic::{AtomicBool, AtomicU64, Ordering},
    },
    time::Duration,
};

use protocol::{
    BROADCAST, ConnectionKind, Frame, FrameReader, FrameWriter, Identity, Message, NodeId, Role,
    Secret, frame::Mode, handshake,
};
use tokio::{
    net::{TcpListener, TcpStream},
    sync::mpsc,
};

use crate::{
    clock::{PreciseTimer, now_ns},
    model::{LinkClock, Model},
    routing::Routes,
    topology::Topology,
};

/// Header flag: the model times are relative to the frame's arrival (the link crosses
/// machines whose monotonic clocks differ).
pub const FLAG_RELATIVE_TIMES: u8 = 2;
/// Header flag: this frame answers the request with the same tag.
pub const FLAG_REPLY: u8 = 4;

/// Most connections a process lets sit in the handshake at once.
pub const MAX_PENDING_HANDSHAKES: usize = 256;

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
/// When routes change, requests still waiting for an answer are sent again now and after
/// these delays: the first copy may have been lost in the dead node, and a node on the way
/// may learn of the death a little later than the sender.
const RESEND_AFTER: [Duration; 3] = [
    Duration::ZERO,
    Duration::from_millis(300),
    Duration::from_millis(1500),
];

/// Which way a frame travels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Route {
    /// Hop by hop through the mesh (serial links).
    Mesh,
    /// Over the direct connection to the peer (DMA or G-bus).
    Direct,
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

/// A request waiting for its answer.
struct Pending {
    answer: tokio::sync::oneshot::Sender<Frame>,
    /// A copy to send again when routes change (mesh requests only: a direct connection
    /// has no route to change).
    resend: Option<Frame>,
}

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
    pending: Mutex<HashMap<u32, Pending>>,
    next_tag: std::sync::atomic::AtomicU32,
}

/// Why a connection to a peer could not be made.
#[derive(Debug, thiserror::Error)]
pub enum DialError {
    #[error("cannot reach node {peer} at {addr}: {source}")]
    Unreachable {
        peer: NodeId,
        addr: String,
        source: std::io::Error,
    },
    #[error("node {peer} at {addr}: {source}")]
    Handshake {
        peer: NodeId,
        addr: String,
        source: handshake::HandshakeError,
    },
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
            next_tag: std::sync::atomic::AtomicU32::new(1),
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

    /// Records whether `peer` shares this machine's monotonic clock.
    pub fn set_same_machine(&self, peer: NodeId, same: bool) {
        self.inner
            .same_machine
            .lock()
            .expect("lock")
            .insert(peer, same);
    }

    fn same_machine(&self, peer: NodeId) -> bool {
        self.inner
            .same_machine
            .lock()
            .expect("lock")
            .get(&peer)
            .copied()
            .unwrap_or(true)
    }

    /// Marks nodes dead or alive and recomputes routes around the dead ones.
    pub fn set_alive(&self, alive: &[bool]) {
        let routes = Routes::compute(&self.inner.topology, alive);
        *self.inner.routes.write().expect("routes lock") = routes;
    }

    pub fn is_alive(&self, id: NodeId) -> bool {
        self.inner.routes.read().expect("routes lock").is_alive(id)
    }

    /// Sends `message` (and `data`) to node `to` through the mesh.
    pub fn send(
        &self,
        to: NodeId,
        message: &Message,
        data: Box<[u32]>,
        tag: u32,
    ) -> Result<(), SendError> {
        let frame = Frame::new(self.inner.me, to, message, data).with_tag(tag);
        self.send_frame(frame, 0)
    }

    /// Sends to every node through the broadcast spanning tree rooted here.
    pub fn broadcast(&self, message: &Message, data: Box<[u32]>) {
        let _ = self.send(BROADCAST, message, data, 0);
    }

    /// Like [`Fabric::send`], for a message whose data is only ready at model time
    /// `ready_ns` (sent now, stamped as if sent then).
    pub fn send_at(
        &self,
        to: NodeId,
        message: &Message,
        data: Box<[u32]>,
        tag: u32,
        flags: u8,
        ready_ns: u64,
    ) -> Result<(), SendError> {
        let mut frame = Frame::new(self.inner.me, to, message, data).with_tag(tag);
        frame.header.flags |= flags;
        self.send_frame(frame, ready_ns)
    }

    /// Stamps a frame leaving this node at model time `ready_ns` (or now) and sends it on
    /// its first link: towards its receiver, or down the broadcast tree.
    fn send_frame(&self, mut frame: Frame, ready_ns: u64) -> Result<(), SendError> {
        self.inner
            .counters
            .frames_sent
            .fetch_add(1, Ordering::Relaxed);
        if self.inner.model.links_delayed() {
            let ready = ready_ns.max(now_ns()) + self.inner.model.base_ns();
            frame.header.first_ns = ready;
            frame.header.last_ns = ready;
        }
        let to = frame.header.receiver;
        if to == self.inner.me {
            self.deliver(frame, Via::Mesh(self.inner.me));
            return Ok(());
        }
        if to == BROADCAST {
            for child in self.broadcast_children(self.inner.me) {
                self.send_on_link(child, frame.clone());
            }
            return Ok(());
        }
        let next = self
            .inner
            .routes
            .read()
            .expect("routes lock")
            .next_hop(self.inner.me, to);
        match next {
            Some(n) => {
                self.send_on_link(n, frame);
                Ok(())
            }
            None => self.send_around_the_mesh(frame),
        }
    }

    /// When lost nodes have cut the mesh between here and `frame`'s receiver, the frame
    /// takes a direct or control connection to it instead, if there is one (a render node
    /// has both to the host and to its fork node): a hole in the mesh then slows nothing
    /// that matters. Such a frame is outside the link model, so it carries no model times.
    fn send_around_the_mesh(&self, mut frame: Frame) -> Result<(), SendError> {
        let to = frame.header.receiver;
        frame.header.first_ns = 0;
        frame.header.last_ns = 0;
        let direct = self.inner.direct.lock().expect("lock").get(&to).cloned();
        let peer = direct.or_else(|| self.inner.control.lock().expect("lock").get(&to).cloned());
        match peer {
            Some(p) => {
                self.inner
                    .counters
                    .frames_around_mesh
                    .fetch_add(1, Ordering::Relaxed);
                let _ = p.tx.send(frame);
                Ok(())
            }
            None => Err(SendError::NoRoute {
                from: self.inner.me,
                to,
            }),
        }
    }

    /// Sends a request and waits for the frame that answers it (same tag, reply flag). A
    /// mesh request is sent again when routes change, so the receiver must treat a repeated
    /// tag from the same sender as the same request.
    pub async fn request(
        &self,
        to: NodeId,
        message: &Message,
        data: Box<[u32]>,
        route: Route,
        timeout: Duration,
    ) -> Result<Frame, RequestError> {
        let tag = self.inner.next_tag.fetch_add(1, Ordering::Relaxed).max(1);
        let (tx, rx) = tokio::sync::oneshot::channel();
        let frame = Frame::new(self.inner.me, to, message, data).with_tag(tag);
        let resend = (route == Route::Mesh).then(|| frame.clone());
        self.inner
            .pending
            .lock()
            .expect("lock")
            .insert(tag, Pending { answer: tx, resend });
        let sent = match route {
            Route::Mesh => self.send_frame(frame, 0),
            Route::Direct => self.send_direct_frame(to, frame),
        };
        if let Err(e) = sent {
            self.inner.pending.lock().expect("lock").remove(&tag);
            return Err(e.into());
        }
        match tokio::time::timeout(timeout, rx).await {
            Ok(Ok(frame)) => Ok(frame),
            Ok(Err(_)) => Err(RequestError::Closed(to)),
            Err(_) => {
                self.inner.pending.lock().expect("lock").remove(&tag);
                Err(RequestError::Timeout {
                    peer: to,
                    seconds: timeout.as_secs(),
                })
            }
        }
    }

    /// Declares `node` dead: routes go around it from now on, and requests waiting for
    /// answers are sent again in case they or their answers were lost in it. Returns false
    /// if it was already known dead.
    pub fn mark_dead(&self, node: NodeId) -> bool {
        {
            let mut routes = self.inner.routes.write().expect("routes lock");
            if !routes.is_alive(node) || node == self.inner.me {
                return false;
            }
            let mut alive = routes.alive().to_vec();
            alive[node as usize] = false;
            *routes = Routes::compute(&self.inner.topology, &alive);
        }
        let me = self.clone();
        tokio::spawn(async move {
            for delay in RESEND_AFTER {
                tokio::time::sleep(delay).await;
                let frames: Vec<Frame> = me
                    .inner
                    .pending
                    .lock()
                    .expect("lock")
                    .values()
                    .filter_map(|p| p.resend.clone())
                    .collect();
                for f in frames {
                    let _ = me.send_frame(f, 0);
                }
            }
        });
        true
    }

    /// Answers `request` (a frame from another node) with `message` and `data`, usable by
    /// the requester from model time `ready_ns` (0: as soon as it arrives).
    pub fn reply(
        &self,
        request: &Frame,
        message: &Message,
        data: Box<[u32]>,
        route: Route,
        ready_ns: u64,
    ) -> Result<(), SendError> {
        let to = request.header.sender;
        let tag = request.header.tag;
        match route {
            Route::Mesh => self.send_at(to, message, data, tag, FLAG_REPLY, ready_ns),
            Route::Direct => {
                let mut frame = Frame::new(self.inner.me, to, message, data).with_tag(tag);
                frame.header.flags |= FLAG_REPLY;
                frame.header.first_ns = ready_ns;
                frame.header.last_ns = ready_ns;
                self.send_direct_frame(to, frame)
            }
        }
    }

    fn broadcast_children(&self, root: NodeId) -> Vec<NodeId> {
        self.inner
            .routes
            .read()
            .expect("routes lock")
            .broadcast_children(self.inner.me, root)
            .to_vec()
    }

    /// Sends a frame over a direct (DMA or G-bus) connection. `ready_ns`, when not 0, is the
    /// model time at which the receiver may use it (the role computes DMA and bus times).
    pub fn send_direct(
        &self,
        peer: NodeId,
        message: &Message,
        data: Box<[u32]>,
        tag: u32,
        ready_ns: u64,
    ) -> Result<(), SendError> {
        let mut frame = Frame::new(self.inner.me, peer, message, data).with_tag(tag);
        frame.header.first_ns = ready_ns;
        frame.header.last_ns = ready_ns;
        self.send_direct_frame(peer, frame)
    }

    fn send_direct_frame(&self, peer: NodeId, frame: Frame) -> Result<(), SendError> {
        self.inner
            .counters
            .frames_sent
            .fetch_add(1, Ordering::Relaxed);
        let p = self.inner.direct.lock().expect("lock").get(&peer).cloned();
        match p {
            Some(p) => {
                self.inner
                    .counters
                    .bytes_direct_out
                    .fetch_add(frame.wire_len() as u64, Ordering::Relaxed);
                let frame = self.to_wire_times(frame, p.same_clock);
                let _ = p.tx.send(frame);
                Ok(())
            }
            None => Err(SendError::NotConnected {
                peer,
                kind: ConnectionKind::Direct,
            }),
        }
    }

    /// Sends on a control connection (a node to the host, or the host to a node).
    pub fn send_control(&self, peer: NodeId, message: &Message) -> Result<(), SendError> {
        let frame = Frame::new(self.inner.me, peer, message, Box::new([]));
        let p = self.inner.control.lock().expect("lock").get(&peer).cloned();
        match p {
            Some(p) => {
                let _ = p.tx.send(frame);
                Ok(())
            }
            None => Err(SendError::NotConnected {
                peer,
                kind: ConnectionKind::Control,
            }),
        }
    }

    pub fn has_direct(&self, peer: NodeId) -> bool {
        self.inner.direct.lock().expect("lock").contains_key(&peer)
    }

    pub fn mesh_links_up(&self) -> usize {
        self.inner.mesh.lock().expect("lock").len()
    }

    pub fn direct_links_up(&self) -> usize {
        self.inner.direct.lock().expect("lock").len()
    }

    /// Stamps a frame with the model times of crossing the link to `neighbor`, and sends it.
    fn send_on_link(&self, neighbor: NodeId, mut frame: Frame) {
        let p = self
            .inner
            .mesh
            .lock()
            .expect("lock")
            .get(&neighbor)
            .cloned();
        let Some(p) = p else {
            tracing::debug!(
                "no link to node {neighbor}; frame for {} dropped",
                frame.header.receiver
            );
            self.inner
                .counters
                .frames_dropped
                .fetch_add(1, Ordering::Relaxed);
            return;
        };
        let model = &self.inner.model;
        if model.links_delayed() {
            let (packets, size) = model.packets(frame.wire_len());
            let hop = model.hop_ns(
                self.inner.topology.is_vertical(self.inner.me, neighbor),
                size,
            );
            let (first, last) = p.clock.lock().expect("lock").cross(
                frame.header.first_ns,
                frame.header.last_ns,
                packets,
                hop,
            );
            frame.header.first_ns = first;
            frame.header.last_ns = last;
        }
        self.inner
            .counters
            .bytes_mesh_out
            .fetch_add(frame.wire_len() as u64, Ordering::Relaxed);
        let frame = self.to_wire_times(frame, p.same_clock);
        let _ = p.tx.send(frame);
    }

    /// Model times cross machines as "so long after arrival"; on one machine they stay absolute.
    fn to_wire_times(&self, mut frame: Frame, same_clock: bool) -> Frame {
        if !same_clock && frame.header.last_ns != 0 {
            let now = now_ns();
            frame.header.first_ns = frame.header.first_ns.saturating_sub(now).max(1);
            frame.header.last_ns = frame.header.last_ns.saturating_sub(now).max(1);
            frame.header.flags |= FLAG_RELATIVE_TIMES;
        }
        frame
    }

    fn from_wire_times(mut frame: Frame) -> Frame {
        if frame.header.flags & FLAG_RELATIVE_TIMES != 0 {
            let now = now_ns();
            frame.header.first_ns += now;
            frame.header.last_ns += now;
            frame.header.flags &= !FLAG_RELATIVE_TIMES;
        }
        frame
    }

    /// Hands a frame to the role code (or to the request it answers), once its model time
    /// has come.
    fn deliver(&self, frame: Frame, via: Via) {
        let deadline = frame.header.last_ns;
        let inner = self.inner.clone();
        if frame.header.flags & FLAG_REPLY != 0 {
            let waiter = inner
                .pending
                .lock()
                .expect("lock")
                .remove(&frame.header.tag);
            match waiter {
                Some(w) => {
                    let timer = inner.timer.clone();
                    tokio::spawn(async move {
                        timer.sleep_until(deadline).await;
                        inner
                            .counters
                            .frames_delivered
                            .fetch_add(1, Ordering::Relaxed);
                        let _ = w.answer.send(frame);
                    });
                }
                // A second answer to a request sent again, or one whose asker gave up.
                None => tracing::debug!(
                    "dropped an answer (tag {}) from node {} that nobody waits for",
                    frame.header.tag,
                    frame.header.sender
                ),
            }
            return;
        }
        if deadline > now_ns() {
            let timer = inner.timer.clone();
            tokio::spawn(async move {
                timer.sleep_until(deadline).await;
                inner
                    .counters
                    .frames_delivered
                    .fetch_add(1, Ordering::Relaxed);
                let _ = inner.inbox.send(Delivery::Frame { frame, via });
            });
        } else {
            inner
                .counters
                .frames_delivered
                .fetch_add(1, Ordering::Relaxed);
            let _ = inner.inbox.send(Delivery::Frame { frame, via });
        }
    }

    /// A frame arrived on a mesh link from `neighbor`: deliver it here, pass it on, or both.
    fn on_mesh_frame(&self, neighbor: NodeId, frame: Frame) {
        let mut frame = Fabric::from_wire_times(frame);
        frame.header.hops = frame.header.hops.saturating_add(1);
        if frame.header.hops > protocol::frame::MAX_HOPS {
            self.inner
                .counters
                .frames_dropped
                .fetch_add(1, Ordering::Relaxed);
            return;
        }
        let me = self.inner.me;
        match frame.header.mode {
            Mode::Broadcast => {
                let root = frame.header.sender;
                for child in self.broadcast_children(root) {
                    self.inner
                        .counters
                        .frames_forwarded
                        .fetch_add(1, Ordering::Relaxed);
                    self.inner
                        .counters
                        .bytes_forwarded
                        .fetch_add(frame.wire_len() as u64, Ordering::Relaxed);
                    self.send_on_link(child, frame.clone());
                }
                self.deliver(frame, Via::Mesh(neighbor));
            }
            Mode::OneToOne if frame.header.receiver == me => {
                self.deliver(frame, Via::Mesh(neighbor))
            }
            Mode::OneToOne => {
                let next = self
                    .inner
                    .routes
                    .read()
                    .expect("routes lock")
                    .next_hop(me, frame.header.receiver);
                match next {
                    Some(n) => {
                        self.inner
                            .counters
                            .frames_forwarded
                            .fetch_add(1, Ordering::Relaxed);
                        self.inner
                            .counters
                            .bytes_forwarded
                            .fetch_add(frame.wire_len() as u64, Ordering::Relaxed);
                        self.send_on_link(n, frame);
                    }
                    None => {
                        let (to, from) = (frame.header.receiver, frame.header.sender);
                        if self.send_around_the_mesh(frame).is_ok() {
                            return;
                        }
                        tracing::warn!("no route to node {to}; frame from {from} dropped");
                        self.inner
                            .counters
                            .frames_dropped
                            .fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }
    }

    /// Takes over an authenticated connection: starts its reader and writer.
    pub(crate) fn attach(
        &self,
        peer: NodeId,
        kind: ConnectionKind,
        mut reader: FrameReader<tokio::net::tcp::OwnedReadHalf>,
        mut writer: FrameWriter<tokio::net::tcp::OwnedWriteHalf>,
    ) {
        let (tx, mut rx) = mpsc::unbounded_channel::<Frame>();
        let same_clock = self.same_machine(peer);
        let p = Arc::new(Peer {
            tx,
            clock: Mutex::new(LinkClock::default()),
            same_clock,
        });
        let table = match kind {
            ConnectionKind::Mesh => &self.inner.mesh,
            ConnectionKind::Direct => &self.inner.direct,
            ConnectionKind::Control => &self.inner.control,
        };
        table.lock().expect("lock").insert(peer, p);
        let me_id = self.inner.me;
        let heartbeat = Frame::new(
            me_id,
            peer,
            &Message::Heartbeat { node: me_id },
            Box::new([]),
        );
        let heartbeat_kind = heartbeat.header.kind;
        tokio::spawn(async move {
            loop {
                let frame = match tokio::time::timeout(HEARTBEAT_INTERVAL, rx.recv()).await {
                    Ok(Some(f)) => f,
                    Ok(None) => break,
                    Err(_) => heartbeat.clone(),
                };
                if writer.write(&frame).await.is_err() {
                    break;
                }
            }
        });
        // Once the handshake is over, a frame may take as long as a big transfer needs.
        reader.frame_timeout = Duration::from_secs(60);
        reader.idle_deadline = Some(match kind {
            ConnectionKind::Control => CONTROL_SILENCE_LIMIT,
            _ => LINK_SILENCE_LIMIT,
        });
        let me = self.clone();
        tokio::spawn(async move {
            let reason = loop {
                match reader.read().await {
                    // Heartbeats only prove the peer is there; they go no further.
                    Ok(frame) if frame.header.kind == heartbeat_kind => {}
                    Ok(frame) => match kind {
                        ConnectionKind::Mesh => me.on_mesh_frame(peer, frame),
                        ConnectionKind::Direct => {
                            me.deliver(Fabric::from_wire_times(frame), Via::Direct(peer))
                        }
                        ConnectionKind::Control => me.deliver(frame, Via::Control(peer)),
                    },
                    Err(e) => {
                        if !me.inner.closing.load(Ordering::Relaxed)
                            && !matches!(e, protocol::ReadError::Closed)
                        {
                            tracing::warn!("connection to node {peer} ({kind:?}) failed: {e}");
                        }
                        break e.to_string();
                    }
                }
            };
            let table = match kind {
                ConnectionKind::Mesh => &me.inner.mesh,
                ConnectionKind::Direct => &me.inner.direct,
                ConnectionKind::Control => &me.inner.control,
            };
            table.lock().expect("lock").remove(&peer);
            if !me.inner.closing.load(Ordering::Relaxed) {
                let _ = me.inner.inbox.send(Delivery::Lost { peer, kind, reason });
            }
        });
    }

    /// Whether a peer may open a connection of this kind to us.
    fn accepts(&self, id: &Identity) -> bool {
        let t = &self.inner.topology;
        let me = self.inner.me;
        let Some(peer) = id.node else {
            // Only the host takes connections from nodes without an id (registration).
            return self.inner.role == Role::Host && id.kind == ConnectionKind::Control;
        };
        if peer as usize >= t.len() || t.role(peer) != id.role || peer == me {
            return false;
        }
        // One connection of each kind per peer: a second claim to be a peer that is already
        // connected is an impostor (or a confused restart) and must not displace the first.
        match id.kind {
            ConnectionKind::Mesh => {
                t.neighbors(me).contains(&peer)
                    && !self.inner.mesh.lock().expect("lock").contains_key(&peer)
            }
            ConnectionKind::Direct => {
                expected_direct(t, me).contains(&peer)
                    && !self.inner.direct.lock().expect("lock").contains_key(&peer)
            }
            ConnectionKind::Control => false,
        }
    }

    /// Accepts connections forever: handshake, check the caller's claim, attach.
    pub(crate) fn serve(&self, listener: TcpListener) {
        let me = self.clone();
        let pending = Arc::new(tokio::sync::Semaphore::new(MAX_PENDING_HANDSHAKES));
        tokio::spawn(async move {
            loop {
                let (stream, addr) = match listener.accept().await {
                    Ok(x) => x,
                    Err(e) => {
                        tracing::warn!("accept failed: {e}");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                };
                // Unauthenticated connections are bounded: beyond this many handshakes in
                // progress, new ones are closed at once.
                let Ok(permit) = pending.clone().try_acquire_owned() else {
                    me.inner
                        .counters
                        .connections_refused
                        .fetch_add(1, Ordering::Relaxed);
                    tracing::warn!(
                        "refused a connection from {addr}: too many handshakes in progress"
                    );
                    continue;
                };
                let me = me.clone();
                tokio::spawn(async move {
                    me.answer(stream, addr).await;
                    drop(permit);
                });
            }
        });
    }

    async fn answer(&self, stream: TcpStream, addr: SocketAddr) {
        let _ = stream.set_nodelay(true);
        let (r, w) = stream.into_split();
        let mut reader = FrameReader::new(r);
        reader.frame_timeout = handshake::HANDSHAKE_TIMEOUT;
        let mut writer = FrameWriter::new(w);
        let identity = match handshake::answer(
            &mut reader,
            &mut writer,
            &self.inner.secret,
            &self.inner.cluster_id,
        )
        .await
        {
            Ok(i) => i,
            Err(e) => {
                self.inner
                    .counters
                    .connections_refused
                    .fetch_add(1, Ordering::Relaxed);
                tracing::warn!("refused a connection from {addr}: {e}");
                return;
            }
        };
        if !self.accepts(&identity) {
            self.inner
                .counters
                .connections_refused
                .fetch_add(1, Ordering::Relaxed);
            tracing::warn!(
                "refused a connection from {addr}: it claims {identity:?}, which this node does not expect"
            );
            let reason = format!(
                "node {} does not take {:?} connections from {:?}",
                self.inner.me, identity.kind, identity.node
            );
            let _ = writer
                .write(&Frame::new(
                    self.inner.me,
                    0,
                    &Message::Refused { reason },
                    Box::new([]),
                ))
                .await;
            return;
        }
        match identity.node {
            Some(peer) => self.attach(peer, identity.kind, reader, writer),
            None => {
                let _ = self.inner.inbox.send(Delivery::Incoming {
                    identity,
                    reader,
                    writer,
                });
            }
        }
    }

    /// Dials `addr`, proves ourselves, and attaches the connection as `kind` to `peer`.
    pub async fn dial(
        &self,
        peer: NodeId,
        addr: &str,
        kind: ConnectionKind,
    ) -> Result<(), DialError> {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
        let mut delay = Duration::from_millis(20);
        let stream = loop {
            match TcpStream::connect(addr).await {
                Ok(s) => break s,
                Err(e) if tokio::time::Instant::now() < deadline => {
                    tracing::debug!("dialing node {peer} at {addr}: {e}; retrying");
                    tokio::time::sleep(delay).await;
                    delay = (delay * 2).min(Duration::from_millis(500));
                }
                Err(source) => {
                    return Err(DialError::Unreachable {
                        peer,
                        addr: addr.to_string(),
                        source,
                    });
                }
            }
        };
        let _ = stream.set_nodelay(true);
        let (r, w) = stream.into_split();
        let mut reader = FrameReader::new(r);
        let mut writer = FrameWriter::new(w);
        let identity = Identity {
            role: self.inner.role,
            node: Some(self.inner.me),
            kind,
        };
        handshake::call(
            &mut reader,
            &mut writer,
            &self.inner.secret,
            &self.inner.cluster_id,
            identity,
        )
        .await
        .map_err(|source| DialError::Handshake {
            peer,
            addr: addr.to_string(),
            source,
        })?;
        self.attach(peer, kind, reader, writer);
        Ok(())
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

    /// Whether the control connection to `peer` is still open.
    pub fn has_control(&self, peer: NodeId) -> bool {
        self.inner.control.lock().expect("lock").contains_key(&peer)
    }

    pub fn is_closing(&self) -> bool {
        self.inner.closing.load(Ordering::Relaxed)
    }
}

/// The direct connections a node has in a topology: a render node to its fork node, a fork
/// node to its render nodes, to every other fork node and to the host (the G-bus).
pub fn expected_direct(t: &Topology, me: NodeId) -> Vec<NodeId> {
    match t.role(me) {
        Role::Render => t.fork_of(me).into_iter().collect(),
        Role::Fork => {
            let mut v: Vec<NodeId> = t
                .render_nodes()
                .into_iter()
                .filter(|&r| t.card(r) == t.card(me))
                .collect();
            v.extend(t.fork_nodes().into_iter().filter(|&f| f != me));
            v.push(0);
            v
        }
        Role::Host => t.fork_nodes(),
    }
}

/// The connections `me` opens itself: mesh links and direct connections to higher ids, and
/// always those of a render node to its fork node and of a fork node to the host.
pub fn dials(t: &Topology, me: NodeId) -> Vec<(NodeId, ConnectionKind)> {
    let mut out: Vec<(NodeId, ConnectionKind)> = t
        .neighbors(me)
        .iter()
        .filter(|&&n| n > me)
        .map(|&n| (n, ConnectionKind::Mesh))
        .collect();
    for peer in expected_direct(t, me) {
        let i_dial = match (t.role(me), t.role(peer)) {
            (Role::Render, Role::Fork) => true,
            (Role::Fork, Role::Render) => false,
            (Role::Fork, Role::Host) => true,
            (Role::Host, Role::Fork) => false,
            _ => me < peer,
        };
        if i_dial {
            out.push((peer, ConnectionKind::Direct));
        }
    }
    out
}
