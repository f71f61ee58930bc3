//! `magg-host bench rays MESH RAYS`: how fast the renderer casts rays, on rays and a mesh
//! anyone can make, so that other engines can be measured on the same data in the same run
//! (`bench/peers/embree.py` does that with Intel Embree).
//!
//! The mesh goes through the normal loader and is prepared exactly as `render --in-process`
//! prepares a scene ([`host::large_pages::prepare`]: chunks, both tree levels, their walking
//! forms built in large pages), and rays go through [`Tracer`], the interface every integrator calls. The same rays are then
//! cast through a render node's cache ([`DemandCache`]) holding every chunk, which is what a
//! cluster renders with.
//!
//! Ray file: no header, little-endian, per ray six `f32`: origin x y z, direction x y z (unit
//! length); the ray runs from t = 0 to infinity. Hit file: per ray one little-endian `f32`,
//! the distance to the closest hit or +infinity on a miss; with `--any-hit`, 1.0 where
//! anything blocks the ray and +infinity where nothing does.

use std::{
    path::{Path, PathBuf},
    time::Instant,
};

use glam::{DVec3, Vec3A};
use render_node::cache::DemandCache;
use renderer::{
    PrepareOptions, SceneData, SceneHeader,
    ray::Ray,
    sampler::Sampler,
    trace::{AlphaKey, Tracer},
};
use serde::Serialize;

#[derive(Clone, Debug)]
pub struct RaysConfig {
    pub mesh: PathBuf,
    pub rays: PathBuf,
    pub hits: Option<PathBuf>,
    pub repeat: usize,
    pub any_hit: bool,
    pub chunk_triangles: usize,
}

/// Rays per second over the repeats of one measurement.
#[derive(Clone, Debug, Serialize)]
pub struct Rate {
    pub best_mrays: f64,
    pub median_mrays: f64,
    pub repeats: usize,
}

#[derive(Clone, Debug, Serialize)]
pub struct RaysReport {
    pub triangles: u64,
    pub chunks: usize,
    /// From the loaded triangles to a scene rays can be cast into (best of the repeats).
    pub build_seconds: f64,
    pub build_seconds_median: f64,
    pub rays: usize,
    /// Rays that hit something.
    pub hits: usize,
    pub any_hit: bool,
    pub in_process: Rate,
    /// The same rays through a render node's cache with every chunk resident.
    pub cache: Rate,
}

