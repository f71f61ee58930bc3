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
    camera::{Camera, CameraRays},
    diffuse_wave::DiffuseWave,
    integrator::{self, IntegratorKind, PathState, WhittedLimits},
    math::luminance,
    sampler::{PixelSeeds, SampleWave, WAVE_LANES},
    scene::SceneHeader,
    source::{DataError, Deferral, Item, SceneData, Touched},
    trace::{QueryMemo, TraceStats, Tracer},
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
    /// The path tracer's light found by a caustic path (a rough bounce, then mirrors or
    /// glass, then the light) is limited to this (largest channel) per sample; 0 (the
    /// default) leaves it unbiased. See `integrator::clamped`.
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

/// The longest side of an image magg renders: what the host accepts, and what everything
/// that reads a render's image or figures back (images, checkpoints, stats files) allows.
pub const MAX_IMAGE_SIDE: u32 = 32768;

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

/// A pixel's samples so far, accumulated in f64 so that long renders do not drift (f32 sums
/// lose the low bits of each new sample once the sum is large). Samples must be added in
/// their order: every way of rendering a pixel folds them here, so the bits agree.
#[derive(Clone, Copy, Default)]
struct PixelSum {
    sum: [f64; 3],
    sum_lum: f64,
    sum_lum2: f64,
    n: u32,
}

/// Adaptive sampling looks at a pixel's error after every this many samples.
const ADAPTIVE_BATCH: u32 = 8;
// A pixel stops only at the end of a wave of samples (`path_wave`): none is traced that
// samples taken one at a time would not have traced.
const _: () = assert!(ADAPTIVE_BATCH.is_multiple_of(WAVE_LANES));

impl PixelSum {
    /// Adds the next sample; true when adaptive sampling stops the pixel here.
    fn add(&mut self, l: Vec3, settings: &RenderSettings, stats: &mut TraceStats) -> bool {
        let l = if l.is_finite() {
            l.max(Vec3::ZERO)
        } else {
            stats.bad_samples += 1;
            Vec3::ZERO
        };
        for c in 0..3 {
            self.sum[c] += l[c] as f64;
        }
        self.n += 1;
        if settings.noise_threshold <= 0.0 {
            return false;
        }
        // Adaptive stop, decided from this pixel's own samples only.
        let lum = luminance(l) as f64;
        self.sum_lum += lum;
        self.sum_lum2 += lum * lum;
        let n = self.n;
        if n >= settings.min_spp.max(2) && n.is_multiple_of(ADAPTIVE_BATCH) {
            let nf = n as f64;
            let mean = self.sum_lum / nf;
            let var = ((self.sum_lum2 - nf * mean * mean) / (nf - 1.0)).max(0.0);
            let stderr = (var / nf).sqrt();
            if stderr <= settings.noise_threshold as f64 * mean.max(1e-3) {
                return true;
            }
        }
        false
    }

    fn finish(&self, stats: &mut TraceStats) -> [f32; 3] {
        stats.samples += self.n as u64;
        stats.pixels += 1;
        let nf = self.n.max(1) as f64;
        self.sum.map(|v| (v / nf) as f32)
    }
}

/// Renders one pixel: the mean of its samples.
pub fn render_pixel<D: SceneData>(
    tracer: &Tracer<D>,
    camera: &Camera,
    settings: &RenderSettings,
    x: u32,
    y: u32,
    stats: &mut TraceStats,
) -> Result<[f32; 3], DataError> {
    let mut sum = PixelSum::default();
    let rays = camera.rays(settings.width, settings.height);
    let seeds = PixelSeeds::new(settings.seed, x, y);
    if settings.integrator == IntegratorKind::Path {
        // On the heap: its 2 KB in this frame, above the ray queries' frames, moved this
        // frame's hot data against theirs, and a build whose frame was 128 bytes larger
        // spent a quarter more time in `Tracer::closest` (a load that waits on an unrelated
        // store at the same address modulo 4 KB, most likely: the instructions were the
        // same); one allocation per pixel costs nothing measurable.
        let mut diffuse = Box::new(DiffuseWave::new());
        let mut first = 0;
        while first < settings.spp {
            let lanes = (settings.spp - first).min(WAVE_LANES) as usize;
            let radiance = path_wave(
                tracer,
                settings,
                (&rays, &seeds, &mut diffuse),
                (x, y),
                first,
                lanes,
            )?;
            for l in &radiance[..lanes] {
                if sum.add(*l, settings, stats) {
                    return Ok(sum.finish(stats));
                }
            }
            first += lanes as u32;
        }
        return Ok(sum.finish(stats));
    }
    for n in 0..settings.spp {
        let mut s = seeds.sampler(n);
        let (du, dv) = s.pixel_2d();
        let ray = rays.ray(x as f32 + du, y as f32 + dv);
        tracer.count_camera_ray();
        let l = integrator::radiance(tracer, settings, ray, &mut s)?;
        if sum.add(l, settings, stats) {
            break;
        }
    }
    Ok(sum.finish(stats))
}

