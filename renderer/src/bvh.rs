//! Building trees (with obvhs) and their compact form on the wire.
//!
//! A chunk's tree travels as its shape only: nodes of eight child references, each an
//! inner node, a leaf of one to four triangles (consecutive in the chunk's leaf order), or
//! nothing. No boxes travel: the receiver computes them from the triangles themselves when
//! it transcodes the tree into the form rays walk ([`crate::accel`]), so they are exact and
//! need no trust in the sender, and a node costs 32 bytes on the wire. [`validate_tree`]
//! checks received nodes before anything else reads them.
//!
//! Building: obvhs makes a binary tree (PLOC, then reinsertion), which is then collapsed
//! into the wide tree of least expected cost under the surface area heuristic, by dynamic
//! programming over the binary tree (Ylitie, Karras and Laine, "Efficient Incoherent Ray
//! Traversal on GPUs Through Compressed Wide BVHs", 2017): for every binary node and every
//! number of slots from one to eight, the cheapest way to represent its subtree in that many
//! child slots, each slot a leaf of up to four primitives (one four-lane test) or a wide
//! node. Deterministic: obvhs is used without its parallel feature, and ties keep the first
//! choice, so the same boxes give the same tree.

use obvhs::{BvhBuildParams, aabb::Aabb, bvh2::Bvh2};

/// Deepest tree accepted: the walk's stack is sized for it.
pub const MAX_DEPTH: usize = 48;

/// Children of one wide node: [`EMPTY`], an inner node index (bit 31 clear), or a leaf
/// ([`LEAF`] set; bits 2..31 the first primitive, bits 0..2 the count less one).
pub type WideNode = [u32; 8];

/// A child slot with nothing in it.
pub const EMPTY: u32 = u32::MAX;

/// The bit that marks a leaf child.
pub const LEAF: u32 = 1 << 31;

/// Most primitives in one leaf: one four-lane triangle test.
pub const MAX_LEAF: u32 = 4;

/// A leaf child reference, or `None` when `first` does not fit.
pub fn leaf(first: u32, count: u32) -> Option<u32> {
    (first < (1 << 29) && (1..=MAX_LEAF).contains(&count))
        .then(|| LEAF | (first << 2) | (count - 1))
}

/// What a child reference holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Child {
    Empty,
    Node(u32),
    Leaf { first: u32, count: u32 },
}

#[inline(always)]
pub fn child(r: u32) -> Child {
    if r == EMPTY {
        Child::Empty
    } else if r & LEAF == 0 {
        Child::Node(r)
    } else {
        Child::Leaf {
            first: (r & !LEAF) >> 2,
            count: (r & 3) + 1,
        }
    }
}

/// A built tree: nodes (root first, parents before children) and the input primitives in
/// leaf order.
pub struct WideTree {
    pub nodes: Vec<WideNode>,
    pub order: Vec<u32>,
}

/// Expected cost of testing a wide node and a leaf, relative to each other (the four-lane
/// triangle test of a leaf costs about what the eight-lane box test of a node does).
const NODE_COST: f32 = 1.0;
const LEAF_COST: f32 = 1.0;

/// Builds a tree over boxes with at most `max_leaf` (1 to 4) primitives a leaf.
pub fn build(boxes: &[Aabb], max_leaf: u32) -> WideTree {
    let mut out = WideTree {
        nodes: Vec::new(),
        order: Vec::with_capacity(boxes.len()),
    };
    if boxes.is_empty() {
        return out;
    }
    let mut params = BvhBuildParams::medium_build();
    // Leaves are chosen by the collapse below; obvhs keeps one primitive a leaf.
    params.max_prims_per_leaf = 1;
    params.post_collapse_reinsertion_batch_ratio_multiplier = 0.0;
    let bvh2 = obvhs::bvh2::builder::build_bvh2(boxes, params, &mut Default::default());
    let plan = Collapse::plan(&bvh2, max_leaf.clamp(1, MAX_LEAF));
    plan.emit_node(&bvh2, 0, &mut out);
    out
}

/// How a binary subtree is best represented in `i` slots (index `i - 1`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Choice {
    /// One slot: a leaf holding every primitive of the subtree.
    Leaf,
    /// One slot: a wide node.
    Node,
    /// The left child in this many slots, the right in the rest.
    Split(u8),
    /// As well as in one slot fewer.
    Fewer,
}

struct Collapse {
    /// Per binary node: the cheapest cost in 1..=8 slots, and how.
    cost: Vec<[f32; 8]>,
    how: Vec<[Choice; 8]>,
    /// The best split of a wide node's eight slots between its binary node's children.
    node_split: Vec<u8>,
}