#[derive(Debug, thiserror::Error)]
pub enum RaysError {
    #[error("loading {0}")]
    Load(#[from] scene_io::LoadError),
    #[error("reading the ray file {path}: {source}")]
    ReadRays {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(
        "the ray file {path} holds {len} bytes, not a whole number of rays (24 bytes each: \
         origin and direction as six little-endian f32)"
    )]
    RayFileLength { path: PathBuf, len: usize },
    #[error("ray {index} of {path} is not finite or has a zero direction")]
    BadRay { path: PathBuf, index: usize },
    #[error("writing the hit file: {0}")]
    WriteHits(#[from] scene_io::ImageError),
    #[error("the render node's cache refused chunk {id}: {source}")]
    Cache {
        id: u32,
        source: renderer::DataError,
    },
    #[error("tracing failed: {0}")]
    Trace(#[from] renderer::DataError),
    #[error("ray {index} found {in_process} in process but {cached} through the cache")]
    Disagree {
        index: usize,
        in_process: f32,
        cached: f32,
    },
}

/// Reads a ray file, moving the origins by the shift the loader applied to the mesh.
fn read_rays(path: &Path, shift: DVec3) -> Result<Vec<Ray>, RaysError> {
    let bytes = std::fs::read(path).map_err(|source| RaysError::ReadRays {
        path: path.into(),
        source,
    })?;
    if !bytes.len().is_multiple_of(24) {
        return Err(RaysError::RayFileLength {
            path: path.into(),
            len: bytes.len(),
        });
    }
    bytes
        .chunks_exact(24)
        .enumerate()
        .map(|(index, r)| {
            let f =
                |i: usize| f32::from_le_bytes([r[4 * i], r[4 * i + 1], r[4 * i + 2], r[4 * i + 3]]);
            // The loader centres the mesh in f64 before rounding to f32; the origins follow
            // the same arithmetic, so rays meet the same surfaces.
            let o = (DVec3::new(f(0) as f64, f(1) as f64, f(2) as f64) - shift).as_vec3();
            let d = glam::Vec3::new(f(3), f(4), f(5));
            if !o.is_finite() || !d.is_finite() || d == glam::Vec3::ZERO {
                return Err(RaysError::BadRay {
                    path: path.into(),
                    index,
                });
            }
            Ok(Ray::new(Vec3A::from(o), Vec3A::from(d), f32::INFINITY))
        })
        .collect()
}

/// Casts every ray once on this thread, writing each result into `out`; returns the
/// seconds taken.
fn cast<D: SceneData>(
    scene: &SceneHeader,
    data: &D,
    rays: &[Ray],
    any_hit: bool,
    out: &mut [f32],
) -> Result<f64, RaysError> {
    let tracer = Tracer::new(scene, data);
    let key = AlphaKey::new(&Sampler::new(0, 0, 0, 0), 0);
    let start = Instant::now();
    for (r, o) in rays.iter().zip(out.iter_mut()) {
        *o = if any_hit {
            if tracer.occluded(r, key)? {
                1.0
            } else {
                f32::INFINITY
            }
        } else {
            match tracer.closest(r, key)? {
                Some(h) => h.tri_hit.t,
                None => f32::INFINITY,
            }
        };
    }
    Ok(start.elapsed().as_secs_f64())
}

fn rate(rays: usize, mut seconds: Vec<f64>) -> Rate {
    seconds.sort_by(f64::total_cmp);
    let best = seconds.first().copied().unwrap_or(f64::NAN);
    let median = seconds.get(seconds.len() / 2).copied().unwrap_or(f64::NAN);
    Rate {
        best_mrays: rays as f64 / best / 1e6,
        median_mrays: rays as f64 / median / 1e6,
        repeats: seconds.len(),
    }
}

/// Loads, prepares (timed), casts (timed, `repeat` times each way) and writes the hits.
pub fn run(cfg: &RaysConfig, progress: &dyn Fn(&str)) -> Result<RaysReport, RaysError> {
    let repeat = cfg.repeat.max(1);
    let mut loaded = scene_io::load_gltf(&cfg.mesh)?;
    // Geometry is measured, as by other engines, without back-face culling (a property of
    // glTF's default single-sided material, not of the triangles).
    for m in &mut loaded.desc.materials {
        m.double_sided = true;
    }
    let rays = read_rays(&cfg.rays, loaded.origin_shift)?;
    let opts = PrepareOptions {
        chunk_triangles: cfg.chunk_triangles.max(1),
    };

    let mut builds = Vec::new();
    let mut prepared = None;
    for _ in 0..repeat.min(3) {
        let desc = loaded.desc.clone();
        let start = Instant::now();
        // As `render --in-process` prepares.
        let p = host::large_pages::prepare(desc, &opts);
        builds.push(start.elapsed().as_secs_f64());
        prepared = Some(p);
    }
    let (scene, data) = prepared.expect("at least one build");
    builds.sort_by(f64::total_cmp);
    progress(&format!(
        "mesh: {} triangles in {} chunks; build {:.3} s",
        scene.triangle_count(),
        scene.chunks.len(),
        builds[0]
    ));

    let mut hits = vec![f32::INFINITY; rays.len()];
    // One untimed pass brings the data into the caches, as for every peer.
    cast(&scene, &data, &rays, cfg.any_hit, &mut hits)?;
    let mut times = Vec::new();
    for _ in 0..repeat {
        times.push(cast(&scene, &data, &rays, cfg.any_hit, &mut hits)?);
    }
    let in_process = rate(rays.len(), times);

    let cache = DemandCache::new(scene.chunk_rules(), 0, u64::MAX, None);
    for (id, c) in data.chunks.iter().enumerate() {
        cache
            .preload(protocol::DataId::Chunk(id as u32), c.words().into())
            .map_err(|source| RaysError::Cache {
                id: id as u32,
                source,
            })?;
    }
    let mut reader = cache.reader();
    reader.refresh();
    let mut from_cache = vec![f32::INFINITY; rays.len()];
    cast(&scene, &reader, &rays, cfg.any_hit, &mut from_cache)?;
    let mut times = Vec::new();
    for _ in 0..repeat {
        times.push(cast(&scene, &reader, &rays, cfg.any_hit, &mut from_cache)?);
    }
    let cached = rate(rays.len(), times);
    if let Some(index) = (0..rays.len()).find(|&i| hits[i].to_bits() != from_cache[i].to_bits()) {
        return Err(RaysError::Disagree {
            index,
            in_process: hits[index],
            cached: from_cache[index],
        });
    }

    if let Some(path) = &cfg.hits {
        let bytes: Vec<u8> = hits.iter().flat_map(|h| h.to_le_bytes()).collect();
        scene_io::image_io::write_atomic(path, &bytes)?;
    }
    Ok(RaysReport {
        triangles: scene.triangle_count(),
        chunks: scene.chunks.len(),
        build_seconds: builds[0],
        build_seconds_median: builds[builds.len() / 2],
        rays: rays.len(),
        hits: hits.iter().filter(|h| h.is_finite()).count(),
        any_hit: cfg.any_hit,
        in_process,
        cache: cached,
    })
}