/// The path tracer's radiance for samples `first..first + lanes` of pixel `(x, y)`, their
/// paths taking each bounce together so that the wave draws their numbers at once (the
/// same numbers and operations as one sample at a time, so the same bits). Adaptive
/// sampling stops a pixel only after a multiple of [`ADAPTIVE_BATCH`] samples, a multiple of
/// a wave, so no sample is traced that one at a time would not have traced.
#[inline(always)]
fn path_wave<D: SceneData>(
    tracer: &Tracer<D>,
    settings: &RenderSettings,
    (rays, seeds, diffuse): (&CameraRays<'_>, &PixelSeeds, &mut DiffuseWave),
    (x, y): (u32, u32),
    first: u32,
    lanes: usize,
) -> Result<[Vec3; WAVE_LANES as usize], DataError> {
    let mut wave = SampleWave::new(seeds, first);
    let pixel = wave.pixel_2d();
    let mut paths = [None; WAVE_LANES as usize];
    for (lane, path) in paths.iter_mut().enumerate().take(lanes) {
        let (du, dv) = pixel[lane];
        let ray = rays.ray(x as f32 + du, y as f32 + dv);
        tracer.count_camera_ray();
        *path = Some(PathState::new(ray, &wave.lane(lane)));
    }
    let mut radiance = [Vec3::ZERO; WAVE_LANES as usize];
    let mut bounce = 0;
    let mut live = lanes;
    let max_depth = settings.max_depth;
    while live > 0 {
        // Eight lanes are drawn for at the cost of about one drawn alone.
        if live > 1 {
            wave.want_bounce(bounce);
        } else {
            wave.release();
        }
        // Lambertian hits wait for the others and are shaded together, in SIMD lanes.
        diffuse.begin(bounce);
        let together = live > 1;
        live = 0;
        for (lane, slot) in paths.iter_mut().enumerate() {
            let Some(path) = slot else { continue };
            // What PathState::step does, in its two halves.
            let more = path.bounce() < max_depth && {
                let mut draws = wave.lane(lane);
                match path.meet(tracer, &mut draws, settings.clamp_indirect)? {
                    None => false,
                    Some(met) => {
                        let met = if together {
                            match diffuse.push(tracer, lane, path, met, &mut draws) {
                                None => continue,
                                Some(met) => met,
                            }
                        } else {
                            met
                        };
                        path.shade(tracer, &mut draws, met)?
                    }
                }
            };
            if path.end_bounce(more, max_depth) {
                live += 1;
            } else {
                radiance[lane] = path.radiance();
                *slot = None;
            }
        }
        live += diffuse.shade(tracer, &mut paths, &mut radiance, max_depth)?;
        bounce += 1;
    }
    Ok(radiance)
}

/// What memory-coherent rendering did: how often a path was put aside for data, and how
/// many items were fetched for waiting paths.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CoherenceStats {
    /// Times a path was put aside to wait for an item.
    pub deferrals: u64,
    /// Items fetched for waiting paths (each served every path waiting for it).
    pub brings: u64,
}

/// Paths one thread keeps in flight at most in [`render_rect_coherent`], however much
/// memory it may use: more share each fetch, but past this few fetches are saved.
const MOST_PATHS_IN_FLIGHT: u32 = 16_384;

/// Paths one thread keeps in flight at least, however little memory it may use: fewer
/// would share too little of each fetch to be worth putting aside.
const LEAST_PATHS_IN_FLIGHT: u32 = 256;

/// What a path in flight can take at most: its state, and while it waits what its queries
/// found (an allocation of its own), its index in two lists and an entry of the queue of
/// what is wanted most.
const PATH_IN_FLIGHT_BYTES: usize = size_of::<Flight>()
    + size_of::<QueryMemo>()
    + 16
    + 2 * size_of::<u32>()
    + size_of::<(usize, std::cmp::Reverse<Item>)>();

