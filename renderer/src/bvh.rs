//! Building trees (with obvhs) and their compact form on the wire.
//!
//! A chunk's tree travels as its shape only: nodes of eight child references, each an
//! inner node, a leaf of one to eight triangles (consecutive in the chunk's leaf order), or
//! nothing. No boxes travel: the receiver computes them from the triangles themselves when
//! it transcodes the tree into the form rays walk ([`crate::accel`]), so they are exact and
//! need no trust in the sender, and a node costs 32 bytes on the wire. [`validate_tree`]
//! checks received nodes before anything else reads them.
//!
//! Building: a binary tree, for a chunk's triangles by top-down binned surface area
//! heuristic (`binned_sah`), for the top-level tree over chunks by obvhs (PLOC, then
//! reinsertion), which is then collapsed into the wide tree of least expected cost under
//! the surface area heuristic, by dynamic programming over the binary tree (Ylitie, Karras
//! and Laine, "Efficient Incoherent Ray Traversal on GPUs Through Compressed Wide BVHs",
//! 2017): for every binary node and every number of slots from one to eight, the cheapest
//! way to represent its subtree in that many child slots, each slot a leaf of up to eight
//! primitives (one block of four triangles, or two for more than four) or a wide node.
//! Deterministic: obvhs is used without its parallel feature, the binned build sorts and
//! bins in a fixed order, and ties keep the first choice, so the same boxes give the same
//! tree.

use obvhs::{
    BvhBuildParams,
    aabb::Aabb,
    bvh2::{Bvh2, reinsertion::ReinsertionOptimizer},
    ploc::{PlocBuilder, PlocSearchDistance},
};

/// Deepest tree accepted: the walk's stack is sized for it.
pub const MAX_DEPTH: usize = 48;

/// Children of one wide node: [`EMPTY`], an inner node index (bit 31 clear), or a leaf
/// ([`LEAF`] set; bits 3..31 the first primitive, bits 0..3 the count less one).
pub type WideNode = [u32; 8];

/// A child slot with nothing in it.
pub const EMPTY: u32 = u32::MAX;

/// The bit that marks a leaf child.
pub const LEAF: u32 = 1 << 31;

/// Most primitives in one leaf: two blocks of four triangles.
pub const MAX_LEAF: u32 = 8;

/// A leaf child reference, or `None` when `first` does not fit (or the two would spell
/// [`EMPTY`]: eight primitives from the highest first that fits).
pub fn leaf(first: u32, count: u32) -> Option<u32> {
    (first < (1 << 28) && (1..=MAX_LEAF).contains(&count))
        .then(|| LEAF | (first << 3) | (count - 1))
        .filter(|&r| r != EMPTY)
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
            first: (r & !LEAF) >> 3,
            count: (r & 7) + 1,
        }
    }
}

/// A built tree: nodes (root first, parents before children) and the input primitives in
/// leaf order.
#[derive(Default)]
pub struct WideTree {
    pub nodes: Vec<WideNode>,
    pub order: Vec<u32>,
}

/// Expected cost of testing a wide node and a leaf, relative to each other (the four-lane
/// triangle test of a leaf costs about what the eight-lane box test of a node does).
const NODE_COST: f64 = 1.0;
const LEAF_COST: f64 = 1.0;

/// What a leaf's second block (five to eight primitives) adds to its cost: less than the
/// first, as closest-hit queries test both blocks in one eight-lane pass (and before that in
/// two four-lane tests that did not wait for each other, where each node test on the way
/// down waits for the one before). Measured on the 1M-triangle landscape of
/// `bench/peers/embree.py` (`bench/rays_ab.py` against leaves of at most four): with 0.25,
/// random rays 4 to 8% faster but diffuse ones 3 to 4% slower (a ray leaving a surface
/// starts inside more, larger leaf boxes); with 0.5, random 5 to 9% faster and the other
/// sets level.
const SECOND_BLOCK_COST: f64 = 0.5;

/// The expected cost of a leaf of `prims` primitives, per unit of its box's area.
fn leaf_cost(prims: u32) -> f64 {
    if prims > 4 {
        LEAF_COST + SECOND_BLOCK_COST
    } else {
        LEAF_COST
    }
}

/// Builds a tree over boxes with at most `max_leaf` (1 to 8) primitives a leaf.
pub fn build(boxes: &[Aabb], max_leaf: u32) -> WideTree {
    Builder::default().build(boxes, max_leaf)
}

/// Builds the top-level tree over chunk boxes ([`Builder::build_top`]).
pub fn build_top(boxes: &[Aabb]) -> WideTree {
    Builder::default().build_top(boxes)
}

/// Builds trees one after another, reusing its buffers (a scene's chunks are built in a
/// row, each a few thousand triangles, so allocation would otherwise cost a good part).
#[derive(Default)]
pub struct Builder {
    ploc: PlocBuilder,
    binary: Bvh2,
    reinsertion: ReinsertionOptimizer,
    collapser: Collapser,
    sah: SahScratch,
}

impl Builder {
    /// A tree over `boxes` with at most `max_leaf` (1 to 8) primitives a leaf.
    pub fn build(&mut self, boxes: &[Aabb], max_leaf: u32) -> WideTree {
        if boxes.is_empty() {
            return WideTree::default();
        }
        // Top-down binned SAH rather than obvhs's PLOC (search distance 2, 1% reinsertion,
        // which an earlier stop chose): on the 1M-triangle landscape of bench/peers its trees
        // take 8.3 node tests and 1.36 leaves a primary ray instead of 8.7 and 1.46, about
        // Embree's 7.8 and 1.35, for 15% more instructions in building chunks' trees.
        binned_sah(boxes, max_leaf, &mut self.binary, &mut self.sah);
        self.collapser.collapse(&self.binary, 0, max_leaf)
    }

