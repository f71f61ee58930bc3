//! The form of a tree this processor walks fastest, and the ray-casting kernels that walk it.
//!
//! Chunks travel in a compact, position-independent form (the tree's shape in 32-byte nodes,
//! triangles in leaf order; [`crate::bvh`]): good for the wire and for caches. Once a chunk
//! has been validated it is transcoded, once, into [`Bvh8`]: nodes of eight children whose
//! boxes are plain `f32` planes (one array per plane, so one 8-lane fused multiply-add per
//! plane tests all eight children) and leaves of one or two blocks of up to four triangles
//! stored lane by lane ([`Tri4`]; a closest-hit query tests a leaf's two blocks together in
//! eight lanes, so a leaf of eight triangles costs little more than one of four, and saves
//! the level of nodes that would split it; an any-hit query tests them one after the other,
//! as a hit in the first often ends it). The boxes are computed from the triangles
//! themselves, so they are exact and need no trust in the sender. The top-level tree over chunks is
//! transcoded the same way, each of its leaves one chunk with that chunk's bounds, so a ray
//! tests a chunk's box before touching it.
//!
//! Robustness: a box test must never reject a box that holds something the ray hits, at any
//! scale or distance from the origin. A plane distance is computed as
//! `plane * inv_dir + offset` with `offset = -origin * inv_dir`; the rounding of `offset` is
//! bounded by a slack folded into it per axis (see [`RayQuery`]), and what remains is
//! relative to the distance itself, which comparing near distances a few units in the last
//! place lowered covers.
//! Triangles are tested by the watertight algorithm ([`triangle`]) four or eight at a time
//! with the same operations as the scalar test, which then confirms the nearest candidate
//! and applies the rounding bound on its distance.
//!
//! Closest hits are unique among the triangles a walk tests: equal distances are decided by
//! (chunk, triangle) index, not by the order in which the walk meets them. One gap remains: a
//! box is skipped when its entry distance lies a few units in the last place beyond the best
//! hit's, and a triangle's computed distance can lie further below its own box's entry than
//! that (once among the 26,465 hits of the grazing rays of
//! `tests::a_box_holding_a_hit_is_entered`, in a box flat along an axis: 12 units), so a tie
//! with such a triangle goes to the one met first. Walks of the same trees meet triangles in
//! the same order (the flat tree is the two levels joined), which is why images stay the same
//! bytes in every configuration.

use std::{mem::MaybeUninit, ops::Range, sync::Arc};

use crate::{
    bvh::{self, Child, MAX_DEPTH, Visit, WideNode},
    math::gamma,
    ray::RayQuery,
    region::{Block, Region},
    simd::{self, F32x4, F32x8, LaneMask, TriLanes},
    triangle::{self, TriHit},
};

/// A child reference with this bit set is a leaf; the other bits index the leaf (its first
/// [`Tri4`] block in a chunk, with [`TWO_BLOCKS`]; a chunk in the top-level tree).
pub const LEAF: u32 = 1 << 31;

/// With [`LEAF`], in a chunk's tree: the leaf is two consecutive blocks (five to eight
/// triangles), both tested.
pub const TWO_BLOCKS: u32 = 1 << 30;

/// `tmax` is widened by this many units in the last place where entry distances are
/// compared with it: the relative rounding of a near distance and of the hit's distance
/// (`1 + 3 * EPSILON` as a factor, which moves a number by three to six units).
const WIDEN_ULPS: i32 = 6;

/// Whether child reference `c` names an inner node: not a leaf, and not 0 (the root, which
/// is nobody's child: an empty slot).
#[inline(always)]
fn names_node(c: u32) -> bool {
    c & LEAF == 0 && c != 0
}

/// Entries the walk's stack can need: at most seven pushes per level of a valid tree.
const STACK: usize = 8 * MAX_DEPTH;

/// Eight children: their boxes as planes (min x, max x, min y, max y, min z, max z; an empty
/// slot has +inf minima and -inf maxima, which no ray enters) and references.
///
/// Inner children come first, in slots `0..inner`, and are the consecutive nodes
/// `first..first + inner`; leaves follow, then empty slots (transcoding lays trees out so).
/// The walk finds the node to go down to by adding the slot to `first`, without waiting for
/// `child` to be read: one load less on the chain of dependent steps a ray's way down is.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(64))]
pub struct Node8 {
    pub planes: [[f32; 8]; 6],
    pub child: [u32; 8],
    pub first: u32,
    pub inner: u32,
    /// In a tree made by [`Bvh8::flatten`]: 1 + the chunk whose root this node is, else 0
    /// (read only where the chunks rays enter are recorded, see [`walk`]).
    pub root_of: u32,
    /// Fills the node to four cache lines' size explicitly, so that it has no padding bytes
    /// and can be written to and read from plain words (a card's shared memory).
    pad: [u32; 5],
}

// SAFETY: `repr(C)` of `f32` and `u32` arrays only, with the tail padding made an explicit
// field (size 256 = 6 * 32 + 32 + 32, a multiple of the alignment): every bit pattern is a
// valid node and there are no uninitialised bytes.
unsafe impl bytemuck::Zeroable for Node8 {}
// SAFETY: as above.
unsafe impl bytemuck::Pod for Node8 {}
const _: () = assert!(size_of::<Node8>() == 256);

impl Node8 {
    /// A node of eight empty slots.
    pub const EMPTY: Node8 = Node8 {
        planes: [
            [f32::INFINITY; 8],
            [f32::NEG_INFINITY; 8],
            [f32::INFINITY; 8],
            [f32::NEG_INFINITY; 8],
            [f32::INFINITY; 8],
            [f32::NEG_INFINITY; 8],
        ],
        child: [0; 8],
        first: 0,
        inner: 0,
        root_of: 0,
        pad: [0; 5],
    };

    fn set(&mut self, slot: usize, child: u32, b: &Bounds) {
        self.child[slot] = child;
        for k in 0..3 {
            self.planes[2 * k][slot] = b.min[k];
            self.planes[2 * k + 1][slot] = b.max[k];
        }
    }

    /// Slot `slot`'s box (what [`Node8::set`] wrote).
    fn slot_bounds(&self, slot: usize) -> Bounds {
        Bounds {
            min: [0, 1, 2].map(|k| self.planes[2 * k][slot]),
            max: [0, 1, 2].map(|k| self.planes[2 * k + 1][slot]),
        }
    }

    /// Whether the children lie as the walk expects (see [`Node8`]): slots `0..inner` hold
    /// nodes `first..first + inner`, the others leaves or nothing.
    fn children_in_place(&self) -> bool {
        self.child.iter().enumerate().all(|(slot, &c)| {
            let is_inner = names_node(c);
            is_inner == (slot < self.inner as usize)
                && (!is_inner || u64::from(c) == u64::from(self.first) + slot as u64)
        })
    }

    /// The union of the children's boxes.
    fn bounds(&self) -> Bounds {
        let mut b = Bounds::EMPTY;
        for k in 0..3 {
            for s in 0..8 {
                b.min[k] = b.min[k].min(self.planes[2 * k][s]);
                b.max[k] = b.max[k].max(self.planes[2 * k + 1][s]);
            }
        }
        b
    }
}

/// Up to four triangles, vertex coordinates lane by lane: `p[3 * vertex + axis][lane]`.
/// Unused lanes repeat lane 0, so they can only find the hit lane 0 finds.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(16))]
pub struct Tri4 {
    pub p: [[f32; 4]; 9],
    /// The chunk's triangle index (leaf order) of each lane.
    pub id: [u32; 4],
}

// SAFETY: `repr(C)` of `f32` and `u32` arrays only, 160 bytes, a multiple of the alignment:
// no padding, every bit pattern valid.
unsafe impl bytemuck::Zeroable for Tri4 {}
// SAFETY: as above.
unsafe impl bytemuck::Pod for Tri4 {}
const _: () = assert!(size_of::<Tri4>() == 160);

#[derive(Clone, Copy, Debug)]
struct Bounds {
    min: [f32; 3],
    max: [f32; 3],
}

impl Bounds {
    const EMPTY: Bounds = Bounds {
        min: [f32::INFINITY; 3],
        max: [f32::NEG_INFINITY; 3],
    };

    fn add_point(&mut self, p: [f32; 3]) {
        for ((lo, hi), v) in self.min.iter_mut().zip(&mut self.max).zip(p) {
            *lo = lo.min(v);
            *hi = hi.max(v);
        }
    }
}

/// A tree in the walking form: node 0 is the root (none when the tree is empty). Its arrays
/// are its own, or lie in a shared block (a card's memory, [`Bvh8::in_block`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Bvh8 {
    pub nodes: Region<Node8>,
    pub leaves: Region<Tri4>,
    /// The chunk's triangle count: a leaf lane naming a triangle at or above it is never
    /// reported. Trees built here name none; a tree read in place ([`Bvh8::in_block`]) is
    /// checked for its shape only, and this is where its triangle ids are checked instead,
    /// as they are used (one compare per hit, not a pass over every leaf of the chunk).
    pub tris: u32,
}

/// What [`Bvh8::flatten`] makes: the one tree, and which chunk its parts come from.
pub struct Flattened {
    pub form: Bvh8,
    /// The chunk of each four-triangle block.
    pub block_chunk: Vec<u32>,
}

/// Where everything of a [`Bvh8::flatten`]ed tree goes, from the top-level tree and each
/// chunk's node and block counts: first the top-level nodes and the chunks' roots, breadth
/// first, each node's inner children given consecutive places as it is reached (a chunk's
/// root in the slot that held the chunk, with the chunk's box as before); then each chunk's
/// other nodes, chunk by chunk, in their order; blocks chunk by chunk. A chunk of one
/// four-triangle block becomes that block in its slot, as the two-level walk skips such a
/// chunk's tree. So the walk's way down is the same, every node's inner children stay
/// consecutive and first, and a query meets the same boxes and triangles, in one tree.
pub struct FlatLayout {
    heads: Vec<Head>,
    /// Per head: where its inner children begin, and how many.
    children: Vec<(usize, usize)>,
    /// Per chunk: where its nodes after the root go (with a tree), its first block.
    body_base: Vec<usize>,
    leaf_base: Vec<u32>,
    /// Per chunk: its node and block counts.
    counts: Vec<(usize, usize)>,
    /// Nodes and blocks in all.
    pub nodes: usize,
    pub leaves: usize,
}

/// Whether chunk `c` of these (nodes, blocks) counts has a tree to walk: a chunk of one
/// block is walked as that block.
fn has_tree(counts: &[(usize, usize)], c: usize) -> bool {
    counts.get(c).is_some_and(|&(n, l)| l > 1 && n > 0)
}

#[derive(Clone, Copy)]
enum Head {
    Top(usize),
    Root(usize),
}

impl FlatLayout {
    /// The layout for `top` over chunks of `counts[c]` = (nodes, blocks); `None` where it
    /// does not fit references.
    pub fn new(top: &Bvh8, counts: &[(usize, usize)]) -> Option<FlatLayout> {
        let has_tree = |c: u32| has_tree(counts, (c & !LEAF) as usize);
        // Blocks with no node to hold them: not a chunk's tree (each would be lost).
        if counts.iter().any(|&(n, l)| l > 1 && n == 0) {
            return None;
        }
        let mut leaf_base = Vec::with_capacity(counts.len());
        let mut leaves = 0usize;
        for &(_, l) in counts {
            leaf_base.push(u32::try_from(leaves).ok()?);
            leaves += l;
        }
        if leaves >= TWO_BLOCKS as usize {
            return None;
        }
        let mut heads = Vec::new();
        let mut children = Vec::new();
        if !top.nodes.is_empty() {
            heads.push(Head::Top(0));
        }
        let mut at = 0;
        while at < heads.len() {
            let first = heads.len();
            if let Head::Top(i) = heads[at] {
                let n = &top.nodes[i];
                for (slot, &c) in n.child.iter().enumerate() {
                    if Self::inner_of(top, n, slot) {
                        heads.push(Head::Top(c as usize));
                    } else if c & LEAF != 0 && has_tree(c) {
                        heads.push(Head::Root((c & !LEAF) as usize));
                    }
                }
            }
            children.push((first, heads.len() - first));
            at += 1;
        }
        let mut body_base = vec![0usize; counts.len()];
        let mut nodes = heads.len();
        for (c, &(n, _)) in counts.iter().enumerate() {
            if has_tree(LEAF | c as u32) {
                body_base[c] = nodes;
                nodes += n - 1;
            }
        }
        if nodes >= LEAF as usize {
            return None;
        }
        Some(FlatLayout {
            heads,
            children,
            body_base,
            leaf_base,
            counts: counts.to_vec(),
            nodes,
            leaves,
        })
    }

