//! The pixel loop, written once: every way of rendering (in one process on many threads,
//! or a subscreen on a render node) calls [`render_rect`], and a pixel's value depends only
//! on the scene, the settings and the pixel's coordinates.

use std::sync::{
    Mutex,
    atomic::{AtomicBool, AtomicUsize, Ordering},
};

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::{
    camera::Camera,
    integrator::{self, IntegratorKind, WhittedLimits},
    math::luminance,
    sampler::PixelSeeds,
    scene::SceneHeader,
    source::{DataError, SceneData, Touched},
    trace::{TraceStats, Tracer},
};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderSettings {
    pub width: u32,
    pub height: u32,
    /// Samples per pixel (the most, when adaptive sampling stops a pixel early).
    pub spp: u32,
    pub seed: u64,
    pub integrator: IntegratorKind,
    pub max_depth: u32,
    /// Adaptive sampling: a pixel stops once the standard error of its mean luminance is
    /// below this fraction of the mean. 0 turns it off.
    pub noise_threshold: f32,
    /// Samples every pixel takes before adaptive sampling may stop it.
    pub min_spp: u32,
    pub whitted: WhittedLimits,
    /// The path tracer's light by more than one bounce is limited to this (largest channel)
    /// per sample; 0 (the default) leaves it unbiased. See `integrator::clamped`.
    pub clamp_indirect: f32,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            width: 640,
            height: 480,
            spp: 64,
            seed: 0,
            integrator: IntegratorKind::Path,
            max_depth: IntegratorKind::Path.default_max_depth(),
            noise_threshold: 0.0,
            min_spp: 16,
            whitted: WhittedLimits::default(),
            clamp_indirect: 0.0,
        }
    }
}

/// A rectangle of pixels, (x, y) its top-left corner.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Rect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl Rect {
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// A linear RGB image, row-major, top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[f32; 3]>,
}

impl Image {
    pub fn new(width: u32, height: u32) -> Image {
        Image {
            width,
            height,
            pixels: vec![[0.0; 3]; width as usize * height as usize],
        }
    }

    /// Copies a rectangle of pixels (row-major within the rectangle) into place.
    pub fn put_rect(&mut self, rect: Rect, pixels: &[[f32; 3]]) {
        for row in 0..rect.height {
            let src = (row * rect.width) as usize;
            let dst = ((rect.y + row) * self.width + rect.x) as usize;
            self.pixels[dst..dst + rect.width as usize]
                .copy_from_slice(&pixels[src..src + rect.width as usize]);
        }
    }

    pub fn channel_means(&self) -> [f64; 3] {
        let mut sum = [0f64; 3];
        for p in &self.pixels {
            for c in 0..3 {
                sum[c] += p[c] as f64;
            }
        }
        let n = self.pixels.len().max(1) as f64;
        sum.map(|s| s / n)
    }
}

/// Renders one pixel: the mean of its samples, accumulated in f64 so that long renders do
/// not drift (f32 sums lose the low bits of each new sample once the sum is large).
pub fn render_pixel<D: SceneData>(
    tracer: &Tracer<D>,
    camera: &Camera,
    settings: &RenderSettings,
    x: u32,
    y: u32,
    stats: &mut TraceStats,
) -> Result<[f32; 3], DataError> {
    let mut sum = [0f64; 3];
    let mut sum_lum = 0f64;
    let mut sum_lum2 = 0f64;
    let mut n = 0u32;
    let batch = 8;
    let rays = camera.rays(settings.width, settings.height);
    let seeds = PixelSeeds::new(settings.seed, x, y);
    while n < settings.spp {
        let mut s = seeds.sampler(n);
        let (du, dv) = s.pixel_2d();
        let ray = rays.ray(x as f32 + du, y as f32 + dv);
        tracer.count_camera_ray();
        let l = integrator::radiance(tracer, settings, ray, &mut s)?;
        let l = if l.is_finite() {
            l.max(Vec3::ZERO)
        } else {
            stats.bad_samples += 1;
            Vec3::ZERO
        };
        for c in 0..3 {
            sum[c] += l[c] as f64;
        }
        let lum = luminance(l) as f64;
        sum_lum += lum;
        sum_lum2 += lum * lum;
        n += 1;
        // Adaptive stop, decided from this pixel's own samples only.
        if settings.noise_threshold > 0.0 && n >= settings.min_spp.max(2) && n.is_multiple_of(batch)
        {
            let nf = n as f64;
            let mean = sum_lum / nf;
            let var = ((sum_lum2 - nf * mean * mean) / (nf - 1.0)).max(0.0);
            let stderr = (var / nf).sqrt();
            if stderr <= settings.noise_threshold as f64 * mean.max(1e-3) {
                break;
            }
        }
    }
    stats.samples += n as u64;
    stats.pixels += 1;
    let nf = n.max(1) as f64;
    Ok(sum.map(|v| (v / nf) as f32))
}

