//! Forming a cluster by registration.
//!
//! Every node is started knowing only the host's address. It opens its own listening port,
//! calls the host (control connection, handshake with the cluster secret) and registers with
//! its role and the address others can reach it at. The host gives it a slot of that role
//! from the topology and, once every slot is filled, sends everyone the address table. Nodes
//! then connect their mesh links and direct connections, report that their links are up, and
//! the host says go.

use std::{collections::HashMap, sync::Arc, time::Duration};

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
    topology::Topology,
};

/// The cluster id nodes use unless told otherwise.
pub const DEFAULT_CLUSTER_ID: &str = "magg";

#[derive(Debug, thiserror::Error)]
pub enum ClusterError {
    #[error("{0}")]
    Io(String),
    #[error(transparent)]
    Dial(#[from] crate::node::DialError),
    #[error("{0}")]
    Handshake(#[from] handshake::HandshakeError),
    #[error("the host refused this node: {0}")]
    Refused(String),
    #[error("timed out after {seconds} s: {missing}")]
    Timeout { seconds: u64, missing: String },
    #[error("lost the connection to the host")]
    HostLost,
    #[error("{0}")]
    Protocol(String),
}

/// A registered member of the cluster.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Member {
    pub node: NodeId,
    pub role: Role,
    pub advertise: String,
    pub pid: u32,
    pub hostname: String,
    pub boot_id: String,
}

/// The host's side of a formed cluster.
pub struct Formed {
    pub fabric: Fabric,
    pub inbox: mpsc::UnboundedReceiver<Delivery>,
    pub members: Vec<Member>,
}

fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .unwrap_or_default()
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

/// Host side: waits until the topology is filled and every node's links are up.
pub async fn form(
    listener: TcpListener,
    topology: Topology,
    secret: Secret,
    cluster_id: &str,
    timeout: Duration,
    progress: &(dyn Fn(usize, usize) + Sync),
    announce_joins: bool,
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
    let slots = topology.len() - 1;
    let mut members: HashMap<NodeId, Member> = HashMap::new();
    let mut links_up: HashMap<NodeId, bool> = HashMap::new();
    let (reg_tx, mut reg_rx) = mpsc::unbounded_channel::<(Message, ControlHalves)>();
    let deadline = tokio::time::Instant::now() + timeout;
    let my_boot = boot_id();
    let mut peers_sent = false;
    let mut host_links_dialed = false;

    loop {
        if peers_sent && links_up.len() == slots && host_links_dialed {
            break;
        }
        let ev = tokio::select! {
            d = inbox.recv() => Event::Delivery(d),
            r = reg_rx.recv() => Event::Registration(r),
            _ = tokio::time::sleep_until(deadline) => Event::Timeout,
        };
        match ev {
            Event::Timeout => {
                let (f, r) = topology.counts();
                let joined_f = members.values().filter(|m| m.role == Role::Fork).count();
                let joined_r = members.values().filter(|m| m.role == Role::Render).count();
                let missing = if members.len() < slots {
                    format!(
                        "{joined_f} of {f} fork nodes and {joined_r} of {r} render nodes joined"
                    )
                } else {
                    let waiting: Vec<NodeId> = members
                        .keys()
                        .copied()
                        .filter(|n| !links_up.contains_key(n))
                        .collect();
                    format!(
                        "{} of {slots} nodes connected their links (waiting for {waiting:?})",
                        links_up.len()
                    )
                };
                for m in members.keys() {
                    let _ = fabric.send_control(
                        *m,
                        &Message::Shutdown {
                            reason: "the cluster did not form in time".into(),
                        },
                    );
                }
                return Err(ClusterError::Timeout {
                    seconds: timeout.as_secs(),
                    missing,
                });
            }
            Event::Delivery(None) => return Err(ClusterError::Io("fabric stopped".into())),
            Event::Delivery(Some(Delivery::Incoming {
                identity,
                mut reader,
                writer,
            })) => {
                if identity.kind != ConnectionKind::Control {
                    continue;
                }
                let tx = reg_tx.clone();
                tokio::spawn(async move {
                    reader.frame_timeout = handshake::HANDSHAKE_TIMEOUT;
                    let read =
                        tokio::time::timeout(handshake::HANDSHAKE_TIMEOUT, reader.read()).await;
                    if let Ok(Ok(frame)) = read
                        && let Ok(msg) = frame.message()
                    {
                        let _ = tx.send((msg, (reader, writer)));
                    }
                });
            }
            Event::Registration(None) => {}
            Event::Registration(Some((msg, (reader, mut writer)))) => {
                let Message::Register {
                    role,
                    advertise,
                    pid,
                    hostname,
                    boot_id,
                } = msg
                else {
                    continue;
                };
                let free = (1..topology.len() as NodeId)
                    .find(|&n| topology.role(n) == role && !members.contains_key(&n));
                let Some(node) = free.filter(|_| !peers_sent) else {
                    let reason = format!(
                        "the cluster has no free {role} slot ({} is full)",
                        topology.name
                    );
                    tracing::warn!("refused a {role} at {advertise}: {reason}");
                    let _ = writer
                        .write(&Frame::new(
                            0,
                            0,
                            &Message::Refused { reason },
                            Box::new([]),
                        ))
                        .await;
                    continue;
                };
                let assigned = Message::Assigned {
                    node,
                    topology: topology.to_toml(),
                };
                if writer
                    .write(&Frame::new(0, node, &assigned, Box::new([])))
                    .await
                    .is_err()
                {
                    continue;
                }
                // Nodes started by hand are worth a line each; the host's own children not.
                let line = format!(
                    "{role} {node} joined from {advertise} (pid {pid} on {hostname}); {} of {slots}",
                    members.len() + 1
                );
                if announce_joins {
                    tracing::info!("{line}");
                } else {
                    tracing::debug!("{line}");
                }
                fabric.set_same_machine(node, boot_id == my_boot);
                fabric.attach(node, ConnectionKind::Control, reader, writer);
                members.insert(
                    node,
                    Member {
                        node,
                        role,
                        advertise,
                        pid,
                        hostname,
                        boot_id,
                    },
                );
                progress(members.len(), slots);
                if members.len() == slots {
                    let mut addresses: Vec<(NodeId, String, String)> = members
                        .values()
                        .map(|m| (m.node, m.advertise.clone(), m.boot_id.clone()))
                        .collect();
                    // Nodes reach the host at the address they joined with.
                    addresses.push((0, String::new(), my_boot.clone()));
                    addresses.sort();
                    for m in members.keys() {
                        let _ = fabric.send_control(
                            *m,
                            &Message::Peers {
                                addresses: addresses.clone(),
                            },
                        );
                    }
                    peers_sent = true;
                    // The host's own links.
                    for (peer, kind) in dials(&topology, 0) {
                        let addr = members[&peer].advertise.clone();
                        fabric.dial(peer, &addr, kind).await?;
                    }
                    host_links_dialed = true;
                }
            }
            Event::Delivery(Some(Delivery::Frame {
                frame,
                via: Via::Control(n),
            })) => match frame.message() {
                Ok(Message::LinksUp { .. }) => {
                    links_up.insert(n, true);
                }
                Ok(Message::NodeFailed { node, message }) => {
                    return Err(ClusterError::Protocol(format!(
                        "node {node} failed while joining: {message}"
                    )));
                }
                _ => {}
            },
            Event::Delivery(Some(Delivery::Lost {
                peer,
                kind: ConnectionKind::Control,
                ..
            })) => {
                if peers_sent {
                    return Err(ClusterError::Protocol(format!(
                        "node {peer} left while the cluster was forming"
                    )));
                }
                tracing::warn!(
                    "node {peer} left before the cluster formed; its slot is free again"
                );
                members.remove(&peer);
            }
            Event::Delivery(Some(_)) => {}
        }
    }
    // Wait for the host's own expected direct connections (fork nodes dial the host).
    let expect = expected_direct(&topology, 0).len();
    let wait_deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while fabric.direct_links_up() < expect || fabric.mesh_links_up() < topology.neighbors(0).len()
    {
        if tokio::time::Instant::now() > wait_deadline {
            return Err(ClusterError::Timeout {
                seconds: 10,
                missing: "the fork nodes' connections to the host".into(),
            });
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    for m in members.keys() {
        let _ = fabric.send_control(*m, &Message::Go);
    }
    let mut members: Vec<Member> = members.into_values().collect();
    members.sort_by_key(|m| m.node);
    Ok(Formed {
        fabric,
        inbox,
        members,
    })
}

enum Event {
    Delivery(Option<Delivery>),
    Registration(Option<(Message, ControlHalves)>),
    Timeout,
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
    let io = |what: &str, e: std::io::Error| ClusterError::Io(format!("{what}: {e}"));
    let listener = TcpListener::bind(&cfg.listen)
        .await
        .map_err(|e| io(&format!("listening on {}", cfg.listen), e))?;
    let port = listener
        .local_addr()
        .map_err(|e| io("listening", e))?
        .port();

    let deadline = tokio::time::Instant::now() + cfg.timeout;
    let stream = loop {
        match TcpStream::connect(&cfg.host).await {
            Ok(s) => break s,
            Err(e) if tokio::time::Instant::now() < deadline => {
                tracing::debug!("host {} not reachable yet ({e}); retrying", cfg.host);
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(e) => return Err(io(&format!("cannot reach the host at {}", cfg.host), e)),
        }
    };
    let _ = stream.set_nodelay(true);
    let local_ip = stream
        .local_addr()
        .map_err(|e| io("connection to the host", e))?
        .ip();
    let advertise = match &cfg.advertise {
        Some(a) => a.clone(),
        None => {
            let listen_ip = cfg
                .listen
                .rsplit_once(':')
                .map(|(ip, _)| ip.trim_matches(['[', ']']))
                .unwrap_or("");
            match listen_ip.parse::<std::net::IpAddr>() {
                Ok(ip) if !ip.is_unspecified() => std::net::SocketAddr::new(ip, port).to_string(),
                _ => std::net::SocketAddr::new(local_ip, port).to_string(),
            }
        }
    };
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
    let register = Message::Register {
        role: cfg.role,
        advertise: advertise.clone(),
        pid: std::process::id(),
        hostname: hostname(),
        boot_id: boot_id(),
    };
    writer
        .write(&Frame::new(0, 0, &register, Box::new([])))
        .await
        .map_err(|e| io("registering", e))?;
    let reply = tokio::time::timeout(cfg.timeout, reader.read())
        .await
        .map_err(|_| ClusterError::Timeout {
            seconds: cfg.timeout.as_secs(),
            missing: "the host's answer".into(),
        })?
        .map_err(|e| ClusterError::Io(format!("registering: {e}")))?;
    let (node, topology) = match reply.message() {
        Ok(Message::Assigned { node, topology }) => (node, topology),
        Ok(Message::Refused { reason }) => return Err(ClusterError::Refused(reason)),
        other => {
            return Err(ClusterError::Protocol(format!(
                "unexpected answer to registration: {other:?}"
            )));
        }
    };
    let topology = Topology::from_toml(&topology)
        .map_err(|e| ClusterError::Protocol(format!("topology from the host: {e}")))?;
    if topology.role(node) != cfg.role {
        return Err(ClusterError::Protocol(format!(
            "the host gave slot {node}, which is not a {}",
            cfg.role
        )));
    }
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

    let my_boot = boot_id();
    let mut early = Vec::new();
    let seconds = cfg.timeout.as_secs();
    async fn wait(
        inbox: &mut mpsc::UnboundedReceiver<Delivery>,
        deadline: tokio::time::Instant,
        seconds: u64,
        what: &str,
    ) -> Result<Option<Delivery>, ClusterError> {
        tokio::time::timeout_at(deadline, inbox.recv())
            .await
            .map_err(|_| ClusterError::Timeout {
                seconds,
                missing: what.to_string(),
            })
    }
    // The address table.
    let addresses = loop {
        match wait(
            &mut inbox,
            deadline,
            seconds,
            "the address table from the host",
        )
        .await?
        {
            Some(Delivery::Frame {
                frame,
                via: Via::Control(0),
            }) => match frame.message() {
                Ok(Message::Peers { addresses }) => break addresses,
                Ok(Message::Shutdown { reason }) => return Err(ClusterError::Refused(reason)),
                _ => {}
            },
            Some(Delivery::Lost { peer: 0, .. }) | None => return Err(ClusterError::HostLost),
            Some(d) => early.push(d),
        }
    };
    let mut table: HashMap<NodeId, (String, String)> =
        addresses.into_iter().map(|(n, a, b)| (n, (a, b))).collect();
    if let Some(host) = table.get_mut(&0) {
        host.0 = cfg.host.clone();
    }
    for (n, (_, b)) in &table {
        fabric.set_same_machine(*n, *b == my_boot);
    }
    let mut dialing = Vec::new();
    for (peer, kind) in dials(&topology, node) {
        let Some((addr, _)) = table.get(&peer) else {
            return Err(ClusterError::Protocol(format!(
                "the address table has no node {peer}"
            )));
        };
        let f = fabric.clone();
        let addr = addr.clone();
        dialing.push(tokio::spawn(async move { f.dial(peer, &addr, kind).await }));
    }
    for d in dialing {
        d.await.map_err(|e| ClusterError::Io(e.to_string()))??;
    }
    let want_mesh = topology.neighbors(node).len();
    let want_direct = expected_direct(&topology, node).len();
    while fabric.mesh_links_up() < want_mesh || fabric.direct_links_up() < want_direct {
        if tokio::time::Instant::now() > deadline {
            let missing = format!(
                "links from neighbours ({} of {want_mesh} mesh, {} of {want_direct} direct)",
                fabric.mesh_links_up(),
                fabric.direct_links_up()
            );
            return Err(ClusterError::Timeout {
                seconds: cfg.timeout.as_secs(),
                missing,
            });
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let _ = fabric.send_control(0, &Message::LinksUp { node });
    loop {
        match wait(&mut inbox, deadline, seconds, "the host's go").await? {
            Some(Delivery::Frame {
                frame,
                via: Via::Control(0),
            }) => match frame.message() {
                Ok(Message::Go) => break,
                Ok(Message::Shutdown { reason }) => return Err(ClusterError::Refused(reason)),
                _ => {}
            },
            Some(Delivery::Lost {
                peer: 0,
                kind: ConnectionKind::Control,
                ..
            })
            | None => return Err(ClusterError::HostLost),
            Some(d) => early.push(d),
        }
    }
    Ok(Joined {
        fabric,
        inbox,
        node,
        early,
    })
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
