//! Wide BVH building (with obvhs) and our own traversal of it.
//!
//! Both levels of the scene use obvhs's compressed 8-wide BVH (CWBVH), the fastest CPU layout
//! it offers. Traversal is written here rather than taken from obvhs because the node test
//! must be robust at every scale: obvhs clips node intervals at a fixed t of 1e-4, which
//! would lose hits in a scene a few millimetres across, and its boxes are only as
//! conservative as f32 rounding happens to make them. Here the primitive boxes are padded by
//! a few ulps before building, and the slab test widens its interval by the rounding bound
//! of its own arithmetic, so a ray never misses a box that holds what it would hit.
//!
//! Node arrays are plain `Pod` data, so a chunk's tree is used straight from received bytes;
//! [`validate_nodes`] checks such bytes before they are trusted.

use glam::{UVec2, Vec3A};
use obvhs::{BvhBuildParams, aabb::Aabb, cwbvh::builder::build_cwbvh, cwbvh::node::CwBvhNode};

use crate::{math::gamma, ray::RayQuery};

/// Deepest tree accepted: the traversal stack holds one entry per level.
pub const MAX_DEPTH: usize = 48;

/// A box padded outwards by a few ulps of its coordinates, so that the rounding of the
/// builder's quantisation can only make child boxes larger than the truth, never smaller.
pub fn padded(aabb: Aabb) -> Aabb {
    let pad = (aabb.min.abs().max(aabb.max.abs()) + (aabb.max - aabb.min)) * (8.0 * f32::EPSILON)
        + Vec3A::splat(f32::MIN_POSITIVE);
    Aabb::new(aabb.min - pad, aabb.max + pad)
}

/// A built wide BVH: nodes plus the permutation from leaf slots to input primitives.
pub struct WideBvh {
    pub nodes: Vec<CwBvhNode>,
    pub primitive_indices: Vec<u32>,
}

/// Builds a wide BVH over boxes. Deterministic: the same boxes give the same bytes (obvhs is
/// used without its parallel feature, so no thread scheduling enters the build).
pub fn build(boxes: &[Aabb]) -> WideBvh {
    if boxes.is_empty() {
        return WideBvh {
            nodes: Vec::new(),
            primitive_indices: Vec::new(),
        };
    }
    let padded: Vec<Aabb> = boxes.iter().map(|b| padded(*b)).collect();
    let mut params = BvhBuildParams::medium_build();
    params.max_prims_per_leaf = 3;
    let bvh = build_cwbvh(&padded, params, &mut std::time::Duration::default());
    WideBvh {
        nodes: bvh.nodes,
        primitive_indices: bvh.primitive_indices,
    }
}

/// Children of `node` that the ray enters within (0, tmax), as the CWBVH hit mask: bits
/// 24..32 are inner children (in front-to-back order), bits 0..24 leaf primitives relative
/// to `primitive_base_idx`.
///
/// Each slab distance is computed as `q * (e / d) + (p - o) / d` (two operations per plane
/// on four children at once) and widened by the rounding bound of that arithmetic, per axis:
/// `gamma(5) * (|p - o| / |d| + 255 e / |d|)`. A child is therefore never rejected because of
/// rounding, at any scale or distance from the origin.
#[inline(always)]
pub fn intersect_node(node: &CwBvhNode, q: &RayQuery, tmax: f32) -> u32 {
    let e = [0, 1, 2].map(|k| f32::from_bits((node.e[k] as u32) << 23));
    let adj_inv = [0, 1, 2].map(|k| e[k] * q.inv_dir[k]);
    let adj_orig = [0, 1, 2].map(|k| (node.p[k] - q.origin[k]) * q.inv_dir[k]);
    let slack = [0, 1, 2].map(|k| gamma(5) * (adj_orig[k].abs() + 255.0 * adj_inv[k].abs()));
    let lo = [&node.child_min_x, &node.child_min_y, &node.child_min_z];
    let hi = [&node.child_max_x, &node.child_max_y, &node.child_max_z];
    let neg = [q.dir.x < 0.0, q.dir.y < 0.0, q.dir.z < 0.0];
    let hits = slab_hits(lo, hi, neg, adj_inv, adj_orig, slack, tmax);

    let (child_bits8, bit_index8) = node.get_child_and_index_bits(q.oct_inv4);
    let mut hit_mask = 0u32;
    let mut m = hits;
    while m != 0 {
        let i = m.trailing_zeros();
        m &= m - 1;
        let child_bits = ((child_bits8 >> (i * 8)) as u32) & 0xff;
        let bit_index = ((bit_index8 >> (i * 8)) as u32) & 0xff;
        hit_mask |= child_bits << bit_index;
    }
    hit_mask
}