/// Renders a rectangle into `out` (row-major within the rectangle).
pub fn render_rect<D: SceneData>(
    scene: &SceneHeader,
    data: &D,
    camera: &Camera,
    settings: &RenderSettings,
    rect: Rect,
    out: &mut [[f32; 3]],
    cancel: &AtomicBool,
) -> Result<TraceStats, DataError> {
    let tracer = Tracer::new(scene, data);
    let mut stats = TraceStats::default();
    for row in 0..rect.height {
        if cancel.load(Ordering::Relaxed) {
            return Err(DataError::Cancelled);
        }
        for col in 0..rect.width {
            let px = render_pixel(
                &tracer,
                camera,
                settings,
                rect.x + col,
                rect.y + row,
                &mut stats,
            )?;
            out[(row * rect.width + col) as usize] = px;
        }
    }
    let t = tracer.stats();
    stats.camera_rays += t.camera_rays;
    stats.secondary_rays += t.secondary_rays;
    stats.shadow_rays += t.shadow_rays;
    Ok(stats)
}

/// Splits an image into tiles of at most `size` x `size` pixels, row by row.
pub fn tiles(width: u32, height: u32, size: u32) -> Vec<Rect> {
    let size = size.max(1);
    let mut out = Vec::new();
    let mut y = 0;
    while y < height {
        let mut x = 0;
        let h = size.min(height - y);
        while x < width {
            let w = size.min(width - x);
            out.push(Rect {
                x,
                y,
                width: w,
                height: h,
            });
            x += w;
        }
        y += h;
    }
    out
}

/// Tiles of at most `size` x `size` pixels covering the scan lines not yet `done` (one flag
/// per line), band by band: what is left of an image after a checkpoint.
pub fn tiles_of_rows_left(width: u32, size: u32, done: &[bool]) -> Vec<Rect> {
    let mut out = Vec::new();
    let mut y = 0;
    while y < done.len() {
        if done[y] {
            y += 1;
            continue;
        }
        let end = (y..done.len()).find(|&e| done[e]).unwrap_or(done.len());
        out.extend(
            tiles(width, (end - y) as u32, size)
                .into_iter()
                .map(|mut r| {
                    r.y += y as u32;
                    r
                }),
        );
        y = end;
    }
    out
}

/// Renders the whole image in this process on `threads` threads, tile by tile.
/// `progress(pixels_done, pixels_total)` is called after every tile.
#[allow(clippy::too_many_arguments)]
pub fn render_image<D: SceneData + Sync>(
    scene: &SceneHeader,
    data: &D,
    camera: &Camera,
    settings: &RenderSettings,
    threads: usize,
    tile_size: u32,
    cancel: &AtomicBool,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<(Image, TraceStats), DataError> {
    let rects = tiles(settings.width, settings.height, tile_size);
    let total = settings.width as u64 * settings.height as u64;
    render_rects(
        scene,
        data,
        camera,
        settings,
        threads,
        &rects,
        Image::new(settings.width, settings.height),
        cancel,
        &Progressing {
            done: AtomicUsize::new(0),
            total,
            progress,
        },
    )
}

/// [`render_image`]'s watch: counts finished pixels for its progress callback.
struct Progressing<'a> {
    done: AtomicUsize,
    total: u64,
    progress: &'a (dyn Fn(u64, u64) + Sync),
}

impl RectWatch for Progressing<'_> {
    fn finished(&self, done: RectDone<'_>) {
        let n = done.rect.pixel_count();
        let d = self.done.fetch_add(n, Ordering::Relaxed) + n;
        (self.progress)(d as u64, self.total);
    }
}