    fn inner_of(top: &Bvh8, n: &Node8, slot: usize) -> bool {
        let c = n.child[slot];
        names_node(c) && slot < n.inner as usize && (c as usize) < top.nodes.len()
    }

    fn has_tree(&self, c: usize) -> bool {
        has_tree(&self.counts, c)
    }

    /// How many of chunk `c`'s nodes go to its body (all but its root, where it has a tree).
    pub fn body_len(&self, c: usize) -> usize {
        if self.has_tree(c) {
            self.counts[c].0 - 1
        } else {
            0
        }
    }

    /// Words of the tree as [`Bvh8::to_words`] writes it.
    pub fn words_len(&self) -> usize {
        walk_words(self.nodes, self.leaves)
    }

    /// `out` ([`FlatLayout::words_len`] words, 64-byte aligned) cut into what goes there:
    /// its header written, the head nodes, each chunk's body and its blocks; `None` if
    /// `out` is not of that length or alignment.
    #[allow(clippy::type_complexity)]
    pub fn cut<'a>(
        &self,
        out: &'a mut [u32],
    ) -> Option<(&'a mut [Node8], Vec<(&'a mut [Node8], &'a mut [Tri4])>)> {
        if out.len() != self.words_len() {
            return None;
        }
        let (head, rest) = out.split_at_mut(WALK_HEADER_WORDS);
        head.fill(0);
        head[..3].copy_from_slice(&[WALK_MAGIC, self.nodes as u32, self.leaves as u32]);
        let (node_words, leaf_words) = rest.split_at_mut(self.nodes * NODE_WORDS);
        let nodes: &mut [Node8] = bytemuck::try_cast_slice_mut(node_words).ok()?;
        let leaves: &mut [Tri4] = bytemuck::try_cast_slice_mut(leaf_words).ok()?;
        Some(self.split(nodes, leaves))
    }

    /// The tree's `nodes` and `leaves` ([`FlatLayout::nodes`] and [`FlatLayout::leaves`]
    /// long) cut into the head nodes and each chunk's body and blocks.
    #[allow(clippy::type_complexity)]
    fn split<'a>(
        &self,
        nodes: &'a mut [Node8],
        mut leaves: &'a mut [Tri4],
    ) -> (&'a mut [Node8], Vec<(&'a mut [Node8], &'a mut [Tri4])>) {
        let (heads, mut bodies) = nodes.split_at_mut(self.heads.len());
        let mut parts = Vec::with_capacity(self.counts.len());
        for c in 0..self.counts.len() {
            let (body, tail) = std::mem::take(&mut bodies).split_at_mut(self.body_len(c));
            bodies = tail;
            let (blocks, tail) = std::mem::take(&mut leaves).split_at_mut(self.counts[c].1);
            leaves = tail;
            parts.push((body, blocks));
        }
        (heads, parts)
    }

    /// The chunk of each block.
    pub fn block_chunk(&self) -> Vec<u32> {
        let mut out = Vec::with_capacity(self.leaves);
        for (c, &(_, l)) in self.counts.iter().enumerate() {
            out.resize(out.len() + l, c as u32);
        }
        out
    }

    /// Writes chunk `c`'s tree `form` (of `tris` triangles): its nodes after the root into
    /// `body` ([`FlatLayout::body_len`] of them) and its blocks into `blocks`, references
    /// moved to their places in the whole tree; returns its root, moved likewise, for
    /// [`FlatLayout::write_heads`]. `None` if the form is not of the counts given, or names
    /// a triangle beyond `tris`.
    pub fn write_chunk(
        &self,
        c: usize,
        form: &Bvh8,
        tris: u32,
        body: &mut [Node8],
        blocks: &mut [Tri4],
    ) -> Option<Node8> {
        if (form.nodes.len(), form.leaves.len()) != *self.counts.get(c)?
            || body.len() != self.body_len(c)
            || blocks.len() != form.leaves.len()
            || form
                .leaves
                .iter()
                .any(|b| b.id.iter().any(|&id| id >= tris))
        {
            return None;
        }
        blocks.copy_from_slice(&form.leaves);
        let (body_base, leaf_base) = (self.body_base[c], self.leaf_base[c]);
        // Nodes after the root move to the body, blocks to the chunk's place among all
        // blocks; an empty slot stays so.
        let moved = |r: u32| -> u32 {
            if r & LEAF != 0 {
                LEAF | (r & TWO_BLOCKS) | ((r & !(LEAF | TWO_BLOCKS)) + leaf_base)
            } else if r == 0 {
                0
            } else {
                (body_base + r as usize - 1) as u32
            }
        };
        let node = |n: &Node8| Node8 {
            child: n.child.map(moved),
            first: if n.inner > 0 { moved(n.first) } else { 0 },
            ..*n
        };
        if self.has_tree(c) {
            for (out, n) in body.iter_mut().zip(&form.nodes[1..]) {
                *out = node(n);
            }
            Some(Node8 {
                root_of: c as u32 + 1,
                ..node(&form.nodes[0])
            })
        } else {
            Some(Node8::EMPTY)
        }
    }

    /// Writes the top-level nodes and the chunks' roots (`roots[c]` from
    /// [`FlatLayout::write_chunk`]) into `heads`, the first part of [`FlatLayout::cut`].
    pub fn write_heads(&self, top: &Bvh8, roots: &[Node8], heads: &mut [Node8]) {
        for ((h, &(first, count)), out) in self.heads.iter().zip(&self.children).zip(heads) {
            *out = match *h {
                Head::Root(c) => roots.get(c).copied().unwrap_or(Node8::EMPTY),
                Head::Top(i) => {
                    let src = &top.nodes[i];
                    let mut n = Node8::EMPTY;
                    let mut next = 0;
                    for (slot, &c) in src.child.iter().enumerate() {
                        let chunk = (c & !LEAF) as usize;
                        if Self::inner_of(top, src, slot) || (c & LEAF != 0 && self.has_tree(chunk))
                        {
                            n.set(next, (first + next) as u32, &src.slot_bounds(slot));
                            next += 1;
                        }
                    }
                    debug_assert_eq!(next, count);
                    n.first = if count > 0 { first as u32 } else { 0 };
                    n.inner = count as u32;
                    for (slot, &c) in src.child.iter().enumerate() {
                        let chunk = (c & !LEAF) as usize;
                        if c & LEAF != 0 && self.counts.get(chunk).is_some_and(|&(_, l)| l == 1) {
                            n.set(next, LEAF | self.leaf_base[chunk], &src.slot_bounds(slot));
                            next += 1;
                        }
                    }
                    n
                }
            };
        }
    }
}

/// Why a walking form found in a block cannot be walked.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum WalkFormError {
    #[error("the walking form does not fit its block or is misaligned")]
    Layout,
    #[error("walking form: {0}")]
    NotATree(String),
}

/// Where a chunk's walking form lies, as [`Bvh8::to_words`] wrote it: words `start..end`
/// of `block`.
#[derive(Clone)]
pub struct WalkPlace {
    pub block: Arc<dyn Block>,
    pub start: usize,
    pub end: usize,
}

/// Words before the nodes in the block form: magic, node count, leaf count, then zeros up to
/// a node's alignment, so that nodes that start 64-byte aligned stay so.
const WALK_HEADER_WORDS: usize = 16;
const WALK_MAGIC: u32 = u32::from_le_bytes(*b"MGW8");
const NODE_WORDS: usize = size_of::<Node8>() / 4;
const TRI4_WORDS: usize = size_of::<Tri4>() / 4;

/// The first words of a tree's walking form ([`Bvh8::walk_header`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WalkHeader([u32; WALK_HEADER_WORDS]);

/// Words of a walking form of `nodes` nodes and `leaves` leaf blocks (see [`Bvh8::to_words`]).
fn walk_words(nodes: usize, leaves: usize) -> usize {
    WALK_HEADER_WORDS + nodes * NODE_WORDS + leaves * TRI4_WORDS
}

/// Transcodes a tree in its wire form. `leaf(first, count, nodes)` makes the reference and
/// box of a leaf child (and may add nodes of its own). Nodes keep their indices. Input that
/// is not a tree (which validation refuses before this is called) gives a tree missing the
/// parts that were not, never a panic or a loop.
fn transcode(
    wire: &[WideNode],
    mut leaf: impl FnMut(u32, u32, &mut Vec<Node8>) -> Option<(u32, Bounds)>,
) -> Vec<Node8> {
    if wire.is_empty() {
        return Vec::new();
    }
    // Pre-order, so that its reverse meets every child before its parent.
    let mut order = Vec::with_capacity(wire.len());
    let mut seen = vec![false; wire.len()];
    let mut work = vec![0usize];
    while let Some(i) = work.pop() {
        if std::mem::replace(&mut seen[i], true) {
            continue;
        }
        order.push(i);
        for &r in &wire[i] {
            if let Child::Node(c) = bvh::child(r)
                && (c as usize) < wire.len()
                && !seen[c as usize]
            {
                work.push(c as usize);
            }
        }
    }
    let mut nodes = vec![Node8::EMPTY; wire.len()];
    let mut done = vec![false; wire.len()];
    for &i in order.iter().rev() {
        let mut node = Node8::EMPTY;
        for (slot, &r) in wire[i].iter().enumerate() {
            match bvh::child(r) {
                Child::Node(c) if (c as usize) < wire.len() && done[c as usize] => {
                    let b = nodes[c as usize].bounds();
                    node.set(slot, c, &b);
                }
                Child::Leaf { first, count } => {
                    if let Some((r, b)) = leaf(first, count, &mut nodes) {
                        node.set(slot, r, &b);
                    }
                }
                _ => {}
            }
        }
        nodes[i] = node;
        done[i] = true;
    }
    nodes
}

/// `nodes` (a tree of [`transcode`]'s, root first) renumbered breadth first, so that every
/// node's inner children are consecutive nodes, and each node's slots ordered inner children
/// first (in their slot order), then leaves, then empty slots; `first` and `inner` set to
/// match. Boxes and references keep their meaning, so every query finds what it found
/// before (closest hits are unique, and any-hit queries answer whether, not which). Nodes
/// no root path reaches keep a place at the end, so the count stays what was promised; a
/// node reached a second time (not a tree) is left out of the later parent.
fn relayout(nodes: &[Node8]) -> Vec<Node8> {
    let n = nodes.len();
    if n == 0 {
        return Vec::new();
    }
    let inner_child = |c: u32| (names_node(c) && (c as usize) < n).then_some(c as usize);
    // Old indices in their new order, and the new parent of each.
    let mut order = vec![0usize];
    let mut parent = vec![u32::MAX];
    let mut new_of = vec![u32::MAX; n];
    new_of[0] = 0;
    let mut at = 0;
    while at < order.len() {
        for &c in &nodes[order[at]].child {
            if let Some(c) = inner_child(c)
                && new_of[c] == u32::MAX
            {
                new_of[c] = order.len() as u32;
                order.push(c);
                parent.push(at as u32);
            }
        }
        at += 1;
    }
    for (old, new) in new_of.iter_mut().enumerate() {
        if *new == u32::MAX {
            *new = order.len() as u32;
            order.push(old);
            parent.push(u32::MAX);
        }
    }
    order
        .iter()
        .enumerate()
        .map(|(new, &old)| {
            let src = &nodes[old];
            let mut out = Node8::EMPTY;
            let mut next = 0;
            for slot in 0..8 {
                if let Some(c) = inner_child(src.child[slot])
                    && parent[new_of[c] as usize] == new as u32
                {
                    if next == 0 {
                        out.first = new_of[c];
                    }
                    out.set(next, new_of[c], &src.slot_bounds(slot));
                    next += 1;
                }
            }
            out.inner = next as u32;
            for slot in 0..8 {
                if src.child[slot] & LEAF != 0 {
                    out.set(next, src.child[slot], &src.slot_bounds(slot));
                    next += 1;
                }
            }
            out
        })
        .collect()
}

impl Bvh8 {
    /// How many leaf blocks [`Bvh8::for_chunk`] makes of a chunk's wire nodes (at most).
    pub(crate) fn leaf_count(wire: &[WideNode]) -> usize {
        wire.iter()
            .flatten()
            .map(|&r| match bvh::child(r) {
                Child::Leaf { count, .. } => count.div_ceil(4) as usize,
                _ => 0,
            })
            .sum()
    }