/// Bit i set when child i's slabs overlap within (0, tmax).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn slab_hits(
    lo: [&[u8; 8]; 3],
    hi: [&[u8; 8]; 3],
    neg: [bool; 3],
    adj_inv: [f32; 3],
    adj_orig: [f32; 3],
    slack: [f32; 3],
    tmax: f32,
) -> u32 {
    use std::arch::x86_64::*;
    // SAFETY: SSE2 is part of the x86_64 baseline; the loads read exactly the 8 bytes of
    // each array (unaligned loads are allowed by _mm_loadl_epi64).
    unsafe {
        let zero_i = _mm_setzero_si128();
        let widen = |b: &[u8; 8]| -> (__m128, __m128) {
            let v = _mm_loadl_epi64(b.as_ptr() as *const __m128i);
            let w = _mm_unpacklo_epi8(v, zero_i);
            (
                _mm_cvtepi32_ps(_mm_unpacklo_epi16(w, zero_i)),
                _mm_cvtepi32_ps(_mm_unpackhi_epi16(w, zero_i)),
            )
        };
        let mut tmin = (_mm_setzero_ps(), _mm_setzero_ps());
        let mut tfar = (_mm_set1_ps(tmax), _mm_set1_ps(tmax));
        for k in 0..3 {
            let (nq, fq) = if neg[k] {
                (hi[k], lo[k])
            } else {
                (lo[k], hi[k])
            };
            let (n0, n1) = widen(nq);
            let (f0, f1) = widen(fq);
            let a = _mm_set1_ps(adj_inv[k]);
            let near_off = _mm_set1_ps(adj_orig[k] - slack[k]);
            let far_off = _mm_set1_ps(adj_orig[k] + slack[k]);
            tmin.0 = _mm_max_ps(tmin.0, _mm_add_ps(_mm_mul_ps(n0, a), near_off));
            tmin.1 = _mm_max_ps(tmin.1, _mm_add_ps(_mm_mul_ps(n1, a), near_off));
            tfar.0 = _mm_min_ps(tfar.0, _mm_add_ps(_mm_mul_ps(f0, a), far_off));
            tfar.1 = _mm_min_ps(tfar.1, _mm_add_ps(_mm_mul_ps(f1, a), far_off));
        }
        let m0 = _mm_movemask_ps(_mm_cmple_ps(tmin.0, tfar.0)) as u32;
        let m1 = _mm_movemask_ps(_mm_cmple_ps(tmin.1, tfar.1)) as u32;
        m0 | (m1 << 4)
    }
}

#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
fn slab_hits(
    lo: [&[u8; 8]; 3],
    hi: [&[u8; 8]; 3],
    neg: [bool; 3],
    adj_inv: [f32; 3],
    adj_orig: [f32; 3],
    slack: [f32; 3],
    tmax: f32,
) -> u32 {
    let mut hits = 0;
    for i in 0..8 {
        let (mut t0, mut t1) = (0.0f32, tmax);
        for k in 0..3 {
            let (nq, fq) = if neg[k] {
                (hi[k][i], lo[k][i])
            } else {
                (lo[k][i], hi[k][i])
            };
            t0 = t0.max(nq as f32 * adj_inv[k] + (adj_orig[k] - slack[k]));
            t1 = t1.min(fq as f32 * adj_inv[k] + (adj_orig[k] + slack[k]));
        }
        if t0 <= t1 {
            hits |= 1 << i;
        }
    }
    hits
}

/// What a leaf visit tells the traversal.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Visit {
    Continue,
    Stop,
}

/// Walks the tree front to back, calling `visit(slot, &mut tmax)` for every leaf primitive
/// slot whose box the ray enters. `visit` shortens `tmax` when it finds a closer hit, which
/// prunes the rest of the walk, or stops the walk (any-hit queries).
#[inline(always)]
pub fn traverse<F: FnMut(u32, &mut f32) -> Visit>(
    nodes: &[CwBvhNode],
    q: &RayQuery,
    tmax: &mut f32,
    mut visit: F,
) {
    if nodes.is_empty() {
        return;
    }
    let mut stack = [UVec2::ZERO; MAX_DEPTH];
    let mut sp = 0usize;
    // The root is the only child of a virtual group based at 0 (bit 31 set, imask bit 0).
    let mut node_group = UVec2::new(0, 0x8000_0000);
    let mut prim_group = UVec2::ZERO;
    loop {
        while prim_group.y != 0 {
            let local = 31 - prim_group.y.leading_zeros();
            prim_group.y &= !(1u32 << local);
            if visit(prim_group.x + local, tmax) == Visit::Stop {
                return;
            }
        }

        if node_group.y & 0xff00_0000 != 0 {
            let hits_imask = node_group.y;
            let child_offset = 31 - hits_imask.leading_zeros();
            node_group.y &= !(1u32 << child_offset);
            // Validated trees are at most MAX_DEPTH deep, so the stack cannot overflow.
            if node_group.y & 0xff00_0000 != 0 && sp < MAX_DEPTH {
                stack[sp] = node_group;
                sp += 1;
            }
            let slot = (child_offset - 24) ^ (q.oct_inv4 & 0xff);
            let relative = (hits_imask & !(u32::MAX << slot)).count_ones();
            let Some(node) = nodes.get((node_group.x + relative) as usize) else {
                return;
            };
            let hit_mask = intersect_node(node, q, *tmax);
            node_group = UVec2::new(
                node.child_base_idx,
                (hit_mask & 0xff00_0000) | node.imask as u32,
            );
            prim_group = UVec2::new(node.primitive_base_idx, hit_mask & 0x00ff_ffff);
        } else {
            node_group = UVec2::ZERO;
        }

        if prim_group.y == 0 && node_group.y & 0xff00_0000 == 0 {
            if sp == 0 {
                return;
            }
            sp -= 1;
            node_group = stack[sp];
        }
    }
}

