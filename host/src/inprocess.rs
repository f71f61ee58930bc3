//! Rendering in this one process, on all its cores: the reference every cluster render must
//! match byte for byte.

use std::{path::PathBuf, sync::atomic::AtomicBool, time::Instant};

use renderer::{DataError, PrepareOptions, RenderSettings, render::render_image};

use crate::{
    progress::Progress,
    scene_source::{SceneSource, load_scene},
    stats::RenderStats,
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
    if s.width > 32768 || s.height > 32768 {
        return bad(format!(
            "image size {}x{} is too large (at most 32768 a side)",
            s.width, s.height
        ));
    }
    if s.spp == 0 {
        return bad("--spp must be at least 1".into());
    }
    if !(s.noise_threshold >= 0.0 && s.noise_threshold.is_finite()) {
        return bad("--noise-threshold must be a number of at least 0".into());
    }
    check_output(&config.output)?;
    if let Some(p) = &config.stats {
        check_writable_dir(p)?;
    }
    Ok(())
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
    check_settings(config)?;
    let t0 = Instant::now();
    let loaded = load_scene(&config.scene, &config.prepare, config.environment)?;
    for w in &loaded.warnings {
        tracing::warn!("{}: {w}", config.scene);
    }
    let mut settings = config.settings.clone();
    let aspect = settings.width as f32 / settings.height as f32;
    let camera = loaded
        .scene
        .camera(config.camera.as_deref(), aspect)
        .map_err(|e| RenderError::Settings(e.to_string()))?;
    if !config.height_given
        && let Some(a) = camera.aspect_ratio
    {
        settings.height = ((settings.width as f32 / a).round() as u32).clamp(1, 32768);
    }
    let load_s = t0.elapsed().as_secs_f64();
    tracing::info!(
        "{}: {} triangles in {} chunks, {} lights, {} textures; camera {:?}; {}x{} at {} spp ({})",
        config.scene,
        loaded.triangles,
        loaded.scene.chunks.len(),
        loaded.scene.lights.len(),
        loaded.scene.textures.len(),
        camera.name,
        settings.width,
        settings.height,
        settings.spp,
        settings.integrator
    );

    let total = settings.width as u64 * settings.height as u64;
    let progress = Progress::new(total, config.progress);
    let cancel = AtomicBool::new(false);
    let t1 = Instant::now();
    let (image, trace) = render_image(
        &loaded.scene,
        &loaded.data,
        &camera,
        &settings,
        config.threads,
        16,
        &cancel,
        &|done, total| progress.update(done, total),
    )?;
    progress.finish();
    let render_s = t1.elapsed().as_secs_f64();

    let t2 = Instant::now();
    scene_io::write_image(&config.output, &image)?;
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
        triangles: loaded.triangles,
        chunks: loaded.scene.chunks.len(),
        shape_bytes: loaded.scene.shape_bytes,
        texture_tiles: loaded.scene.tile_count,
        ..Default::default()
    };
    stats.seconds.load = load_s;
    stats.seconds.render = render_s;
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