    /// The words [`Bvh8::to_words`] gives for the chunk tree of these validated wire nodes,
    /// known before it is built (every node is kept, and a valid tree's every leaf).
    pub fn words_len_for(wire: &[WideNode]) -> usize {
        walk_words(wire.len(), Bvh8::leaf_count(wire))
    }

    /// A chunk's tree, from its validated wire nodes and its triangles in leaf order.
    pub fn for_chunk(wire: &[WideNode], positions: &[[f32; 9]]) -> Bvh8 {
        // Sized exactly at once: a render node transcodes every chunk it fetches, and blocks
        // grown by doubling left holes in its heap that kept its memory above its budget.
        let leaf_count = Bvh8::leaf_count(wire);
        let mut leaves = Vec::with_capacity(leaf_count);
        let nodes = transcode(wire, |first, count, _| {
            let start = first as usize;
            let all = positions.get(start..start + count.min(8) as usize)?;
            let at = leaves.len() as u32;
            let mut b = Bounds::EMPTY;
            for (part, tris) in all.chunks(4).enumerate() {
                let base = first + 4 * part as u32;
                let mut block = Tri4 {
                    p: [[0.0; 4]; 9],
                    id: [base; 4],
                };
                for lane in 0..4 {
                    let t = lane.min(tris.len() - 1);
                    for (c, v) in tris[t].iter().enumerate() {
                        block.p[c][lane] = *v;
                    }
                    block.id[lane] = base + t as u32;
                }
                for t in tris {
                    for v in 0..3 {
                        b.add_point([t[3 * v], t[3 * v + 1], t[3 * v + 2]]);
                    }
                }
                leaves.push(block);
            }
            let two = if all.len() > 4 { TWO_BLOCKS } else { 0 };
            Some((LEAF | two | at, b))
        });
        Bvh8 {
            nodes: relayout(&nodes).into(),
            leaves: leaves.into(),
            tris: positions.len() as u32,
        }
    }

    /// The top-level tree, from its validated wire nodes, the chunk of each leaf slot and
    /// each chunk's bounds. A leaf of several chunks becomes a node of its own.
    pub fn for_chunks(wire: &[WideNode], slots: &[u32], bounds: &[([f32; 3], [f32; 3])]) -> Bvh8 {
        let chunk = |slot: u32| -> Option<(u32, Bounds)> {
            let id = *slots.get(slot as usize)?;
            let (min, max) = *bounds.get(id as usize)?;
            Some((LEAF | id, Bounds { min, max }))
        };
        let nodes = transcode(wire, |first, count, nodes| {
            if count == 1 {
                return chunk(first);
            }
            let mut node = Node8::EMPTY;
            for s in 0..count {
                if let Some((r, b)) = chunk(first + s) {
                    node.set(s as usize, r, &b);
                }
            }
            nodes.push(node);
            Some(((nodes.len() - 1) as u32, node.bounds()))
        });
        Bvh8 {
            nodes: relayout(&nodes).into(),
            leaves: Region::empty(),
            tris: 0,
        }
    }

    /// The top-level tree `top` and the chunk trees below it as one tree, for data that
    /// holds every chunk in this process: a ray then walks one tree with one stack instead
    /// of a tree per chunk it enters, each entered through the top-level leaf (finding the
    /// chunk, its material and its form, and starting a walk of its own). With it, the
    /// chunk of each block ([`Bvh8::closest_in`] and [`Bvh8::each_hit_in`] take it); each
    /// chunk's root node says whose it is ([`Node8::root_of`]).
    ///
    /// `parts[c]` is chunk `c`'s tree and its triangle count; [`FlatLayout`] says where
    /// everything goes. `None` where the parts do not fit one tree (too many blocks or nodes
    /// for a reference, a triangle id beyond its chunk's count, or deeper than the walk's
    /// stack). Preparation builds the same tree straight into its memory instead
    /// ([`FlatLayout::write_chunk`]), without the chunks' own forms.
    pub fn flatten(top: &Bvh8, parts: &[(&Bvh8, u32)]) -> Option<Flattened> {
        let counts: Vec<(usize, usize)> = parts
            .iter()
            .map(|(f, _)| (f.nodes.len(), f.leaves.len()))
            .collect();
        let layout = FlatLayout::new(top, &counts)?;
        let mut nodes = vec![Node8::EMPTY; layout.nodes];
        let mut leaves = vec![<Tri4 as bytemuck::Zeroable>::zeroed(); layout.leaves];
        let (heads, bodies) = layout.split(&mut nodes, &mut leaves);
        let roots = parts
            .iter()
            .zip(bodies)
            .enumerate()
            .map(|(c, ((form, tris), (body, blocks)))| {
                layout.write_chunk(c, form, *tris, body, blocks)
            })
            .collect::<Option<Vec<_>>>()?;
        layout.write_heads(top, &roots, heads);
        let flat = Bvh8 {
            nodes: nodes.into(),
            leaves: leaves.into(),
            // Checked chunk by chunk by `write_chunk`.
            tris: u32::MAX,
        };
        flat.validate().ok()?;
        Some(Flattened {
            form: flat,
            block_chunk: layout.block_chunk(),
        })
    }

    /// This tree as words, for a block that [`Bvh8::in_block`] reads in place: a header,
    /// the nodes, the leaves. Placed at a 64-byte aligned word, its nodes are aligned too.
    pub fn to_words(&self) -> Vec<u32> {
        self.word_pieces(&self.walk_header()).concat()
    }

    /// How many words [`Bvh8::to_words`] gives.
    pub fn words_len(&self) -> usize {
        walk_words(self.nodes.len(), self.leaves.len())
    }

    /// Writes what [`Bvh8::to_words`] gives into `out`, which must be
    /// [`Bvh8::words_len`] words long.
    pub fn write_words(&self, out: &mut [u32]) {
        let mut at = 0;
        for piece in self.word_pieces(&self.walk_header()) {
            out[at..at + piece.len()].copy_from_slice(piece);
            at += piece.len();
        }
    }

    /// The header that [`Bvh8::to_words`] begins with.
    pub fn walk_header(&self) -> WalkHeader {
        let mut head = [0; WALK_HEADER_WORDS];
        head[..3].copy_from_slice(&[
            WALK_MAGIC,
            self.nodes.len() as u32,
            self.leaves.len() as u32,
        ]);
        WalkHeader(head)
    }

    /// The words of [`Bvh8::to_words`] as the pieces they are made of, `head` (this tree's
    /// [`Bvh8::walk_header`]), the nodes and the leaves, without joining them: for a writer
    /// that puts them one after another where they go.
    pub fn word_pieces<'a>(&'a self, head: &'a WalkHeader) -> [&'a [u32]; 3] {
        [
            &head.0,
            bytemuck::cast_slice(&self.nodes),
            bytemuck::cast_slice(&self.leaves),
        ]
    }

    /// The tree [`Bvh8::to_words`] wrote at words `start..end` of `block`, walked in place,
    /// after checking that it is a tree: every child in range and reached once from the
    /// root, every leaf in range. Triangle ids are checked as hits are reported (against
    /// `tri_count`, see [`Bvh8::tris`]): a check of every leaf here would read the whole
    /// tree, on every render node, before its first ray. Boxes and triangles are taken as
    /// they are: wrong ones can make rays miss, but not read out of bounds or loop.
    pub fn in_block(
        block: Arc<dyn Block>,
        start: usize,
        end: usize,
        tri_count: u32,
    ) -> Result<Bvh8, WalkFormError> {
        let head = block
            .words()
            .get(start..end)
            .and_then(|w| w.get(..WALK_HEADER_WORDS))
            .ok_or(WalkFormError::Layout)?;
        if head[0] != WALK_MAGIC {
            return Err(WalkFormError::Layout);
        }
        let (nodes, leaves) = (head[1] as usize, head[2] as usize);
        let nodes_end = nodes
            .checked_mul(NODE_WORDS)
            .and_then(|n| n.checked_add(start + WALK_HEADER_WORDS))
            .ok_or(WalkFormError::Layout)?;
        let leaves_end = leaves
            .checked_mul(TRI4_WORDS)
            .and_then(|n| n.checked_add(nodes_end))
            .filter(|&e| e == end)
            .ok_or(WalkFormError::Layout)?;
        let bvh = Bvh8 {
            nodes: Region::in_block(block.clone(), start + WALK_HEADER_WORDS, nodes_end)
                .ok_or(WalkFormError::Layout)?,
            leaves: Region::in_block(block, nodes_end, leaves_end).ok_or(WalkFormError::Layout)?,
            tris: tri_count,
        };
        bvh.validate()?;
        Ok(bvh)
    }

    /// Checks what [`Bvh8::in_block`] promises, and that the tree is no deeper than the walk's
    /// stack is made for (as `bvh::validate_tree` does for the wire form), with every child
    /// after its parent, as our builder writes them, and inner children where
    /// [`relayout`] puts them. A slot whose child is node 0 (the root, nobody's child) must be
    /// empty: boxes no ray enters.
    fn validate(&self) -> Result<(), WalkFormError> {
        let bad = |what: String| Err(WalkFormError::NotATree(what));
        if self.nodes.is_empty() {
            return Ok(());
        }
        // Our builder writes every node before its children, so a child's index is above its
        // parent's: one pass in index order then sees each parent's depth before its
        // children, refuses cycles (an index never goes down) and shared nodes (a node is
        // reached once), and reads the nodes in memory order.
        let count = self.nodes.len();
        let mut depth = vec![0u16; count];
        depth[0] = 1;
        for (i, n) in self.nodes.iter().enumerate() {
            let d = depth[i];
            if d == 0 {
                continue; // not reached from the root: never walked
            }
            if !n.children_in_place() {
                return bad(format!(
                    "node {i}: its inner children are not nodes {}.. in its first {} slots",
                    n.first, n.inner
                ));
            }
            for (slot, &c) in n.child.iter().enumerate() {
                if c & LEAF != 0 {
                    if leaf_span(c & !LEAF).end > self.leaves.len() {
                        return bad(format!(
                            "node {i} names leaf {} of {}",
                            c & !LEAF,
                            self.leaves.len()
                        ));
                    }
                } else if c == 0 {
                    let empty = (0..3).all(|k| {
                        n.planes[2 * k][slot] == f32::INFINITY
                            && n.planes[2 * k + 1][slot] == f32::NEG_INFINITY
                    });
                    if !empty {
                        return bad(format!("node {i} slot {slot} leads back to the root"));
                    }
                } else {
                    let Some(reached) = depth.get_mut(c as usize).filter(|_| c as usize > i) else {
                        return bad(format!("node {i} names node {c} of {count}"));
                    };
                    if *reached != 0 {
                        return bad(format!("node {c} is reached twice"));
                    }
                    if d as usize >= MAX_DEPTH {
                        return bad(format!("deeper than {MAX_DEPTH} levels"));
                    }
                    *reached = d + 1;
                }
            }
        }
        Ok(())
    }

    /// Bytes this form takes in memory.
    pub fn byte_len(&self) -> usize {
        self.nodes.len() * size_of::<Node8>() + self.leaves.len() * size_of::<Tri4>()
    }
}

const _: () = assert!(crate::ray::PLANE_BYTES == size_of::<[f32; 8]>());