/// Why received node bytes were refused.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum NodeError {
    #[error("node {node} points at children {first}..{end} but the tree has {count} nodes")]
    ChildOutOfRange {
        node: usize,
        first: u32,
        end: u64,
        count: usize,
    },
    #[error("node {node} points at primitives up to {end} but there are {count}")]
    PrimitiveOutOfRange { node: usize, end: u64, count: usize },
    #[error("the tree is deeper than {MAX_DEPTH} levels or has a cycle")]
    TooDeep,
    #[error("node {node} has a non-finite or malformed box")]
    BadBox { node: usize },
}

/// Checks that a node array (from the network or disk) is a tree that traversal can walk
/// without leaving the arrays, without looping, within its stack. Returns the depth.
pub fn validate_nodes(nodes: &[CwBvhNode], primitive_count: usize) -> Result<usize, NodeError> {
    if nodes.is_empty() {
        return Ok(0);
    }
    let mut visited = vec![false; nodes.len()];
    let mut max_depth = 0;
    let mut work = vec![(0usize, 1usize)];
    while let Some((index, depth)) = work.pop() {
        if depth > MAX_DEPTH || visited[index] {
            return Err(NodeError::TooDeep);
        }
        visited[index] = true;
        max_depth = max_depth.max(depth);
        let node = &nodes[index];
        if !Vec3A::from(node.p).is_finite() || node.e.iter().any(|&e| e == 0 || e == 255) {
            return Err(NodeError::BadBox { node: index });
        }
        let inner = node.imask.count_ones() as u64;
        let end = node.child_base_idx as u64 + inner;
        if end > nodes.len() as u64 {
            return Err(NodeError::ChildOutOfRange {
                node: index,
                first: node.child_base_idx,
                end,
                count: nodes.len(),
            });
        }
        for slot in 0..8 {
            let meta = node.child_meta[slot];
            if meta == 0 {
                continue;
            }
            if node.imask & (1 << slot) != 0 {
                if (meta & 0b1_1111) < 24 || (meta >> 5) != 1 {
                    return Err(NodeError::TooDeep);
                }
            } else {
                let offset = (meta & 0b1_1111) as u64;
                let count = (meta >> 5).count_ones() as u64;
                let prim_end = node.primitive_base_idx as u64 + offset + count;
                if offset >= 24 || prim_end > primitive_count as u64 {
                    return Err(NodeError::PrimitiveOutOfRange {
                        node: index,
                        end: prim_end,
                        count: primitive_count,
                    });
                }
            }
        }
        for child in 0..inner {
            work.push(((node.child_base_idx as u64 + child) as usize, depth + 1));
        }
    }
    Ok(max_depth)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ray::Ray;
    use glam::Vec3;

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
    fn traversal_finds_every_box_a_brute_force_finds() {
        let b = boxes(1000);
        let bvh = build(&b);
        assert!(validate_nodes(&bvh.nodes, bvh.primitive_indices.len()).is_ok());
        let dirs = [
            Vec3::new(1.0, 0.9, 0.8),
            Vec3::new(-0.3, 1.0, 0.2),
            Vec3::new(0.0, 0.0, 1.0),
        ];
        for (k, d) in dirs.iter().enumerate() {
            for i in 0..50 {
                let o = Vec3::new(-2.0 + i as f32 * 0.27, 3.1 + k as f32, -1.0);
                let ray = Ray::infinite(o, d.normalize());
                let q = RayQuery::new(&ray);
                let mut found = vec![false; b.len()];
                let mut tmax = f32::INFINITY;
                traverse(&bvh.nodes, &q, &mut tmax, |slot, _| {
                    found[bvh.primitive_indices[slot as usize] as usize] = true;
                    Visit::Continue
                });
                for (j, bx) in b.iter().enumerate() {
                    let hit =
                        bx.intersect_ray(&obvhs::ray::Ray::new_inf(o.into(), d.normalize().into()));
                    if hit.is_finite() && hit > 1e-3 {
                        assert!(found[j], "box {j} missed by ray {i}");
                    }
                }
            }
        }
    }

    #[test]
    fn corrupt_child_index_is_refused() {
        let bvh = build(&boxes(300));
        let mut nodes = bvh.nodes.clone();
        nodes[0].child_base_idx = 10_000;
        assert!(validate_nodes(&nodes, bvh.primitive_indices.len()).is_err());
        let mut nodes = bvh.nodes.clone();
        nodes[0].child_base_idx = 0;
        assert!(validate_nodes(&nodes, bvh.primitive_indices.len()).is_err());
    }
}