    /// The top-level tree over the boxes of a scene's chunks, one chunk a leaf. Nearly every
    /// ray walks its upper levels, and it holds a few hundred to a few thousand boxes where
    /// a chunk's tree holds thousands of triangles, so it gets a search that would cost a
    /// chunk's tree several times its build: a binary tree from PLOC at each search distance
    /// obvhs offers (one only above 4,096 chunks), every node offered for reinsertion, each
    /// collapsed, and the one of least expected cost (the collapse's surface area heuristic)
    /// kept; ties keep the first. Heuristic builds vary with the distance in no order (on
    /// the 1M-triangle landscape of `bench/peers/embree.py`, 423 chunks, a distance of 14
    /// gave the cheapest tree and 6 one of the dearest).
    pub fn build_top(&mut self, boxes: &[Aabb]) -> WideTree {
        if boxes.is_empty() {
            return WideTree::default();
        }
        let distances = if boxes.len() <= TOP_SEARCH_ALL_BELOW {
            &TOP_SEARCH_DISTANCES[..]
        } else {
            &TOP_SEARCH_DISTANCES[..1]
        };
        let mut best: Option<(f64, WideTree)> = None;
        for &distance in distances {
            self.binary_tree(boxes, distance);
            let tree = self.collapser.collapse(&self.binary, 0, 1);
            let cost = self.collapser.cost[0][0];
            // A tree deeper than the walk's stack is no candidate: thousands of copies of a
            // mesh in one place made every one of them so (and a cluster refused the header
            // one process rendered with).
            let walkable = validate_tree(&tree.nodes, tree.order.len()).is_ok();
            if walkable && best.as_ref().is_none_or(|(c, _)| cost < *c) {
                best = Some((cost, tree));
            }
        }
        best.map(|(_, t)| t).unwrap_or_else(|| {
            median_splits(boxes, &mut self.binary);
            self.collapser.collapse(&self.binary, 0, 1)
        })
    }

    /// PLOC at `distance` over `boxes`, one box a leaf, then every node offered for
    /// reinsertion, into `binary`.
    fn binary_tree(&mut self, boxes: &[Aabb], distance: PlocSearchDistance) {
        let params = BvhBuildParams::medium_build();
        self.ploc.build_with_bvh(
            &mut self.binary,
            distance,
            boxes,
            (0..boxes.len() as u32).collect(),
            params.sort_precision,
            params.search_depth_threshold,
        );
        self.reinsertion.run(&mut self.binary, 1.0, None);
    }
}

/// PLOC search distances tried for the top-level tree ([`Builder::build_top`]); `Medium`
/// first, as it gave the cheapest tree on the million-triangle landscape and it alone is
/// tried over many boxes.
const TOP_SEARCH_DISTANCES: [PlocSearchDistance; 6] = [
    PlocSearchDistance::Medium,
    PlocSearchDistance::Minimum,
    PlocSearchDistance::VeryLow,
    PlocSearchDistance::Low,
    PlocSearchDistance::High,
    PlocSearchDistance::VeryHigh,
];

/// Above this many chunks, the top-level tree is built at one search distance: the six
/// builds grow with the boxes (at 3,768 chunks of the million-triangle landscape they added
/// 22 ms, a tenth of its build).
const TOP_SEARCH_ALL_BELOW: usize = 4_096;