/// Which of the eight children the ray enters within [0, tmax], and where it enters;
/// `limit` is [`box_limit`] of `tmax` in every lane.
///
/// Past the six plane distances everything is done on the distances' bits as integers
/// ([`crate::simd`]), one cycle an operation instead of four: a node's test lies on the
/// chain each step down the tree waits for. The near distance is clamped at zero, so its
/// integer maximum is its float maximum; the far distance's integer minimum is the float
/// minimum where no far distance is negative and negative where one is, and a box whose far
/// side is behind the origin is missed either way.
///
/// Near distances are compared lowered, so that rounding never rejects a box the ray enters:
/// [`NEAR_SHRINK_ULPS`] units in the last place down, one integer subtraction. Near and far
/// distances use the same inverse direction, each axis's rounded once (a factor of at most
/// 1 + EPSILON / 2 either way), and the fused multiply-add rounds once more; the offsets'
/// rounding is covered by their slack (see [`RayQuery`]). A hit at distance t in the box lies
/// between each axis's exact near and far distance, so the computed near distance is at most
/// t times (1 + EPSILON / 2) squared and the computed far one at least t times
/// (1 - EPSILON / 2) squared: the near one exceeds the far one by under 2 EPSILON of it, at
/// most four units in the last place, which the lowering covers with room to spare.
/// Computing the far distances with a slightly larger inverse direction instead adds no
/// step to the chain, where the subtraction adds one, but takes three more eight-lane
/// constants a ray, in registers the leaf test needs too. On the Zen 3 of 2026-12-07 the
/// subtraction came out 1 to 3% faster in most runs; on an Intel Xeon (model 207) the same
/// day, 3 to 7% slower on primary rays and 1 to 5% faster on random and diffuse ones
/// (diffuse rays are the set furthest behind Embree; README).
#[inline(always)]
fn test_node(q: &RayQuery, n: &Node8, limit: F32x8) -> (u32, F32x8) {
    let (near, far) = q.planes();
    let plane = |offset: usize, inv: &[F32x8; 3], off: &[F32x8; 3], axis: usize| {
        // SAFETY: `RayQuery::planes` are byte offsets of whole plane arrays within the six
        // of `planes` (multiples of their size, below six times it).
        let p = unsafe { &*n.planes.as_ptr().byte_add(offset) };
        F32x8::load(p).mul_add(inv[axis], off[axis])
    };
    let tn = [0, 1, 2].map(|k| plane(near[k], &q.inv8, &q.near_off8, k));
    let tf = [0, 1, 2].map(|k| plane(far[k], &q.inv8, &q.far_off8, k));
    let tnear = tn[0]
        .max_bits(tn[1])
        .max_bits(tn[2].max_bits(F32x8::splat(0.0)));
    let tfar = tf[0].min_bits(tf[1]).min_bits(tf[2].min_bits(limit));
    (
        tnear.less_ulps(NEAR_SHRINK_ULPS).below_bits(tfar).bits() & 0xff,
        tnear,
    )
}

/// How far [`test_node`] lowers near distances before comparing them with far ones, in
/// units in the last place: twice the four that rounding can put between them.
const NEAR_SHRINK_ULPS: i32 = 8;

/// `tmax` as entry distances are compared with it (below it, as integers: [`test_node`] and
/// the walk's pops alike): [`WIDEN_ULPS`] units in the last place and one more up, so that a
/// box entered at `tmax` or a little beyond (rounding) is entered.
#[inline(always)]
fn box_limit(tmax: f32) -> f32 {
    simd::widen_ulps(tmax, WIDEN_ULPS + 1)
}

/// Asks for the cache lines of `p` (a hint: it never faults): every line it touches, counted
/// from the start of its first line, so that an object starting mid-line (a leaf of two
/// 160-byte blocks at 32 bytes into a line spans six lines) has its last line asked for too.
#[inline(always)]
fn prefetch_lines<T: ?Sized>(p: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let skew = (p as *const T).cast::<u8>() as usize & 63;
        let end = size_of_val(p) + skew;
        let line = (p as *const T).cast::<i8>().wrapping_sub(skew);
        let mut at = 0;
        while at < end {
            // SAFETY: a prefetch never faults; `line + at` lies in a cache line that holds
            // part of the object `p` refers to.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(line.wrapping_add(at)) };
            at += 64;
        }
    }
}

/// Asks for child `c` of a node ahead of its test: a far child pushed now is popped after
/// the near side's subtree, and its lines arrive meanwhile (random rays spend most of their
/// time waiting for memory); the nearer of two is asked for before the walk knows it is the
/// nearer, a little ahead of its own loads. Leaves are asked for through `leaf_lines`.
#[inline(always)]
fn prefetch_child(nodes: &[Node8], c: u32, leaf_lines: &impl Fn(u32)) {
    if c & LEAF != 0 {
        leaf_lines(c & !LEAF);
    } else if let Some(n) = nodes.get(c as usize) {
        prefetch_lines(n);
    }
}

/// A stack entry: the child reference in the low half, the entry distance's bits in the
/// high half. Distances are >= 0, so entries order like their distances (ties by child).
#[inline(always)]
fn entry(child: u32, t: f32) -> u64 {
    child as u64 | (t.to_bits() as u64) << 32
}

/// The first `n` (3 to 8) of `keys` ordered farthest first, so that pushed in that order
/// the nearest is popped first. Three and four, the common counts, by sorting networks
/// (compare and exchange without branches, whose outcome no predictor could guess);
/// more by insertion. In place: sorted into a new array, the keys were copied from one
/// array on the frame to another before the pushes.
#[inline(always)]
fn farthest_first(k: &mut [u64; 8], n: usize) {
    #[inline(always)]
    fn order(k: &mut [u64; 8], i: usize, j: usize) {
        let (a, b) = (k[i], k[j]);
        k[i] = a.max(b);
        k[j] = a.min(b);
    }
    match n {
        3 => {
            order(k, 0, 1);
            order(k, 1, 2);
            order(k, 0, 1);
        }
        4 => {
            order(k, 0, 1);
            order(k, 2, 3);
            order(k, 0, 2);
            order(k, 1, 3);
            order(k, 1, 2);
        }
        _ => {
            for i in 1..n.min(8) {
                let e = k[i];
                let mut j = i;
                while j > 0 && k[j - 1] < e {
                    k[j] = k[j - 1];
                    j -= 1;
                }
                k[j] = e;
            }
        }
    }
}

/// The walk's stack of (child, entry distance): child reference in the low half, entry
/// distance's bits in the high half, one word written and read whole (two narrower stores
/// read back as one would stall the load). Never initialised as a whole (it is needed once
/// per ray and per chunk the ray enters). Its length is the walk's own local, not a field
/// beside the entries: as a field it stayed in memory, stored and loaded again at every push.
type Stack = [MaybeUninit<u64>; STACK];

/// Pushes `e` onto `stack` of `len` entries. A valid tree needs fewer entries than the stack
/// holds; an entry beyond it would only be a subtree skipped, never memory written out of
/// bounds.
#[inline(always)]
fn push_entry(stack: &mut Stack, len: &mut usize, e: u64) {
    if let Some(slot) = stack.get_mut(*len) {
        slot.write(e);
        *len += 1;
    }
}

/// Pops the last of `len` entries of `stack`, as (child, entry distance).
#[inline(always)]
fn pop_entry(stack: &Stack, len: &mut usize) -> Option<(u32, f32)> {
    *len = len.checked_sub(1)?;
    // SAFETY: every entry below `len` was written by `push_entry`.
    let e = unsafe { stack[*len].assume_init() };
    Some((e as u32, f32::from_bits((e >> 32) as u32)))
}

/// Walks `nodes` from the root and calls `leaf(index, &mut tmax)` for every leaf whose box
/// the ray enters within [0, tmax], and `node_seen(node)` for every node it tests (a no-op
/// but where chunks entered are recorded, see [`Node8::root_of`]). `leaf` may shorten
/// `tmax`, which prunes what is left, or stop the walk. With `NEAREST_FIRST`, children are
/// visited in order of entry distance and those entered beyond `tmax` are skipped
/// (closest-hit queries); without, in slot order (any-hit queries, where order matters
/// little and sorting costs).
#[inline(always)]
pub fn walk<const NEAREST_FIRST: bool>(
    nodes: &[Node8],
    q: &RayQuery,
    tmax: &mut f32,
    leaf_lines: impl Fn(u32),
    node_seen: impl Fn(&Node8),
    mut leaf: impl FnMut(u32, &mut f32) -> Visit,
) {
    if nodes.is_empty() || !q.is_finite() {
        return;
    }
    let mut stack: Stack = [const { MaybeUninit::uninit() }; STACK];
    let mut len = 0usize;
    let mut cur = 0u32;
    let mut limit = F32x8::splat(box_limit(*tmax));
    loop {
        if cur & LEAF == 0 {
            let Some(node) = nodes.get(cur as usize) else {
                return;
            };
            node_seen(node);
            let (mask, tnear) = test_node(q, node, limit);
            if mask != 0 {
                let a = (mask.trailing_zeros() & 7) as usize;
                let rest = mask & (mask - 1);
                if rest == 0 {
                    // An inner child is `first + slot` (see `Node8`): no wait for `child`.
                    cur = if a < node.inner as usize {
                        node.first.wrapping_add(a as u32)
                    } else {
                        node.child[a]
                    };
                    continue;
                }
                if NEAREST_FIRST {
                    let mut t = [0.0f32; 8];
                    tnear.store(&mut t);
                    let b = (rest.trailing_zeros() & 7) as usize;
                    let more = rest & (rest - 1);
                    if more == 0 {
                        // Two children, the commonest case after one: no sort, and no
                        // branch on which is nearer (it is as often one as the other). Both
                        // are asked for before their distances are compared: the nearer's
                        // lines start coming about ten cycles sooner than its first load
                        // would ask for them (primary rays 2 to 3% faster on the Zen 3).
                        let (ca, cb) = (node.child[a], node.child[b]);
                        prefetch_child(nodes, ca, &leaf_lines);
                        prefetch_child(nodes, cb, &leaf_lines);
                        let (ta, tb) = (t[a].to_bits(), t[b].to_bits());
                        let swap = 0u32.wrapping_sub((tb < ta) as u32);
                        let near = ca ^ ((ca ^ cb) & swap);
                        let far = cb ^ ((ca ^ cb) & swap);
                        let far_t = tb ^ ((ta ^ tb) & swap);
                        push_entry(&mut stack, &mut len, entry(far, f32::from_bits(far_t)));
                        cur = near;
                        continue;
                    }
                    // Three or more: ordered in registers, the nearest taken next, the
                    // others pushed so that the nearer of them are popped first.
                    let mut keys = [0u64; 8];
                    let mut n = 0;
                    let mut m = mask;
                    while m != 0 {
                        let i = (m.trailing_zeros() & 7) as usize;
                        m &= m - 1;
                        prefetch_child(nodes, node.child[i], &leaf_lines);
                        keys[n & 7] = entry(node.child[i], t[i]);
                        n += 1;
                    }
                    farthest_first(&mut keys, n);
                    for &k in &keys[..n - 1] {
                        push_entry(&mut stack, &mut len, k);
                    }
                    cur = keys[n - 1] as u32;
                } else {
                    // Any hit: the last slot first (a leaf where the node has one, see
                    // `Node8`: a leaf can end the query, a subtree only leads to one), the
                    // others pushed so that they are popped from the last slot down.
                    let z = (31 - mask.leading_zeros()) as usize & 7;
                    let mut m = mask & !(1 << z);
                    while m != 0 {
                        let i = (m.trailing_zeros() & 7) as usize;
                        m &= m - 1;
                        prefetch_child(nodes, node.child[i], &leaf_lines);
                        push_entry(&mut stack, &mut len, entry(node.child[i], 0.0));
                    }
                    cur = node.child[z];
                }
                continue;
            }
        } else {
            if leaf(cur & !LEAF, tmax) == Visit::Stop {
                return;
            }
            limit = F32x8::splat(box_limit(*tmax));
        }
        loop {
            let Some((c, t)) = pop_entry(&stack, &mut len) else {
                return;
            };
            // A child entered at `t` is still worth a visit: `test_node`'s comparison.
            // `box_limit` again (one integer addition) rather than kept from the last leaf:
            // kept, it moved the walk's instructions by under 1%, up on one path and down on
            // the other.
            if !NEAREST_FIRST || simd::below_bits(t, box_limit(*tmax)) {
                cur = c;
                break;
            }
        }
    }
}

/// The blocks of chunk leaf `leaf` (a child reference less [`LEAF`]): one, or two with
/// [`TWO_BLOCKS`].
#[inline(always)]
fn leaf_span(leaf: u32) -> Range<usize> {
    let at = (leaf & !TWO_BLOCKS) as usize;
    at..at + 1 + usize::from(leaf & TWO_BLOCKS != 0)
}

/// What the triangle test found, for one block (four lanes) or two (eight: the first
/// block's lanes, then the second's). Every field a vector or a mask, none an array: with
/// the distances as an array indexed by lane, the whole value lived in memory and every leaf
/// a ray met stored it there, hit or not.
struct Lanes<V> {
    /// Lanes that hit within (0, tmax], their rounding bound cleared.
    hits: u32,
    /// Lanes whose edge functions came out exactly zero: the scalar test (in f64) decides.
    undecided: u32,
    t: V,
    u: V,
    v: V,
    w: V,
    inv_det: V,
}