impl Collapse {
    fn plan(b: &Bvh2, max_leaf: u32) -> Collapse {
        let n = &b.nodes;
        let mut c = Collapse {
            cost: vec![[f32::INFINITY; 8]; n.len()],
            how: vec![[Choice::Fewer; 8]; n.len()],
            node_split: vec![0; n.len()],
        };
        let mut prims = vec![0u32; n.len()];
        // Children before parents: a post-order of the binary tree.
        let mut post = Vec::with_capacity(n.len());
        let mut work = vec![(0usize, false)];
        while let Some((i, expanded)) = work.pop() {
            if expanded || n[i].prim_count != 0 {
                post.push(i);
            } else {
                let first = n[i].first_index as usize;
                work.push((i, true));
                work.push((first + 1, false));
                work.push((first, false));
            }
        }
        for &i in &post {
            let area = n[i].aabb.half_area().max(0.0);
            if n[i].prim_count != 0 {
                prims[i] = n[i].prim_count;
                let leaf = if prims[i] <= max_leaf {
                    area * LEAF_COST
                } else {
                    f32::INFINITY
                };
                c.cost[i] = [leaf; 8];
                c.how[i] = [Choice::Leaf; 8];
                for k in 1..8 {
                    c.how[i][k] = Choice::Fewer;
                }
                continue;
            }
            let (l, r) = (n[i].first_index as usize, n[i].first_index as usize + 1);
            prims[i] = prims[l] + prims[r];
            // distribute[j]: the children in at most j + 1 slots.
            let mut distribute = [(f32::INFINITY, 0u8); 8];
            for (j, d) in distribute.iter_mut().enumerate().skip(1) {
                for k in 1..=j {
                    let cost = c.cost[l][k - 1] + c.cost[r][j - k];
                    if cost < d.0 {
                        *d = (cost, k as u8);
                    }
                }
            }
            let as_node = area * NODE_COST + distribute[7].0;
            c.node_split[i] = distribute[7].1;
            let as_leaf = if prims[i] <= max_leaf {
                area * LEAF_COST
            } else {
                f32::INFINITY
            };
            let (one, how) = if as_leaf <= as_node {
                (as_leaf, Choice::Leaf)
            } else {
                (as_node, Choice::Node)
            };
            c.cost[i][0] = one;
            c.how[i][0] = how;
            for j in 1..8 {
                let (split, k) = distribute[j];
                if split < c.cost[i][j - 1] {
                    c.cost[i][j] = split;
                    c.how[i][j] = Choice::Split(k);
                } else {
                    c.cost[i][j] = c.cost[i][j - 1];
                    c.how[i][j] = Choice::Fewer;
                }
            }
        }
        c
    }

    /// The slots binary node `i` takes when given `slots`: (node, leaf or not).
    fn slots(&self, b: &Bvh2, i: usize, slots: usize, out: &mut Vec<(usize, bool)>) {
        match self.how[i][slots - 1] {
            Choice::Leaf => out.push((i, true)),
            Choice::Node => out.push((i, false)),
            Choice::Fewer => self.slots(b, i, slots - 1, out),
            Choice::Split(k) => {
                let first = b.nodes[i].first_index as usize;
                self.slots(b, first, k as usize, out);
                self.slots(b, first + 1, slots - k as usize, out);
            }
        }
    }

    /// Emits the wide node for binary node `i` (parents before children); its index.
    fn emit_node(&self, b: &Bvh2, i: usize, out: &mut WideTree) -> u32 {
        let me = out.nodes.len();
        out.nodes.push([EMPTY; 8]);
        let mut kids = Vec::with_capacity(8);
        if b.nodes[i].prim_count != 0 || self.how[i][0] == Choice::Leaf {
            kids.push((i, true));
        } else {
            let first = b.nodes[i].first_index as usize;
            let k = self.node_split[i] as usize;
            self.slots(b, first, k, &mut kids);
            self.slots(b, first + 1, 8 - k, &mut kids);
        }
        for (slot, (k, is_leaf)) in kids.into_iter().enumerate() {
            out.nodes[me][slot] = if is_leaf {
                let first = out.order.len() as u32;
                self.emit_leaf(b, k, out);
                let count = out.order.len() as u32 - first;
                // The plan makes leaves of at most MAX_LEAF primitives.
                leaf(first, count).expect("planned leaves hold at most four primitives")
            } else {
                self.emit_node(b, k, out)
            };
        }
        me as u32
    }