/// The nodes of the binary subtree at `root`, children before parents, into `post`.
fn post_order(b: &Bvh2, root: usize, post: &mut Vec<usize>) {
    let n = &b.nodes;
    post.clear();
    let mut work = vec![(root, false)];
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

/// The least cost of two children sharing at most `j + 1` slots, for each `j`, with the fewest
/// slots for the left child that gives it (the left in `k` slots, the right in `j + 1 - k`;
/// `(inf, 0)` where none is finite). `left` and `right` are the children's costs in 1 to 8
/// slots, each never rising with more slots; `left_is_leaf` says the left child's are all one
/// value.
#[inline(always)]
fn distribute(left: &[f64; 8], right: &[f64; 8], left_is_leaf: bool) -> [(f64, u8); 8] {
    std::array::from_fn(|j| {
        let mut best = (f64::INFINITY, 0u8);
        // A leaf's costs are the same in any number of slots, and the right child's fall or
        // stay as it gets more: the left in one slot is the least (rounding is monotonic)
        // and the first, which the loop below would keep. Half the loop's work.
        if left_is_leaf {
            let cost = if j > 0 {
                left[0] + right[j - 1]
            } else {
                f64::INFINITY
            };
            return if cost < best.0 { (cost, 1) } else { best };
        }
        // The best so far in a local, kept in registers: written through an array, each of
        // the 28 steps waited for the store of the one before (a sixth of the whole build).
        for k in 1..=j {
            let cost = left[k - 1] + right[j - k];
            if cost < best.0 {
                best = (cost, k as u8);
            }
        }
        best
    })
}

/// Collapses binary trees into wide trees, reusing its buffers.
#[derive(Default)]
struct Collapser {
    /// Per binary node: how to represent it in 1..=8 slots, and the best split of a wide
    /// node's eight slots between its children (valid for the tree last planned).
    how: Vec<[Choice; 8]>,
    node_split: Vec<u8>,
    /// In f64: the box areas of finite f32 coordinates overflow f32 (a mesh spanning 1e20
    /// units), and infinite costs left every choice tied, which chose leaves of more
    /// primitives than a leaf holds.
    cost: Vec<[f64; 8]>,
    prims: Vec<u32>,
    post: Vec<usize>,
}

impl Collapser {
    /// The wide tree of least expected cost for the binary subtree at `root`, with at most
    /// `max_leaf` (1 to 8) primitives a leaf; its order holds the input's primitive indices.
    fn collapse(&mut self, b: &Bvh2, root: usize, max_leaf: u32) -> WideTree {
        let n = b.nodes.len();
        // Every entry of the subtree is written before it is read: no need to clear.
        self.how.resize(n, [Choice::Fewer; 8]);
        self.node_split.resize(n, 0);
        self.cost.resize(n, [f64::INFINITY; 8]);
        self.prims.resize(n, 0);
        self.plan(b, root, max_leaf.clamp(1, MAX_LEAF));
        let mut out = WideTree {
            nodes: Vec::new(),
            order: Vec::with_capacity(self.prims[root] as usize),
        };
        self.emit_node(b, root, &mut out);
        out
    }

    fn plan(&mut self, b: &Bvh2, root: usize, max_leaf: u32) {
        let n = &b.nodes;
        let mut post = std::mem::take(&mut self.post);
        post_order(b, root, &mut post);
        for &i in &post {
            let area = half_area_f64(&n[i].aabb);
            if n[i].prim_count != 0 {
                self.prims[i] = n[i].prim_count;
                let leaf = if self.prims[i] <= max_leaf {
                    area * leaf_cost(self.prims[i])
                } else {
                    f64::INFINITY
                };
                self.cost[i] = [leaf; 8];
                self.how[i] = [Choice::Fewer; 8];
                self.how[i][0] = Choice::Leaf;
                continue;
            }
            let (l, r) = (n[i].first_index as usize, n[i].first_index as usize + 1);
            self.prims[i] = self.prims[l] + self.prims[r];
            let distribute = distribute(&self.cost[l], &self.cost[r], n[l].prim_count != 0);
            let as_node = area * NODE_COST + distribute[7].0;
            self.node_split[i] = distribute[7].1;
            let as_leaf = if self.prims[i] <= max_leaf {
                area * leaf_cost(self.prims[i])
            } else {
                f64::INFINITY
            };
            let mut cost = [0.0f64; 8];
            let mut how = [Choice::Fewer; 8];
            (cost[0], how[0]) = if self.prims[i] <= max_leaf && as_leaf <= as_node {
                (as_leaf, Choice::Leaf)
            } else {
                (as_node, Choice::Node)
            };
            for j in 1..8 {
                let (split, k) = distribute[j];
                if split < cost[j - 1] {
                    cost[j] = split;
                    how[j] = Choice::Split(k);
                } else {
                    cost[j] = cost[j - 1];
                }
            }
            self.cost[i] = cost;
            self.how[i] = how;
        }
        self.post = post;
    }

    /// The slots binary node `i` takes when given `slots`: (node, leaf or not).
    fn slots(
        &self,
        b: &Bvh2,
        i: usize,
        slots: usize,
        out: &mut [(usize, bool); 8],
        len: &mut usize,
    ) {
        match self.how[i][slots - 1] {
            Choice::Leaf | Choice::Node if *len < 8 => {
                out[*len] = (i, self.how[i][slots - 1] == Choice::Leaf);
                *len += 1;
            }
            Choice::Leaf | Choice::Node => {}
            Choice::Fewer => self.slots(b, i, slots - 1, out, len),
            Choice::Split(k) => {
                let first = b.nodes[i].first_index as usize;
                self.slots(b, first, k as usize, out, len);
                self.slots(b, first + 1, slots - k as usize, out, len);
            }
        }
    }

    /// Emits the wide node for binary node `i` (parents before children); its index.
    fn emit_node(&self, b: &Bvh2, i: usize, out: &mut WideTree) -> u32 {
        let me = out.nodes.len();
        out.nodes.push([EMPTY; 8]);
        let mut kids = [(0usize, false); 8];
        let mut len = 0;
        if b.nodes[i].prim_count != 0 || self.how[i][0] == Choice::Leaf {
            kids[0] = (i, true);
            len = 1;
        } else {
            let first = b.nodes[i].first_index as usize;
            let k = self.node_split[i] as usize;
            self.slots(b, first, k, &mut kids, &mut len);
            self.slots(b, first + 1, 8 - k, &mut kids, &mut len);
        }
        for (slot, &(k, is_leaf)) in kids[..len].iter().enumerate() {
            out.nodes[me][slot] = if is_leaf {
                let first = out.order.len() as u32;
                emit_leaf(b, k, out);
                let count = out.order.len() as u32 - first;
                // The plan makes leaves of at most MAX_LEAF primitives.
                leaf(first, count).expect("planned leaves hold at most eight primitives")
            } else {
                self.emit_node(b, k, out)
            };
        }
        me as u32
    }
}

/// Half the surface area of a box, in f64 (finite for any finite f32 box; 0 for an empty or
/// inverted one).
///
/// With AVX2, the same operations in the same order on the three axes at once (the same bits:
/// `areas_agree_with_the_scalar_sum` checks): the splits' sweeps call it for every bin and the
/// collapse for every node, and one axis at a time (conversions and NaN-aware maxima, each
/// scalar) the chunks' trees took 15% more instructions to build.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
fn half_area_f64(b: &Aabb) -> f64 {
    use std::arch::x86_64::*;
    // SAFETY: AVX2 is enabled for this build (the cfg above); `Vec3A` is four `f32`s, 16-byte
    // aligned, so each load reads one whole vector. The fourth lane is never summed.
    unsafe {
        let lo = _mm256_cvtps_pd(_mm_load_ps((&b.min as *const glam::Vec3A).cast()));
        let hi = _mm256_cvtps_pd(_mm_load_ps((&b.max as *const glam::Vec3A).cast()));
        // `max_pd` gives its second operand where the first is NaN: 0, as `f64::max` does.
        let d = _mm256_max_pd(_mm256_sub_pd(hi, lo), _mm256_setzero_pd());
        // (d0 d1, d1 d2, d2 d0, -): the products of the scalar sum, each rounded alike.
        let p = _mm256_mul_pd(d, _mm256_permute4x64_pd::<0b11_00_10_01>(d));
        let p01 = _mm256_castpd256_pd128(p);
        let sum = _mm_add_sd(
            _mm_add_sd(p01, _mm_unpackhi_pd(p01, p01)),
            _mm256_extractf128_pd::<1>(p),
        );
        let a = _mm_cvtsd_f64(sum);
        if a.is_finite() { a } else { 0.0 }
    }
}

#[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
fn half_area_f64(b: &Aabb) -> f64 {
    half_area_f64_scalar(b)
}

/// [`half_area_f64`] one axis at a time (with AVX2, only the tests' reference).
#[cfg(any(test, not(all(target_arch = "x86_64", target_feature = "avx2"))))]
fn half_area_f64_scalar(b: &Aabb) -> f64 {
    let d = [0, 1, 2].map(|k| (b.max[k] as f64 - b.min[k] as f64).max(0.0));
    let a = d[0] * d[1] + d[1] * d[2] + d[2] * d[0];
    if a.is_finite() { a } else { 0.0 }
}

/// Appends every primitive of binary subtree `i` to the leaf order.
fn emit_leaf(b: &Bvh2, i: usize, out: &mut WideTree) {
    let n = &b.nodes[i];
    if n.prim_count != 0 {
        let start = n.first_index as usize;
        out.order
            .extend_from_slice(&b.primitive_indices[start..start + n.prim_count as usize]);
    } else {
        emit_leaf(b, n.first_index as usize, out);
        emit_leaf(b, n.first_index as usize + 1, out);
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

/// Bins per axis of [`binned_sah`].
const SAH_BINS: usize = 32;

/// Ranges of at most this many boxes (and at most the wide tree's largest leaf) are leaves of
/// the binary tree: one block of four triangles, which the collapse would not split.
const SAH_LEAF: usize = 4;

/// At most this many boxes are split by sorting their centres along each axis and trying
/// every split (exact, where a leaf's boxes are chosen); more are binned.
const SAH_SWEEP_MAX: usize = 8;

/// Buffers of [`binned_sah`], kept from one tree to the next.
#[derive(Default)]
struct SahScratch {
    centres: Vec<glam::Vec3A>,
    work: Vec<SahTask>,
    /// The blocks `n` boxes fill, as f64, at `n`: the sweeps cost a side by them at every bin,
    /// where dividing by a leaf size known only at run time, few instructions but long ones,
    /// took 6% of a scene's preparation.
    blocks: Vec<f64>,
}

/// One range of boxes still to split: the node it becomes, the range of `prims`, its bounds
/// and the bounds of its boxes' centres.
struct SahTask {
    node: usize,
    start: usize,
    end: usize,
    bounds: Aabb,
    centres: Aabb,
}

/// A binary tree over `boxes` by top-down binned surface area heuristic on the boxes'
/// centres (bins as Embree sizes them: `4 + n / 20`, at most 32), ranges of up to eight
/// boxes split exactly, leaves of up to [`SAH_LEAF`] boxes and `max_leaf`, into `out`.
///
/// A side's cost counts its boxes in whole leaf blocks (`ceil(n / SAH_LEAF)`), as Embree's
/// builder does: a leaf's triangles are tested a block at a time, so a split that leaves a
/// block part empty saves nothing for it. Against counting boxes one by one, on the
/// landscape of `bench/peers/embree.py`, node tests and blocks a query fell by under 1% and
/// primary rays ran 1 to 3% faster (README).
fn binned_sah(boxes: &[Aabb], max_leaf: u32, out: &mut Bvh2, scratch: &mut SahScratch) {
    use glam::Vec3A;
    use obvhs::bvh2::node::Bvh2Node;
    let n = boxes.len();
    let centres = &mut scratch.centres;
    centres.clear();
    centres.extend(boxes.iter().map(|b| (b.min + b.max) * 0.5));
    let centres = &*centres;
    let mut prims = std::mem::take(&mut out.primitive_indices);
    prims.clear();
    prims.extend(0..n as u32);
    let mut nodes = std::mem::take(&mut out.nodes);
    nodes.clear();
    nodes.push(Default::default());
    let (bounds, cb) = bounds_of(boxes, centres, &prims);
    let work = &mut scratch.work;
    work.clear();
    work.push(SahTask {
        node: 0,
        start: 0,
        end: n,
        bounds,
        centres: cb,
    });
    let mut bin_box = [[Aabb::INVALID; SAH_BINS]; 3];
    let mut bin_count = [[0u32; SAH_BINS]; 3];
    let mut right_area = [0.0f64; SAH_BINS];
    let leaf_size = SAH_LEAF.min(max_leaf.max(1) as usize);
    scratch.blocks.clear();
    scratch
        .blocks
        .extend((0..=n).map(|k| k.div_ceil(leaf_size) as f64));
    let blocks_of = &scratch.blocks[..];
    let blocks = |k: usize| blocks_of[k];
    while let Some(t) = work.pop() {
        let count = t.end - t.start;
        if count <= leaf_size {
            nodes[t.node] = Bvh2Node::new(t.bounds, count as u32, t.start as u32);
            continue;
        }
        let slice = &mut prims[t.start..t.end];
        let extent = t.centres.max - t.centres.min;
        let (mid, left, right);
        if count <= SAH_SWEEP_MAX || extent.max_element() <= 0.0 {
            // Exact: along each axis, the boxes in order of their centres, every split tried.
            let mut best = (f64::INFINITY, 0usize, count / 2);
            // The best axis's order so far, kept rather than sorted again.
            let (mut order, mut best_order) = ([0u64; SAH_SWEEP_MAX], [0u64; SAH_SWEEP_MAX]);
            let mut suffix = [0.0f64; SAH_SWEEP_MAX];
            let sweep = count <= SAH_SWEEP_MAX;
            for a in 0..3 {
                if !sweep || extent[a] <= 0.0 {
                    continue;
                }
                let order = &mut order[..count];
                for (o, &p) in order.iter_mut().zip(slice.iter()) {
                    *o = sort_key(centres[p as usize][a], p);
                }
                insertion_sort(order);
                let mut acc = Aabb::INVALID;
                for k in (1..count).rev() {
                    acc = acc.union(&boxes[order[k] as u32 as usize]);
                    suffix[k] = half_area_f64(&acc);
                }
                let mut acc = Aabb::INVALID;
                for k in 0..count - 1 {
                    acc = acc.union(&boxes[order[k] as u32 as usize]);
                    let cost =
                        half_area_f64(&acc) * blocks(k + 1) + suffix[k + 1] * blocks(count - k - 1);
                    if cost < best.0 {
                        best = (cost, a, k + 1);
                    }
                }
                if best.1 == a && best.0.is_finite() {
                    best_order[..count].copy_from_slice(order);
                }
            }
            if best.0.is_finite() {
                for (p, o) in slice.iter_mut().zip(&best_order[..count]) {
                    *p = *o as u32;
                }
            }
            let at = best.2;
            mid = t.start + at;
            left = bounds_of(boxes, centres, &slice[..at]);
            right = bounds_of(boxes, centres, &slice[at..]);
        } else {
            let bins = (4 + count / 20).min(SAH_BINS);
            let scale = Vec3A::select(
                extent.cmpgt(Vec3A::ZERO),
                Vec3A::splat(bins as f32) / extent,
                Vec3A::ZERO,
            );
            // A centre's place in [0, bins - 1] along each axis, rounded to an integer by
            // adding 2^23 (whose float's low bits then hold it): any rounding does, as long
            // as it never decreases, since binning and partitioning both use this one.
            let offset = -t.centres.min * scale - Vec3A::splat(0.5);
            let last = Vec3A::splat((bins - 1) as f32);
            let bins_of = |c: Vec3A| -> [usize; 3] {
                let b =
                    c.mul_add(scale, offset).clamp(Vec3A::ZERO, last) + Vec3A::splat(8_388_608.0);
                let b = b.to_array();
                [0, 1, 2].map(|a| (b[a].to_bits() as usize) & (SAH_BINS - 1))
            };
            for a in 0..3 {
                bin_box[a][..bins].fill(Aabb::INVALID);
                bin_count[a][..bins].fill(0);
            }
            for &p in slice.iter() {
                let [k0, k1, k2] = bins_of(centres[p as usize]);
                let b = &boxes[p as usize];
                // Axis by axis with constant indices: no bounds checks in this loop.
                bin_box[0][k0] = bin_box[0][k0].union(b);
                bin_box[1][k1] = bin_box[1][k1].union(b);
                bin_box[2][k2] = bin_box[2][k2].union(b);
                bin_count[0][k0] += 1;
                bin_count[1][k1] += 1;
                bin_count[2][k2] += 1;
            }
            // The exact split's sweep again, over bins and their counts. Made one function
            // for both, the build took 8% more instructions (the binning loop around it was
            // compiled worse), so it is written out twice.
            let mut best = (f64::INFINITY, 0usize, 0usize);
            for a in 0..3 {
                if extent[a] <= 0.0 {
                    continue;
                }
                let mut acc = Aabb::INVALID;
                for k in (1..bins).rev() {
                    acc = acc.union(&bin_box[a][k]);
                    right_area[k] = half_area_f64(&acc);
                }
                let (mut acc, mut below) = (Aabb::INVALID, 0u32);
                for k in 0..bins - 1 {
                    acc = acc.union(&bin_box[a][k]);
                    below += bin_count[a][k];
                    if below == 0 || below as usize == count {
                        continue;
                    }
                    let cost = half_area_f64(&acc) * blocks(below as usize)
                        + right_area[k + 1] * blocks(count - below as usize);
                    if cost < best.0 {
                        best = (cost, a, k);
                    }
                }
            }
            // Every centre in one bin along every axis: an extent so small next to the
            // coordinates that the offset's rounding swallows it. Split in the middle.
            let (_, a, k) = best;
            let mut i = 0;
            let (mut lc, mut rc) = (Aabb::INVALID, Aabb::INVALID);
            if best.0.is_finite() {
                for j in 0..slice.len() {
                    let c = centres[slice[j] as usize];
                    if bins_of(c)[a] <= k {
                        slice.swap(i, j);
                        i += 1;
                        lc.extend(c);
                    } else {
                        rc.extend(c);
                    }
                }
                let union = |bins: &[Aabb]| bins.iter().fold(Aabb::INVALID, |u, b| u.union(b));
                left = (union(&bin_box[a][..=k]), lc);
                right = (union(&bin_box[a][k + 1..bins]), rc);
            } else {
                i = count / 2;
                left = bounds_of(boxes, centres, &slice[..i]);
                right = bounds_of(boxes, centres, &slice[i..]);
            }
            mid = t.start + i;
        }
        let l = nodes.len();
        nodes.push(Default::default());
        nodes.push(Default::default());
        nodes[t.node] = Bvh2Node::new(t.bounds, 0, l as u32);
        work.push(SahTask {
            node: l + 1,
            start: mid,
            end: t.end,
            bounds: right.0,
            centres: right.1,
        });
        work.push(SahTask {
            node: l,
            start: t.start,
            end: mid,
            bounds: left.0,
            centres: left.1,
        });
    }
    *out = Bvh2 {
        nodes,
        primitive_indices: prims,
        ..Default::default()
    };
}

/// A binary tree over `boxes`, one a leaf, each node's boxes halved by count along the
/// widest axis of their centres (ties by index): no cheaper than a search, but never deeper
/// than log2 of the count plus one, whatever the boxes, where a search's tree can be a chain.
fn median_splits(boxes: &[Aabb], out: &mut Bvh2) {
    use obvhs::bvh2::node::Bvh2Node;
    let centres: Vec<glam::Vec3A> = boxes.iter().map(|b| (b.min + b.max) * 0.5).collect();
    let mut prims: Vec<u32> = (0..boxes.len() as u32).collect();
    let mut nodes = vec![Bvh2Node::default()];
    let mut keys = Vec::new();
    let mut work = vec![(0usize, 0usize, boxes.len())];
    while let Some((node, start, end)) = work.pop() {
        let (bounds, spread) = bounds_of(boxes, &centres, &prims[start..end]);
        if end - start <= 1 {
            nodes[node] = Bvh2Node::new(bounds, (end - start) as u32, start as u32);
            continue;
        }
        let axis = (spread.max - spread.min).max_position();
        keys.clear();
        keys.extend(
            prims[start..end]
                .iter()
                .map(|&p| sort_key(centres[p as usize][axis], p)),
        );
        keys.sort_unstable();
        for (p, k) in prims[start..end].iter_mut().zip(&keys) {
            *p = *k as u32;
        }
        let left = nodes.len();
        nodes.extend([Bvh2Node::default(); 2]);
        nodes[node] = Bvh2Node::new(bounds, 0, left as u32);
        let mid = start + (end - start) / 2;
        work.push((left + 1, mid, end));
        work.push((left, start, mid));
    }
    *out = Bvh2 {
        nodes,
        primitive_indices: prims,
        ..Default::default()
    };
}

/// The union of the boxes `prims` and the bounds of their centres.
fn bounds_of(boxes: &[Aabb], centres: &[glam::Vec3A], prims: &[u32]) -> (Aabb, Aabb) {
    let (mut b, mut c) = (Aabb::INVALID, Aabb::INVALID);
    for &p in prims {
        b = b.union(&boxes[p as usize]);
        c.extend(centres[p as usize]);
    }
    (b, c)
}

/// A box's place in a sort by centre along one axis, then by index: the float's bits made
/// to order as the floats do, above the index.
fn sort_key(x: f32, p: u32) -> u64 {
    let b = x.to_bits();
    let ordered = if b >> 31 == 1 { !b } else { b | (1 << 31) };
    (u64::from(ordered) << 32) | u64::from(p)
}

/// Sorts a few keys: the same order whatever the input's.
fn insertion_sort(v: &mut [u64]) {
    for i in 1..v.len() {
        let x = v[i];
        let mut j = i;
        while j > 0 && v[j - 1] > x {
            v[j] = v[j - 1];
            j -= 1;
        }
        v[j] = x;
    }
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

    /// A row of costs in 1 to 8 slots as the plan makes them: never rising with more slots,
    /// with repeats (a subtree that gains nothing from another slot) and, for a leaf, one
    /// value throughout.
    fn cost_row() -> impl proptest::strategy::Strategy<Value = [f64; 8]> {
        use proptest::prelude::*;
        (prop::array::uniform8(0u8..4), 1.0f64..1e6, any::<bool>()).prop_map(
            |(drops, start, constant)| {
                let mut row = [start; 8];
                for j in 1..8 {
                    let step = if constant {
                        0.0
                    } else {
                        f64::from(drops[j]) * 0.125
                    };
                    row[j] = row[j - 1] * (1.0 - step * 0.5);
                }
                row
            },
        )
    }

    /// Box corners of every kind the build can meet: ordinary, equal (flat), inverted
    /// (empty), infinite and of far apart magnitudes.
    fn corner() -> impl proptest::strategy::Strategy<Value = f32> {
        use proptest::prelude::*;
        prop_oneof![
            -1e3f32..1e3,
            -1e30f32..1e30,
            Just(0.0f32),
            Just(-0.0f32),
            Just(f32::INFINITY),
            Just(f32::NEG_INFINITY),
            Just(f32::MAX),
            Just(f32::MIN_POSITIVE),
        ]
    }

    #[test]
    fn areas_of_flat_empty_and_signed_zero_boxes_agree_with_the_scalar_sum() {
        let v = [0.0f32, -0.0, 1.0, -1.0];
        let mut boxes = vec![Aabb::INVALID];
        for &x in &v {
            for &y in &v {
                for &z in &v {
                    boxes.push(Aabb::new(Vec3A::new(x, y, z), Vec3A::new(z, x, y)));
                }
            }
        }
        for b in boxes {
            assert_eq!(
                half_area_f64(&b).to_bits(),
                half_area_f64_scalar(&b).to_bits(),
                "{b:?}"
            );
        }
    }

    proptest::proptest! {
        /// The half area in four lanes has the scalar sum's bits, whatever the box: the
        /// splits, and so the trees, come out the same on every machine.
        #[test]
        fn areas_agree_with_the_scalar_sum(
            min in proptest::array::uniform3(corner()),
            max in proptest::array::uniform3(corner()),
        ) {
            let b = Aabb::new(Vec3A::from(min), Vec3A::from(max));
            proptest::prop_assert_eq!(
                half_area_f64(&b).to_bits(),
                half_area_f64_scalar(&b).to_bits()
            );
        }

        /// The shortcut for a left leaf gives what the plain loop over every split gives,
        /// costs and the left child's slots alike (the trees come out the same).
        #[test]
        fn distributing_slots_matches_trying_every_split(
            left in cost_row(),
            right in cost_row(),
            leaf_cost in 1.0f64..1e6,
        ) {
            let plain = |left: &[f64; 8]| -> [(f64, u8); 8] {
                std::array::from_fn(|j| {
                    let mut best = (f64::INFINITY, 0u8);
                    for k in 1..=j {
                        let cost = left[k - 1] + right[j - k];
                        if cost < best.0 {
                            best = (cost, k as u8);
                        }
                    }
                    best
                })
            };
            let leaf = [leaf_cost; 8];
            proptest::prop_assert_eq!(distribute(&leaf, &right, true), plain(&leaf));
            proptest::prop_assert_eq!(distribute(&left, &right, false), plain(&left));
        }
    }

    /// Boxes far apart enough that their areas overflow f32 (a mesh spanning 1e30 units)
    /// still make a tree of leaves of at most eight: the builder once chose a leaf of every
    /// primitive below a node whose cost had become infinite, and panicked emitting it.
    #[test]
    fn boxes_whose_areas_overflow_f32_still_build() {
        let b: Vec<Aabb> = (0..300)
            .map(|i| {
                let x = 1.3f32.powi(i);
                Aabb::new(Vec3A::new(x, -x, -x), Vec3A::new(1.1 * x, x, x))
            })
            .collect();
        assert!(b[299].half_area().is_infinite());
        let t = build(&b, MAX_LEAF);
        assert!(validate_tree(&t.nodes, b.len()).is_ok());
        let mut order = t.order.clone();
        order.sort();
        assert_eq!(order, (0..300).collect::<Vec<u32>>());
    }

    /// Boxes from a fixed generator: `n` boxes of random size around random points, at
    /// `offset` from the origin and spread over `spread` units.
    fn scattered(n: usize, offset: f32, spread: f32, seed: u64) -> Vec<Aabb> {
        let mut state = seed;
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        (0..n)
            .map(|_| {
                let c = Vec3A::new(next(), next(), next()) * spread + Vec3A::splat(offset);
                let h = Vec3A::new(next(), next(), next()) * spread * 0.01;
                Aabb::new(c - h, c + h)
            })
            .collect()
    }

    /// The binned build's binary tree: every box in exactly one leaf of at most the leaf
    /// size, each node's box exactly its children's (or its leaf's boxes') union, and the
    /// same tree from the same boxes. Cases: many boxes (binned), few (split exactly), all
    /// at one point (no axis to split along), and far from the origin over a few units
    /// (coordinates whole numbers, bins placed by a rounded offset).
    #[test]
    fn binned_trees_hold_every_box_once_in_exact_bounds() {
        let cases = [
            scattered(5000, 0.0, 100.0, 1),
            scattered(7, -3.0, 1.0, 2),
            vec![Aabb::new(Vec3A::splat(1.0), Vec3A::splat(2.0)); 300],
            scattered(300, 1.0e7, 8.0, 3),
        ];
        for (case, b) in cases.iter().enumerate() {
            for max_leaf in [1, 4, MAX_LEAF] {
                let (mut t, mut again) = (Bvh2::default(), Bvh2::default());
                let mut scratch = SahScratch::default();
                binned_sah(b, max_leaf, &mut t, &mut scratch);
                binned_sah(b, max_leaf, &mut again, &mut scratch);
                let same = |x: &Bvh2, y: &Bvh2| {
                    x.primitive_indices == y.primitive_indices
                        && x.nodes.len() == y.nodes.len()
                        && x.nodes.iter().zip(&y.nodes).all(|(m, n)| {
                            (m.aabb.min, m.aabb.max, m.prim_count, m.first_index)
                                == (n.aabb.min, n.aabb.max, n.prim_count, n.first_index)
                        })
                };
                assert!(same(&t, &again), "case {case}: not deterministic");
                let mut seen = vec![0; b.len()];
                let mut work = vec![0usize];
                while let Some(i) = work.pop() {
                    let node = &t.nodes[i];
                    let union = if node.prim_count != 0 {
                        assert!(node.prim_count as usize <= SAH_LEAF.min(max_leaf as usize));
                        let first = node.first_index as usize;
                        let mut u = Aabb::INVALID;
                        for &p in &t.primitive_indices[first..first + node.prim_count as usize] {
                            seen[p as usize] += 1;
                            u = u.union(&b[p as usize]);
                        }
                        u
                    } else {
                        let l = node.first_index as usize;
                        work.extend([l, l + 1]);
                        t.nodes[l].aabb.union(&t.nodes[l + 1].aabb)
                    };
                    assert_eq!(
                        (union.min, union.max),
                        (node.aabb.min, node.aabb.max),
                        "case {case}"
                    );
                }
                assert!(
                    seen.iter().all(|&s| s == 1),
                    "case {case}: boxes not once each"
                );
            }
        }
    }

    /// Costs count whole blocks: eight unit cubes, five in a row and three more further on.
    /// Counted box by box, cutting after the fifth is cheapest (11 x 5 + 7 x 3 = 76 against
    /// 9 x 4 + 19 x 4 = 112 for after the fourth); counted in blocks of four, after the
    /// fourth (9 + 19 = 28 against 11 x 2 + 7 = 29), which leaves no block part empty.
    #[test]
    fn splits_are_costed_in_whole_blocks() {
        let b: Vec<Aabb> = [0.0f32, 1.0, 2.0, 3.0, 4.0, 10.0, 11.0, 12.0]
            .iter()
            .map(|&x| Aabb::new(Vec3A::new(x, 0.0, 0.0), Vec3A::new(x + 1.0, 1.0, 1.0)))
            .collect();
        let mut t = Bvh2::default();
        binned_sah(&b, MAX_LEAF, &mut t, &mut SahScratch::default());
        let root = &t.nodes[0];
        assert_eq!(root.prim_count, 0);
        let sides = [0, 1].map(|k| t.nodes[root.first_index as usize + k].prim_count);
        assert_eq!(sides, [4, 4]);
    }

    #[test]
    fn every_primitive_is_in_exactly_one_leaf() {
        for n in [1, 2, 3, 4, 5, 9, 100, 1000] {
            let t = build(&boxes(n), MAX_LEAF);
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

    /// Thousands of nearly coincident chunk boxes (copies of a mesh in one place) made every
    /// searched top-level tree deeper than the walk's stack, and a cluster refused the
    /// header; the build falls back to halving by count, which holds every box once within
    /// the depth. Many boxes of one size in a row keep the search's tree.
    #[test]
    fn the_top_level_tree_stays_within_the_walks_depth() {
        let piled: Vec<Aabb> = (0..3000)
            .map(|i| {
                let x = (i % 7) as f32 * 0.01;
                Aabb::new(
                    Vec3A::new(x - 1.0, -1.0, -5.0),
                    Vec3A::new(x + 1.0, 1.0, -3.0),
                )
            })
            .collect();
        let searched_too_deep = {
            let mut b = Builder::default();
            b.binary_tree(&piled, PlocSearchDistance::Medium);
            let t = b.collapser.collapse(&b.binary, 0, 1);
            validate_tree(&t.nodes, t.order.len()).is_err()
        };
        assert!(searched_too_deep, "the case the fallback is for");
        for boxes in [piled, boxes(3000)] {
            let t = build_top(&boxes);
            let depth = validate_tree(&t.nodes, t.order.len()).expect("walkable");
            let mut seen = vec![0; boxes.len()];
            for &p in &t.order {
                seen[p as usize] += 1;
            }
            assert!(
                seen.iter().all(|&s| s == 1),
                "every box once (depth {depth})"
            );
        }
        let mut halved = Bvh2::default();
        median_splits(&boxes(5000), &mut halved);
        let t = Collapser::default().collapse(&halved, 0, 1);
        let depth = validate_tree(&t.nodes, t.order.len()).unwrap();
        assert!(depth <= 14, "5000 boxes halved: {depth} levels");
    }

    /// The expected cost of the subtree at node `i` under the collapse's heuristic (areas
    /// times costs, as the collapse sums them), and its box.
    fn wide_cost(t: &WideTree, boxes: &[Aabb], i: usize) -> (f64, Aabb) {
        let mut cost = 0.0;
        let mut bounds = Aabb::empty();
        for &r in &t.nodes[i] {
            match child(r) {
                Child::Empty => {}
                Child::Node(n) => {
                    let (c, b) = wide_cost(t, boxes, n as usize);
                    cost += c;
                    bounds = bounds.union(&b);
                }
                Child::Leaf { first, count } => {
                    let mut b = Aabb::empty();
                    for p in &t.order[first as usize..(first + count) as usize] {
                        b = b.union(&boxes[*p as usize]);
                    }
                    cost += half_area_f64(&b) * leaf_cost(count);
                    bounds = bounds.union(&b);
                }
            }
        }
        (cost + half_area_f64(&bounds) * NODE_COST, bounds)
    }

    /// The top-level tree holds every chunk box in a leaf of its own, and the search for it
    /// finds a cheaper tree than the chunks' builder makes over the same boxes (a grid, and
    /// clusters of overlapping boxes of many sizes, as chunks of meshes of many sizes are).
    #[test]
    fn the_top_level_tree_holds_every_box_once_and_costs_no_more() {
        let mut r = crate::testing::Lcg(7);
        let clusters: Vec<Aabb> = (0..400)
            .map(|_| {
                let c = Vec3A::new(r.next(), r.next(), r.next() * 0.2) * 100.0;
                let size = Vec3A::new(r.next(), r.next(), r.next()) * (1.0 + 20.0 * r.next());
                Aabb::new(c - size, c + size)
            })
            .collect();
        for set in [boxes(1), boxes(7), boxes(300), clusters] {
            let n = set.len();
            let top = build_top(&set);
            assert!(validate_tree(&top.nodes, n).is_ok(), "{n} boxes");
            let mut seen = vec![0; n];
            for node in &top.nodes {
                for &r in node {
                    if let Child::Leaf { first, count } = child(r) {
                        assert_eq!(count, 1, "{n} boxes: one chunk a leaf");
                        seen[top.order[first as usize] as usize] += 1;
                    }
                }
            }
            assert!(seen.iter().all(|&s| s == 1), "{n} boxes");
            let (top_cost, _) = wide_cost(&top, &set, 0);
            let (plain_cost, _) = wide_cost(&build(&set, 1), &set, 0);
            // A few boxes leave no choice; over hundreds the search must find a cheaper tree.
            if n < 100 {
                assert_eq!(top_cost, plain_cost, "{n} boxes");
            } else {
                assert!(
                    top_cost < plain_cost,
                    "{n} boxes: {top_cost} >= {plain_cost}"
                );
            }
        }
    }

    /// Every count a leaf may hold, at the lowest and highest first primitive, reads back as
    /// written; what does not fit is refused, not wrapped.
    #[test]
    fn leaf_references_read_back() {
        for count in 1..=MAX_LEAF {
            for first in [0, 1, (1 << 28) - 2] {
                let r = leaf(first, count).unwrap();
                assert_eq!(child(r), Child::Leaf { first, count });
            }
        }
        assert_eq!(leaf((1 << 28) - 1, MAX_LEAF), None);
        assert_eq!(leaf(0, 0), None);
        assert_eq!(leaf(0, MAX_LEAF + 1), None);
        assert_eq!(leaf(1 << 28, 1), None);
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