impl<V: TriLanes> Lanes<V> {
    /// The distances, lane by lane: what the callers pick a lane by and hand to
    /// [`Lanes::hit`] (stored once, where a lane hits).
    #[inline(always)]
    fn distances(&self) -> V::Array {
        self.t.to_array()
    }

    /// The hit of `lane`, at its distance `t` (from [`Lanes::distances`]), as the scalar test
    /// would report it. Inlined: out of line, it wrote the hit as four scalars that its
    /// caller read back as one 16-byte word, a load the store buffer cannot forward.
    #[inline(always)]
    fn hit(&self, lane: usize, t: f32) -> TriHit {
        let (u, v, w, inv) = (
            self.u.to_array(),
            self.v.to_array(),
            self.w.to_array(),
            self.inv_det.to_array(),
        );
        TriHit {
            t,
            b0: u[lane] * inv[lane],
            b1: v[lane] * inv[lane],
            b2: w[lane] * inv[lane],
        }
    }
}

/// The triangles a leaf's test reads: one block in four lanes, or a leaf's two blocks in
/// eight, tested at once (one pass of the test instead of two: 1 to 3% fewer instructions a
/// closest-hit query on the landscape of `bench/peers/embree.py`).
trait Blocks<'a>: Copy {
    type V: TriLanes;
    /// Lanes: four a block.
    const LANES: usize;
    /// The blocks themselves (the scalar test of undecided lanes takes them one by one).
    fn blocks(self) -> &'a [Tri4];
    /// Row `row` (`3 * vertex + axis`) of the vertex coordinates, lane by lane.
    ///
    /// # Safety
    /// `row` is below 9.
    unsafe fn row(self, row: usize) -> Self::V;
    /// The chunk's triangle index (leaf order) of `lane`.
    fn id(self, lane: usize) -> u32;
}

impl<'a> Blocks<'a> for &'a [Tri4; 1] {
    type V = F32x4;
    const LANES: usize = 4;
    #[inline(always)]
    fn blocks(self) -> &'a [Tri4] {
        self
    }
    #[inline(always)]
    unsafe fn row(self, row: usize) -> F32x4 {
        // SAFETY: the caller keeps `row` below 9.
        F32x4::load(unsafe { self[0].p.get_unchecked(row) })
    }
    #[inline(always)]
    fn id(self, lane: usize) -> u32 {
        self[0].id[lane & 3]
    }
}

impl<'a> Blocks<'a> for &'a [Tri4; 2] {
    type V = F32x8;
    const LANES: usize = 8;
    #[inline(always)]
    fn blocks(self) -> &'a [Tri4] {
        self
    }
    #[inline(always)]
    unsafe fn row(self, row: usize) -> F32x8 {
        // SAFETY: the caller keeps `row` below 9.
        unsafe { F32x8::load_halves(self[0].p.get_unchecked(row), self[1].p.get_unchecked(row)) }
    }
    #[inline(always)]
    fn id(self, lane: usize) -> u32 {
        self[lane >> 2 & 1].id[lane & 3]
    }
}

/// Vertex `v` of a block's triangles relative to the ray's origin, permuted and sheared as
/// [`triangle::intersect_upto`] does it. A function of its own, inlined always: as a closure
/// it was left out of line where the triangle test was inlined into a larger walk.
#[inline(always)]
fn tri_vertex<'a, B: Blocks<'a>>(
    q: &RayQuery,
    b: B,
    origin: &[f32; 3],
    k: [usize; 3],
    v: usize,
) -> (B::V, B::V, B::V) {
    let rel = |axis: usize| {
        // SAFETY: `RayQuery::axes` are below 3, so `3 * v + axis` is below 9 for v < 3, and
        // `axis` indexes `origin`.
        unsafe {
            b.row(3 * v + axis)
                .sub(B::V::splat(*origin.get_unchecked(axis)))
        }
    };
    let (ax, ay, az) = (rel(k[0]), rel(k[1]), rel(k[2]));
    (
        B::V::splat(q.sx).neg_mul_add(az, ax),
        B::V::splat(q.sy).neg_mul_add(az, ay),
        B::V::splat(q.sz).mul(az),
    )
}

/// A block's triangles against one ray: the operations of [`triangle::intersect_upto`], in
/// the same order, lane by lane, so each lane gives the same bits as the scalar test.
#[inline(always)]
fn test_tris<'a, B: Blocks<'a>>(q: &RayQuery, b: B, tmax: f32) -> Lanes<B::V> {
    let lanes_of = |m: u32| m & ((1 << B::LANES) - 1);
    // The origin and axes once for the three vertices (read in each, the queries took 2 to
    // 3% more instructions).
    let (k, origin) = (q.axes(), q.origin.to_array());
    let (ax, ay, az) = tri_vertex(q, b, &origin, k, 0);
    let (bx, by, bz) = tri_vertex(q, b, &origin, k, 1);
    let (cx, cy, cz) = tri_vertex(q, b, &origin, k, 2);
    let u = cx.mul(by).sub(cy.mul(bx));
    let v = ax.mul(cy).sub(ay.mul(cx));
    let w = bx.mul(ay).sub(by.mul(ax));
    let zero = B::V::zero();
    let undecided = u.eq(zero).or(v.eq(zero)).or(w.eq(zero)).bits();
    // Most triangles a ray is tested against lie beside it: their edge functions disagree
    // in sign, and nothing below (the division least of all) can make them a hit. Sign bits
    // say so in three operations where no edge function is zero (the undecided lanes, which
    // the scalar test decides) and none is NaN (no hit: its determinant is NaN as well).
    let inside = lanes_of(!u.signs_differ(v, w));
    // What the test answers before it knows any hit: the undecided lanes for the scalar test.
    let no_hits = |inv_det| Lanes {
        hits: 0,
        undecided: lanes_of(undecided),
        t: zero,
        u,
        v,
        w,
        inv_det,
    };
    if inside & !undecided == 0 {
        return no_hits(zero);
    }
    let det = u.add(v).add(w);
    let det_abs = det.abs();
    let det_ok = det.ne(zero).and(det_abs.lt(B::V::splat(f32::INFINITY)));
    let t_scaled = u.mul_add(az, v.mul_add(bz, w.mul(cz)));
    let t_signed = t_scaled.xor_sign(det);
    let in_range = t_signed
        .gt(zero)
        .and(t_signed.gt(B::V::splat(tmax).mul(det_abs)).not());
    let inv_det = B::V::splat(1.0).div(det);
    let t = t_scaled.mul(inv_det);
    let t_ok = t.gt(zero).and(t.gt(B::V::splat(tmax)).not());
    let maybe = det_ok.and(in_range).and(t_ok).bits() & inside & !undecided;
    let mut out = no_hits(inv_det);
    if maybe == 0 {
        return out;
    }
    // The rounding bound on t (see the scalar test), for every lane at once.
    let max3 = |a: B::V, b: B::V, c: B::V| a.abs().max(b.abs()).max(c.abs());
    let (max_x, max_y, max_z) = (max3(ax, bx, cx), max3(ay, by, cy), max3(az, bz, cz));
    let g = |n: i32| B::V::splat(gamma(n));
    let delta_z = g(3).mul(max_z);
    let delta_x = g(5).mul(max_x.add(max_z));
    let delta_y = g(5).mul(max_y.add(max_z));
    let delta_e = B::V::splat(2.0).mul(
        g(2).mul(max_x)
            .mul(max_y)
            .add(delta_y.mul(max_x))
            .add(delta_x.mul(max_y)),
    );
    let max_e = max3(u, v, w);
    let delta_t = B::V::splat(3.0)
        .mul(
            g(3).mul(max_e)
                .mul(max_z)
                .add(delta_e.mul(max_z))
                .add(delta_z.mul(max_e)),
        )
        .mul(inv_det.abs());
    out.hits = maybe & t.gt(delta_t).bits();
    out.t = t;
    out
}

/// The closest hit so far: distance, then (chunk, triangle) to break ties. Starts at the
/// ray's `tmax` with no hit, which only a strictly nearer hit beats.
#[derive(Clone, Copy, Debug)]
pub struct Closest {
    pub t: f32,
    pub chunk: u32,
    pub tri: u32,
    pub hit: Option<TriHit>,
}

impl Closest {
    pub fn new(tmax: f32) -> Closest {
        Closest {
            t: tmax,
            chunk: 0,
            tri: 0,
            hit: None,
        }
    }

    /// Whether a hit at `t` on (`chunk`, `tri`) would be nearer than the best so far.
    #[inline(always)]
    pub fn beaten_by(&self, t: f32, chunk: u32, tri: u32) -> bool {
        t < self.t || (t == self.t && (chunk, tri) < (self.chunk, self.tri))
    }
}

fn lane_points(b: &Tri4, lane: usize) -> (glam::Vec3A, glam::Vec3A, glam::Vec3A) {
    let v =
        |i: usize| glam::Vec3A::new(b.p[3 * i][lane], b.p[3 * i + 1][lane], b.p[3 * i + 2][lane]);
    (v(0), v(1), v(2))
}

/// Updates `best` with the nearest hit among the triangles of `blocks` (a leaf's one or two,
/// of chunk `chunk`) that `accept` agrees to; true if it did.
#[inline(always)]
fn closest_in_leaf<A: FnMut(u32, &TriHit) -> bool>(
    q: &RayQuery,
    blocks: &[Tri4],
    tris: u32,
    chunk: u32,
    best: &mut Closest,
    accept: &mut A,
) -> bool {
    if let Ok(one) = <&[Tri4; 1]>::try_from(blocks) {
        closest_in_blocks(q, one, tris, chunk, best, accept)
    } else if let Ok(two) = <&[Tri4; 2]>::try_from(blocks) {
        closest_in_blocks(q, two, tris, chunk, best, accept)
    } else {
        false
    }
}

/// [`closest_in_leaf`] for its blocks `b`, in lanes. Only the winning lane's hit is put
/// together.
#[inline(always)]
fn closest_in_blocks<'a, B: Blocks<'a>, A: FnMut(u32, &TriHit) -> bool>(
    q: &RayQuery,
    b: B,
    tris: u32,
    chunk: u32,
    best: &mut Closest,
    accept: &mut A,
) -> bool {
    let lanes = test_tris(q, b, best.t);
    if lanes.undecided != 0 {
        let mut found = false;
        for block in b.blocks() {
            found |= closest_in_undecided_block(q, block, tris, chunk, best, accept);
        }
        return found;
    }
    if lanes.hits == 0 {
        return false;
    }
    let t = lanes.distances();
    take_nearest(
        b,
        tris,
        chunk,
        best,
        accept,
        lanes.hits,
        &t,
        #[inline(always)]
        |lane| lanes.hit(lane, t[lane]),
    )
}

/// [`closest_in_leaf`] for one block of a leaf where some lane's edge functions came out
/// exactly zero (a ray through an edge or a vertex): those lanes are decided by the scalar
/// test. Rare, and out of line, so that the common case keeps its registers; it tests the
/// block again rather than take the lanes' results, which the common case would then have
/// to store for it.
#[cold]
#[inline(never)]
fn closest_in_undecided_block<A: FnMut(u32, &TriHit) -> bool>(
    q: &RayQuery,
    block: &Tri4,
    tris: u32,
    chunk: u32,
    best: &mut Closest,
    accept: &mut A,
) -> bool {
    let one = std::array::from_ref(block);
    let lanes = test_tris(q, one, best.t);
    let mut left = lanes.hits | lanes.undecided;
    let mut t = lanes.distances();
    let mut exact: [Option<TriHit>; 4] = [None; 4];
    let mut z = lanes.undecided;
    while z != 0 {
        let lane = z.trailing_zeros() as usize & 3;
        z &= z - 1;
        let (v0, v1, v2) = lane_points(block, lane);
        match triangle::intersect_upto(q, v0, v1, v2, best.t) {
            Some(h) => {
                t[lane] = h.t;
                exact[lane] = Some(h);
            }
            None => left &= !(1 << lane),
        }
    }
    take_nearest(
        one,
        tris,
        chunk,
        best,
        accept,
        left,
        &t,
        #[inline(always)]
        |lane| exact[lane & 3].unwrap_or_else(|| lanes.hit(lane, t[lane & 3])),
    )
}

