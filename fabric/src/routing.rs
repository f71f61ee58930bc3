//! Where a frame goes next.
//!
//! Unicast routes are shortest paths over the live nodes; among equally short next hops a
//! node prefers a step along its mesh row, then along its column, then any other link, then
//! the lowest id. On a mesh that is dimension-ordered routing (column distance first, then
//! row), and it still finds a way around a dead node. A broadcast from a root travels the
//! spanning tree made of everyone's unicast route towards that root, reversed, so every live
//! node receives it exactly once.

use std::collections::VecDeque;

use protocol::NodeId;

use crate::topology::Topology;

const NONE: NodeId = NodeId::MAX;

#[derive(Clone, Debug)]
pub struct Routes {
    n: usize,
    next: Vec<NodeId>,
    alive: Vec<bool>,
    /// Broadcast children, flat: those of `at` for a broadcast from `root` are
    /// `children[child_start[root * n + at]..child_start[root * n + at + 1]]`. Every process
    /// of a cluster computes its routes at start, so they are built without an allocation
    /// per (root, node) pair (86 x 86 of them on the paper's machine).
    children: Vec<NodeId>,
    child_start: Vec<u32>,
}

fn step_rank(t: &Topology, from: NodeId, to: NodeId) -> u8 {
    match (t.position(from), t.position(to)) {
        (Some((ra, _)), Some((rb, _))) if ra == rb => 0,
        (Some((_, ca)), Some((_, cb))) if ca == cb => 1,
        _ => 2,
    }
}

impl Routes {
    pub fn compute(t: &Topology, alive: &[bool]) -> Routes {
        let n = t.len();
        let mut next = vec![NONE; n * n];
        let mut dist = vec![u32::MAX; n];
        let mut q = VecDeque::with_capacity(n);
        for dest in 0..n {
            if !alive[dest] {
                continue;
            }
            dist.fill(u32::MAX);
            dist[dest] = 0;
            q.push_back(dest as NodeId);
            while let Some(x) = q.pop_front() {
                for &y in t.neighbors(x) {
                    if alive[y as usize] && dist[y as usize] == u32::MAX {
                        dist[y as usize] = dist[x as usize] + 1;
                        q.push_back(y);
                    }
                }
            }
            for at in 0..n {
                if at == dest || !alive[at] || dist[at] == u32::MAX {
                    continue;
                }
                let best = t
                    .neighbors(at as NodeId)
                    .iter()
                    .copied()
                    .filter(|&m| alive[m as usize] && dist[m as usize] + 1 == dist[at])
                    .min_by_key(|&m| (step_rank(t, at as NodeId, m), m));
                if let Some(m) = best {
                    next[at * n + dest] = m;
                }
            }
        }
        // Counted first, then filled in place: each (root, hop) list in increasing id order.
        let mut child_start = vec![0u32; n * n + 1];
        for root in 0..n {
            for m in 0..n {
                let hop = next[m * n + root];
                if hop != NONE {
                    child_start[root * n + hop as usize + 1] += 1;
                }
            }
        }
        for i in 1..child_start.len() {
            child_start[i] += child_start[i - 1];
        }
        let mut fill = child_start.clone();
        let mut children = vec![NONE; child_start[n * n] as usize];
        for root in 0..n {
            for m in 0..n {
                let hop = next[m * n + root];
                if hop != NONE {
                    let at = &mut fill[root * n + hop as usize];
                    children[*at as usize] = m as NodeId;
                    *at += 1;
                }
            }
        }
        Routes {
            n,
            next,
            alive: alive.to_vec(),
            children,
            child_start,
        }
    }

    pub fn all_alive(t: &Topology) -> Routes {
        Routes::compute(t, &vec![true; t.len()])
    }

    /// The neighbour to send a frame for `dest` to, or `None` when it cannot be reached.
    pub fn next_hop(&self, at: NodeId, dest: NodeId) -> Option<NodeId> {
        let (at, dest) = (at as usize, dest as usize);
        if at >= self.n || dest >= self.n {
            return None;
        }
        let h = self.next[at * self.n + dest];
        (h != NONE).then_some(h)
    }

    /// Neighbours `at` passes a broadcast from `root` on to.
    pub fn broadcast_children(&self, at: NodeId, root: NodeId) -> &[NodeId] {
        let (root, at) = (root as usize, at as usize);
        if root >= self.n || at >= self.n {
            return &[];
        }
        let slot = root * self.n + at;
        &self.children[self.child_start[slot] as usize..self.child_start[slot + 1] as usize]
    }

    /// Which nodes these routes treat as alive, by id.
    pub fn alive(&self) -> &[bool] {
        &self.alive
    }

    pub fn is_alive(&self, id: NodeId) -> bool {
        self.alive.get(id as usize).copied().unwrap_or(false)
    }

    /// The whole path from `from` to `to`, both included.
    pub fn path(&self, from: NodeId, to: NodeId) -> Option<Vec<NodeId>> {
        let mut path = vec![from];
        let mut at = from;
        while at != to {
            at = self.next_hop(at, to)?;
            path.push(at);
            if path.len() > self.n {
                return None;
            }
        }
        Some(path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mesh_routes_go_column_first_then_row() {
        let t = Topology::preset("magg").unwrap();
        let r = Routes::all_alive(&t);
        let at = |row: i32, col: i32| {
            (0..t.len() as NodeId)
                .find(|&i| t.position(i) == Some((row, col)))
                .unwrap()
        };
        let path = r.path(at(3, 3), at(0, 0)).unwrap();
        let pos: Vec<(i32, i32)> = path.iter().map(|&i| t.position(i).unwrap()).collect();
        assert_eq!(
            pos,
            vec![(3, 3), (3, 2), (3, 1), (3, 0), (2, 0), (1, 0), (0, 0)]
        );
        // A render node reaches its fork node through the card's entry node.
        let fork = t.fork_of(at(3, 3)).unwrap();
        assert_eq!(*r.path(at(3, 3), fork).unwrap().last().unwrap(), fork);
    }

    #[test]
    fn broadcast_reaches_everyone_once() {
        let t = Topology::preset("magg").unwrap();
        let r = Routes::all_alive(&t);
        for root in [0u16, 1, 30] {
            let mut got = vec![0; t.len()];
            let mut q = VecDeque::from([root]);
            got[root as usize] += 1;
            while let Some(x) = q.pop_front() {
                for &c in r.broadcast_children(x, root) {
                    got[c as usize] += 1;
                    q.push_back(c);
                }
            }
            assert!(got.iter().all(|&g| g == 1), "root {root}: {got:?}");
        }
    }

    #[test]
    fn routes_avoid_a_dead_node() {
        let t = Topology::preset("magg").unwrap();
        let mut alive = vec![true; t.len()];
        let at = |row: i32, col: i32| {
            (0..t.len() as NodeId)
                .find(|&i| t.position(i) == Some((row, col)))
                .unwrap()
        };
        let dead = at(3, 1);
        alive[dead as usize] = false;
        let r = Routes::compute(&t, &alive);
        let path = r.path(at(3, 3), at(3, 0)).unwrap();
        assert!(!path.contains(&dead));
        assert!(r.next_hop(at(3, 2), dead).is_none());
    }
}
