//! Forming a cluster by registration.
//!
//! Every node is started knowing only the host's address. It opens its own listening port,
//! calls the host (control connection, handshake with the cluster secret) and registers with
//! its role and the address others can reach it at. The host gives it a slot of that role
//! from the topology and, once every slot is filled, sends everyone the address table. Nodes
//! then connect their mesh links and direct connections, report that their links are up, and
//! the host says go.
//!
//! What is decided along the way lives in [`crate::registry`]; this module moves messages
//! between it and the sockets.

use std::{
    collections::HashMap,
    sync::Arc,
    time::{Duration, Instant},
};

use protocol::{
    ConnectionKind, Frame, FrameReader, FrameWriter, Identity, Message, NodeId, Role, Secret,
    handshake,
};
use tokio::{
    net::{TcpListener, TcpStream},
    sync::mpsc,
};

use crate::{
    clock::boot_id,
    node::{Delivery, Fabric, Via, dials, expected_direct},
    registry::{Registration, Registry, advertise_address, peer_table, read_assignment},
    topology::{Topology, TopologyError},
};

/// The cluster id nodes use unless told otherwise.
pub const DEFAULT_CLUSTER_ID: &str = "magg";

/// Why a cluster did not form, on the host's side or a node's.
#[derive(Debug, thiserror::Error)]
pub enum ClusterError {
    #[error("cannot listen on {address}: {source}")]
    Listen {
        address: String,
        source: std::io::Error,
    },
    #[error("cannot reach the host at {host}: {source}")]
    HostUnreachable {
        host: String,
        source: std::io::Error,
    },
    #[error("cannot tell which address {what} has: {source}")]
    LocalAddress {
        what: &'static str,
        source: std::io::Error,
    },
    #[error("registering with the host: {source}")]
    Register { source: std::io::Error },
    #[error("waiting for the host's answer to registration: {source}")]
    RegisterAnswer { source: protocol::ReadError },
    #[error("the host's answer to registration is unreadable: {0}")]
    UndecodableAnswer(#[source] protocol::DecodeError),
    #[error("unexpected answer to registration: {0:?}")]
    UnexpectedAnswer(Box<Message>),
    #[error("the host sent a topology this node cannot use: {0}")]
    HostTopology(#[source] TopologyError),
    #[error("the host gave slot {node}, which is not a {role}")]
    WrongSlot { node: NodeId, role: Role },
    #[error("the address table has no node {node}")]
    MissingAddress { node: NodeId },
    #[error(transparent)]
    Dial(#[from] crate::node::DialError),
    #[error("a task dialing a peer ended without an answer: {0}")]
    DialTask(#[from] tokio::task::JoinError),
    #[error("{0}")]
    Handshake(#[from] handshake::HandshakeError),
    #[error("the host refused this node: {0}")]
    Refused(String),
    #[error("timed out after {seconds} s: {waiting_for}")]
    Timeout { seconds: u64, waiting_for: Waiting },
    #[error("lost the connection to the host")]
    HostLost,
    #[error("the host's fabric stopped while the cluster was forming")]
    FabricStopped,
    #[error("node {node} failed while joining: {message}")]
    NodeFailed { node: NodeId, message: String },
    #[error("node {node} left while the cluster was forming")]
    NodeLeft { node: NodeId },
    #[error("stopped before the cluster formed")]
    Stopped,
    #[error("the host stopped the cluster before it formed: {reason}")]
    StoppedByHost { node: NodeId, reason: String },
}

/// What formation was still waiting for when it timed out.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Waiting {
    /// Nodes to register (host side).
    Joins {
        forks_joined: usize,
        forks: usize,
        renders_joined: usize,
        renders: usize,
    },
    /// Registered nodes to report their links up (host side).
    LinksUp {
        up: usize,
        slots: usize,
        waiting: Vec<NodeId>,
    },
    /// The fork nodes' direct connections and the mesh link to the host (host side).
    HostLinks {
        direct: usize,
        want_direct: usize,
        mesh: usize,
        want_mesh: usize,
    },
    /// The host's answer to registration (node side).
    HostAnswer,
    /// The address table (node side).
    AddressTable,
    /// Links that neighbours open to this node (node side).
    NeighbourLinks {
        mesh: usize,
        want_mesh: usize,
        direct: usize,
        want_direct: usize,
    },
    /// The host's go (node side).
    Go,
}

impl std::fmt::Display for Waiting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Waiting::Joins {
                forks_joined,
                forks,
                renders_joined,
                renders,
            } => write!(
                f,
                "{forks_joined} of {forks} fork nodes and {renders_joined} of {renders} render nodes joined"
            ),
            Waiting::LinksUp { up, slots, waiting } => write!(
                f,
                "{up} of {slots} nodes connected their links (waiting for {waiting:?})"
            ),
            Waiting::HostLinks {
                direct,
                want_direct,
                mesh,
                want_mesh,
            } => write!(
                f,
                "the fork nodes' connections to the host ({direct} of {want_direct} direct, {mesh} of {want_mesh} mesh)"
            ),
            Waiting::HostAnswer => write!(f, "the host's answer"),
            Waiting::AddressTable => write!(f, "the address table from the host"),
            Waiting::NeighbourLinks {
                mesh,
                want_mesh,
                direct,
                want_direct,
            } => write!(
                f,
                "links from neighbours ({mesh} of {want_mesh} mesh, {direct} of {want_direct} direct)"
            ),
            Waiting::Go => write!(f, "the host's go"),
        }
    }
}

pub use crate::registry::Member;

/// The host's side of a formed cluster.
pub struct Formed {
    pub fabric: Fabric,
    pub inbox: mpsc::UnboundedReceiver<Delivery>,
    pub members: Vec<Member>,
}

/// How long the host waits, once every node reported its links, for the fork nodes'
/// connections to itself (they are dialled by then; this only covers their handshakes).
const HOST_LINKS_WAIT: Duration = Duration::from_secs(10);

fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .unwrap_or_default()
}

