//! The decisions of forming a cluster, kept apart from the sockets that carry them.
//!
//! Forming a cluster is a conversation over TCP, but everything decided in it depends only
//! on what has been heard so far: which slot a registering node gets, who is refused and
//! why, when every slot is filled and the address table goes out, when the cluster is
//! formed, and when waiting has gone on too long. [`Registry`] holds that state on the host;
//! the free functions at the end make a node's decisions (its address, what the host's
//! answer means, where its peers are). Nothing here does I/O, spawns a task or reads a
//! clock (the time is an argument), so that every case can be tested without a network and
//! without waiting; [`crate::cluster`] moves the messages.

use std::{
    collections::{BTreeMap, BTreeSet, HashMap},
    net::{IpAddr, SocketAddr},
    sync::Arc,
    time::{Duration, Instant},
};

use protocol::{ConnectionKind, DecodeError, Message, NodeId, Role};

use crate::{
    cluster::{ClusterError, Waiting},
    node::dials,
    topology::Topology,
};

/// What a node says about itself when it registers.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Registration {
    pub role: Role,
    /// The address its peers should dial.
    pub advertise: String,
    pub pid: u32,
    pub hostname: String,
    /// Which boot of which machine it runs on (nodes with the host's share its clock).
    pub boot_id: String,
    /// Which shared memory it sees ([`crate::shm::domain`]).
    pub shm_domain: String,
    /// CPUs the process may run on, and CPUs online on its machine.
    pub cpus: u32,
    pub machine_cpus: u32,
}

impl Registration {
    /// The registration a control message carries, if it is one.
    pub fn from_message(message: Message) -> Option<Registration> {
        match message {
            Message::Register {
                role,
                advertise,
                pid,
                hostname,
                boot_id,
                shm_domain,
                cpus,
                machine_cpus,
            } => Some(Registration {
                role,
                advertise,
                pid,
                hostname,
                boot_id,
                shm_domain,
                cpus,
                machine_cpus,
            }),
            _ => None,
        }
    }
}

/// A registered member of the cluster.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Member {
    pub node: NodeId,
    pub role: Role,
    pub advertise: String,
    pub pid: u32,
    pub hostname: String,
    pub boot_id: String,
    /// Which shared memory it sees: render nodes read a card's segment in place only with
    /// its fork node's domain.
    pub shm_domain: String,
    /// CPUs the process may run on, and CPUs online on its machine (the host's scheduler
    /// keeps a machine from running more render nodes at once than it has CPUs).
    pub cpus: u32,
    pub machine_cpus: u32,
}

/// Why the host turns a registering node away. The text is what that node prints.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    #[error("a {role} cannot join a cluster as a node")]
    NotANode { role: Role },
    #[error("the cluster has no free {role} slot ({topology} is full and connecting its links)")]
    Late { role: Role, topology: String },
    #[error("node {node} already registered from {advertise}; two nodes cannot share an address")]
    DuplicateAddress { node: NodeId, advertise: String },
    #[error("the cluster has no free {role} slot ({topology} is full)")]
    Full { role: Role, topology: String },
}

/// Where formation stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Slots are still free; nodes register.
    Registering,
    /// Every slot is filled and the address table is out; nodes connect their links.
    Linking,
    /// Every node reported its links up.
    Formed,
}

/// What admitting a node changed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Admitted {
    /// Members so far, this one included.
    pub joined: usize,
    pub slots: usize,
    /// The node shares the host's machine (and so its monotonic clock).
    pub same_machine: bool,
    /// Set when this node filled the last slot: the address table every member gets
    /// (node, address, boot id; the host's own address is left empty, since nodes reach it
    /// at the address they joined with).
    pub addresses: Option<Vec<(NodeId, String, String)>>,
}

/// The host's record of a forming cluster.
pub struct Registry {
    topology: Arc<Topology>,
    host_boot_id: String,
    members: BTreeMap<NodeId, Member>,
    links_up: BTreeSet<NodeId>,
    phase: Phase,
    deadline: Instant,
    timeout: Duration,
}