/// Paths one thread keeps in flight in [`render_rect_coherent`] within `memory` bytes.
/// A render node's private memory is its cache's budget plus a small allowance, and a
/// render over TCP with a small cache has nearly every path waiting with a memo at once,
/// so the paths' memory is what the node's threads share of that allowance, not a number
/// of paths per thread (16,384 paths per thread took 6.4 MiB).
pub fn paths_in_flight(memory: usize) -> u32 {
    (memory / PATH_IN_FLIGHT_BYTES).clamp(
        LEAST_PATHS_IN_FLIGHT as usize,
        MOST_PATHS_IN_FLIGHT as usize,
    ) as u32
}

/// Rows of `width` pixels at `spp` samples that fill one batch of `paths` paths in flight
/// (at least one).
pub fn coherent_rows(width: u32, spp: u32, paths: u32) -> u32 {
    let per_row = (width.max(1) as u64) * spp.max(1) as u64;
    (paths as u64 / per_row).clamp(1, u32::MAX as u64) as u32
}
/// A bounce put aside this often is finished fetching as it goes: it needs more at once
/// than the cache keeps (a cache smaller than one bounce's data), and waiting again would
/// not end. Each wait brings one more item (the query memo keeps what was searched), so a
/// ray that crosses many chunks waits once for each; finishing such a bounce by fetching as
/// it goes holds every chunk it evicts until the bounce ends, which at 16 waits kept a
/// render node's cache up to 2.8 MiB above its budget (44% at cache 5%).
const MAX_WAITS_PER_BOUNCE: u32 = 64;

/// A path in flight in [`render_rect_coherent`].
struct Flight {
    pixel: u32,
    sample: u32,
    state: integrator::PathState,
    waits: u32,
    /// What the waiting bounce's ray queries found so far.
    memo: Option<Box<QueryMemo>>,
}

/// Turns deferral off when dropped, however the render ends.
struct Deferring<'a, F: Deferral>(&'a F);

impl<'a, F: Deferral> Deferring<'a, F> {
    fn on(f: &'a F) -> Self {
        f.defer(true);
        Deferring(f)
    }
}

impl<F: Deferral> Drop for Deferring<'_, F> {
    fn drop(&mut self) {
        self.0.defer(false);
    }
}

/// Renders `rect` (its pixels row-major) with memory-coherent rays (Pharr, Kolb, Gershbein
/// and Hanrahan 1997): many paths are in flight at once; a path whose bounce needs a chunk
/// or tile that `data` lacks is put aside, waiting for that item, and the thread goes on
/// with the others; then the item most paths wait for is fetched and its paths go on
/// together. So one fetch serves every path that needs the item, where fetching on each
/// miss has a small cache fetch the same items over and over.
///
/// The pixels are the same bits as [`render_pixel`]'s: a bounce that waited is run again
/// from the state it started in, with the same numbers (the sampler's depend on the sample
/// and the bounce only), and each pixel's samples are added in their order. Only the path
/// tracer's bounces can wait; another integrator renders pixel by pixel, fetching as it goes.
/// At most `paths` paths are in flight at once (see [`paths_in_flight`]), unless the rect's
/// pixels are too many for that: then one sample of each at a time, or with adaptive sampling
/// one batch of each (the stop is decided after whole batches, as pixel by pixel).
pub fn render_rect_coherent<D: SceneData + Deferral>(
    tracer: &Tracer<D>,
    camera: &Camera,
    settings: &RenderSettings,
    rect: Rect,
    paths: u32,
    stats: &mut TraceStats,
    coherence: &mut CoherenceStats,
) -> Result<Vec<[f32; 3]>, DataError> {
    let coords: Vec<(u32, u32)> = (rect.y..rect.y + rect.height)
        .flat_map(|y| (rect.x..rect.x + rect.width).map(move |x| (x, y)))
        .collect();
    let data = tracer.data;
    if settings.integrator != IntegratorKind::Path {
        return coords
            .iter()
            .map(|&(x, y)| {
                data.tick();
                render_pixel(tracer, camera, settings, x, y, stats)
            })
            .collect();
    }
    let rays = camera.rays(settings.width, settings.height);
    let seeds: Vec<PixelSeeds> = coords
        .iter()
        .map(|&(x, y)| PixelSeeds::new(settings.seed, x, y))
        .collect();
    let mut sums = vec![PixelSum::default(); coords.len()];
    let mut stopped = vec![false; coords.len()];
    // Samples a pixel takes per round: all of them when they fit, and rounds of the
    // adaptive batch when pixels may stop early (the stop is decided between rounds).
    let per_round = if settings.noise_threshold > 0.0 {
        ADAPTIVE_BATCH
    } else {
        (paths / (coords.len() as u32).max(1)).max(1)
    };
    let _deferring = Deferring::on(data);
    let mut first = 0;
    while first < settings.spp && stopped.iter().any(|s| !s) {
        let end = settings.spp.min(first.saturating_add(per_round));
        let live = stopped.iter().filter(|s| !**s).count();
        let mut flights = Vec::with_capacity(live * (end - first) as usize);
        for (pixel, &(x, y)) in coords.iter().enumerate() {
            if stopped[pixel] {
                continue;
            }
            for sample in first..end {
                let mut s = seeds[pixel].sampler(sample);
                let (du, dv) = s.pixel_2d();
                let ray = rays.ray(x as f32 + du, y as f32 + dv);
                tracer.count_camera_ray();
                flights.push(Flight {
                    pixel: pixel as u32,
                    sample,
                    state: integrator::PathState::new(ray, &s),
                    waits: 0,
                    memo: None,
                });
            }
        }
        fly(tracer, settings, &seeds, &mut flights, coherence)?;
        // In pixel order, each pixel's samples in their order.
        for f in &flights {
            let p = f.pixel as usize;
            if !stopped[p] && sums[p].add(f.state.radiance(), settings, stats) {
                stopped[p] = true;
            }
        }
        first = end;
    }
    Ok(sums.iter().map(|s| s.finish(stats)).collect())
}

