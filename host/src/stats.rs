//! The `--stats FILE.json` report: what was rendered, how long it took, how much work it was.

use std::path::Path;

use renderer::trace::TraceStats;
use serde::Serialize;

#[derive(Clone, Debug, Serialize, Default)]
pub struct Seconds {
    pub load: f64,
    pub render: f64,
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
