//! Rendering in this one process, on all its cores: the reference every cluster render must
//! match byte for byte.

use std::{
    path::PathBuf,
    sync::{
        Mutex,
        atomic::{AtomicBool, AtomicU64, Ordering},
    },
    time::{Duration, Instant},
};

use fabric::clock::thread_cpu_time;
use renderer::{
    DataError, PrepareOptions, RenderSettings,
    render::{self, RectDone, RectWatch},
};

use crate::{
    checkpoint::{self, Checkpoint, CheckpointError, CheckpointKey},
    progress::Progress,
    scene_source::{SceneSource, read_scene},
    stats::{self, RenderStats, SubscreenRecord},
};

#[derive(Clone, Debug)]
pub struct RenderConfig {
    pub scene: SceneSource,
    pub output: PathBuf,
    pub settings: RenderSettings,
    /// Whether width/height were given; if not, the camera's aspect ratio may set the height.
    pub height_given: bool,
    pub camera: Option<String>,
    pub threads: usize,
    pub stats: Option<PathBuf>,
    pub prepare: PrepareOptions,
    /// Radiance from outside the scene; `None` for the scene's default.
    pub environment: Option<renderer::light::Environment>,
    pub progress: bool,
    /// Continue from the checkpoint beside the output (`OUT.partial`) instead of refusing
    /// to start over it.
    pub resume: bool,
    /// How often the checkpoint of a render in progress is replaced.
    pub checkpoint_interval: std::time::Duration,
    /// Filter the finished image with the edge-aware denoiser (biased; see
    /// [`renderer::denoise`]).
    pub denoise: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error(transparent)]
    Load(#[from] scene_io::LoadError),
    #[error("{0}")]
    Settings(String),
    #[error("rendering failed: {0}")]
    Render(#[from] DataError),
    #[error(transparent)]
    Output(#[from] scene_io::ImageError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// Stopped by the user; the finished lines are in the checkpoint.
    #[error("interrupted; {kept} of {height} scan lines are kept in {} (run again with --resume to finish)", path.display())]
    Interrupted {
        path: PathBuf,
        kept: usize,
        height: u32,
    },
}

/// Checks settings that do not need the scene, so mistakes surface before minutes of work.
pub fn check_settings(config: &RenderConfig) -> Result<(), RenderError> {
    let s = &config.settings;
    let bad = |m: String| Err(RenderError::Settings(m));
    if s.width == 0 || s.height == 0 {
        return bad(format!(
            "image size {}x{} is empty: width and height must be at least 1",
            s.width, s.height
        ));
    }
    if s.width > renderer::MAX_IMAGE_SIDE || s.height > renderer::MAX_IMAGE_SIDE {
        return bad(format!(
            "image size {}x{} is too large (at most {} a side)",
            s.width,
            s.height,
            renderer::MAX_IMAGE_SIDE
        ));
    }
    if s.spp == 0 {
        return bad("--spp must be at least 1".into());
    }
    if !(s.noise_threshold >= 0.0 && s.noise_threshold.is_finite()) {
        return bad("--noise-threshold must be a number of at least 0".into());
    }
    check_output(&config.output)?;
    // Before minutes of loading and starting a cluster, not after.
    let partial = checkpoint::path_for(&config.output);
    if !config.resume && partial.exists() {
        return Err(CheckpointError::Exists { path: partial }.into());
    }
    if let Some(p) = &config.stats {
        check_writable_dir(p)?;
    }
    check_no_file_twice(config)
}

/// Refuses a render that would write one file twice, or over its own scene: `-o a.png
/// --stats a.png` wrote the image and then the statistics over it (saying it wrote the
/// image), `--stats scene.gltf` replaced the scene, and `-o` onto its texture or `--stats`
/// onto its `.bin` replaced the scene's data.
fn check_no_file_twice(config: &RenderConfig) -> Result<(), RenderError> {
    let checkpoint = checkpoint::path_for(&config.output);
    let (scene, data) = match &config.scene {
        SceneSource::File(p) => (Some(p.as_path()), scene_io::files_named(p)),
        SceneSource::Demo => (None, Vec::new()),
    };
    let mut files = vec![
        (
            "the image (-o)",
            Some(config.output.as_path()),
            FileUse::Written,
        ),
        (
            "the image's checkpoint",
            Some(checkpoint.as_path()),
            FileUse::Written,
        ),
        (
            "the statistics (--stats)",
            config.stats.as_deref(),
            FileUse::Written,
        ),
        ("the scene", scene, FileUse::Read),
    ];
    files.extend(
        data.iter()
            .map(|p| ("a file the scene reads", Some(p.as_path()), FileUse::Read)),
    );
    refuse_same_files(&files).map_err(RenderError::Settings)
}

/// Whether a command reads a file it names or writes it.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum FileUse {
    Read,
    Written,
}

/// Refuses a command whose files, named (what, path, use) in the order it lists them, would
/// have it write one file twice or over one it reads; files it only reads may be one file
/// (`simulate --overheads-from` the recorded render itself). The error names the later of
/// the two and both uses.
pub fn refuse_same_files(
    files: &[(&str, Option<&std::path::Path>, FileUse)],
) -> Result<(), String> {
    let named: Vec<_> = files
        .iter()
        .filter_map(|&(what, p, u)| Some((what, p?, u)))
        .collect();
    for (i, &(what, a, use_a)) in named.iter().enumerate() {
        for &(other, b, use_b) in &named[..i] {
            let writes = use_a == FileUse::Written || use_b == FileUse::Written;
            if writes && same_file(a, b) {
                return Err(format!(
                    "{}: {other} and {what} would be the same file",
                    a.display()
                ));
            }
        }
    }
    Ok(())
}

/// Whether two paths name one file: the same device and inode where both exist, else the
/// same place once links (to files not yet there too, where a write would land) and their
/// folders are resolved.
pub fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    let resolved = |p: &std::path::Path| {
        scene_io::image_io::link_target(p).unwrap_or_else(|_| p.to_path_buf())
    };
    let (a, b) = (&resolved(a), &resolved(b));
    if let (Ok(ma), Ok(mb)) = (std::fs::metadata(a), std::fs::metadata(b)) {
        return (ma.dev(), ma.ino()) == (mb.dev(), mb.ino());
    }
    let place = |p: &std::path::Path| {
        let dir = match p.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => std::path::Path::new("."),
        };
        Some(std::fs::canonicalize(dir).ok()?.join(p.file_name()?))
    };
    match (place(a), place(b)) {
        (Some(pa), Some(pb)) => pa == pb,
        _ => a == b,
    }
}