/// Runs every path in `flights` to its end, putting aside those that wait for data until
/// the item is fetched.
fn fly<D: SceneData + Deferral>(
    tracer: &Tracer<D>,
    settings: &RenderSettings,
    seeds: &[PixelSeeds],
    flights: &mut [Flight],
    coherence: &mut CoherenceStats,
) -> Result<(), DataError> {
    let mut waiting = Waiting::default();
    let all: Vec<u32> = (0..flights.len() as u32).collect();
    let mut runner = Runner {
        tracer,
        settings,
        seeds,
        flights,
        coherence,
    };
    runner.run(&all, &mut |i, item| waiting.add(i, item))?;
    // The item the most paths wait for is fetched first, and its paths run on at once:
    // what many paths need is fetched once for all of them, while it is resident.
    while let Some((item, paths)) = waiting.most_wanted() {
        // SAFETY: between runs no path holds a chunk or tile: a path's state and memo are
        // plain values and ids; hits live only within one bounce.
        unsafe { tracer.data.bring(item) }?;
        runner.coherence.brings += 1;
        runner.run(&paths, &mut |i, item| waiting.add(i, item))?;
    }
    Ok(())
}

/// Paths waiting for items, by item, and which item the most wait for.
#[derive(Default)]
struct Waiting {
    paths: std::collections::HashMap<Item, Vec<u32>>,
    /// (paths waiting, item) as each list grew; an entry whose count is no longer its
    /// item's is stale and skipped.
    by_count: std::collections::BinaryHeap<(usize, std::cmp::Reverse<Item>)>,
}

impl Waiting {
    fn add(&mut self, path: u32, item: Item) {
        let list = self.paths.entry(item).or_default();
        list.push(path);
        self.by_count.push((list.len(), std::cmp::Reverse(item)));
    }

    /// Takes the paths of the item the most wait for (ties to the lowest id, so that a
    /// render's fetches do not depend on hashing).
    fn most_wanted(&mut self) -> Option<(Item, Vec<u32>)> {
        while let Some((count, std::cmp::Reverse(item))) = self.by_count.pop() {
            if self.paths.get(&item).is_some_and(|l| l.len() == count) {
                return self.paths.remove(&item).map(|l| (item, l));
            }
        }
        None
    }
}

/// What running paths needs.
struct Runner<'r, 'a, D: SceneData> {
    tracer: &'r Tracer<'a, D>,
    settings: &'r RenderSettings,
    seeds: &'r [PixelSeeds],
    flights: &'r mut [Flight],
    coherence: &'r mut CoherenceStats,
}