/// CPUs online on this machine, whatever this process may use of them.
fn machine_cpus() -> u32 {
    std::fs::read_to_string("/sys/devices/system/cpu/online")
        .ok()
        .and_then(|list| count_cpu_list(&list))
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get() as u32))
}

/// The number of CPUs in a kernel CPU list ("0-3,8-11\n" is 8); `None` if it is not one.
fn count_cpu_list(list: &str) -> Option<u32> {
    list.trim().split(',').try_fold(0u32, |sum, range| {
        let (first, last) = range.split_once('-').unwrap_or((range, range));
        let (first, last): (u32, u32) = (first.parse().ok()?, last.parse().ok()?);
        sum.checked_add(last.checked_sub(first)?.checked_add(1)?)
    })
}

type ControlHalves = (
    FrameReader<tokio::net::tcp::OwnedReadHalf>,
    FrameWriter<tokio::net::tcp::OwnedWriteHalf>,
);

/// Host side, once the cluster is formed: answers a node that asks to join with a refusal
/// saying why, in the background (a late node must not hang until its own timeout).
pub fn refuse_late_joiner(delivery: Delivery, reason: String) {
    let Delivery::Incoming {
        identity,
        mut reader,
        mut writer,
    } = delivery
    else {
        return;
    };
    tracing::warn!("refused a {} that asked to join: {reason}", identity.role);
    tokio::spawn(async move {
        reader.frame_timeout = handshake::HANDSHAKE_TIMEOUT;
        // Its registration comes first; the answer follows it.
        let _ = tokio::time::timeout(handshake::HANDSHAKE_TIMEOUT, reader.read()).await;
        let _ = writer
            .write(&Frame::new(
                0,
                0,
                &Message::Refused { reason },
                Box::new([]),
            ))
            .await;
    });
}

/// How `form` reports joins as they happen.
struct Announce<'a> {
    progress: &'a (dyn Fn(usize, usize) + Sync),
    /// Nodes started by hand are worth a line each; the host's own children are not.
    each_join: bool,
}

/// How long the host, giving up on a cluster that will not form, waits for the nodes that
/// had joined to read why and hang up. They exit as soon as they read it; this bounds only
/// the wait for one that is hung.
const DISMISS_WAIT: Duration = Duration::from_secs(2);