/// What a rendering thread did for one rectangle.
pub struct RectDone<'a> {
    pub rect: Rect,
    /// Which of the threads rendered it (`0..threads`).
    pub thread: usize,
    /// Its pixels, row-major within the rectangle.
    pub pixels: &'a [[f32; 3]],
    pub trace: TraceStats,
    /// Ids of the chunks and of the texture tiles its rays touched, ascending.
    pub chunks: Vec<u32>,
    pub tiles: Vec<u32>,
}

/// What [`render_rects`] tells as it goes. Both calls come from the rendering thread
/// itself, so that thread's own clocks (its CPU time) can be read around each rectangle.
pub trait RectWatch: Sync {
    /// `thread` is about to begin `rect`.
    fn begin(&self, _thread: usize, _rect: Rect) {}
    /// A rectangle is finished and already in the image.
    fn finished(&self, done: RectDone<'_>);
}

/// Renders `rects` into `image` (whose other pixels are kept) on `threads` threads, telling
/// `watch` as each rectangle begins and ends, from the thread that renders it.
#[allow(clippy::too_many_arguments)]
pub fn render_rects<D: SceneData + Sync>(
    scene: &SceneHeader,
    data: &D,
    camera: &Camera,
    settings: &RenderSettings,
    threads: usize,
    rects: &[Rect],
    image: Image,
    cancel: &AtomicBool,
    watch: &dyn RectWatch,
) -> Result<(Image, TraceStats), DataError> {
    let next = AtomicUsize::new(0);
    let image = Mutex::new(image);
    let stats = Mutex::new(TraceStats::default());
    let error: Mutex<Option<DataError>> = Mutex::new(None);
    let local_cancel = AtomicBool::new(false);
    std::thread::scope(|s| {
        for thread in 0..threads.max(1) {
            let (next, image, stats, error, local_cancel) =
                (&next, &image, &stats, &error, &local_cancel);
            s.spawn(move || {
                let mut buf = Vec::new();
                let touched = Touched::new(scene.chunks.len(), scene.tile_count as usize);
                let data = touched.watching(data);
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&rect) = rects.get(i) else { break };
                    if cancel.load(Ordering::Relaxed) || local_cancel.load(Ordering::Relaxed) {
                        break;
                    }
                    buf.clear();
                    buf.resize(rect.pixel_count(), [0.0; 3]);
                    watch.begin(thread, rect);
                    match render_rect(scene, &data, camera, settings, rect, &mut buf, cancel) {
                        Ok(st) => {
                            image.lock().expect("image lock").put_rect(rect, &buf);
                            stats.lock().expect("stats lock").add(&st);
                            let (chunks, tiles) = touched.take();
                            watch.finished(RectDone {
                                rect,
                                thread,
                                pixels: &buf,
                                trace: st,
                                chunks,
                                tiles,
                            });
                        }
                        Err(e) => {
                            error.lock().expect("error lock").get_or_insert(e);
                            local_cancel.store(true, Ordering::Relaxed);
                            break;
                        }
                    }
                }
            });
        }
    });
    if let Some(e) = error.into_inner().expect("error lock") {
        return Err(e);
    }
    if cancel.load(Ordering::Relaxed) {
        return Err(DataError::Cancelled);
    }
    Ok((
        image.into_inner().expect("image lock"),
        stats.into_inner().expect("stats lock"),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_cover_the_image_once() {
        let t = tiles(37, 21, 8);
        let mut cover = vec![0; 37 * 21];
        for r in &t {
            for y in r.y..r.y + r.height {
                for x in r.x..r.x + r.width {
                    cover[(y * 37 + x) as usize] += 1;
                }
            }
        }
        assert!(cover.iter().all(|&c| c == 1));
    }

    #[test]
    fn tiles_of_rows_left_cover_exactly_the_lines_not_done() {
        let done = [true, false, false, false, true, true, false, true, false];
        let t = tiles_of_rows_left(10, 2, &done);
        let mut cover = vec![0; 10 * done.len()];
        for r in &t {
            assert!(r.width <= 2 && r.height <= 2);
            for y in r.y..r.y + r.height {
                for x in r.x..r.x + r.width {
                    cover[(y * 10 + x) as usize] += 1;
                }
            }
        }
        for (y, &d) in done.iter().enumerate() {
            for x in 0..10 {
                assert_eq!(cover[y * 10 + x], u32::from(!d), "pixel ({x}, {y})");
            }
        }
        assert!(tiles_of_rows_left(10, 4, &[true; 3]).is_empty());
    }
}