pub fn check_output(path: &std::path::Path) -> Result<(), RenderError> {
    if scene_io::image_io::Format::of(path).is_none() {
        return Err(RenderError::Settings(format!(
            "{}: unknown image format (use .png, .exr or .pfm)",
            path.display()
        )));
    }
    check_writable_dir(path)
}

fn check_writable_dir(path: &std::path::Path) -> Result<(), RenderError> {
    // A file is written by renaming a temporary one over it: onto a folder that fails, and
    // only once the render is done.
    if path.is_dir() {
        return Err(RenderError::Settings(format!(
            "{}: is a folder, not a file to write",
            path.display()
        )));
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    match std::fs::metadata(&dir) {
        Ok(m) if m.is_dir() => {
            if m.permissions().readonly() {
                Err(RenderError::Settings(format!(
                    "{}: folder is not writable",
                    dir.display()
                )))
            } else {
                Ok(())
            }
        }
        _ => Err(RenderError::Settings(format!(
            "{}: output folder does not exist",
            dir.display()
        ))),
    }
}

/// Loads, renders and writes, returning the statistics of the run.
pub fn render_in_process(config: &RenderConfig) -> Result<RenderStats, RenderError> {
    render_in_process_until(config, &Stop::default())
}

/// How a user's stop (Ctrl-C, SIGTERM) reaches a render in one process. Once rows are being
/// rendered it ends the render at the next row with the finished lines kept; before then
/// there is nothing to keep and nothing written, so whoever watches for the signal may end
/// the process at once, where loading and preparing a large scene took half a minute and
/// the signal waited for it.
#[derive(Default)]
pub struct Stop {
    requested: AtomicBool,
    rendering: AtomicBool,
}

impl Stop {
    /// Asks the render to stop; true while no row has been rendered (the process may end
    /// now, losing nothing).
    pub fn request(&self) -> bool {
        self.requested.store(true, Ordering::SeqCst);
        !self.rendering.load(Ordering::SeqCst)
    }
}

/// The finished rectangles of a render in progress, kept as a checkpoint and written to
/// disk now and then.
struct Keeper {
    checkpoint: Checkpoint,
    pending: Vec<u32>,
    path: PathBuf,
    last_write: Instant,
    interval: std::time::Duration,
    /// The first error writing the checkpoint; the render goes on, the user is told.
    failed: Option<CheckpointError>,
}

impl Keeper {
    fn take(&mut self, rect: renderer::Rect, pixels: &[[f32; 3]]) {
        self.checkpoint.put_rect(rect, pixels, &mut self.pending);
        if self.last_write.elapsed() >= self.interval {
            self.save();
        }
    }

    /// The render stopped before the image was whole: what is finished is kept on disk.
    fn ended_early(mut self, e: DataError) -> RenderError {
        self.save();
        match (e, self.failed) {
            // Interrupted with nothing kept: that the checkpoint failed is the news.
            (DataError::Cancelled, Some(failed)) => failed.into(),
            (DataError::Cancelled, None) => RenderError::Interrupted {
                kept: self.checkpoint.rows_finished(),
                height: self.checkpoint.image.height,
                path: self.path,
            },
            (e, _) => e.into(),
        }
    }

    fn save(&mut self) {
        self.last_write = Instant::now();
        if let Err(e) = self.checkpoint.write(&self.path)
            && self.failed.is_none()
        {
            tracing::warn!("cannot keep a checkpoint: {e}");
            self.failed = Some(e);
        }
    }
}

/// What the rendering threads report as they go: finished tiles into the checkpoint and the
/// progress bar, and a record of each tile's cost for the stats.
struct Watch<'a> {
    keeper: &'a Mutex<Keeper>,
    progress: Progress,
    done: AtomicU64,
    total: u64,
    /// When rendering began: records' times count from it.
    began: Instant,
    /// Per thread: when its current tile began (seconds since `began`) and its CPU time then.
    starts: Mutex<Vec<(f64, Duration)>>,
    records: Mutex<Vec<SubscreenRecord>>,
}