impl Registry {
    /// A registry with every slot free, which gives up at `started + timeout`.
    pub fn new(
        topology: Arc<Topology>,
        host_boot_id: String,
        started: Instant,
        timeout: Duration,
    ) -> Registry {
        Registry {
            topology,
            host_boot_id,
            members: BTreeMap::new(),
            links_up: BTreeSet::new(),
            phase: Phase::Registering,
            deadline: started + timeout,
            timeout,
        }
    }

    /// Node slots to fill: every node of the topology but the host.
    pub fn slots(&self) -> usize {
        self.topology.len() - 1
    }

    pub fn phase(&self) -> Phase {
        self.phase
    }

    pub fn deadline(&self) -> Instant {
        self.deadline
    }

    pub fn members(&self) -> impl Iterator<Item = &Member> {
        self.members.values()
    }

    /// The slot `registration` would get: the lowest free id of its role. Nothing changes
    /// until [`Registry::admit`], so that a node whose answer cannot be written takes no slot.
    pub fn slot_for(&self, registration: &Registration) -> Result<NodeId, Refusal> {
        let role = registration.role;
        if role == Role::Host {
            return Err(Refusal::NotANode { role });
        }
        if self.phase != Phase::Registering {
            return Err(Refusal::Late {
                role,
                topology: self.topology.name.clone(),
            });
        }
        if let Some(m) = self
            .members
            .values()
            .find(|m| m.advertise == registration.advertise)
        {
            return Err(Refusal::DuplicateAddress {
                node: m.node,
                advertise: m.advertise.clone(),
            });
        }
        (1..self.topology.len() as NodeId)
            .find(|&n| self.topology.role(n) == role && !self.members.contains_key(&n))
            .ok_or_else(|| Refusal::Full {
                role,
                topology: self.topology.name.clone(),
            })
    }

    /// Takes `registration` into slot `node` (which [`Registry::slot_for`] chose).
    pub fn admit(&mut self, node: NodeId, registration: Registration) -> Admitted {
        debug_assert_eq!(self.slot_for(&registration), Ok(node));
        let same_machine = registration.boot_id == self.host_boot_id;
        self.members.insert(
            node,
            Member {
                node,
                role: registration.role,
                advertise: registration.advertise,
                pid: registration.pid,
                hostname: registration.hostname,
                boot_id: registration.boot_id,
                shm_domain: registration.shm_domain,
                cpus: registration.cpus,
                machine_cpus: registration.machine_cpus,
            },
        );
        let full = self.members.len() == self.slots();
        if full {
            self.phase = Phase::Linking;
        }
        Admitted {
            joined: self.members.len(),
            slots: self.slots(),
            same_machine,
            addresses: full.then(|| self.address_table()),
        }
    }

    fn address_table(&self) -> Vec<(NodeId, String, String)> {
        let mut table: Vec<(NodeId, String, String)> = self
            .members
            .values()
            .map(|m| (m.node, m.advertise.clone(), m.boot_id.clone()))
            .collect();
        table.push((0, String::new(), self.host_boot_id.clone()));
        table.sort();
        table
    }

    /// The connections the host opens itself once the address table is out, with the
    /// address of each.
    pub fn host_dials(&self) -> Vec<(NodeId, String, ConnectionKind)> {
        dials(&self.topology, 0)
            .into_iter()
            .filter_map(|(peer, kind)| {
                let member = self.members.get(&peer)?;
                Some((peer, member.advertise.clone(), kind))
            })
            .collect()
    }

    /// Member `node` reports that its links are up.
    pub fn links_up(&mut self, node: NodeId) {
        if self.phase != Phase::Linking || !self.members.contains_key(&node) {
            return;
        }
        self.links_up.insert(node);
        if self.links_up.len() == self.slots() {
            self.phase = Phase::Formed;
        }
    }

    /// Member `node`'s control connection closed. Before the address table its slot is
    /// simply free again; after it, every member has been told to link to that node, so
    /// the cluster cannot form.
    pub fn lost(&mut self, node: NodeId) -> Result<(), ClusterError> {
        match self.phase {
            Phase::Registering => {
                self.members.remove(&node);
                Ok(())
            }
            Phase::Linking | Phase::Formed => Err(ClusterError::NodeLeft { node }),
        }
    }

