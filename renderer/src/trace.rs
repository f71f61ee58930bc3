//! Tracing rays through the two-level BVH: the top-level tree over chunk bounds, then the
//! tree inside each chunk the ray reaches, fetching chunks through [`SceneData`]. Data that
//! holds every chunk and made the two levels one tree ([`SceneData::flat`]) is walked as
//! that one tree: no walk of its own, no lookup of the chunk and its material, for every
//! chunk a ray enters.

use std::cell::Cell;

use glam::Vec3;

use crate::{
    accel::{self, Closest, Node8},
    bvh::Visit,
    chunk::Chunk,
    material::{self, AlphaMode},
    ray::{Ray, RayQuery},
    sampler::{SampleKey, Sampler},
    scene::SceneHeader,
    simd::AlignedFrame,
    source::{DataError, FlatTree, Item, SceneData},
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
pub(crate) enum SurfaceKind {
    /// Every hit counts.
    Solid,
    /// Hits on back faces do not count.
    Culled,
    /// Hits are alpha-tested (and back faces culled when `cull`).
    Alpha { cull: bool },
}

/// How the surfaces of a chunk take rays (from the header, which is at hand, and whose
/// material indices were checked; a chunk must agree with it, see `ChunkRules`).
#[inline(always)]
pub(crate) fn surface_kind(scene: &SceneHeader, chunk_id: u32) -> SurfaceKind {
    let Some(m) = scene
        .chunks
        .get(chunk_id as usize)
        .and_then(|c| scene.materials.get(c.material as usize))
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

/// What a path's ray queries found before they stopped for missing data, each with the ray
/// it is of.
#[derive(Debug, Default)]
pub struct QueryMemo {
    closest: Option<(RayBits, ClosestFound)>,
    occluded: Option<(RayBits, Searched)>,
}

/// A ray as bits, to know a memo is of this very ray.
type RayBits = [u32; 7];

fn ray_bits(r: &Ray) -> RayBits {
    let (o, d) = (r.origin, r.dir);
    [o.x, o.y, o.z, d.x, d.y, d.z, r.tmax].map(f32::to_bits)
}

/// How far a closest-hit query got.
#[derive(Clone, Copy, Debug)]
struct ClosestFound {
    best: Closest,
    searched: Searched,
    /// Every chunk was searched: only the best hit's chunk is still to be had.
    complete: bool,
}

/// Chunks a query has searched, the first few of them: searching one again is only work
/// done twice, so those past the end are simply not noted. Sixteen of them, two 32-byte
/// words: fifteen (60 bytes) were zeroed by two overlapping 32-byte stores and copied by a
/// load spanning both, which the processor cannot forward from its store buffer, and the
/// query waited for both to reach the cache (12% of a render node's closest-hit query by
/// `perf`, on primary rays).
#[derive(Clone, Copy, Debug, Default)]
struct Searched {
    ids: [u32; 16],
    len: u32,
}

impl Searched {
    #[inline(always)]
    fn add(&mut self, id: u32) {
        if let Some(slot) = self.ids.get_mut(self.len as usize) {
            *slot = id;
            self.len += 1;
        }
    }

    /// Whether `id` is among the first `noted` chunks noted (those a walk found noted when
    /// it began: a walk meets each chunk once, so what it notes itself it never meets again,
    /// and a query that never waited looks at none).
    #[inline(always)]
    fn holds(&self, id: u32, noted: u32) -> bool {
        noted > 0 && self.ids[..(noted.min(self.len) as usize)].contains(&id)
    }

    /// How many chunks are noted.
    fn noted(&self) -> u32 {
        self.len
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
        let s = chunk.surface_reading(tri, hit, || m.reads());
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
    /// walk goes on through the others, and the answer is the nearest missing chunk that
    /// could still hold a nearer hit (the top-level walk, run again within the best distance
    /// found, says which); what was searched is kept in [`Tracer::memo`], so that asking
    /// again for the same ray, once the chunk is here, searches only what is left. Searching
    /// a chunk again would give the same answer (ties are broken by index), so the memo only
    /// saves work and the need to have every chunk here at once.
    pub fn closest(
        &self,
        ray: &Ray,
        key: AlphaKey,
    ) -> Result<Option<Hit<D::ChunkRef<'a>>>, DataError> {
        if let Some(flat) = self.data.flat() {
            return self.closest_in_flat(flat, ray, key);
        }
        // The query's 8-lane constants live on this frame (see `AlignedFrame`).
        let _frame = AlignedFrame::new();
        let q = RayQuery::new(ray);
        let found = self.memo_of(ray, |m| &mut m.closest);
        let ClosestFound {
            mut best,
            mut searched,
            complete,
        } = found.unwrap_or(ClosestFound {
            best: Closest::new(ray.tmax),
            searched: Searched::default(),
            complete: false,
        });
        let mut tmax = best.t;
        let mut best_chunk: Option<D::ChunkRef<'a>> = None;
        let missing = Cell::new(None);
        let mut search = || {
            self.search_closest(
                &q,
                key,
                &mut tmax,
                &mut best,
                &mut searched,
                &mut best_chunk,
                &missing,
            )
        };
        let mut failure = None;
        if !complete {
            failure = search();
            // A chunk met missing matters only if it may hold a hit nearer than the best
            // found since: walked again within that distance, the first missing is the one.
            if D::MAY_DEFER && failure.is_none() && missing.take().is_some() {
                failure = search();
            }
        }
        let found = |complete| ClosestFound {
            best,
            searched,
            complete,
        };
        if let Some(e) = failure {
            return Err(self.waits(ray, e, |m| &mut m.closest, found(false)));
        }
        if D::MAY_DEFER
            && let Some(c) = missing.take()
        {
            let e = DataError::Missing(Item::Chunk(c));
            return Err(self.waits(ray, e, |m| &mut m.closest, found(false)));
        }
        let Some(tri_hit) = best.hit else {
            return Ok(None);
        };
        let chunk = match best_chunk {
            Some(c) => c,
            // Found before the path waited: the chunk is asked for again.
            None => self
                .data
                .chunk(best.chunk)
                .map_err(|e| self.waits(ray, e, |m| &mut m.closest, found(true)))?,
        };
        Ok(Some(Hit {
            chunk,
            tri: best.tri,
            tri_hit,
        }))
    }

    /// [`Tracer::closest`] through the whole scene's trees as one (data that holds every
    /// chunk, and so never defers).
    fn closest_in_flat(
        &self,
        flat: &FlatTree,
        ray: &Ray,
        key: AlphaKey,
    ) -> Result<Option<Hit<D::ChunkRef<'a>>>, DataError> {
        let _frame = AlignedFrame::new();
        let q = RayQuery::new(ray);
        let mut best = Closest::new(ray.tmax);
        let mut error = None;
        let chunk_of = |block| self.chunk_of(flat, block);
        let node_seen = |node: &Node8| self.node_seen(node);
        if flat.all_solid {
            flat.form
                .closest_in(&q, chunk_of, node_seen, &mut best, |_, _, _| true);
        } else {
            flat.form
                .closest_in(&q, chunk_of, node_seen, &mut best, |c, tri, hit| {
                    self.takes(flat, c, &q, tri, hit, key).unwrap_or_else(|e| {
                        error = Some(e);
                        false
                    })
                });
        }
        if let Some(e) = error {
            return Err(e);
        }
        let Some(tri_hit) = best.hit else {
            return Ok(None);
        };
        Ok(Some(Hit {
            chunk: self.data.chunk(best.chunk)?,
            tri: best.tri,
            tri_hit,
        }))
    }

    /// The chunk of block `block` of the flat tree, noted as entered where the data notes
    /// entries (the two-level walk asks the data for every chunk it enters; the flat walk
    /// asks only for the chunk of its hit).
    #[inline(always)]
    fn chunk_of(&self, flat: &FlatTree, block: usize) -> u32 {
        let c = flat.chunk_of(block);
        if D::NOTES_ENTRIES {
            self.data.entered(c);
        }
        c
    }

    /// Notes the chunk whose root `node` of the flat tree is, where the data notes entries.
    #[inline(always)]
    fn node_seen(&self, node: &Node8) {
        if D::NOTES_ENTRIES && node.root_of != 0 {
            self.data.entered(node.root_of - 1);
        }
    }

    /// Whether triangle `tri` of chunk `c` takes the ray at `hit` (see
    /// [`Tracer::passes_through`]).
    fn takes(
        &self,
        flat: &FlatTree,
        c: u32,
        q: &RayQuery,
        tri: u32,
        hit: &TriHit,
        key: AlphaKey,
    ) -> Result<bool, DataError> {
        let kind = flat.kind(c);
        if kind == SurfaceKind::Solid {
            return Ok(true);
        }
        let chunk = self.data.chunk(c)?;
        Ok(!self.passes_through(&chunk, kind, q, tri, hit, key)?)
    }

    /// One walk of the top-level tree for [`Tracer::closest`], within `tmax`: updates
    /// `best` and the chunk it lies in, skips chunks `searched` before, notes them as it
    /// searches and notes the first chunk that is missing; the error that stopped it.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn search_closest(
        &self,
        q: &RayQuery,
        key: AlphaKey,
        tmax: &mut f32,
        best: &mut Closest,
        searched: &mut Searched,
        best_chunk: &mut Option<D::ChunkRef<'a>>,
        missing: &Cell<Option<u32>>,
    ) -> Option<DataError> {
        let mut error = None;
        let noted = searched.noted();
        accel::walk::<true>(
            &self.scene.tlas.accel().nodes,
            q,
            tmax,
            |_| {},
            |_| {},
            // Inlined into the top-level walk: out of line (the compiler's choice), every
            // chunk a ray enters paid a call with six saved registers and a fresh frame; in
            // the Cornell box, where a query enters 1.35 chunks, that was 8% of a query.
            #[inline(always)]
            |chunk_id, tmax| {
                let chunk = match self.reach(chunk_id, searched, noted, missing, &mut error) {
                    Ok(c) => c,
                    Err(visit) => return visit,
                };
                let kind = surface_kind(self.scene, chunk_id);
                let improved = if kind == SurfaceKind::Solid {
                    chunk.accel().closest(q, chunk_id, best, |_, _| true)
                } else {
                    chunk.accel().closest(q, chunk_id, best, |tri, hit| {
                        match self.passes_through(&chunk, kind, q, tri, hit, key) {
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
                    *best_chunk = Some(chunk);
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
        error
    }

    /// The chunk a top-level walk reaches, or how the walk goes on without it: past it
    /// ([`Visit::Continue`]) when the query searched it before it waited (among the first
    /// `noted` of `searched`, see [`Searched::holds`]) or when it is
    /// missing (the first such is noted in `missing`, while deferring); stopped
    /// ([`Visit::Stop`]) by an error, put in `error`, that ends the query.
    #[inline(always)]
    fn reach(
        &self,
        chunk_id: u32,
        searched: &Searched,
        noted: u32,
        missing: &Cell<Option<u32>>,
        error: &mut Option<DataError>,
    ) -> Result<D::ChunkRef<'a>, Visit> {
        if D::MAY_DEFER && searched.holds(chunk_id, noted) {
            return Err(Visit::Continue);
        }
        match self.data.chunk(chunk_id) {
            Ok(c) => Ok(c),
            Err(DataError::Missing(_)) => {
                missing.set(missing.get().or(Some(chunk_id)));
                Err(Visit::Continue)
            }
            Err(e) => {
                *error = Some(e);
                Err(Visit::Stop)
            }
        }
    }

    /// The memo of `ray`'s query of one kind, taken out, if one was kept for this very ray
    /// (never, for data that cannot defer).
    fn memo_of<M>(
        &self,
        ray: &Ray,
        part: impl FnOnce(&mut QueryMemo) -> &mut Option<(RayBits, M)>,
    ) -> Option<M> {
        if !D::MAY_DEFER {
            return None;
        }
        let mut memo = self.memo.take()?;
        let kept = part(&mut memo).take();
        self.memo.set(Some(memo));
        kept.filter(|(bits, _)| *bits == ray_bits(ray))
            .map(|(_, m)| m)
    }

    /// `error`, which ends a query of one kind; if it is a wait for data, what the query
    /// `found` is kept for when it is asked again for `ray`.
    #[cold]
    fn waits<M>(
        &self,
        ray: &Ray,
        error: DataError,
        part: impl FnOnce(&mut QueryMemo) -> &mut Option<(RayBits, M)>,
        found: M,
    ) -> DataError {
        if matches!(error, DataError::Missing(_)) {
            let mut memo = self.memo.take().unwrap_or_default();
            *part(&mut memo) = Some((ray_bits(ray), found));
            self.memo.set(Some(memo));
        }
        error
    }

    /// Whether anything blocks the ray within (0, tmax). Missing chunks are handled as in
    /// [`Tracer::closest`]: the others are searched first, and a blocker found in any of
    /// them answers without the missing ones.
    pub fn occluded(&self, ray: &Ray, key: AlphaKey) -> Result<bool, DataError> {
        self.shadow_rays.set(self.shadow_rays.get() + 1);
        let _frame = AlignedFrame::new();
        let q = RayQuery::new(ray);
        if let Some(flat) = self.data.flat() {
            let node_seen = |node: &Node8| self.node_seen(node);
            if flat.all_solid && !D::NOTES_ENTRIES {
                // Any hit blocks, whatever its chunk: no chunk to look up at each leaf.
                let mut blocked = false;
                flat.form.each_hit_in(
                    &q,
                    ray.tmax,
                    |_| 0,
                    node_seen,
                    |_, _, _| {
                        blocked = true;
                        Visit::Stop
                    },
                );
                return Ok(blocked);
            }
            let mut blocked = Ok(false);
            let chunk_of = |block| self.chunk_of(flat, block);
            flat.form
                .each_hit_in(&q, ray.tmax, chunk_of, node_seen, |c, tri, hit| {
                    // A solid chunk's hit is taken at once (`takes`).
                    match self.takes(flat, c, &q, tri, &hit, key) {
                        Ok(false) => Visit::Continue,
                        taken => {
                            blocked = taken;
                            Visit::Stop
                        }
                    }
                });
            return blocked;
        }
        let mut searched = self.memo_of(ray, |m| &mut m.occluded).unwrap_or_default();
        let mut tmax = ray.tmax;
        let mut blocked = false;
        let mut error = None;
        let missing = Cell::new(None);
        let noted = searched.noted();
        accel::walk::<false>(
            &self.scene.tlas.accel().nodes,
            &q,
            &mut tmax,
            |_| {},
            |_| {},
            |chunk_id, tmax| {
                let chunk = match self.reach(chunk_id, &searched, noted, &missing, &mut error) {
                    Ok(c) => c,
                    Err(visit) => return visit,
                };
                let kind = surface_kind(self.scene, chunk_id);
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
        if let Some(e) = error {
            return Err(self.waits(ray, e, |m| &mut m.occluded, searched));
        }
        if D::MAY_DEFER
            && let Some(c) = missing.get()
        {
            let e = DataError::Missing(Item::Chunk(c));
            return Err(self.waits(ray, e, |m| &mut m.occluded, searched));
        }
        Ok(false)
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

#[cfg(test)]
mod tests {
    use std::cell::RefCell;

    use super::*;
    use crate::{
        demo::demo_scene,
        scene::{PrepareOptions, prepare},
        source::MemoryData,
        texture::Tile,
    };

    /// Every chunk of `data` but `absent`, which is missing while deferring; notes every
    /// chunk asked for, in order.
    struct Asked {
        data: MemoryData,
        absent: Cell<Option<u32>>,
        asked: RefCell<Vec<u32>>,
    }

    impl SceneData for Asked {
        type ChunkRef<'a> = &'a Chunk;
        type TileRef<'a> = &'a Tile;

        const MAY_DEFER: bool = true;

        fn chunk(&self, id: u32) -> Result<&Chunk, DataError> {
            self.asked.borrow_mut().push(id);
            if self.absent.get() == Some(id) {
                return Err(DataError::Missing(Item::Chunk(id)));
            }
            self.data.chunk(id)
        }

        fn tile(&self, id: u32) -> Result<&Tile, DataError> {
            self.data.tile(id)
        }
    }

    /// A closest-hit query that waited for a chunk, asked again once it is here, searches
    /// only what it had not: of the chunks searched before the wait, at most the best hit's
    /// is asked for again (to be handed out with the hit), and the answer is the one found
    /// with every chunk here.
    #[test]
    fn a_query_asked_again_after_a_wait_searches_only_what_is_left() {
        let (header, data) = prepare(
            demo_scene(),
            &PrepareOptions {
                chunk_triangles: 16,
            },
        );
        let key = AlphaKey::new(&Sampler::new(0, 0, 0, 0), 0);
        let centre = (header.bounds_min + header.bounds_max) * 0.5;
        let all = Asked {
            data,
            absent: Cell::new(None),
            asked: RefCell::new(Vec::new()),
        };
        let found = |h: Hit<&Chunk>| (h.tri_hit.t.to_bits(), h.chunk.header().chunk_id, h.tri);
        let mut checked = 0;
        for i in 0..200 {
            // Directions spread over the sphere (a Fibonacci lattice).
            let u = ((i as f32 + 0.5) / 200.0, (i as f32 * 0.618_034).fract());
            let ray = Ray::infinite(centre, crate::light::uniform_sphere(u));
            all.absent.set(None);
            all.asked.borrow_mut().clear();
            let Ok(Some(want)) = Tracer::new(&header, &all).closest(&ray, key) else {
                continue;
            };
            let want = found(want);
            let entered = all.asked.borrow().clone();
            if entered.len() < 3 {
                continue;
            }
            for &x in &entered {
                let tracer = Tracer::new(&header, &all);
                all.absent.set(Some(x));
                all.asked.borrow_mut().clear();
                let Err(DataError::Missing(Item::Chunk(waited))) = tracer.closest(&ray, key) else {
                    continue;
                };
                assert_eq!(waited, x);
                let before: Vec<u32> = all
                    .asked
                    .borrow()
                    .iter()
                    .copied()
                    .filter(|&c| c != x)
                    .collect();
                all.absent.set(None);
                all.asked.borrow_mut().clear();
                let got = tracer
                    .closest(&ray, key)
                    .expect("every chunk here")
                    .expect("a hit");
                assert_eq!(found(got), want);
                let again: Vec<u32> = all
                    .asked
                    .borrow()
                    .iter()
                    .copied()
                    .filter(|c| before.contains(c))
                    .collect();
                assert!(
                    again.len() <= 1,
                    "ray {i}, waited for chunk {x}: searched {before:?} before, asked again for {again:?}"
                );
                checked += usize::from(before.len() >= 2);
            }
        }
        assert!(
            checked >= 10,
            "only {checked} waits with two chunks searched before them"
        );
    }
}