/// Host side: waits until the topology is filled and every node's links are up, or until
/// `stop` resolves (`ClusterError::Stopped`). The [`Registry`] decides; this loop only
/// carries its decisions to and from the sockets. Nodes that joined a cluster that does not
/// form are told why, and have read it, before this returns.
pub async fn form(
    listener: TcpListener,
    topology: Topology,
    secret: Secret,
    cluster_id: &str,
    timeout: Duration,
    progress: &(dyn Fn(usize, usize) + Sync),
    announce_joins: bool,
    stop: impl std::future::Future<Output = ()>,
) -> Result<Formed, ClusterError> {
    let topology = Arc::new(topology);
    let (fabric, mut inbox) = Fabric::new(
        0,
        Role::Host,
        topology.clone(),
        secret,
        cluster_id.to_string(),
    );
    fabric.serve(listener);
    let mut registry = Registry::new(topology.clone(), boot_id(), Instant::now(), timeout);
    let announce = Announce {
        progress,
        each_join: announce_joins,
    };
    let gathered = tokio::select! {
        gathered = gather(&fabric, &mut inbox, &mut registry, &announce) => gathered,
        () = stop => Err(ClusterError::Stopped),
    };
    if let Err(e) = gathered {
        let reason = match &e {
            ClusterError::Stopped => "the host was stopped".to_string(),
            e => format!("the cluster did not form: {e}"),
        };
        dismiss(&fabric, &registry, reason).await;
        return Err(e);
    }
    tell_members(&fabric, &registry, &Message::Go);
    Ok(Formed {
        fabric,
        inbox,
        members: registry.into_members(),
    })
}

