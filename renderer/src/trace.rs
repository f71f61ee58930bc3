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
    source::{DataError, SceneData},
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
}

impl<'a, D: SceneData> Tracer<'a, D> {
    pub fn new(scene: &'a SceneHeader, data: &'a D) -> Tracer<'a, D> {
        Tracer {
            scene,
            data,
            camera_rays: Cell::new(0),
            secondary_rays: Cell::new(0),
            shadow_rays: Cell::new(0),
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
    pub fn closest(
        &self,
        ray: &Ray,
        key: AlphaKey,
    ) -> Result<Option<Hit<D::ChunkRef<'a>>>, DataError> {
        let q = RayQuery::new(ray);
        let mut tmax = ray.tmax;
        let mut best = Closest::new(ray.tmax);
        let mut best_chunk: Option<D::ChunkRef<'a>> = None;
        let mut error = None;
        accel::walk::<true>(
            &self.scene.tlas.accel().nodes,
            &q,
            &mut tmax,
            |_| {},
            |chunk_id, tmax| {
                let chunk = match self.data.chunk(chunk_id) {
                    Ok(c) => c,
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
                    Visit::Continue
                }
            },
        );
        if let Some(e) = error {
            return Err(e);
        }
        Ok(match (best_chunk, best.hit) {
            (Some(chunk), Some(tri_hit)) => Some(Hit {
                chunk,
                tri: best.tri,
                tri_hit,
            }),
            _ => None,
        })
    }

    /// Whether anything blocks the ray within (0, tmax).
    pub fn occluded(&self, ray: &Ray, key: AlphaKey) -> Result<bool, DataError> {
        self.shadow_rays.set(self.shadow_rays.get() + 1);
        let q = RayQuery::new(ray);
        let mut tmax = ray.tmax;
        let mut blocked = false;
        let mut error = None;
        accel::walk::<false>(
            &self.scene.tlas.accel().nodes,
            &q,
            &mut tmax,
            |_| {},
            |chunk_id, tmax| {
                let chunk = match self.data.chunk(chunk_id) {
                    Ok(c) => c,
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
                    Visit::Continue
                }
            },
        );
        match error {
            Some(e) => Err(e),
            None => Ok(blocked),
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