    pub fn is_formed(&self) -> bool {
        self.phase == Phase::Formed
    }

    /// At time `now`: fine, or a timeout saying what formation was still waiting for.
    pub fn check_time(&self, now: Instant) -> Result<(), ClusterError> {
        if now < self.deadline || self.is_formed() {
            return Ok(());
        }
        let waiting_for = match self.phase {
            Phase::Registering => {
                let (forks, renders) = self.topology.counts();
                let joined = |role| self.members.values().filter(|m| m.role == role).count();
                Waiting::Joins {
                    forks_joined: joined(Role::Fork),
                    forks,
                    renders_joined: joined(Role::Render),
                    renders,
                }
            }
            Phase::Linking | Phase::Formed => Waiting::LinksUp {
                up: self.links_up.len(),
                slots: self.slots(),
                waiting: self
                    .members
                    .keys()
                    .copied()
                    .filter(|n| !self.links_up.contains(n))
                    .collect(),
            },
        };
        Err(ClusterError::Timeout {
            seconds: self.timeout.as_secs(),
            waiting_for,
        })
    }

    /// The members, by node id, once formed.
    pub fn into_members(self) -> Vec<Member> {
        self.members.into_values().collect()
    }
}

/// The address a node asks its peers to dial: the one configured, else the listening
/// address when it names one interface, else the address this machine reaches the host
/// from (the listening port in every case but the first).
pub fn advertise_address(
    configured: Option<&str>,
    listen: &str,
    port: u16,
    toward_host: IpAddr,
) -> String {
    if let Some(address) = configured {
        return address.to_string();
    }
    let listen_ip = listen
        .rsplit_once(':')
        .map(|(ip, _)| ip.trim_matches(['[', ']']))
        .unwrap_or("");
    match listen_ip.parse::<IpAddr>() {
        Ok(ip) if !ip.is_unspecified() => SocketAddr::new(ip, port).to_string(),
        _ => SocketAddr::new(toward_host, port).to_string(),
    }
}

/// What the host's answer to a `role`'s registration means: its slot and the topology, or
/// why not.
pub fn read_assignment(
    answer: Result<Message, DecodeError>,
    role: Role,
) -> Result<(NodeId, Topology), ClusterError> {
    let (node, topology) = match answer {
        Ok(Message::Assigned { node, topology }) => (node, topology),
        Ok(Message::Refused { reason }) => return Err(ClusterError::Refused(reason)),
        Ok(other) => return Err(ClusterError::UnexpectedAnswer(Box::new(other))),
        Err(e) => return Err(ClusterError::UndecodableAnswer(e)),
    };
    let topology = Topology::from_wire(&topology).map_err(ClusterError::HostTopology)?;
    if node == 0 || node as usize >= topology.len() || topology.role(node) != role {
        return Err(ClusterError::WrongSlot { node, role });
    }
    Ok((node, topology))
}

/// The address table as a node uses it: by node, with the host at `host` (the address the
/// node joined with; the table leaves it empty).
pub fn peer_table(
    addresses: Vec<(NodeId, String, String)>,
    host: &str,
) -> HashMap<NodeId, (String, String)> {
    let mut table: HashMap<NodeId, (String, String)> =
        addresses.into_iter().map(|(n, a, b)| (n, (a, b))).collect();
    if let Some(entry) = table.get_mut(&0) {
        entry.0 = host.to_string();
    }
    table
}

#[cfg(test)]
mod tests {
    use super::*;

    const HOST_BOOT: &str = "host-boot";

    fn registry(preset: &str) -> (Registry, Instant) {
        let started = Instant::now();
        let topology = Arc::new(Topology::preset(preset).unwrap());
        let registry = Registry::new(topology, HOST_BOOT.into(), started, Duration::from_secs(20));
        (registry, started)
    }

    fn node(role: Role, port: u16) -> Registration {
        Registration {
            role,
            advertise: format!("10.0.0.1:{port}"),
            pid: 1000 + port as u32,
            hostname: "box".into(),
            boot_id: if port.is_multiple_of(2) {
                HOST_BOOT
            } else {
                "other"
            }
            .into(),
            shm_domain: "box-shm".into(),
            cpus: 2,
            machine_cpus: 2,
        }
    }