    /// Appends every primitive of binary subtree `i` to the leaf order.
    fn emit_leaf(&self, b: &Bvh2, i: usize, out: &mut WideTree) {
        let n = &b.nodes[i];
        if n.prim_count != 0 {
            let start = n.first_index as usize;
            out.order
                .extend_from_slice(&b.primitive_indices[start..start + n.prim_count as usize]);
        } else {
            self.emit_leaf(b, n.first_index as usize, out);
            self.emit_leaf(b, n.first_index as usize + 1, out);
        }
    }
}

/// Why received tree nodes were refused.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum NodeError {
    #[error("node {node} points at node {child} but the tree has {count} nodes")]
    ChildOutOfRange {
        node: usize,
        child: u32,
        count: usize,
    },
    #[error("node {node} points at primitives up to {end} but there are {count}")]
    PrimitiveOutOfRange { node: usize, end: u64, count: usize },
    #[error("the tree is deeper than {MAX_DEPTH} levels or is not a tree")]
    TooDeep,
}

/// Checks that nodes (from the network or disk) form a tree that the walk can follow
/// without leaving the arrays, without looping, within its stack. Returns the depth.
pub fn validate_tree(nodes: &[WideNode], primitive_count: usize) -> Result<usize, NodeError> {
    if nodes.is_empty() {
        return Ok(0);
    }
    let mut visited = vec![false; nodes.len()];
    let mut max_depth = 0;
    let mut work = vec![(0usize, 1usize)];
    while let Some((index, depth)) = work.pop() {
        if depth > MAX_DEPTH || std::mem::replace(&mut visited[index], true) {
            return Err(NodeError::TooDeep);
        }
        max_depth = max_depth.max(depth);
        for &r in &nodes[index] {
            match child(r) {
                Child::Empty => {}
                Child::Node(c) => {
                    if c as usize >= nodes.len() {
                        return Err(NodeError::ChildOutOfRange {
                            node: index,
                            child: c,
                            count: nodes.len(),
                        });
                    }
                    work.push((c as usize, depth + 1));
                }
                Child::Leaf { first, count } => {
                    let end = first as u64 + count as u64;
                    if end > primitive_count as u64 {
                        return Err(NodeError::PrimitiveOutOfRange {
                            node: index,
                            end,
                            count: primitive_count,
                        });
                    }
                }
            }
        }
    }
    Ok(max_depth)
}

/// What a leaf visit tells the walk.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Visit {
    Continue,
    Stop,
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3A;

    fn boxes(n: usize) -> Vec<Aabb> {
        (0..n)
            .map(|i| {
                let x = (i % 10) as f32;
                let y = ((i / 10) % 10) as f32;
                let z = (i / 100) as f32;
                Aabb::new(Vec3A::new(x, y, z), Vec3A::new(x + 0.5, y + 0.5, z + 0.5))
            })
            .collect()
    }

    #[test]
    fn every_primitive_is_in_exactly_one_leaf() {
        for n in [1, 2, 3, 4, 5, 9, 100, 1000] {
            let t = build(&boxes(n), 4);
            assert!(validate_tree(&t.nodes, n).is_ok(), "{n} boxes");
            let mut seen = vec![0; n];
            for &p in &t.order {
                seen[p as usize] += 1;
            }
            assert!(seen.iter().all(|&s| s == 1), "{n} boxes");
            let mut covered = vec![0; n];
            for node in &t.nodes {
                for &r in node {
                    if let Child::Leaf { first, count } = child(r) {
                        for i in first..first + count {
                            covered[i as usize] += 1;
                        }
                    }
                }
            }
            assert!(covered.iter().all(|&c| c == 1), "{n} boxes");
        }
    }

    #[test]
    fn corrupt_trees_are_refused() {
        let t = build(&boxes(300), 4);
        let mut nodes = t.nodes.clone();
        nodes[0][0] = 10_000;
        assert!(matches!(
            validate_tree(&nodes, 300),
            Err(NodeError::ChildOutOfRange { .. })
        ));
        let mut nodes = t.nodes.clone();
        nodes[0][1] = 0;
        assert_eq!(validate_tree(&nodes, 300), Err(NodeError::TooDeep));
        let mut nodes = t.nodes.clone();
        nodes[0][2] = leaf(299, 4).unwrap();
        assert!(matches!(
            validate_tree(&nodes, 300),
            Err(NodeError::PrimitiveOutOfRange { .. })
        ));
    }
}