/// Tells every node that joined why the cluster will not form, and waits (at most
/// [`DISMISS_WAIT`]) until each has hung up: this process may exit right after, and a node
/// that saw only the connection end would report the host lost (after its own timeout, if
/// the process lingered).
async fn dismiss(fabric: &Fabric, registry: &Registry, reason: String) {
    tell_members(fabric, registry, &Message::Shutdown { reason });
    let until = tokio::time::Instant::now() + DISMISS_WAIT;
    while registry.members().any(|m| fabric.has_control(m.node))
        && tokio::time::Instant::now() < until
    {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    fabric.hang_up();
}

/// Registers nodes until the topology is filled and every link is up, the host's too.
async fn gather(
    fabric: &Fabric,
    inbox: &mut mpsc::UnboundedReceiver<Delivery>,
    registry: &mut Registry,
    announce: &Announce<'_>,
) -> Result<(), ClusterError> {
    let deadline = tokio::time::Instant::from_std(registry.deadline());
    let (registrations_tx, mut registrations) = mpsc::unbounded_channel();
    while !registry.is_formed() {
        let event = tokio::select! {
            d = inbox.recv() => Event::Delivery(d),
            r = registrations.recv() => Event::Registration(r),
            _ = tokio::time::sleep_until(deadline) => Event::Timeout,
        };
        match event {
            Event::Timeout => registry.check_time(Instant::now())?,
            Event::Delivery(None) => return Err(ClusterError::FabricStopped),
            Event::Delivery(Some(Delivery::Incoming {
                identity,
                reader,
                writer,
            })) => {
                if identity.kind == ConnectionKind::Control {
                    read_registration((reader, writer), registrations_tx.clone());
                }
            }
            Event::Registration(None) => {}
            Event::Registration(Some((message, halves))) => {
                if let Some(registration) = Registration::from_message(message) {
                    register(fabric, registry, registration, halves, announce).await?;
                }
            }
            Event::Delivery(Some(Delivery::Frame {
                frame,
                via: Via::Control(n),
            })) => match frame.message() {
                Ok(Message::LinksUp { .. }) => registry.links_up(n),
                Ok(Message::NodeFailed { node, message }) => {
                    return Err(ClusterError::NodeFailed { node, message });
                }
                _ => {}
            },
            Event::Delivery(Some(Delivery::Lost {
                peer,
                kind: ConnectionKind::Control,
                ..
            })) => {
                registry.lost(peer)?;
                tracing::warn!(
                    "node {peer} left before the cluster formed; its slot is free again"
                );
            }
            Event::Delivery(Some(_)) => {}
        }
    }
    let topology = fabric.topology();
    let want_direct = expected_direct(topology, 0).len();
    let want_mesh = topology.neighbors(0).len();
    let until = tokio::time::Instant::now() + HOST_LINKS_WAIT;
    wait_for_links(fabric, want_mesh, want_direct, until)
        .await
        .map_err(|(mesh, direct)| ClusterError::Timeout {
            seconds: HOST_LINKS_WAIT.as_secs(),
            waiting_for: Waiting::HostLinks {
                direct,
                want_direct,
                mesh,
                want_mesh,
            },
        })
}

enum Event {
    Delivery(Option<Delivery>),
    Registration(Option<(Message, ControlHalves)>),
    Timeout,
}

/// Reads a registering node's first frame in the background, so that a slow or silent
/// caller holds up no other node's registration.
fn read_registration(
    (mut reader, writer): ControlHalves,
    to: mpsc::UnboundedSender<(Message, ControlHalves)>,
) {
    tokio::spawn(async move {
        reader.frame_timeout = handshake::HANDSHAKE_TIMEOUT;
        let read = tokio::time::timeout(handshake::HANDSHAKE_TIMEOUT, reader.read()).await;
        if let Ok(Ok(frame)) = read
            && let Ok(message) = frame.message()
        {
            let _ = to.send((message, (reader, writer)));
        }
    });
}

/// Answers one registration with a slot or with a refusal saying why. The node that fills
/// the last slot also sends everyone the address table and has the host dial its own links.
async fn register(
    fabric: &Fabric,
    registry: &mut Registry,
    registration: Registration,
    (reader, mut writer): ControlHalves,
    announce: &Announce<'_>,
) -> Result<(), ClusterError> {
    let node = match registry.slot_for(&registration) {
        Ok(node) => node,
        Err(refusal) => {
            let Registration {
                role, advertise, ..
            } = &registration;
            tracing::warn!("refused a {role} at {advertise}: {refusal}");
            let reason = refusal.to_string();
            let refused = Frame::new(0, 0, &Message::Refused { reason }, Box::new([]));
            let _ = writer.write(&refused).await;
            return Ok(());
        }
    };
    let assigned = Message::Assigned {
        node,
        topology: fabric.topology().to_wire(),
    };
    if writer
        .write(&Frame::new(0, node, &assigned, Box::new([])))
        .await
        .is_err()
    {
        // It hung up: its slot stays free.
        return Ok(());
    }
    let line = format!(
        "{} {node} joined from {} (pid {} on {}); {} of {}",
        registration.role,
        registration.advertise,
        registration.pid,
        registration.hostname,
        registry.members().count() + 1,
        registry.slots()
    );
    if announce.each_join {
        tracing::info!("{line}");
    } else {
        tracing::debug!("{line}");
    }
    let admitted = registry.admit(node, registration);
    fabric.set_same_machine(node, admitted.same_machine);
    fabric.attach(node, ConnectionKind::Control, reader, writer);
    (announce.progress)(admitted.joined, admitted.slots);
    if let Some(addresses) = admitted.addresses {
        tell_members(fabric, registry, &Message::Peers { addresses });
        for (peer, address, kind) in registry.host_dials() {
            fabric.dial(peer, &address, kind).await?;
        }
    }
    Ok(())
}

/// Sends `message` to every member on its control connection.
fn tell_members(fabric: &Fabric, registry: &Registry, message: &Message) {
    for member in registry.members() {
        let _ = fabric.send_control(member.node, message);
    }
}

/// Waits until `fabric` has at least `want_mesh` mesh links and `want_direct` direct
/// connections up, or gives the counts it had at `deadline`.
async fn wait_for_links(
    fabric: &Fabric,
    want_mesh: usize,
    want_direct: usize,
    deadline: tokio::time::Instant,
) -> Result<(), (usize, usize)> {
    while fabric.mesh_links_up() < want_mesh || fabric.direct_links_up() < want_direct {
        if tokio::time::Instant::now() > deadline {
            return Err((fabric.mesh_links_up(), fabric.direct_links_up()));
        }
        // Links come up on other tasks; polling this often costs nothing next to formation.
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    Ok(())
}

#[derive(Clone, Debug)]
pub struct JoinConfig {
    /// The host's address, `HOST:PORT`.
    pub host: String,
    /// Where to listen for peers (`0.0.0.0:0` picks any port on every interface).
    pub listen: String,
    /// The address peers should dial; by default this machine's address on the route to
    /// the host, with the listening port.
    pub advertise: Option<String>,
    pub role: Role,
    pub secret: Secret,
    pub cluster_id: String,
    pub timeout: Duration,
}

/// A node's side of a formed cluster.
pub struct Joined {
    pub fabric: Fabric,
    pub inbox: mpsc::UnboundedReceiver<Delivery>,
    pub node: NodeId,
    /// What arrived before the host said go.
    pub early: Vec<Delivery>,
}

/// Node side: registers with the host, connects links, waits for go.
pub async fn join(cfg: JoinConfig) -> Result<Joined, ClusterError> {
    let listener = TcpListener::bind(&cfg.listen)
        .await
        .map_err(|source| ClusterError::Listen {
            address: cfg.listen.clone(),
            source,
        })?;
    let port = listener
        .local_addr()
        .map_err(|source| ClusterError::LocalAddress {
            what: "the listening port",
            source,
        })?
        .port();
    let deadline = tokio::time::Instant::now() + cfg.timeout;
    let seconds = cfg.timeout.as_secs();
    let stream = connect_to_host(&cfg.host, deadline).await?;
    let toward_host = stream
        .local_addr()
        .map_err(|source| ClusterError::LocalAddress {
            what: "the connection to the host",
            source,
        })?
        .ip();
    let advertise = advertise_address(cfg.advertise.as_deref(), &cfg.listen, port, toward_host);
    let (node, topology, (reader, writer)) = register_with_host(&cfg, stream, &advertise).await?;
    tracing::info!("joined as {} {node}; listening at {advertise}", cfg.role);
    let topology = Arc::new(topology);
    let (fabric, mut inbox) = Fabric::new(
        node,
        cfg.role,
        topology.clone(),
        cfg.secret.clone(),
        cfg.cluster_id.clone(),
    );
    fabric.attach(0, ConnectionKind::Control, reader, writer);
    fabric.serve(listener);

    let mut early = Vec::new();
    let mut host = HostWait {
        node,
        inbox: &mut inbox,
        early: &mut early,
        deadline,
        seconds,
    };
    let addresses = host
        .until(Waiting::AddressTable, |m| match m {
            Message::Peers { addresses } => Some(addresses),
            _ => None,
        })
        .await?;
    let table = peer_table(addresses, &cfg.host);
    let my_boot = boot_id();
    for (n, (_, boot)) in &table {
        fabric.set_same_machine(*n, *boot == my_boot);
    }
    dial_peers(&fabric, &topology, node, &table).await?;
    let want_mesh = topology.neighbors(node).len();
    let want_direct = expected_direct(&topology, node).len();
    wait_for_links(&fabric, want_mesh, want_direct, deadline)
        .await
        .map_err(|(mesh, direct)| ClusterError::Timeout {
            seconds,
            waiting_for: Waiting::NeighbourLinks {
                mesh,
                want_mesh,
                direct,
                want_direct,
            },
        })?;
    let _ = fabric.send_control(0, &Message::LinksUp { node });
    host.until(Waiting::Go, |m| matches!(m, Message::Go).then_some(()))
        .await?;
    Ok(Joined {
        fabric,
        inbox,
        node,
        early,
    })
}

/// Calls the host until it answers or `deadline` passes: nodes may start before it listens.
async fn connect_to_host(
    host: &str,
    deadline: tokio::time::Instant,
) -> Result<TcpStream, ClusterError> {
    loop {
        match TcpStream::connect(host).await {
            Ok(stream) => {
                let _ = stream.set_nodelay(true);
                return Ok(stream);
            }
            Err(e) if tokio::time::Instant::now() < deadline => {
                tracing::debug!("host {host} not reachable yet ({e}); retrying");
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(source) => {
                return Err(ClusterError::HostUnreachable {
                    host: host.to_string(),
                    source,
                });
            }
        }
    }
}

/// Proves this node to the host, registers, and reads its slot and the topology.
async fn register_with_host(
    cfg: &JoinConfig,
    stream: TcpStream,
    advertise: &str,
) -> Result<(NodeId, Topology, ControlHalves), ClusterError> {
    let (r, w) = stream.into_split();
    let mut reader = FrameReader::new(r);
    let mut writer = FrameWriter::new(w);
    let identity = Identity {
        role: cfg.role,
        node: None,
        kind: ConnectionKind::Control,
    };
    handshake::call(
        &mut reader,
        &mut writer,
        &cfg.secret,
        &cfg.cluster_id,
        identity,
    )
    .await?;
    let boot = boot_id();
    let register = Message::Register {
        role: cfg.role,
        advertise: advertise.to_string(),
        pid: std::process::id(),
        hostname: hostname(),
        shm_domain: crate::shm::domain(&boot),
        boot_id: boot,
        cpus: std::thread::available_parallelism().map_or(1, |n| n.get() as u32),
        machine_cpus: machine_cpus(),
    };
    writer
        .write(&Frame::new(0, 0, &register, Box::new([])))
        .await
        .map_err(|source| ClusterError::Register { source })?;
    let answer = tokio::time::timeout(cfg.timeout, reader.read())
        .await
        .map_err(|_| ClusterError::Timeout {
            seconds: cfg.timeout.as_secs(),
            waiting_for: Waiting::HostAnswer,
        })?
        .map_err(|source| ClusterError::RegisterAnswer { source })?;
    let (node, topology) = read_assignment(answer.message(), cfg.role)?;
    Ok((node, topology, (reader, writer)))
}

/// A joining node's wait for the host's next word.
struct HostWait<'a> {
    node: NodeId,
    inbox: &'a mut mpsc::UnboundedReceiver<Delivery>,
    /// What arrives meanwhile for the role code (frames from peers that are ready first).
    early: &'a mut Vec<Delivery>,
    deadline: tokio::time::Instant,
    seconds: u64,
}

impl HostWait<'_> {
    /// Waits for the host's control message that `pick` takes. A shutdown from the host
    /// means the cluster will not form (`ClusterError::StoppedByHost`); other control
    /// messages from it are dropped.
    async fn until<T>(
        &mut self,
        waiting_for: Waiting,
        pick: impl Fn(Message) -> Option<T>,
    ) -> Result<T, ClusterError> {
        loop {
            let delivery = tokio::time::timeout_at(self.deadline, self.inbox.recv())
                .await
                .map_err(|_| ClusterError::Timeout {
                    seconds: self.seconds,
                    waiting_for: waiting_for.clone(),
                })?;
            match delivery {
                Some(Delivery::Frame {
                    frame,
                    via: Via::Control(0),
                }) => match frame.message() {
                    Ok(Message::Shutdown { reason }) => {
                        return Err(ClusterError::StoppedByHost {
                            node: self.node,
                            reason,
                        });
                    }
                    Ok(message) => {
                        if let Some(picked) = pick(message) {
                            return Ok(picked);
                        }
                    }
                    Err(_) => {}
                },
                Some(Delivery::Lost {
                    peer: 0,
                    kind: ConnectionKind::Control,
                    ..
                })
                | None => return Err(ClusterError::HostLost),
                Some(d) => self.early.push(d),
            }
        }
    }
}

/// Opens this node's own connections, all at once (each may have to wait for its peer to
/// start listening).
async fn dial_peers(
    fabric: &Fabric,
    topology: &Topology,
    node: NodeId,
    table: &HashMap<NodeId, (String, String)>,
) -> Result<(), ClusterError> {
    let mut dialing = Vec::new();
    for (peer, kind) in dials(topology, node) {
        let Some((address, _)) = table.get(&peer) else {
            return Err(ClusterError::MissingAddress { node: peer });
        };
        let fabric = fabric.clone();
        let address = address.clone();
        dialing.push(tokio::spawn(async move {
            fabric.dial(peer, &address, kind).await
        }));
    }
    for dial in dialing {
        dial.await??;
    }
    Ok(())
}

/// A node's way out after the host said stop: stop reporting losses, then wait (briefly)
/// for the host to hang up first, so that whoever watches the processes (a shell, compose)
/// sees the host end before its nodes and takes the host's exit status as the cluster's.
pub async fn leave(fabric: &Fabric) {
    fabric.begin_shutdown();
    let until = tokio::time::Instant::now() + Duration::from_secs(5);
    while fabric.has_control(0) && tokio::time::Instant::now() < until {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

#[cfg(test)]
mod tests {
    use super::count_cpu_list;

    #[test]
    fn cpu_lists_are_counted_range_by_range() {
        assert_eq!(count_cpu_list("0-1\n"), Some(2));
        assert_eq!(count_cpu_list("0"), Some(1));
        assert_eq!(count_cpu_list("0-3,8-11"), Some(8));
        assert_eq!(count_cpu_list("0,2,4-5"), Some(4));
        assert_eq!(count_cpu_list(""), None);
        assert_eq!(count_cpu_list("3-1"), None);
        assert_eq!(count_cpu_list("a-b"), None);
    }
}