    /// Offers and admits, as `form` does.
    fn register(r: &mut Registry, reg: Registration) -> Result<Admitted, Refusal> {
        let slot = r.slot_for(&reg)?;
        Ok(r.admit(slot, reg))
    }

    /// Fills every slot of a tiny cluster (host 0, fork 1, render nodes 2 to 5).
    fn fill_tiny(r: &mut Registry) -> Admitted {
        register(r, node(Role::Fork, 1)).unwrap();
        for port in 2..5 {
            register(r, node(Role::Render, port)).unwrap();
        }
        register(r, node(Role::Render, 5)).unwrap()
    }

    #[test]
    fn slots_go_by_role_in_id_order() {
        // grid:2x1x1 is host 0, fork nodes 1 and 2, render nodes 3 (card 0) and 4 (card 1).
        let (mut r, _) = registry("grid:2x1x1");
        assert_eq!(r.slots(), 4);
        let a = register(&mut r, node(Role::Render, 10)).unwrap();
        assert_eq!((a.joined, a.slots), (1, 4));
        assert_eq!(r.members().last().unwrap().node, 3);
        register(&mut r, node(Role::Fork, 11)).unwrap();
        register(&mut r, node(Role::Render, 12)).unwrap();
        register(&mut r, node(Role::Fork, 13)).unwrap();
        let ids: Vec<(NodeId, u16)> = r
            .members()
            .map(|m| (m.node, m.advertise[9..].parse().unwrap()))
            .collect();
        assert_eq!(ids, vec![(1, 11), (2, 13), (3, 10), (4, 12)]);
    }

    #[test]
    fn offering_a_slot_takes_nothing_until_admitted() {
        let (mut r, _) = registry("tiny");
        let reg = node(Role::Fork, 1);
        assert_eq!(r.slot_for(&reg), Ok(1));
        // The answer could not be written: the next fork node gets the same slot.
        assert_eq!(r.slot_for(&node(Role::Fork, 2)), Ok(1));
        assert_eq!(r.members().count(), 0);
        r.admit(1, reg);
        assert_eq!(r.members().count(), 1);
    }

    #[test]
    fn same_machine_follows_the_boot_id() {
        let (mut r, _) = registry("tiny");
        assert!(
            register(&mut r, node(Role::Render, 2))
                .unwrap()
                .same_machine
        );
        assert!(
            !register(&mut r, node(Role::Render, 3))
                .unwrap()
                .same_machine
        );
    }

    #[test]
    fn a_role_with_no_free_slot_is_refused_as_full() {
        let (mut r, _) = registry("tiny");
        register(&mut r, node(Role::Fork, 1)).unwrap();
        let refusal = register(&mut r, node(Role::Fork, 2)).unwrap_err();
        assert_eq!(
            refusal,
            Refusal::Full {
                role: Role::Fork,
                topology: "tiny".into()
            }
        );
        assert!(refusal.to_string().contains("full"), "{refusal}");
        assert_eq!(r.phase(), Phase::Registering);
    }

    #[test]
    fn the_host_role_is_refused() {
        let (mut r, _) = registry("tiny");
        assert_eq!(
            register(&mut r, node(Role::Host, 1)).unwrap_err(),
            Refusal::NotANode { role: Role::Host }
        );
    }

    #[test]
    fn a_second_node_at_the_same_address_is_refused() {
        let (mut r, _) = registry("tiny");
        register(&mut r, node(Role::Render, 7)).unwrap();
        let mut twin = node(Role::Render, 7);
        twin.pid = 4242;
        assert_eq!(
            register(&mut r, twin).unwrap_err(),
            Refusal::DuplicateAddress {
                node: 2,
                advertise: "10.0.0.1:7".into()
            }
        );
        assert_eq!(r.members().count(), 1);
    }