impl RectWatch for Watch<'_> {
    fn begin(&self, thread: usize, _rect: renderer::Rect) {
        let start = (self.began.elapsed().as_secs_f64(), thread_cpu_time());
        if let Some(s) = self.starts.lock().expect("starts lock").get_mut(thread) {
            *s = start;
        }
    }

    fn finished(&self, done: RectDone<'_>) {
        let (end_s, cpu) = (self.began.elapsed().as_secs_f64(), thread_cpu_time());
        let (start_s, cpu0) = self
            .starts
            .lock()
            .expect("starts lock")
            .get(done.thread)
            .copied()
            .unwrap_or_default();
        let rect = done.rect;
        self.records
            .lock()
            .expect("records lock")
            .push(SubscreenRecord {
                node: done.thread as u32,
                x: rect.x,
                y: rect.y,
                width: rect.width,
                height: rect.height,
                start_s,
                end_s,
                cpu_s: cpu.saturating_sub(cpu0).as_secs_f64(),
                pixels: done.trace.pixels,
                samples: done.trace.samples,
                rays: done.trace.rays(),
                chunks: done.chunks,
                tiles: done.tiles,
                ..Default::default()
            });
        self.keeper
            .lock()
            .expect("checkpoint lock")
            .take(rect, done.pixels);
        let n = rect.pixel_count() as u64;
        self.progress
            .update(self.done.fetch_add(n, Ordering::Relaxed) + n, self.total);
    }
}

/// A scene read and prepared, with the settings and camera it will be rendered with.
struct Prepared {
    scene: renderer::SceneHeader,
    data: renderer::MemoryData,
    settings: RenderSettings,
    camera: renderer::Camera,
    /// What the pixels depend on, for the checkpoint.
    key: CheckpointKey,
    triangles: u64,
}

/// The camera the render looks through, and the settings with the height the camera's
/// aspect ratio gives when none was asked for: the same in one process and on a cluster.
pub(crate) fn camera_and_settings(
    config: &RenderConfig,
    scene: &renderer::SceneHeader,
) -> Result<(RenderSettings, renderer::Camera), RenderError> {
    let mut settings = config.settings.clone();
    let aspect = settings.width as f32 / settings.height as f32;
    let camera = scene
        .camera(config.camera.as_deref(), aspect)
        .map_err(|e| RenderError::Settings(e.to_string()))?;
    if !config.height_given
        && let Some(a) = camera.aspect_ratio
    {
        settings.height =
            ((settings.width as f32 / a).round() as u32).clamp(1, renderer::MAX_IMAGE_SIDE);
    }
    Ok((settings, camera))
}

fn prepare(config: &RenderConfig) -> Result<Prepared, RenderError> {
    let (desc, warnings) = read_scene(&config.scene, config.environment)?;
    for w in &warnings {
        tracing::warn!("{}: {w}", config.scene);
    }
    let scene_sha256 = checkpoint::scene_digest(&desc);
    let (scene, data) = crate::large_pages::prepare(desc, &config.prepare);
    let triangles = scene.triangle_count();
    let (settings, camera) = camera_and_settings(config, &scene)?;
    let key = CheckpointKey::new(scene_sha256, &config.prepare, &settings, &camera);
    Ok(Prepared {
        scene,
        data,
        settings,
        camera,
        key,
        triangles,
    })
}