impl<D: SceneData + Deferral> Runner<'_, '_, D> {
    /// Runs the paths `list` names (in its order) until each ends or waits for an item;
    /// `wait(path, item)` is told of each that waits.
    fn run(&mut self, list: &[u32], wait: &mut impl FnMut(u32, Item)) -> Result<(), DataError> {
        let (tracer, settings) = (self.tracer, self.settings);
        let data = tracer.data;
        for &i in list {
            let f = &mut self.flights[i as usize];
            data.tick();
            loop {
                let before = f.state;
                let counts = (tracer.secondary_rays.get(), tracer.shadow_rays.get());
                let mut sampler = self.seeds[f.pixel as usize].sampler(f.sample);
                let give_up = f.waits >= MAX_WAITS_PER_BOUNCE;
                tracer.memo.set(f.memo.take());
                if give_up {
                    data.defer(false);
                }
                let stepped = f.state.step(
                    tracer,
                    &mut sampler,
                    settings.max_depth,
                    settings.clamp_indirect,
                );
                if give_up {
                    data.defer(true);
                }
                // Kept only while the bounce waits.
                let memo = tracer.memo.take();
                match stepped {
                    Ok(true) => f.waits = 0,
                    Ok(false) => break,
                    Err(DataError::Missing(item)) => {
                        f.memo = memo;
                        // The bounce is run again from where it began once `item` is here.
                        f.state = before;
                        tracer.secondary_rays.set(counts.0);
                        tracer.shadow_rays.set(counts.1);
                        f.waits += 1;
                        self.coherence.deferrals += 1;
                        wait(i, item);
                        break;
                    }
                    Err(e) => return Err(e),
                }
            }
        }
        Ok(())
    }
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
    stats.add(&tracer.stats());
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
    use std::cell::{Cell, RefCell};

    use super::*;
    use crate::{
        MemoryData, PrepareOptions,
        chunk::Chunk,
        demo::demo_scene,
        integrator::{IntegratorKind, WhittedLimits},
        prepare,
        texture::Tile,
    };

    /// All the scene's data, of which only the last `room` chunks asked for count as here:
    /// a small least-recently-used cache, without the fetching, for the renderer's side of
    /// memory-coherent rays. It counts what it would have fetched.
    struct Scarce {
        data: MemoryData,
        room: usize,
        here: RefCell<Vec<u32>>,
        deferring: Cell<bool>,
        fetches: Cell<u64>,
    }

    impl Scarce {
        fn new(data: MemoryData, room: usize) -> Scarce {
            Scarce {
                data,
                room,
                here: RefCell::new(Vec::new()),
                deferring: Cell::new(false),
                fetches: Cell::new(0),
            }
        }

        /// Marks `id` used; false if it is not here and may not be fetched now.
        fn use_chunk(&self, id: u32) -> bool {
            let mut here = self.here.borrow_mut();
            if let Some(at) = here.iter().position(|&c| c == id) {
                here.remove(at);
            } else if self.deferring.get() && here.len() >= self.room {
                return false;
            } else {
                self.fetches.set(self.fetches.get() + 1);
                if here.len() >= self.room {
                    here.remove(0);
                }
            }
            here.push(id);
            true
        }
    }

    impl SceneData for Scarce {
        type ChunkRef<'a> = &'a Chunk;
        type TileRef<'a> = &'a Tile;

        const MAY_DEFER: bool = true;

        fn chunk(&self, id: u32) -> Result<&Chunk, DataError> {
            if !self.use_chunk(id) {
                return Err(DataError::Missing(Item::Chunk(id)));
            }
            self.data.chunk(id)
        }

        fn tile(&self, id: u32) -> Result<&Tile, DataError> {
            self.data.tile(id)
        }
    }

    impl Deferral for Scarce {
        fn defer(&self, on: bool) {
            self.deferring.set(on);
        }

        unsafe fn bring(&self, item: Item) -> Result<(), DataError> {
            let was = self.deferring.replace(false);
            if let Item::Chunk(id) = item {
                self.use_chunk(id);
            }
            self.deferring.set(was);
            Ok(())
        }

        fn tick(&self) {}
    }

    /// The demo scene in chunks of 64 triangles, and its camera.
    fn scene() -> (SceneHeader, MemoryData, Camera) {
        scene_of(demo_scene())
    }

