//! Tracing rays through the two-level BVH: the top-level tree over chunk bounds, then the
//! tree inside each chunk the ray reaches, fetching chunks through [`SceneData`].

use std::cell::Cell;

use glam::Vec3;

use crate::{
    accel::{self, Closest},
    bvh::Visit,
    chunk::Chunk,
    material::{self, AlphaMode},
    ray::{Ray, RayQuery},
    sampler::{SampleKey, Sampler},
    scene::SceneHeader,
    source::{DataError, Item, SceneData},
    triangle::TriHit,
};

/// Counts of the work done, kept per thread.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct TraceStats {
    pub camera_rays: u64,
    pub secondary_rays: u64,
    pub shadow_rays: u64,
    pub samples: u64,
    pub pixels: u64,
    /// Samples whose radiance came out NaN or infinite and were counted as black.
    pub bad_samples: u64,
}

impl TraceStats {
    pub fn rays(&self) -> u64 {
        self.camera_rays + self.secondary_rays + self.shadow_rays
    }

    pub fn add(&mut self, o: &TraceStats) {
        self.camera_rays += o.camera_rays;
        self.secondary_rays += o.secondary_rays;
        self.shadow_rays += o.shadow_rays;
        self.samples += o.samples;
        self.pixels += o.pixels;
        self.bad_samples += o.bad_samples;
    }
}

/// A hit: which chunk and triangle, where along the ray, and the chunk itself.
pub struct Hit<C> {
    pub chunk: C,
    pub tri: u32,
    pub tri_hit: TriHit,
}

/// What an alpha-tested surface needs to decide, deterministically, whether a ray passes.
#[derive(Clone, Copy)]
pub struct AlphaKey {
    pub sample: SampleKey,
    pub bounce: u32,
}

