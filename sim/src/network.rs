//! The mesh as the simulator sees it: every directed link's model clock, and the routes the
//! real fabric takes, fixed once (no node dies in a simulation).
//!
//! A message is a **flow**, not packets one by one: when it is sent, it books every link of
//! its route at once, in the order messages are sent, with `fabric::model::LinkClock::cross`
//! (its packets pipelined store-and-forward, each link FIFO). That is what the real fabric
//! does too: a frame is forwarded at once and stamped with model times as it crosses each
//! link, and only its receiver waits for them, so the two book the same clocks in the same
//! way.

use std::collections::HashMap;

use fabric::{Model, Topology, model::LinkClock, routing::Routes};
use protocol::NodeId;

/// One link crossing of a route.
#[derive(Clone, Copy, Debug)]
pub struct Hop {
    link: usize,
    vertical: bool,
}

pub struct Network {
    pub model: Model,
    clocks: Vec<LinkClock>,
    index: HashMap<(NodeId, NodeId), usize>,
    routes: Routes,
    topology: Topology,
    pub messages: u64,
    pub wire_bytes: u64,
    /// Real time each hop costs beyond its modelled link time ([`crate::Overheads`]).
    pub hop_overhead_ns: u64,
}

/// The hops of a message from `from` to `to` along the fabric's routes, all nodes alive.
pub fn hops(topology: &Topology, from: NodeId, to: NodeId) -> usize {
    Routes::all_alive(topology)
        .path(from, to)
        .map_or(0, |p| p.len().saturating_sub(1))
}

impl Network {
    pub fn new(topology: &Topology, model: Model) -> Network {
        let mut index = HashMap::new();
        for &[a, b] in &topology.links {
            let next = index.len();
            index.insert((a, b), next);
            index.insert((b, a), next + 1);
        }
        Network {
            model,
            clocks: vec![LinkClock::default(); index.len()],
            index,
            routes: Routes::all_alive(topology),
            topology: topology.clone(),
            messages: 0,
            wire_bytes: 0,
            hop_overhead_ns: 0,
        }
    }

    /// The links from `from` to `to` along the fabric's routes.
    pub fn route(&self, from: NodeId, to: NodeId) -> Vec<Hop> {
        let path = self
            .routes
            .path(from, to)
            .expect("a validated topology is connected");
        path.windows(2)
            .map(|w| Hop {
                link: self.index[&(w[0], w[1])],
                vertical: self.topology.is_vertical(w[0], w[1]),
            })
            .collect()
    }

    /// A message of `wire_bytes` whose data is ready at `ready` crosses `route`: when its
    /// last packet is at the far end. The sender's software overhead is paid once, first.
    pub fn send(&mut self, route: &[Hop], wire_bytes: usize, ready: u64) -> u64 {
        self.messages += 1;
        self.wire_bytes += wire_bytes as u64;
        let ready = ready + self.hop_overhead_ns * route.len().max(1) as u64;
        if !self.model.links_delayed() {
            return ready;
        }
        let start = ready + self.model.base_ns();
        let (packets, size) = self.model.packets(wire_bytes);
        let (mut first, mut last) = (start, start);
        for hop in route {
            let time = self.model.hop_ns(hop.vertical, size);
            (first, last) = self.clocks[hop.link].cross(first, last, packets, time);
        }
        last
    }
}

#[cfg(test)]
mod tests {
    use fabric::model::ModelParams;

    use super::*;

    #[test]
    fn routes_follow_the_fabric_and_know_their_direction() {
        let t = Topology::preset("tiny").unwrap();
        let n = Network::new(&t, Model::paper());
        // Host 0 - fork 1 - render 2 (0,0); 5 is at (1,1): one column step, one row step.
        let r = n.route(5, 0);
        assert_eq!(r.len(), 4);
        assert_eq!(r.iter().filter(|h| h.vertical).count(), 1);
    }

    #[test]
    fn an_84_byte_packet_takes_the_papers_formula_hop_by_hop() {
        let t = Topology::preset("magg").unwrap();
        let mut n = Network::new(&t, Model::paper());
        let at = |row: i32, col: i32| {
            (0..t.len() as NodeId)
                .find(|&i| t.position(i) == Some((row, col)))
                .unwrap()
        };
        // One step along a row: 310 + 300 us.
        let one = n.route(at(0, 0), at(0, 1));
        assert_eq!(n.send(&one, 84, 0), 610_000);
        // (3,3) to (0,0): three steps along the row, three along the column.
        let chain = n.route(at(3, 3), at(0, 0));
        assert_eq!(chain.len(), 6);
        let start = 10_000_000;
        assert_eq!(
            n.send(&chain, 84, start),
            start + (310 + 3 * 234 + 3 * 300) * 1000
        );
        // A second message on the same links waits for the first, link by link: it arrives
        // one (slowest) hop after it.
        assert_eq!(
            n.send(&chain, 84, start),
            start + (310 + 3 * 234 + 3 * 300 + 300) * 1000
        );
    }

    #[test]
    fn without_a_link_model_a_message_arrives_when_sent() {
        let t = Topology::preset("tiny").unwrap();
        let mut n = Network::new(&t, Model::new(ModelParams::default()));
        let r = n.route(5, 0);
        assert_eq!(n.send(&r, 100_000, 77), 77);
        assert_eq!((n.messages, n.wire_bytes), (1, 100_000));
    }
}