    /// The demo scene lit also by a uniform sky and a point light: lights that a wave's
    /// diffuse hits leave to the path's own next-event estimation.
    fn sky_scene() -> (SceneHeader, MemoryData, Camera) {
        let mut desc = demo_scene();
        desc.environment = Some(crate::light::Environment::uniform(Vec3::splat(0.4)));
        desc.lights.push(crate::light::Light::Point {
            position: Vec3::new(0.5, 3.0, 1.0),
            intensity: Vec3::splat(6.0),
        });
        scene_of(desc)
    }

    fn scene_of(desc: crate::scene::SceneDesc) -> (SceneHeader, MemoryData, Camera) {
        let camera = desc.cameras[0].clone();
        let (header, data) = prepare(
            desc,
            &PrepareOptions {
                chunk_triangles: 64,
            },
        );
        assert!(header.chunks.len() > 20, "{} chunks", header.chunks.len());
        (header, data, camera)
    }

    /// Renders `rect` pixel by pixel, fetching on each miss, and with coherent rays, each
    /// from a cache of `room` chunks; returns (pixels, stats, fetches) of each.
    #[allow(clippy::type_complexity)]
    fn both_ways(
        settings: &RenderSettings,
        rect: Rect,
        room: usize,
    ) -> (
        (Vec<[f32; 3]>, TraceStats, u64),
        (Vec<[f32; 3]>, TraceStats, u64, CoherenceStats),
    ) {
        both_ways_in(scene(), settings, rect, room)
    }

    #[allow(clippy::type_complexity)]
    fn both_ways_in(
        (header, data, camera): (SceneHeader, MemoryData, Camera),
        settings: &RenderSettings,
        rect: Rect,
        room: usize,
    ) -> (
        (Vec<[f32; 3]>, TraceStats, u64),
        (Vec<[f32; 3]>, TraceStats, u64, CoherenceStats),
    ) {
        let plain = Scarce::new(data.clone(), room);
        let tracer = Tracer::new(&header, &plain);
        let mut stats = TraceStats::default();
        let mut pixels = Vec::new();
        for y in rect.y..rect.y + rect.height {
            for x in rect.x..rect.x + rect.width {
                pixels.push(render_pixel(&tracer, &camera, settings, x, y, &mut stats).unwrap());
            }
        }
        stats.add(&tracer.stats());
        let coherent = coherently(
            (&header, data, &camera),
            settings,
            rect,
            room,
            paths_in_flight(usize::MAX),
        );
        ((pixels, stats, plain.fetches.get()), coherent)
    }

    /// Renders `rect` with coherent rays, `paths` in flight, from a cache of `room` chunks;
    /// returns (pixels, stats, fetches, coherence).
    fn coherently(
        (header, data, camera): (&SceneHeader, MemoryData, &Camera),
        settings: &RenderSettings,
        rect: Rect,
        room: usize,
        paths: u32,
    ) -> (Vec<[f32; 3]>, TraceStats, u64, CoherenceStats) {
        let scarce = Scarce::new(data, room);
        let tracer = Tracer::new(header, &scarce);
        let mut stats = TraceStats::default();
        let mut coherence = CoherenceStats::default();
        let pixels = render_rect_coherent(
            &tracer,
            camera,
            settings,
            rect,
            paths,
            &mut stats,
            &mut coherence,
        )
        .unwrap();
        stats.add(&tracer.stats());
        assert!(!scarce.deferring.get(), "deferral is off after the render");
        (pixels, stats, scarce.fetches.get(), coherence)
    }

    /// A small image and a rect of it of 1,440 paths (30 x 4 pixels at 12 spp).
    fn small_rect() -> (RenderSettings, Rect) {
        let settings = RenderSettings {
            width: 48,
            height: 36,
            spp: 12,
            ..RenderSettings::default()
        };
        let rect = Rect {
            x: 5,
            y: 7,
            width: 30,
            height: 4,
        };
        (settings, rect)
    }

    fn bits(p: &[[f32; 3]]) -> Vec<u32> {
        p.iter().flatten().map(|v| v.to_bits()).collect()
    }

