//! `magg-host bench whitted`: the Whitted integrator's cost and its pruning's error, scene by
//! scene, so that no scene file can make the paper's integrator run away unnoticed.
//!
//! Every glTF file under a folder is rendered in one process with the path tracer and with
//! the Whitted tracer at the same size and samples, and the two render times compared. On
//! scenes with glass (any material that transmits), Whitted is rendered once more with ten
//! times tighter pruning and twice the ray budget, and the relative MSE between the two says
//! what the defaults' pruning costs. Last, a deliberately hostile scene: a hundred nested
//! glass shells.

use std::{path::PathBuf, sync::atomic::AtomicBool, time::Instant};

use renderer::{
    Image, IntegratorKind, MemoryData, PrepareOptions, RenderSettings, SceneHeader,
    integrator::WhittedLimits, render::render_image, trace::TraceStats,
};
use serde::Serialize;

#[derive(Clone, Debug)]
pub struct WhittedConfig {
    /// Every `.gltf` and `.glb` below this folder.
    pub scenes: PathBuf,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub threads: usize,
}

#[derive(Clone, Debug, Serialize)]
pub struct SceneRow {
    pub scene: String,
    pub triangles: u64,
    pub path_seconds: f64,
    pub whitted_seconds: f64,
    /// Whitted's time over the path tracer's.
    pub ratio: f64,
    /// Reflected and refracted rays per camera ray.
    pub specular_rays_per_camera_ray: f64,
    /// Scenes with glass: relMSE of the default Whitted image against one with ten times
    /// tighter pruning and twice the ray budget.
    pub pruning_rel_mse: Option<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct HostileRow {
    pub shells: u32,
    pub width: u32,
    pub height: u32,
    pub seconds: f64,
    pub specular_rays_per_camera_ray: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct WhittedReport {
    pub rows: Vec<SceneRow>,
    /// Files that did not load, with the loader's reason.
    pub refused: Vec<(String, String)>,
    pub hostile: HostileRow,
}

#[derive(Debug, thiserror::Error)]
pub enum WhittedBenchError {
    #[error("reading the scene folder {path}: {source}")]
    Folder {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("no .gltf or .glb file under {0}")]
    NoScenes(PathBuf),
    #[error("rendering {scene}: {source}")]
    Render {
        scene: String,
        source: RenderFailure,
    },
}

/// Why one scene of the benchmark could not be rendered or compared.
#[derive(Debug, thiserror::Error)]
pub enum RenderFailure {
    #[error(transparent)]
    Camera(#[from] renderer::scene::SceneError),
    #[error(transparent)]
    Data(#[from] renderer::DataError),
    #[error(transparent)]
    Compare(#[from] crate::compare::SizeMismatch),
}

fn render(
    scene: &SceneHeader,
    data: &MemoryData,
    settings: &RenderSettings,
    threads: usize,
) -> Result<(Image, TraceStats, f64), RenderFailure> {
    let camera = scene.camera(None, settings.width as f32 / settings.height as f32)?;
    let start = Instant::now();
    let (img, stats) = render_image(
        scene,
        data,
        &camera,
        settings,
        threads,
        16,
        &AtomicBool::new(false),
        &|_, _| {},
    )?;
    Ok((img, stats, start.elapsed().as_secs_f64()))
}

fn specular_per_camera_ray(s: &TraceStats) -> f64 {
    s.secondary_rays as f64 / s.camera_rays.max(1) as f64
}

/// Runs the whole benchmark; `progress` hears one line per scene.
pub fn run(
    cfg: &WhittedConfig,
    progress: &dyn Fn(&str),
) -> Result<WhittedReport, WhittedBenchError> {
    let files =
        crate::gallery::scene_files(&cfg.scenes).map_err(|source| WhittedBenchError::Folder {
            path: cfg.scenes.clone(),
            source,
        })?;
    if files.is_empty() {
        return Err(WhittedBenchError::NoScenes(cfg.scenes.clone()));
    }
    let base = RenderSettings {
        width: cfg.width,
        height: cfg.height,
        spp: cfg.spp,
        ..RenderSettings::default()
    };
    let path_settings = RenderSettings {
        integrator: IntegratorKind::Path,
        max_depth: IntegratorKind::Path.default_max_depth(),
        ..base.clone()
    };
    let whitted_settings = RenderSettings {
        integrator: IntegratorKind::Whitted,
        max_depth: IntegratorKind::Whitted.default_max_depth(),
        ..base
    };
    let defaults = WhittedLimits::default();
    let tight_settings = RenderSettings {
        whitted: WhittedLimits {
            min_contribution: defaults.min_contribution / 10.0,
            max_specular_rays: defaults.max_specular_rays * 2,
        },
        ..whitted_settings.clone()
    };
    let mut rows = Vec::new();
    let mut refused = Vec::new();
    for f in files {
        let name = f
            .strip_prefix(&cfg.scenes)
            .unwrap_or(&f)
            .display()
            .to_string();
        let loaded = match scene_io::load_gltf(&f) {
            Ok(l) => l,
            Err(e) => {
                progress(&format!("{name}: refused by the loader: {e}"));
                refused.push((name, e.to_string()));
                continue;
            }
        };
        let triangles = loaded.desc.triangle_count() as u64;
        let has_glass = loaded.desc.materials.iter().any(|m| m.transmission > 0.0);
        let (scene, data) = renderer::prepare(loaded.desc, &PrepareOptions::default());
        let fail = |source: RenderFailure| WhittedBenchError::Render {
            scene: name.clone(),
            source,
        };
        let (_, _, path_seconds) =
            render(&scene, &data, &path_settings, cfg.threads).map_err(fail)?;
        let (img, stats, whitted_seconds) =
            render(&scene, &data, &whitted_settings, cfg.threads).map_err(fail)?;
        let pruning_rel_mse = if has_glass {
            let (tight, _, _) =
                render(&scene, &data, &tight_settings, cfg.threads).map_err(fail)?;
            Some(
                crate::compare::compare(&img, &tight)
                    .map_err(|e| fail(e.into()))?
                    .rel_mse,
            )
        } else {
            None
        };
        let row = SceneRow {
            scene: name,
            triangles,
            path_seconds,
            whitted_seconds,
            ratio: whitted_seconds / path_seconds.max(1e-9),
            specular_rays_per_camera_ray: specular_per_camera_ray(&stats),
            pruning_rel_mse,
        };
        progress(&format!(
            "{}: path {:.2} s, whitted {:.2} s ({:.2}x), {:.1} specular rays a camera ray{}",
            row.scene,
            row.path_seconds,
            row.whitted_seconds,
            row.ratio,
            row.specular_rays_per_camera_ray,
            row.pruning_rel_mse
                .map(|e| format!(", pruning relMSE {e:.2e}"))
                .unwrap_or_default()
        ));
        rows.push(row);
    }

    let shells = 100;
    let (scene, data) = renderer::prepare(
        renderer::demo::glass_shells(shells),
        &PrepareOptions::default(),
    );
    let hostile_settings = RenderSettings {
        width: 64,
        height: 64,
        spp: 1,
        ..whitted_settings
    };
    let (_, stats, seconds) =
        render(&scene, &data, &hostile_settings, cfg.threads).map_err(|source| {
            WhittedBenchError::Render {
                scene: "glass shells".into(),
                source,
            }
        })?;
    let hostile = HostileRow {
        shells,
        width: hostile_settings.width,
        height: hostile_settings.height,
        seconds,
        specular_rays_per_camera_ray: specular_per_camera_ray(&stats),
    };
    Ok(WhittedReport {
        rows,
        refused,
        hostile,
    })
}