impl AlphaKey {
    pub fn new(sampler: &Sampler<'_>, bounce: u32) -> AlphaKey {
        AlphaKey {
            sample: sampler.key(),
            bounce,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum SurfaceKind {
    /// Every hit counts.
    Solid,
    /// Hits on back faces do not count.
    Culled,
    /// Hits are alpha-tested (and back faces culled when `cull`).
    Alpha { cull: bool },
}

pub struct Tracer<'a, D: SceneData> {
    pub scene: &'a SceneHeader,
    pub data: &'a D,
    pub camera_rays: Cell<u64>,
    pub secondary_rays: Cell<u64>,
    pub shadow_rays: Cell<u64>,
    /// What the queries of the path being traced found before they stopped for a missing
    /// item (memory-coherent rays swap each path's in and out; empty otherwise).
    pub memo: Cell<Option<Box<QueryMemo>>>,
}

/// What a path's ray queries found before they stopped for missing data.
#[derive(Debug, Default)]
pub struct QueryMemo {
    closest: Option<ClosestMemo>,
    occluded: Option<OccludedMemo>,
}

/// A ray as bits, to know a memo is of this very ray.
type RayBits = [u32; 7];

fn ray_bits(r: &Ray) -> RayBits {
    let (o, d) = (r.origin, r.dir);
    [o.x, o.y, o.z, d.x, d.y, d.z, r.tmax].map(f32::to_bits)
}

trait RayMemo {
    fn ray(&self) -> RayBits;
}

#[derive(Debug)]
struct ClosestMemo {
    ray: RayBits,
    best: Closest,
    searched: Searched,
    /// Every chunk was searched: only the best hit's chunk is still to be had.
    complete: bool,
}

impl RayMemo for ClosestMemo {
    fn ray(&self) -> RayBits {
        self.ray
    }
}

#[derive(Debug)]
struct OccludedMemo {
    ray: RayBits,
    searched: Searched,
}

impl RayMemo for OccludedMemo {
    fn ray(&self) -> RayBits {
        self.ray
    }
}

/// Chunks a query has searched, the first few of them: searching one again is only work
/// done twice, so those past the end are simply not noted.
#[derive(Clone, Copy, Debug, Default)]
struct Searched {
    ids: [u32; 15],
    len: u8,
}

impl Searched {
    #[inline(always)]
    fn add(&mut self, id: u32) {
        if let Some(slot) = self.ids.get_mut(self.len as usize) {
            *slot = id;
            self.len += 1;
        }
    }

    #[inline(always)]
    fn holds(&self, id: u32) -> bool {
        self.len > 0 && self.ids[..self.len as usize].contains(&id)
    }
}

impl<'a, D: SceneData> Tracer<'a, D> {
    pub fn new(scene: &'a SceneHeader, data: &'a D) -> Tracer<'a, D> {
        Tracer {
            scene,
            data,
            camera_rays: Cell::new(0),
            secondary_rays: Cell::new(0),
            shadow_rays: Cell::new(0),
            memo: Cell::new(None),
        }
    }

    /// How the surfaces of a chunk take rays (from the header, which is at hand, and whose
    /// material indices were checked; a chunk must agree with it, see `ChunkRules`).
    fn surface_kind(&self, chunk_id: u32) -> SurfaceKind {
        let Some(m) = self
            .scene
            .chunks
            .get(chunk_id as usize)
            .and_then(|c| self.scene.materials.get(c.material as usize))
        else {
            return SurfaceKind::Solid;
        };
        // glTF: a single-sided material is invisible from behind (back faces are culled),
        // except where light must cross it, as into and out of a transmissive volume.
        let cull = !m.double_sided && m.transmission <= 0.0;
        match (m.alpha_mode, cull) {
            (AlphaMode::Opaque, false) => SurfaceKind::Solid,
            (AlphaMode::Opaque, true) => SurfaceKind::Culled,
            (_, cull) => SurfaceKind::Alpha { cull },
        }
    }

    /// Whether the ray passes through triangle `tri` of `chunk` at `hit`: a culled back face,
    /// alpha MASK below the cutoff, or BLEND chosen transparent with probability 1 - alpha.
    fn passes_through(
        &self,
        chunk: &Chunk,
        kind: SurfaceKind,
        q: &RayQuery,
        tri: u32,
        hit: &TriHit,
        key: AlphaKey,
    ) -> Result<bool, DataError> {
        let cull = match kind {
            SurfaceKind::Solid => return Ok(false),
            SurfaceKind::Culled => true,
            SurfaceKind::Alpha { cull } => cull,
        };
        if cull {
            let (v0, v1, v2) = crate::chunk::tri_points(&chunk.tri_positions()[tri as usize]);
            if (v1 - v0).cross(v2 - v0).dot(q.dir) >= 0.0 {
                return Ok(true);
            }
        }
        let SurfaceKind::Alpha { .. } = kind else {
            return Ok(false);
        };
        let m = &self.scene.materials[chunk.header().material as usize];
        let s = chunk.surface(tri, hit);
        let alpha = material::alpha_at(self.scene, self.data, m, &s)?;
        Ok(match m.alpha_mode {
            AlphaMode::Opaque => false,
            AlphaMode::Mask => alpha < m.alpha_cutoff,
            AlphaMode::Blend => key.sample.keyed(key.bounce, chunk.header().chunk_id, tri) >= alpha,
        })
    }

    /// The nearest surface the ray meets in (0, tmax). Of surfaces at exactly the same
    /// distance, the one of the lowest (chunk, triangle) index, whatever order the walk met
    /// them in.
    ///
    /// Where the data says a chunk is missing ([`DataError::Missing`], while deferring), the
    /// walk goes on through the others, and the answer is that missing chunk (the nearest
    /// that could still hold a nearer hit); what was searched is kept in [`Tracer::memo`],
    /// so that asking again for the same ray, once the chunk is here, searches only what is
    /// left. Searching a chunk again would give the same answer (ties are broken by index),
    /// so the memo only saves work and the need to have every chunk here at once.
    pub fn closest(
        &self,
        ray: &Ray,
        key: AlphaKey,
    ) -> Result<Option<Hit<D::ChunkRef<'a>>>, DataError> {
        let q = RayQuery::new(ray);
        let memo = if D::MAY_DEFER {
            self.memo_of(ray, |m| &mut m.closest)
        } else {
            None
        };
        let (mut best, mut searched, complete) = match memo {
            Some(m) => (m.best, m.searched, m.complete),
            None => (Closest::new(ray.tmax), Searched::default(), false),
        };
        let mut tmax = best.t;
        let mut best_chunk: Option<D::ChunkRef<'a>> = None;
        let mut error = None;
        let mut missing: Vec<u32> = Vec::new();
        if !complete {
            accel::walk::<true>(
                &self.scene.tlas.accel().nodes,
                &q,
                &mut tmax,
                |_| {},
                |chunk_id, tmax| {
                    if D::MAY_DEFER && searched.holds(chunk_id) {
                        return Visit::Continue;
                    }
                    let chunk = match self.data.chunk(chunk_id) {
                        Ok(c) => c,
                        Err(DataError::Missing(_)) => {
                            missing.push(chunk_id);
                            return Visit::Continue;
                        }
                        Err(e) => {
                            error = Some(e);
                            return Visit::Stop;
                        }
                    };
                    let kind = self.surface_kind(chunk_id);
                    let improved = if kind == SurfaceKind::Solid {
                        chunk.accel().closest(&q, chunk_id, &mut best, |_, _| true)
                    } else {
                        chunk.accel().closest(&q, chunk_id, &mut best, |tri, hit| {
                            match self.passes_through(&chunk, kind, &q, tri, hit, key) {
                                Ok(pass) => !pass,
                                Err(e) => {
                                    error = Some(e);
                                    false
                                }
                            }
                        })
                    };
                    if improved {
                        *tmax = best.t;
                        best_chunk = Some(chunk);
                    }
                    if error.is_some() {
                        Visit::Stop
                    } else {
                        if D::MAY_DEFER {
                            searched.add(chunk_id);
                        }
                        Visit::Continue
                    }
                },
            );
        }
        if let Some(e) = error {
            if matches!(e, DataError::Missing(_)) {
                self.keep_closest(ray, best, searched, false);
            }
            return Err(e);
        }
        // A missing chunk matters if a hit in it could still be nearer than the best.
        if !missing.is_empty()
            && let Some(&wanted) = missing
                .iter()
                .filter_map(|&c| self.chunk_entry(ray, c).map(|t| (t, c)))
                .filter(|&(t, _)| t <= best.t)
                .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)))
                .map(|(_, c)| c)
                .as_ref()
        {
            self.keep_closest(ray, best, searched, false);
            return Err(DataError::Missing(Item::Chunk(wanted)));
        }
        let Some(tri_hit) = best.hit else {
            return Ok(None);
        };
        let chunk = match best_chunk {
            Some(c) => c,
            // Found before the path waited: the chunk is asked for again.
            None => match self.data.chunk(best.chunk) {
                Ok(c) => c,
                Err(e) => {
                    if matches!(e, DataError::Missing(_)) {
                        self.keep_closest(ray, best, searched, true);
                    }
                    return Err(e);
                }
            },
        };
        Ok(Some(Hit {
            chunk,
            tri: best.tri,
            tri_hit,
        }))
    }

    /// Where the ray may enter chunk `id`'s box, a little early (None if it misses it by
    /// a clear margin): whether a missing chunk can matter. Erring early only makes a path
    /// wait for a chunk it turns out not to need.
    fn chunk_entry(&self, ray: &Ray, id: u32) -> Option<f32> {
        let Some(info) = self.scene.chunks.get(id as usize) else {
            return Some(0.0);
        };
        let (lo, hi) = (info.bounds_min.to_array(), info.bounds_max.to_array());
        let (o, d) = (ray.origin.to_array(), ray.dir.to_array());
        let (mut near, mut far) = (0.0f32, f32::INFINITY);
        for k in 0..3 {
            let pad = 1e-4 * (hi[k] - lo[k]).abs().max(lo[k].abs().max(hi[k].abs()));
            let (a, b) = (lo[k] - pad, hi[k] + pad);
            if d[k] == 0.0 {
                if o[k] < a || o[k] > b {
                    return None;
                }
                continue;
            }
            let (t0, t1) = ((a - o[k]) / d[k], (b - o[k]) / d[k]);
            near = near.max(t0.min(t1));
            far = far.min(t0.max(t1));
        }
        if !(near.is_finite() || near == f32::INFINITY) {
            return Some(0.0);
        }
        (near <= far * (1.0 + 1e-4)).then_some(near * (1.0 - 1e-4))
    }

    /// The memo of `ray`'s query of one kind, taken out, if one was kept for this very ray.
    fn memo_of<M: RayMemo>(
        &self,
        ray: &Ray,
        part: impl FnOnce(&mut QueryMemo) -> &mut Option<M>,
    ) -> Option<M> {
        let mut memo = self.memo.take()?;
        let m = part(&mut memo).take();
        self.memo.set(Some(memo));
        m.filter(|m| m.ray() == ray_bits(ray))
    }

    fn keep_closest(&self, ray: &Ray, best: Closest, searched: Searched, complete: bool) {
        let mut memo = self.memo.take().unwrap_or_default();
        memo.closest = Some(ClosestMemo {
            ray: ray_bits(ray),
            best,
            searched,
            complete,
        });
        self.memo.set(Some(memo));
    }

    /// Whether anything blocks the ray within (0, tmax). Missing chunks are handled as in
    /// [`Tracer::closest`]: the others are searched first, and a blocker found in any of
    /// them answers without the missing ones.
    pub fn occluded(&self, ray: &Ray, key: AlphaKey) -> Result<bool, DataError> {
        self.shadow_rays.set(self.shadow_rays.get() + 1);
        let q = RayQuery::new(ray);
        let mut searched = if D::MAY_DEFER {
            self.memo_of(ray, |m| &mut m.occluded)
                .map_or_else(Searched::default, |m| m.searched)
        } else {
            Searched::default()
        };
        let mut tmax = ray.tmax;
        let mut blocked = false;
        let mut error = None;
        let mut missing = None;
        accel::walk::<false>(
            &self.scene.tlas.accel().nodes,
            &q,
            &mut tmax,
            |_| {},
            |chunk_id, tmax| {
                if D::MAY_DEFER && searched.holds(chunk_id) {
                    return Visit::Continue;
                }
                let chunk = match self.data.chunk(chunk_id) {
                    Ok(c) => c,
                    Err(DataError::Missing(_)) => {
                        missing = missing.or(Some(chunk_id));
                        return Visit::Continue;
                    }
                    Err(e) => {
                        error = Some(e);
                        return Visit::Stop;
                    }
                };
                let kind = self.surface_kind(chunk_id);
                chunk.accel().each_hit(&q, *tmax, |tri, hit| {
                    if kind == SurfaceKind::Solid {
                        blocked = true;
                        return Visit::Stop;
                    }
                    match self.passes_through(&chunk, kind, &q, tri, &hit, key) {
                        Ok(true) => Visit::Continue,
                        Ok(false) => {
                            blocked = true;
                            Visit::Stop
                        }
                        Err(e) => {
                            error = Some(e);
                            Visit::Stop
                        }
                    }
                });
                if blocked || error.is_some() {
                    Visit::Stop
                } else {
                    if D::MAY_DEFER {
                        searched.add(chunk_id);
                    }
                    Visit::Continue
                }
            },
        );
        if blocked {
            return Ok(true);
        }
        let error = error.or(missing.map(|c| DataError::Missing(Item::Chunk(c))));
        match error {
            Some(e) => {
                if matches!(e, DataError::Missing(_)) {
                    let mut memo = self.memo.take().unwrap_or_default();
                    memo.occluded = Some(OccludedMemo {
                        ray: ray_bits(ray),
                        searched,
                    });
                    self.memo.set(Some(memo));
                }
                Err(e)
            }
            None => Ok(false),
        }
    }

    pub fn count_camera_ray(&self) {
        self.camera_rays.set(self.camera_rays.get() + 1);
    }

    pub fn count_secondary_ray(&self) {
        self.secondary_rays.set(self.secondary_rays.get() + 1);
    }

    pub fn stats(&self) -> TraceStats {
        TraceStats {
            camera_rays: self.camera_rays.get(),
            secondary_rays: self.secondary_rays.get(),
            shadow_rays: self.shadow_rays.get(),
            ..Default::default()
        }
    }
}

/// A shadow ray from a surface point towards a target (or to infinity along `dir`).
pub fn shadow_ray(origin: glam::Vec3A, target: Option<glam::Vec3A>, dir: Vec3) -> Ray {
    match target {
        // A hair short of the target, so the light's own surface does not block it.
        Some(t) => Ray::new(origin, t - origin, 1.0 - 1e-4),
        None => Ray::new(origin, dir.into(), f32::INFINITY),
    }
}