/// Of the lanes `left` of `b`, hit at distances `t`, the nearest that `accept` takes
/// (ties to the lower triangle index) becomes `best` if it beats it; true if one did.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn take_nearest<'a, B: Blocks<'a>, A: FnMut(u32, &TriHit) -> bool>(
    b: B,
    tris: u32,
    chunk: u32,
    best: &mut Closest,
    accept: &mut A,
    mut left: u32,
    t: &<B::V as TriLanes>::Array,
    hit: impl Fn(usize) -> TriHit,
) -> bool {
    while left != 0 {
        let mut pick = left.trailing_zeros() as usize & (B::LANES - 1);
        let mut m = left & (left - 1);
        while m != 0 {
            let lane = m.trailing_zeros() as usize & (B::LANES - 1);
            m &= m - 1;
            if (t[lane], b.id(lane)) < (t[pick], b.id(pick)) {
                pick = lane;
            }
        }
        left &= !(1 << pick);
        let tri = b.id(pick);
        if tri >= tris {
            continue;
        }
        if !best.beaten_by(t[pick], chunk, tri) {
            return false;
        }
        let h = hit(pick);
        if accept(tri, &h) {
            *best = Closest {
                t: h.t,
                chunk,
                tri,
                hit: Some(h),
            };
            return true;
        }
    }
    false
}

/// Calls `f` for the hits within (0, tmax) among the triangles of `block`, each triangle
/// once, until it says stop. A leaf's two blocks are tested one after the other, unlike
/// [`closest_in_leaf`]: a hit in the first often ends the query, and then the second is
/// never read (both in eight lanes, random rays' any-hit queries took 8% longer, waiting for
/// the second block's lines, although they ran 2% fewer instructions).
#[inline(always)]
fn hits_in_leaf<F: FnMut(u32, TriHit) -> Visit>(
    q: &RayQuery,
    block: &Tri4,
    tris: u32,
    tmax: f32,
    f: &mut F,
) -> Visit {
    let lanes = test_tris(q, std::array::from_ref(block), tmax);
    if lanes.undecided != 0 {
        return hits_in_undecided_block(q, block, tris, tmax, f);
    }
    if lanes.hits == 0 {
        return Visit::Continue;
    }
    let t = lanes.distances();
    report_each(
        block,
        tris,
        lanes.hits,
        f,
        #[inline(always)]
        |lane| Some(lanes.hit(lane, t[lane])).filter(|h| h.t < tmax),
    )
}

/// [`hits_in_leaf`] for one block where some lane's edge functions came out exactly zero:
/// as [`closest_in_undecided_block`], out of line, those lanes decided by the scalar test.
#[cold]
#[inline(never)]
fn hits_in_undecided_block<F: FnMut(u32, TriHit) -> Visit>(
    q: &RayQuery,
    block: &Tri4,
    tris: u32,
    tmax: f32,
    f: &mut F,
) -> Visit {
    let lanes = test_tris(q, std::array::from_ref(block), tmax);
    let t = lanes.distances();
    report_each(
        block,
        tris,
        lanes.hits | lanes.undecided,
        f,
        #[inline(always)]
        |lane| {
            if lanes.hits & (1 << lane) != 0 {
                Some(lanes.hit(lane, t[lane & 3])).filter(|h| h.t < tmax)
            } else {
                let (v0, v1, v2) = lane_points(block, lane & 3);
                triangle::intersect(q, v0, v1, v2, tmax)
            }
        },
    )
}

/// Calls `f` for the hit `hit(lane)` finds, if any, of each lane of `lanes` of `block`, each
/// triangle once (unused lanes repeat lane 0), until it says stop.
#[inline(always)]
fn report_each<F: FnMut(u32, TriHit) -> Visit>(
    block: &Tri4,
    tris: u32,
    mut lanes: u32,
    f: &mut F,
    hit: impl Fn(usize) -> Option<TriHit>,
) -> Visit {
    let mut reported = [u32::MAX; 4];
    while lanes != 0 {
        let lane = lanes.trailing_zeros() as usize & 3;
        lanes &= lanes - 1;
        let tri = block.id[lane];
        if tri >= tris || reported.contains(&tri) {
            continue;
        }
        reported[lane] = tri;
        if let Some(h) = hit(lane)
            && f(tri, h) == Visit::Stop
        {
            return Visit::Stop;
        }
    }
    Visit::Continue
}

impl Bvh8 {
    /// Asks for the lines of leaf `leaf`'s blocks (the walk's `leaf_lines` for a chunk's tree).
    #[inline(always)]
    fn prefetch_leaf(&self, leaf: u32) {
        if let Some(b) = self.leaf(leaf) {
            prefetch_lines(b);
        }
    }

    /// The blocks of leaf `leaf` ([`leaf_span`]), if they lie in this tree.
    #[inline(always)]
    fn leaf(&self, leaf: u32) -> Option<&[Tri4]> {
        let Range { start, end } = leaf_span(leaf);
        // One comparison: `leaves.get(start..end)` also checked `start <= end` (the compiler
        // could not see that it holds), six instructions at every leaf a ray meets.
        if end <= self.leaves.len() {
            // SAFETY: `leaf_span` gives `start < end` (`end` is `start` plus one or two, and
            // `start` is below 2^30), and `end` is within the slice.
            Some(unsafe { self.leaves.get_unchecked(start..end) })
        } else {
            None
        }
    }

    /// Updates `best` with the closest hit in this chunk (`chunk` is its id) that `accept`
    /// agrees to; true if it did.
    #[inline(always)]
    pub fn closest<A: FnMut(u32, &TriHit) -> bool>(
        &self,
        q: &RayQuery,
        chunk: u32,
        best: &mut Closest,
        mut accept: A,
    ) -> bool {
        // A chunk of one leaf (up to four triangles: a wall, a quad light) was entered
        // through the top-level box of the chunk, which holds the leaf's: its own tree would
        // only test that box again. Boxes only prune, so skipping one changes no hit.
        if let [b] = &self.leaves[..] {
            return q.is_finite()
                && closest_in_blocks(
                    q,
                    std::array::from_ref(b),
                    self.tris,
                    chunk,
                    best,
                    &mut accept,
                );
        }
        self.closest_in(q, |_| chunk, |_| {}, best, |_, tri, hit| accept(tri, hit))
    }

    /// [`Bvh8::closest`] for a tree whose blocks belong to different chunks
    /// ([`Bvh8::flatten`]): `chunk_of(block)` says whose, and `accept` is asked with it;
    /// `node_seen` is told every node tested ([`walk`]).
    #[inline(always)]
    pub fn closest_in<C: Fn(usize) -> u32, A: FnMut(u32, u32, &TriHit) -> bool>(
        &self,
        q: &RayQuery,
        chunk_of: C,
        node_seen: impl Fn(&Node8),
        best: &mut Closest,
        mut accept: A,
    ) -> bool {
        let mut found = false;
        let mut tmax = best.t;
        walk::<true>(
            &self.nodes,
            q,
            &mut tmax,
            |l| self.prefetch_leaf(l),
            node_seen,
            #[inline(always)]
            |leaf, tmax| {
                if let Some(b) = self.leaf(leaf) {
                    let chunk = chunk_of(leaf_span(leaf).start);
                    let mut accept = |tri, hit: &TriHit| accept(chunk, tri, hit);
                    if closest_in_leaf(q, b, self.tris, chunk, best, &mut accept) {
                        *tmax = best.t;
                        found = true;
                    }
                }
                Visit::Continue
            },
        );
        found
    }

    /// Calls `f` for hits in this chunk within (0, tmax), in no particular order, until it
    /// says stop. Each triangle is reported at most once.
    #[inline(always)]
    pub fn each_hit<F: FnMut(u32, TriHit) -> Visit>(&self, q: &RayQuery, tmax: f32, mut f: F) {
        // One leaf: straight to it, as in `closest`.
        if let [b] = &self.leaves[..] {
            if q.is_finite() {
                hits_in_leaf(q, b, self.tris, tmax, &mut f);
            }
            return;
        }
        self.each_hit_in(q, tmax, |_| 0, |_| {}, |_, tri, hit| f(tri, hit));
    }