    #[test]
    fn the_last_slot_sends_the_address_table_and_the_host_dials() {
        let (mut r, _) = registry("tiny");
        let last = fill_tiny(&mut r);
        assert_eq!((last.joined, last.slots), (5, 5));
        assert_eq!(r.phase(), Phase::Linking);
        let table = last.addresses.unwrap();
        let ids: Vec<NodeId> = table.iter().map(|(n, _, _)| *n).collect();
        assert_eq!(ids, vec![0, 1, 2, 3, 4, 5]);
        assert_eq!(table[0], (0, String::new(), HOST_BOOT.to_string()));
        assert_eq!(table[1], (1, "10.0.0.1:1".into(), "other".into()));
        // The host's only link is the mesh link to the fork node; the fork node dials the
        // host's direct connection itself.
        assert_eq!(
            r.host_dials(),
            vec![(1, "10.0.0.1:1".to_string(), ConnectionKind::Mesh)]
        );
    }

    #[test]
    fn only_the_last_slot_carries_the_address_table() {
        let (mut r, _) = registry("tiny");
        let first = register(&mut r, node(Role::Fork, 1)).unwrap();
        assert_eq!(first.addresses, None);
        assert_eq!(r.phase(), Phase::Registering);
    }

    #[test]
    fn a_late_joiner_is_refused_with_the_reason() {
        let (mut r, _) = registry("tiny");
        fill_tiny(&mut r);
        let refusal = register(&mut r, node(Role::Render, 9)).unwrap_err();
        assert_eq!(
            refusal,
            Refusal::Late {
                role: Role::Render,
                topology: "tiny".into()
            }
        );
        assert!(refusal.to_string().contains("full"), "{refusal}");
    }

    #[test]
    fn formed_once_every_member_reports_its_links() {
        let (mut r, _) = registry("tiny");
        // Reports before the table, or from strangers, count for nothing.
        r.links_up(1);
        fill_tiny(&mut r);
        r.links_up(9);
        for n in [5, 1, 3, 2] {
            r.links_up(n);
            assert!(!r.is_formed(), "formed after node {n}");
        }
        r.links_up(3);
        assert!(!r.is_formed());
        r.links_up(4);
        assert!(r.is_formed());
        let members = r.into_members();
        let ids: Vec<NodeId> = members.iter().map(|m| m.node).collect();
        assert_eq!(ids, vec![1, 2, 3, 4, 5]);
        assert_eq!(members[0].role, Role::Fork);
    }

    #[test]
    fn a_node_lost_while_registering_frees_its_slot() {
        let (mut r, _) = registry("tiny");
        register(&mut r, node(Role::Render, 2)).unwrap();
        register(&mut r, node(Role::Render, 3)).unwrap();
        r.lost(2).unwrap();
        assert_eq!(r.slot_for(&node(Role::Render, 4)), Ok(2));
        // Its address is free again too.
        assert_eq!(r.slot_for(&node(Role::Render, 2)), Ok(2));
    }

    #[test]
    fn a_node_lost_after_the_address_table_ends_formation() {
        let (mut r, _) = registry("tiny");
        fill_tiny(&mut r);
        let e = r.lost(4).unwrap_err();
        assert!(matches!(e, ClusterError::NodeLeft { node: 4 }), "{e}");
    }

    #[test]
    fn waiting_for_joins_times_out_at_the_deadline_saying_who_is_missing() {
        let (mut r, started) = registry("tiny");
        register(&mut r, node(Role::Render, 2)).unwrap();
        assert!(r.check_time(started + Duration::from_secs(19)).is_ok());
        assert_eq!(r.deadline(), started + Duration::from_secs(20));
        let e = r.check_time(started + Duration::from_secs(20)).unwrap_err();
        let ClusterError::Timeout {
            seconds,
            waiting_for,
        } = e
        else {
            panic!("{e}")
        };
        assert_eq!(seconds, 20);
        assert_eq!(
            waiting_for,
            Waiting::Joins {
                forks_joined: 0,
                forks: 1,
                renders_joined: 1,
                renders: 4
            }
        );
        assert_eq!(
            waiting_for.to_string(),
            "0 of 1 fork nodes and 1 of 4 render nodes joined"
        );
    }