    /// Renders `rect` of `scene` both ways ([`both_ways_in`]), asserts the same bits and
    /// the same ray counts (`what` names the case), and returns the pixels.
    fn agree_both_ways(
        scene: (SceneHeader, MemoryData, Camera),
        settings: &RenderSettings,
        rect: Rect,
        room: usize,
        what: &str,
    ) -> Vec<[f32; 3]> {
        let ((pixels, stats, _), (c_pixels, c_stats, _, _)) =
            both_ways_in(scene, settings, rect, room);
        assert_eq!(bits(&pixels), bits(&c_pixels), "{what}");
        assert_eq!(stats, c_stats, "{what}");
        pixels
    }

    #[test]
    fn coherent_rays_give_the_same_bits_and_fetch_less() {
        let (settings, rect) = small_rect();
        let ((pixels, stats, fetches), (c_pixels, c_stats, c_fetches, coherence)) =
            both_ways(&settings, rect, 8);
        assert_eq!(bits(&pixels), bits(&c_pixels));
        assert_eq!(stats, c_stats, "rays put aside are not counted twice");
        assert!(
            coherence.deferrals > 0 && coherence.brings > 0,
            "{coherence:?}"
        );
        // A cache of 8 of the scene's chunks: 950 fetches against 3953 when measured.
        assert!(
            c_fetches * 3 < fetches,
            "coherent rays fetched {c_fetches} chunks, against {fetches} fetching on each miss"
        );
    }

    #[test]
    fn fewer_paths_in_flight_give_the_same_bits() {
        let (settings, rect) = small_rect();
        let (header, data, camera) = scene();
        let render = |paths: u32| {
            let (pixels, stats, fetches, _) =
                coherently((&header, data.clone(), &camera), &settings, rect, 8, paths);
            (bits(&pixels), stats, fetches)
        };
        // 1,440 paths: all in one batch, or in six of two samples a pixel.
        let (all, few) = (
            render(paths_in_flight(usize::MAX)),
            render(paths_in_flight(0)),
        );
        assert_eq!(all.0, few.0);
        assert_eq!(all.1, few.1);
        assert!(
            few.2 > all.2,
            "fewer paths share each fetch: {} against {}",
            few.2,
            all.2
        );
    }

    #[test]
    fn paths_in_flight_fit_the_memory_given() {
        assert_eq!(paths_in_flight(usize::MAX), MOST_PATHS_IN_FLIGHT);
        assert_eq!(paths_in_flight(0), LEAST_PATHS_IN_FLIGHT);
        let memory = 2 << 20;
        let paths = paths_in_flight(memory);
        assert!(paths as usize * PATH_IN_FLIGHT_BYTES <= memory);
        assert!((paths as usize + 1) * PATH_IN_FLIGHT_BYTES > memory);
        // A batch is whole rows, at least one.
        assert_eq!(coherent_rows(320, 64, paths), 1);
        assert_eq!(coherent_rows(32, 4, 1024), 8);
    }

    #[test]
    fn coherent_rays_agree_with_adaptive_sampling_whitted_and_a_cache_of_one() {
        let base = RenderSettings {
            width: 40,
            height: 30,
            spp: 24,
            ..RenderSettings::default()
        };
        let rect = Rect {
            x: 3,
            y: 10,
            width: 20,
            height: 3,
        };
        let adaptive = RenderSettings {
            noise_threshold: 0.2,
            min_spp: 8,
            ..base.clone()
        };
        let whitted = RenderSettings {
            integrator: IntegratorKind::Whitted,
            max_depth: 8,
            whitted: WhittedLimits::default(),
            ..base.clone()
        };
        for (settings, room) in [(&adaptive, 3), (&whitted, 3), (&base, 1)] {
            agree_both_ways(
                scene(),
                settings,
                rect,
                room,
                &format!("{settings:?} room {room}"),
            );
        }
    }

    /// The wave's diffuse hits take the sky and a point light through the path's own
    /// next-event estimation, and still give the bits of paths stepped one at a time.
    #[test]
    fn coherent_rays_agree_under_a_sky_and_a_point_light() {
        let settings = RenderSettings {
            width: 40,
            height: 30,
            spp: 16,
            ..RenderSettings::default()
        };
        let rect = Rect {
            x: 2,
            y: 12,
            width: 30,
            height: 3,
        };
        let pixels = agree_both_ways(sky_scene(), &settings, rect, 4, "sky and point light");
        let (lit, dark) = (bits(&pixels), both_ways(&settings, rect, 4).0.0);
        assert_ne!(lit, bits(&dark), "the sky and the point light add light");
    }

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