    /// [`Bvh8::each_hit`] for a tree whose blocks belong to different chunks
    /// ([`Bvh8::flatten`]): `chunk_of(block)` says whose, and `f` is told it; `node_seen`
    /// is told every node tested ([`walk`]).
    #[inline(always)]
    pub fn each_hit_in<C: Fn(usize) -> u32, F: FnMut(u32, u32, TriHit) -> Visit>(
        &self,
        q: &RayQuery,
        tmax: f32,
        chunk_of: C,
        node_seen: impl Fn(&Node8),
        mut f: F,
    ) {
        let mut t = tmax;
        walk::<false>(
            &self.nodes,
            q,
            &mut t,
            |l| self.prefetch_leaf(l),
            node_seen,
            |leaf, _| {
                let Some(b) = self.leaf(leaf) else {
                    return Visit::Continue;
                };
                let chunk = chunk_of(leaf_span(leaf).start);
                let mut f = |tri, hit| f(chunk, tri, hit);
                if hits_in_leaf(q, &b[0], self.tris, tmax, &mut f) == Visit::Stop {
                    return Visit::Stop;
                }
                match b {
                    [_, second] => hits_in_leaf(q, second, self.tris, tmax, &mut f),
                    _ => Visit::Continue,
                }
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{
        chunk::{Chunk, MeshData, build_chunk},
        ray::Ray,
    };
    use glam::{Vec3, Vec3A};

    use crate::testing::Lcg;

    proptest::proptest! {
        /// Children to visit come out farthest first, every one of them once, for each
        /// count the walk sorts (the networks for three and four, insertion beyond).
        #[test]
        fn children_are_ordered_farthest_first(
            t in proptest::collection::vec(0.0f32..8.0, 3..=8),
            same in proptest::bool::ANY,
        ) {
            let mut keys = [0u64; 8];
            for (i, &d) in t.iter().enumerate() {
                // Equal distances too: they must keep both children.
                let d = if same { d.floor() } else { d };
                keys[i] = entry(i as u32, d);
            }
            let n = t.len();
            let mut sorted = keys;
            farthest_first(&mut sorted, n);
            let mut want = keys[..n].to_vec();
            want.sort_unstable_by(|a, b| b.cmp(a));
            proptest::prop_assert_eq!(&sorted[..n], &want[..]);
        }
    }

    /// The box test never rejects a box that holds a hit, whatever the scale and distance
    /// from the origin: triangles of sizes 2^-12 to 2^20 up to 2^20 of their size away, some
    /// of them flat along an axis (a box of no thickness), rays aimed at their corners, edges
    /// and insides from every side.
    #[test]
    fn a_box_holding_a_hit_is_entered() {
        let mut r = Lcg(11);
        let mut hits = 0;
        for i in 0..40_000 {
            let scale = 2.0f32.powi((r.next() * 32.0) as i32 - 12);
            let away = scale * 2.0f32.powi((r.next() * 20.0) as i32);
            let center = r.vec(away);
            let mut v = [0; 3].map(|_| Vec3A::from(center + r.vec(scale)));
            if i % 3 == 0 {
                let axis = i / 3 % 3;
                let flat = v[0][axis];
                for p in &mut v {
                    p[axis] = flat;
                }
            }
            // A corner, a point on an edge or one inside, as the ray's target.
            let (a, b) = match i % 4 {
                0 => (1.0, 0.0),
                1 => (r.next(), 0.0),
                _ => (r.next() * 0.5, r.next() * 0.5),
            };
            let target = v[0] + (v[1] - v[0]) * a + (v[2] - v[0]) * b;
            let reach = scale * 2.0f32.powi((r.next() * 8.0) as i32);
            let origin = target + Vec3A::from(r.vec(reach));
            let dir = (target - origin).normalize();
            if !dir.is_finite() {
                continue;
            }
            let q = RayQuery::new(&Ray::infinite(origin.into(), dir.into()));
            if triangle::intersect(&q, v[0], v[1], v[2], f32::INFINITY).is_none() {
                continue;
            }
            hits += 1;
            let mut b = Bounds::EMPTY;
            for p in v {
                b.add_point(p.to_array());
            }
            let mut node = Node8::EMPTY;
            node.set(3, LEAF, &b);
            let (mask, _) = test_node(&q, &node, F32x8::splat(box_limit(f32::INFINITY)));
            assert_eq!(
                mask,
                1 << 3,
                "ray {origin} {dir} misses the box {b:?} of its hit"
            );
        }
        assert!(hits > 20_000, "{hits} hits");
    }

    #[test]
    fn four_and_eight_lanes_give_the_bits_of_the_scalar_test() {
        let mut r = Lcg(7);
        let mut hits = 0;
        for _ in 0..20_000 {
            let mut blocks = [0, 1].map(|b| Tri4 {
                p: [[0.0; 4]; 9],
                id: [0, 1, 2, 3].map(|i| 4 * b + i),
            });
            let tris: Vec<[Vec3; 3]> = (0..8)
                .map(|_| {
                    let c = r.vec(1.0);
                    [c + r.vec(0.5), c + r.vec(0.5), c + r.vec(0.5)]
                })
                .collect();
            for (i, t) in tris.iter().enumerate() {
                for (v, corner) in t.iter().enumerate() {
                    for (k, coord) in corner.to_array().into_iter().enumerate() {
                        blocks[i / 4].p[3 * v + k][i % 4] = coord;
                    }
                }
            }
            let o = r.vec(3.0);
            let aim = tris[(r.next() * 8.0) as usize % 8];
            let d = ((aim[0] + aim[1] + aim[2]) / 3.0 + r.vec(0.2) - o).normalize();
            let q = RayQuery::new(&Ray::infinite(o, d));
            let tmax = if r.next() < 0.5 {
                f32::INFINITY
            } else {
                r.next() * 4.0
            };
            let four = [0, 1].map(|b| test_tris(&q, std::array::from_ref(&blocks[b]), tmax));
            let eight = test_tris(&q, &blocks, tmax);
            let bits = |h: Option<TriHit>| h.map(|h| [h.t, h.b0, h.b1, h.b2].map(f32::to_bits));
            for (i, t) in tris.iter().enumerate() {
                let scalar = triangle::intersect_upto(
                    &q,
                    Vec3A::from(t[0]),
                    Vec3A::from(t[1]),
                    Vec3A::from(t[2]),
                    tmax,
                );
                let (lanes, lane) = (&four[i / 4], i % 4);
                assert_eq!(
                    eight.undecided >> i & 1,
                    lanes.undecided >> lane & 1,
                    "triangle {i}"
                );
                if lanes.undecided & (1 << lane) != 0 {
                    continue;
                }
                let simd = (lanes.hits & (1 << lane) != 0)
                    .then(|| lanes.hit(lane, lanes.distances()[lane]));
                assert_eq!(bits(simd), bits(scalar), "triangle {i}, four lanes");
                let simd = (eight.hits & (1 << i) != 0).then(|| eight.hit(i, eight.distances()[i]));
                assert_eq!(bits(simd), bits(scalar), "triangle {i}, eight lanes");
                hits += scalar.is_some() as usize;
            }
        }
        assert!(hits > 2000, "the test should meet many hits, met {hits}");
    }

    fn grid(n: u32, z: f32) -> MeshData {
        let mut m = MeshData::default();
        for j in 0..=n {
            for i in 0..=n {
                m.positions.push(Vec3::new(i as f32, j as f32, z));
            }
        }
        let w = n + 1;
        for j in 0..n {
            for i in 0..n {
                let a = j * w + i;
                m.triangles.push([a, a + 1, a + w + 1]);
                m.triangles.push([a, a + w + 1, a + w]);
            }
        }
        m
    }

    /// Both kinds of tree are laid out as the walk expects (what `Bvh8::validate` checks),
    /// and the layout keeps every node and every leaf: a chunk's tree, and a top-level tree
    /// whose leaves hold several chunks (each such leaf a node of its own).
    #[test]
    fn trees_keep_inner_children_consecutive_and_first() {
        let m = grid(60, 0.0);
        let chunk = whole_chunk(&m);
        let bvh = chunk.accel();
        assert!(
            bvh.nodes.len() > 8,
            "the test needs a tree of several levels"
        );
        bvh.validate().unwrap();
        // Every block is in exactly one leaf (of one block or two).
        let mut blocks: Vec<u32> = bvh
            .nodes
            .iter()
            .flat_map(|n| n.child)
            .filter(|c| c & LEAF != 0)
            .flat_map(|c| leaf_span(c & !LEAF).map(|b| b as u32))
            .collect();
        blocks.sort();
        assert_eq!(blocks, (0..bvh.leaves.len() as u32).collect::<Vec<_>>());

        let boxes: Vec<([f32; 3], [f32; 3])> = (0..300)
            .map(|i| {
                let (x, y) = ((i % 20) as f32, (i / 20) as f32);
                ([x, y, 0.0], [x + 1.5, y + 1.5, 1.0])
            })
            .collect();
        let aabbs: Vec<obvhs::aabb::Aabb> = boxes
            .iter()
            .map(|(lo, hi)| obvhs::aabb::Aabb::new(glam::Vec3A::from(*lo), glam::Vec3A::from(*hi)))
            .collect();
        let wide = crate::bvh::Builder::default().build(&aabbs, 4);
        let top = Bvh8::for_chunks(&wide.nodes, &wide.order, &boxes);
        // `validate` is for a chunk's form (its leaves are blocks): the layout node by node.
        assert!(top.nodes.iter().all(Node8::children_in_place));
        assert!(
            top.nodes.len() > wide.nodes.len(),
            "leaves of several chunks became nodes"
        );
        let mut chunks: Vec<u32> = top
            .nodes
            .iter()
            .flat_map(|n| n.child)
            .filter(|c| c & LEAF != 0)
            .map(|c| c & !LEAF)
            .collect();
        chunks.sort();
        assert_eq!(chunks, (0..300).collect::<Vec<u32>>());
    }

    /// A chunk of several levels and a chunk of one block, under a top-level tree, made one
    /// tree: the layout the walk expects, every block once and with its chunk, the first
    /// chunk's root among the first nodes (the second has no tree to enter); a part naming a
    /// triangle beyond its chunk's count is refused.
    #[test]
    fn two_levels_flatten_into_one_tree_or_are_refused() {
        let chunks = [whole_chunk(&grid(20, 0.0)), whole_chunk(&grid(1, 2.0))];
        let boxes: Vec<([f32; 3], [f32; 3])> = chunks
            .iter()
            .map(|c| (c.bounds().min.to_array(), c.bounds().max.to_array()))
            .collect();
        let aabbs: Vec<obvhs::aabb::Aabb> = chunks.iter().map(|c| c.bounds()).collect();
        let wide = crate::bvh::Builder::default().build(&aabbs, 1);
        let top = Bvh8::for_chunks(&wide.nodes, &wide.order, &boxes);
        let parts: Vec<(&Bvh8, u32)> = chunks.iter().map(|c| (c.accel(), c.tri_count())).collect();
        let (a, b) = (parts[0].0, parts[1].0);
        assert!(a.leaves.len() > 8 && b.leaves.len() == 1);

        let flat = Bvh8::flatten(&top, &parts).unwrap();
        flat.form.validate().unwrap();
        assert_eq!(flat.form.nodes.len(), top.nodes.len() + a.nodes.len());
        assert_eq!(flat.form.leaves.len(), a.leaves.len() + 1);
        let mut want = vec![0; a.leaves.len()];
        want.push(1);
        assert_eq!(flat.block_chunk, want);
        let roots: Vec<u32> = flat
            .form
            .nodes
            .iter()
            .map(|n| n.root_of)
            .filter(|&r| r != 0)
            .collect();
        assert_eq!(roots, [1], "chunk 0's root, once; chunk 1 has none");
        let mut blocks: Vec<usize> = flat
            .form
            .nodes
            .iter()
            .flat_map(|n| n.child)
            .filter(|c| c & LEAF != 0)
            .flat_map(|c| leaf_span(c & !LEAF))
            .collect();
        blocks.sort();
        assert_eq!(blocks, (0..flat.form.leaves.len()).collect::<Vec<_>>());

        let short = [(a, chunks[0].tri_count() - 1), parts[1]];
        assert!(Bvh8::flatten(&top, &short).is_none());
        // Blocks no node holds would be lost: refused.
        assert!(FlatLayout::new(&top, &[(0, 3), (1, 1)]).is_none());
    }

    /// One chunk of every triangle of `m`.
    fn whole_chunk(m: &MeshData) -> Chunk {
        let all: Vec<u32> = (0..m.triangles.len() as u32).collect();
        build_chunk(m, &all, 0, 0).unwrap()
    }

    /// `words` at a 64-byte aligned place of a block, as a card's segment holds them.
    fn aligned_block(words: &[u32]) -> (Arc<dyn Block>, usize, usize) {
        let (block, places) = crate::region::testing::aligned_block(&[words]);
        (block, places[0].0, places[0].1)
    }

    #[test]
    fn a_walking_form_written_as_words_is_walked_in_place_and_a_broken_one_refused() {
        let m = grid(40, 1.0);
        let chunk = whole_chunk(&m);
        let tris = chunk.tri_count();
        let bvh = chunk.accel();
        assert!(
            bvh.nodes.len() > 1,
            "the test needs a tree of several nodes"
        );
        let words = bvh.to_words();
        assert_eq!(words.len(), bvh.words_len());
        // Written from its pieces (as a fork node writes a segment), the same words.
        let head = bvh.walk_header();
        assert_eq!(bvh.word_pieces(&head).concat(), words);
        let (block, start, end) = aligned_block(&words);
        let read = Bvh8::in_block(block, start, end, tris).unwrap();
        assert_eq!(&read, bvh);
        assert!(read.nodes.is_shared() && read.leaves.is_shared());

        let refused = |change: &dyn Fn(&mut Bvh8), tris: u32| {
            let mut b = bvh.clone();
            change(&mut b);
            let (block, start, end) = aligned_block(&b.to_words());
            Bvh8::in_block(block, start, end, tris).unwrap_err()
        };
        let inner = |b: &Bvh8| {
            let n = &b.nodes[0];
            (0..8)
                .find(|&s| n.child[s] & LEAF == 0 && n.child[s] != 0)
                .unwrap()
        };
        let set = |b: &mut Bvh8, c: u32| {
            let s = inner(b);
            b.nodes.make_mut()[0].child[s] = c;
        };
        assert!(matches!(
            refused(&|b| set(b, 0), tris),
            WalkFormError::NotATree(_)
        ));
        let past = bvh.nodes.len() as u32;
        assert!(matches!(
            refused(&|b| set(b, past), tris),
            WalkFormError::NotATree(_)
        ));
        let twice = |b: &mut Bvh8| {
            let n = &mut b.nodes.make_mut()[0];
            let s = (0..8)
                .find(|&s| n.child[s] & LEAF == 0 && n.child[s] != 0)
                .unwrap();
            let other = (0..8).find(|&o| o != s && n.child[o] != 0).unwrap();
            n.child[other] = n.child[s];
        };
        assert!(matches!(refused(&twice, tris), WalkFormError::NotATree(_)));
        // Inner children elsewhere than `first..` in the first slots (see `Node8`).
        let moved = |b: &mut Bvh8| b.nodes.make_mut()[0].first += 1;
        assert!(matches!(refused(&moved, tris), WalkFormError::NotATree(_)));
        let fewer_inner = |b: &mut Bvh8| b.nodes.make_mut()[0].inner -= 1;
        assert!(matches!(
            refused(&fewer_inner, tris),
            WalkFormError::NotATree(_)
        ));
        let leaves = bvh.leaves.len() as u32;
        assert!(matches!(
            refused(&|b| set(b, LEAF | leaves), tris),
            WalkFormError::NotATree(_)
        ));
        // Triangle ids are checked as hits are reported: read as a tree over one triangle
        // fewer, the last triangle is never hit, by either query, and the others still are.
        let (block, start, end) = aligned_block(&words);
        let fewer = Bvh8::in_block(block, start, end, tris - 1).unwrap();
        let hits = |b: &Bvh8, tri: u32| {
            let (v0, v1, v2) = crate::chunk::tri_points(&chunk.tri_positions()[tri as usize]);
            let centre = (v0 + v1 + v2) / 3.0;
            let q = RayQuery::new(&Ray::new(centre + Vec3A::Z, -Vec3A::Z, f32::INFINITY));
            let mut best = Closest::new(f32::INFINITY);
            b.closest(&q, 0, &mut best, |_, _| true);
            let mut any = Vec::new();
            b.each_hit(&q, f32::INFINITY, |t, _| {
                any.push(t);
                Visit::Continue
            });
            (best.hit.map(|_| best.tri), any)
        };
        assert_eq!(hits(bvh, tris - 1), (Some(tris - 1), vec![tris - 1]));
        assert_eq!(hits(&fewer, tris - 1), (None, vec![]));
        assert_eq!(hits(&fewer, 0), (Some(0), vec![0]));
        // Cut short, misplaced or not a walking form at all.
        let (block, start, end) = aligned_block(&words);
        assert_eq!(
            Bvh8::in_block(block.clone(), start, end - 1, tris).unwrap_err(),
            WalkFormError::Layout
        );
        assert_eq!(
            Bvh8::in_block(block, start + 1, end, tris).unwrap_err(),
            WalkFormError::Layout
        );
        let (block, start, end) = aligned_block(&[7; 64]);
        assert_eq!(
            Bvh8::in_block(block, start, end, tris).unwrap_err(),
            WalkFormError::Layout
        );
    }

    #[test]
    fn equal_distances_go_to_the_lowest_triangle_whatever_the_walk_meets_first() {
        // The same grid twice: every hit is a tie between two triangles.
        let mut m = grid(12, 1.0);
        let copy = grid(12, 1.0);
        let base = m.positions.len() as u32;
        m.positions.extend(copy.positions);
        m.triangles
            .extend(copy.triangles.iter().map(|t| t.map(|v| v + base)));
        let chunk = whole_chunk(&m);
        let mut r = Lcg(3);
        for _ in 0..500 {
            let o = Vec3::new(r.next() * 12.0, r.next() * 12.0, 5.0);
            let d = Vec3::new(r.next() - 0.5, r.next() - 0.5, -3.0).normalize();
            let q = RayQuery::new(&Ray::infinite(o, d));
            let mut tmax = f32::INFINITY;
            let got = chunk.intersect(&q, &mut tmax);
            let mut brute: Option<(f32, u32)> = None;
            for (i, p) in chunk.tri_positions().iter().enumerate() {
                let (a, b, c) = crate::chunk::tri_points(p);
                if let Some(h) = triangle::intersect(&q, a, b, c, f32::INFINITY)
                    && brute.is_none_or(|(t, j)| (h.t, i as u32) < (t, j))
                {
                    brute = Some((h.t, i as u32));
                }
            }
            assert_eq!(got.map(|(i, h)| (h.t, i)), brute);
        }
    }

    /// Leaves of five to eight triangles are two blocks, and the walks test both: rays at a
    /// chunk with many such leaves find what brute force finds, nearest and every hit, and
    /// many of the nearest lie in second blocks.
    #[test]
    fn leaves_of_two_blocks_find_what_brute_force_finds() {
        // Clusters of six overlapping triangles, one a unit cell, each triangle spanning
        // nearly the cluster's box: a leaf of two blocks costs less than two leaves.
        let mut m = MeshData::default();
        let mut r = Lcg(7);
        for cell in 0..24 * 24 {
            let (x, y) = ((cell % 24) as f32 + 0.2, (cell / 24) as f32 + 0.2);
            for _ in 0..6 {
                let base = m.positions.len() as u32;
                let mut jitter = |dx: f32, dy: f32| {
                    let (jx, jy, z) = (r.next() * 0.05, r.next() * 0.05, r.next() * 0.2);
                    m.positions.push(Vec3::new(x + dx + jx, y + dy + jy, z));
                };
                jitter(0.0, 0.0);
                jitter(0.6, 0.0);
                jitter(0.0, 0.6);
                m.triangles.push([base, base + 1, base + 2]);
            }
        }
        let chunk = whole_chunk(&m);
        let a = chunk.accel();
        let mut in_second = std::collections::HashSet::new();
        for c in a.nodes.iter().flat_map(|n| n.child) {
            let span = leaf_span(c & !LEAF);
            if c & LEAF != 0 && span.len() == 2 {
                in_second.extend(a.leaves[span.end - 1].id);
            }
        }
        assert!(
            in_second.len() > 100,
            "{} triangles in second blocks",
            in_second.len()
        );
        let mut r = Lcg(11);
        let mut nearest_in_second = 0;
        for _ in 0..2000 {
            // At a random cell's triangles, from above, a little tilted.
            let cell = Vec3::new((r.next() * 24.0).floor(), (r.next() * 24.0).floor(), 0.0);
            let aim = cell + Vec3::new(0.3 + r.next() * 0.2, 0.3 + r.next() * 0.2, 0.1);
            let d = Vec3::new(r.next() - 0.5, r.next() - 0.5, -4.0).normalize();
            let o = aim - d * 3.0;
            let q = RayQuery::new(&Ray::infinite(o, d));
            if finds_what_brute_force_finds(&chunk, &q) {
                let mut tmax = f32::INFINITY;
                let tri = chunk.intersect(&q, &mut tmax).map(|(i, _)| i);
                nearest_in_second += usize::from(tri.is_some_and(|i| in_second.contains(&i)));
            }
        }
        assert!(
            nearest_in_second > 40,
            "{nearest_in_second} nearest in second blocks"
        );
    }

    /// A deep tree (triangles at exponentially growing distances nest their boxes one in
    /// the next, out to 1e33) finds what brute force finds, nearest and every hit. The
    /// binned build makes 14 levels of it: it splits off a few blocks of triangles a level,
    /// where PLOC merged one at a time and made 17 or more (counting blocks, not triangles,
    /// it made 11 of the 300 triangles that gave 13 before).
    #[test]
    fn a_deep_tree_finds_what_brute_force_finds() {
        let mut m = MeshData::default();
        for i in 0..420 {
            let x = 1.2f32.powi(i);
            let s = x * 0.1;
            let base = m.positions.len() as u32;
            m.positions.extend([
                Vec3::new(x, -s, -s),
                Vec3::new(x, s, -s),
                Vec3::new(x + s, 0.0, s),
            ]);
            m.triangles.push([base, base + 1, base + 2]);
        }
        let chunk = whole_chunk(&m);
        let depth = levels(&chunk.accel().nodes);
        assert!(depth > 12, "a tree of {depth} levels");
        let mut r = Lcg(5);
        let mut hits = 0;
        for k in 0..600 {
            let target = chunk.tri_positions()[k % m.triangles.len()];
            let (a, b, c) = crate::chunk::tri_points(&target);
            let aim = Vec3::from((a + b + c) / 3.0);
            let o = aim + r.vec(1.0) * (aim.x * 0.5) + Vec3::new(0.0, 0.0, aim.x);
            let q = RayQuery::new(&Ray::infinite(o, (aim - o).normalize()));
            hits += usize::from(finds_what_brute_force_finds(&chunk, &q));
        }
        assert!(hits > 150, "the test should meet many hits, met {hits}");
    }

    /// Checks one ray against `chunk`: the closest hit and the set of all hits are those of
    /// every triangle tested on its own. Whether the ray hit anything.
    fn finds_what_brute_force_finds(chunk: &Chunk, q: &RayQuery) -> bool {
        let mut tmax = f32::INFINITY;
        let got = chunk.intersect(q, &mut tmax).map(|(i, h)| (h.t, i));
        let mut brute: Option<(f32, u32)> = None;
        let mut all_hits = Vec::new();
        for (i, p) in chunk.tri_positions().iter().enumerate() {
            let (a, b, c) = crate::chunk::tri_points(p);
            if let Some(h) = triangle::intersect(q, a, b, c, f32::INFINITY) {
                all_hits.push(i as u32);
                if brute.is_none_or(|(t, j)| (h.t, i as u32) < (t, j)) {
                    brute = Some((h.t, i as u32));
                }
            }
        }
        assert_eq!(got, brute);
        let mut seen = Vec::new();
        chunk.for_each_hit(q, f32::INFINITY, |tri, _| {
            seen.push(tri);
            Visit::Continue
        });
        seen.sort();
        assert_eq!(seen, all_hits);
        got.is_some()
    }

    /// Levels of a walking-form tree from its root down.
    fn levels(nodes: &[Node8]) -> u32 {
        let mut deepest = 0;
        let mut work = vec![(0usize, 1u32)];
        while let Some((i, d)) = work.pop() {
            deepest = deepest.max(d);
            for &c in &nodes[i].child {
                if names_node(c) {
                    work.push((c as usize, d + 1));
                }
            }
        }
        deepest
    }

    /// A chunk of one leaf is tested without its tree: the same hits as every triangle
    /// tested on its own, misses included, for the closest and the any-hit query.
    #[test]
    fn a_chunk_of_one_leaf_finds_what_brute_force_finds() {
        let mut m = grid(1, 0.0);
        m.positions
            .extend([Vec3::new(0.2, 0.1, 0.5), Vec3::new(0.9, 0.3, 0.4)]);
        m.positions.push(Vec3::new(0.5, 0.9, 0.6));
        m.triangles.push([4, 5, 6]);
        let chunk = whole_chunk(&m);
        assert_eq!(chunk.accel().leaves.len(), 1);
        let mut r = Lcg(11);
        let mut hits = 0;
        for _ in 0..2000 {
            let o = r.vec(2.0);
            let d = (Vec3::new(r.next(), r.next(), r.next() - 0.5) - o).normalize();
            let q = RayQuery::new(&Ray::infinite(o, d));
            hits += usize::from(finds_what_brute_force_finds(&chunk, &q));
        }
        assert!(hits > 200, "the test should meet many hits, met {hits}");
    }

    /// Rays that are not finite numbers, or whose box constants overflow, meet nothing, and
    /// the walk over a tree with empty child slots ends. (The fuzzer found a chunk whose
    /// bounds' centre overflowed: the ray from there made NaN box distances, and the build
    /// without AVX2, whose min and max ignore NaN, entered an empty slot, which points at the
    /// root, forever.) Each ray runs on a thread that must finish within ten seconds.
    #[test]
    fn rays_that_are_not_finite_meet_nothing_and_the_walk_ends() {
        let m = grid(12, 1.0);
        let chunk = std::sync::Arc::new(whole_chunk(&m));
        assert!(
            chunk.accel().nodes.len() > 1,
            "the tree needs inner nodes with empty slots"
        );
        let (nan, inf, big) = (f32::NAN, f32::INFINITY, f32::MAX);
        let rays = [
            (Vec3::new(nan, 5.0, 5.0), Vec3::new(0.1, 0.2, -1.0)),
            (Vec3::new(5.0, 5.0, inf), Vec3::new(0.1, 0.2, -1.0)),
            (Vec3::new(5.0, 5.0, 5.0), Vec3::new(nan, 0.0, -1.0)),
            (Vec3::new(5.0, 5.0, 5.0), Vec3::new(0.0, -inf, -1.0)),
            // Finite, but origin / dir overflows on every axis.
            (Vec3::new(big, -big, big), Vec3::new(1e-30, 1e-30, -1.0)),
            (
                Vec3::new(-big, 6.0, big * 0.5),
                Vec3::new(1.0, 1e-25, -1e-25),
            ),
        ];
        for (o, d) in rays {
            let c = chunk.clone();
            let (tx, rx) = std::sync::mpsc::channel();
            std::thread::spawn(move || {
                let q = RayQuery::new(&Ray::infinite(o, d));
                let mut tmax = f32::INFINITY;
                let closest = c.intersect(&q, &mut tmax).map(|(tri, _)| tri);
                let mut any = 0;
                c.for_each_hit(&q, f32::INFINITY, |_, _| {
                    any += 1;
                    Visit::Continue
                });
                let _ = tx.send((q.is_finite(), closest, any));
            });
            let got = rx
                .recv_timeout(std::time::Duration::from_secs(10))
                .unwrap_or_else(|_| panic!("the walk did not end for origin {o}, dir {d}"));
            assert_eq!(got, (false, None, 0), "origin {o}, dir {d}");
        }
        // An ordinary ray is finite and still hits.
        let q = RayQuery::new(&Ray::infinite(
            Vec3::new(5.5, 5.5, 5.0),
            Vec3::new(0.01, 0.02, -1.0).normalize(),
        ));
        assert!(q.is_finite());
        let mut tmax = f32::INFINITY;
        assert!(chunk.intersect(&q, &mut tmax).is_some());
    }

    #[test]
    fn any_hit_reports_each_triangle_once_and_only_real_hits() {
        let m = grid(6, 0.0);
        let chunk = whole_chunk(&m);
        let q = RayQuery::new(&Ray::infinite(Vec3::new(2.3, 3.7, 1.0), -Vec3::Z));
        let mut seen = Vec::new();
        chunk.for_each_hit(&q, f32::INFINITY, |tri, h| {
            assert!((h.t - 1.0).abs() < 1e-6);
            seen.push(tri);
            Visit::Continue
        });
        assert_eq!(seen.len(), 1, "{seen:?}");
    }
}