/// `image` denoised with guides traced through the scene from `camera`.
fn denoised<D: renderer::SceneData + Sync>(
    image: &renderer::Image,
    scene: &renderer::SceneHeader,
    data: &D,
    camera: &renderer::Camera,
    threads: usize,
) -> Result<renderer::Image, RenderError> {
    let t0 = Instant::now();
    let guides =
        renderer::denoise::guides(scene, data, camera, image.width, image.height, threads)?;
    let t1 = Instant::now();
    let denoised = renderer::denoise::denoise(image, &guides, threads);
    tracing::debug!(
        "denoiser: guides traced in {:.3} s, image filtered in {:.3} s",
        (t1 - t0).as_secs_f64(),
        t1.elapsed().as_secs_f64()
    );
    Ok(denoised)
}

/// As [`render_in_process`], stopping early (with the finished lines in the checkpoint)
/// once `stop` is requested.
pub fn render_in_process_until(
    config: &RenderConfig,
    stop: &Stop,
) -> Result<RenderStats, RenderError> {
    check_settings(config)?;
    let t0 = Instant::now();
    let Prepared {
        scene,
        data,
        settings,
        camera,
        key,
        triangles,
    } = prepare(config)?;
    let path = checkpoint::path_for(&config.output);
    let start = checkpoint::start(&path, config.resume, key, settings.width, settings.height)?;
    // From here (before the line saying the render begins) a stop ends the render through
    // its rows, the first of which checks for one, keeping what is finished.
    stop.rendering.store(true, Ordering::SeqCst);
    let load_s = t0.elapsed().as_secs_f64();
    tracing::info!(
        "{}: {} triangles in {} chunks, {} lights, {} textures; camera {:?}; {}x{} at {} spp ({})",
        config.scene,
        triangles,
        scene.chunks.len(),
        scene.lights.len(),
        scene.textures.len(),
        camera.name,
        settings.width,
        settings.height,
        settings.spp,
        settings.integrator
    );

    let total = settings.width as u64 * settings.height as u64;
    let already = start.rows_finished() as u64 * settings.width as u64;
    let rects = render::tiles_of_rows_left(settings.width, 16, &start.rows_done);
    let image = start.image.clone();
    let keeper = Mutex::new(Keeper {
        pending: start.pending(),
        checkpoint: start,
        path: path.clone(),
        last_write: Instant::now(),
        interval: config.checkpoint_interval,
        failed: None,
    });
    let t1 = Instant::now();
    let watch = Watch {
        keeper: &keeper,
        progress: Progress::new(total, config.progress),
        done: AtomicU64::new(already),
        total,
        began: t1,
        starts: Mutex::new(vec![(0.0, Duration::ZERO); config.threads.max(1)]),
        records: Mutex::new(Vec::new()),
    };
    let rendered = render::render_rects(
        &scene,
        &data,
        &camera,
        &settings,
        config.threads,
        &rects,
        image,
        &stop.requested,
        &watch,
    );
    let Watch {
        progress, records, ..
    } = watch;
    progress.finish();
    let (image, trace) = rendered.map_err(|e| keeper.into_inner().expect("lock").ended_early(e))?;
    let render_s = t1.elapsed().as_secs_f64();

    let t_denoise = Instant::now();
    let image = if config.denoise {
        denoised(&image, &scene, &data, &camera, config.threads)?
    } else {
        image
    };
    let denoise_s = t_denoise.elapsed().as_secs_f64();

    let t2 = Instant::now();
    scene_io::write_image(&config.output, &image)?;
    // The image is whole: its checkpoint, if one was written, has served.
    if path.exists() {
        let _ = std::fs::remove_file(&path);
    }
    let write_s = t2.elapsed().as_secs_f64();

    let mut stats = RenderStats {
        scene: config.scene.to_string(),
        output: config.output.display().to_string(),
        mode: "in-process".into(),
        width: settings.width,
        height: settings.height,
        spp: settings.spp,
        seed: settings.seed,
        integrator: settings.integrator.to_string(),
        threads: config.threads,
        triangles,
        chunks: scene.chunks.len(),
        shape_bytes: scene.shape_bytes,
        texture_tiles: scene.tile_count,
        subscreens: records.into_inner().expect("records lock"),
        chunk_bytes: stats::chunk_bytes(&scene),
        tile_bytes: stats::tile_bytes(&scene),
        ..Default::default()
    };
    stats.seconds.load = load_s;
    stats.seconds.render = render_s;
    stats.seconds.denoise = denoise_s;
    stats.seconds.write = write_s;
    stats.seconds.total = t0.elapsed().as_secs_f64();
    stats.set_trace(&trace);
    stats.peak_rss_bytes = fabric::peak_rss_bytes();
    if trace.bad_samples > 0 {
        tracing::warn!(
            "{} samples were NaN or infinite and counted as black",
            trace.bad_samples
        );
    }
    if let Some(p) = &config.stats {
        stats.write(p)?;
    }
    Ok(stats)
}
