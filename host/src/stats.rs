//! The `--stats FILE.json` report: what was rendered, how long it took, how much work it was.

use std::path::Path;

use renderer::trace::TraceStats;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Default)]
pub struct Seconds {
    pub load: f64,
    pub render: f64,
    /// Tracing the denoiser's guides and filtering (0 when the image is not denoised).
    pub denoise: f64,
    pub write: f64,
    pub total: f64,
}

#[derive(Clone, Debug, Serialize, Default)]
pub struct Rays {
    pub camera: u64,
    pub secondary: u64,
    pub shadow: u64,
    pub total: u64,
}

#[derive(Clone, Debug, Serialize, Default)]
pub struct RenderStats {
    pub scene: String,
    pub output: String,
    pub mode: String,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub seed: u64,
    pub integrator: String,
    pub threads: usize,
    pub triangles: u64,
    pub chunks: usize,
    pub shape_bytes: u64,
    pub texture_tiles: u32,
    pub seconds: Seconds,
    pub rays: Rays,
    pub samples: u64,
    pub samples_per_second: f64,
    pub rays_per_second: f64,
    /// Samples that came out NaN or infinite and were counted as black (should be 0).
    pub bad_samples: u64,
    /// Peak resident memory of this process, in bytes.
    pub peak_rss_bytes: u64,
    /// What each subscreen cost (in one process: each tile), in the order they finished:
    /// what a simulator replays to predict renders on more nodes than this machine has.
    pub subscreens: Vec<SubscreenRecord>,
    /// Bytes of every chunk and of every texture tile, by id, the sizes behind
    /// [`SubscreenRecord::chunks`] and [`SubscreenRecord::tiles`].
    pub chunk_bytes: Vec<u64>,
    pub tile_bytes: Vec<u64>,
}

/// How the data a subscreen's rays needed reached the render node.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FetchedVia {
    /// Fetched on demand by DMA from the fork node's card.
    Dma,
    /// Fetched on demand through the mesh (serial links).
    Mesh,
    /// Everything was sent before rendering began.
    Batch,
    /// Nothing fetched: all of it was at hand (in one process, or every item a cache hit).
    #[default]
    None,
}

/// One subscreen rendered: where, by whom, when, and what it cost.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SubscreenRecord {
    /// Render node id; in one process, the index of the thread.
    pub node: u32,
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
    /// Seconds since rendering began, by the host's clock: handed out, and its last pixels
    /// in (in one process: begun and finished).
    pub start_s: f64,
    pub end_s: f64,
    /// CPU time the rendering thread spent on it (its thread CPU clock).
    pub cpu_s: f64,
    pub pixels: u64,
    pub samples: u64,
    pub rays: u64,
    /// Ids of the chunks and texture tiles its rays touched, ascending.
    pub chunks: Vec<u32>,
    pub tiles: Vec<u32>,
    /// What the render node fetched for it (cache misses), and how.
    pub fetched_bytes: u64,
    pub fetches: u32,
    pub fetched_via: FetchedVia,
}

/// Bytes of every chunk by id, from the header every render has.
pub fn chunk_bytes(scene: &renderer::SceneHeader) -> Vec<u64> {
    scene.chunks.iter().map(|c| c.byte_len as u64).collect()
}

/// Bytes of every texture tile by id (all tiles are the same size).
pub fn tile_bytes(scene: &renderer::SceneHeader) -> Vec<u64> {
    let bytes = renderer::texture::TILE_TEXELS as u64 * 4;
    vec![bytes; scene.tile_count as usize]
}

impl RenderStats {
    pub fn set_trace(&mut self, t: &TraceStats) {
        self.rays = Rays {
            camera: t.camera_rays,
            secondary: t.secondary_rays,
            shadow: t.shadow_rays,
            total: t.rays(),
        };
        self.samples = t.samples;
        self.bad_samples = t.bad_samples;
        if self.seconds.render > 0.0 {
            self.samples_per_second = t.samples as f64 / self.seconds.render;
            self.rays_per_second = t.rays() as f64 / self.seconds.render;
        }
    }

    pub fn write(&self, path: &Path) -> Result<(), scene_io::ImageError> {
        let json = serde_json::to_vec_pretty(self).unwrap_or_default();
        scene_io::image_io::write_atomic(path, &json)
    }
}