    #[test]
    fn waiting_for_links_times_out_naming_the_silent_nodes() {
        let (mut r, started) = registry("tiny");
        fill_tiny(&mut r);
        r.links_up(1);
        r.links_up(3);
        let e = r.check_time(started + Duration::from_secs(21)).unwrap_err();
        let ClusterError::Timeout { waiting_for, .. } = e else {
            panic!("{e}")
        };
        assert_eq!(
            waiting_for,
            Waiting::LinksUp {
                up: 2,
                slots: 5,
                waiting: vec![2, 4, 5]
            }
        );
    }

    #[test]
    fn a_formed_cluster_does_not_time_out() {
        let (mut r, started) = registry("tiny");
        fill_tiny(&mut r);
        for n in 1..=5 {
            r.links_up(n);
        }
        assert!(r.check_time(started + Duration::from_secs(3600)).is_ok());
    }

    #[test]
    fn registration_comes_only_from_register_messages() {
        assert_eq!(Registration::from_message(Message::Go), None);
        let m = Message::Register {
            role: Role::Fork,
            advertise: "a:1".into(),
            pid: 7,
            hostname: "h".into(),
            boot_id: "b".into(),
            shm_domain: "b/1:2".into(),
            cpus: 2,
            machine_cpus: 4,
        };
        assert_eq!(Registration::from_message(m).unwrap().pid, 7);
    }

    #[test]
    fn advertise_prefers_configured_then_listen_then_the_route_to_the_host() {
        let toward_host: IpAddr = "192.168.1.5".parse().unwrap();
        assert_eq!(
            advertise_address(Some("node7:9000"), "0.0.0.0:0", 4000, toward_host),
            "node7:9000"
        );
        assert_eq!(
            advertise_address(None, "10.1.2.3:0", 4000, toward_host),
            "10.1.2.3:4000"
        );
        assert_eq!(
            advertise_address(None, "0.0.0.0:0", 4000, toward_host),
            "192.168.1.5:4000"
        );
        assert_eq!(
            advertise_address(None, "[::1]:0", 4000, toward_host),
            "[::1]:4000"
        );
        assert_eq!(
            advertise_address(None, "[::]:0", 4000, toward_host),
            "192.168.1.5:4000"
        );
    }

    #[test]
    fn an_assignment_is_checked_against_the_role() {
        let tiny = Topology::preset("tiny").unwrap().to_wire();
        let assigned = |node| {
            Ok(Message::Assigned {
                node,
                topology: tiny.clone(),
            })
        };
        let (node, topology) = read_assignment(assigned(3), Role::Render).unwrap();
        assert_eq!((node, topology.len()), (3, 6));
        let e = read_assignment(assigned(1), Role::Render).unwrap_err();
        assert!(
            matches!(
                e,
                ClusterError::WrongSlot {
                    node: 1,
                    role: Role::Render
                }
            ),
            "{e}"
        );
        let e = read_assignment(assigned(40), Role::Render).unwrap_err();
        assert!(matches!(e, ClusterError::WrongSlot { node: 40, .. }), "{e}");
    }

    #[test]
    fn a_refusal_or_a_stray_answer_is_an_error() {
        let refused = Ok(Message::Refused {
            reason: "no room".into(),
        });
        let e = read_assignment(refused, Role::Fork).unwrap_err();
        assert_eq!(e.to_string(), "the host refused this node: no room");
        let e = read_assignment(Ok(Message::Go), Role::Fork).unwrap_err();
        assert!(matches!(e, ClusterError::UnexpectedAnswer(_)), "{e}");
        let bad = Ok(Message::Assigned {
            node: 1,
            topology: b"not a topology".to_vec(),
        });
        let e = read_assignment(bad, Role::Fork).unwrap_err();
        assert!(matches!(e, ClusterError::HostTopology(_)), "{e}");
    }

    #[test]
    fn the_peer_table_reaches_the_host_where_the_node_joined() {
        let table = peer_table(
            vec![
                (0, String::new(), "hb".into()),
                (1, "10.0.0.1:1".into(), "b1".into()),
            ],
            "host.example:7000",
        );
        assert_eq!(table[&0], ("host.example:7000".into(), "hb".into()));
        assert_eq!(table[&1], ("10.0.0.1:1".into(), "b1".into()));
    }
}
