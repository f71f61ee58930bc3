//! The host role (the paper's HP): reads the scene from disk, renders it in this process
//! (`inprocess`) or hands the work out to a cluster (`distributed`, `cluster`, `spawn`), and
//! saves the image. It also carries, for now, the lab: `bench`, `gallery`, `experiment`,
//! `runs`, `plot`, whose errors are [`LabError`].

pub mod bench;
pub mod cluster;
pub mod compare;
pub mod distributed;
pub mod experiment;
pub mod gallery;
pub mod inprocess;
pub mod plot;
pub mod progress;
pub mod runs;
pub mod scene_source;
pub mod schedule;
pub mod spawn;
pub mod stats;

pub use inprocess::{RenderConfig, RenderError, render_in_process};
pub use scene_source::{SceneSource, load_scene};

/// Why a lab command (bench, gallery, plots) could not finish.
#[derive(Debug, thiserror::Error)]
pub enum LabError {
    #[error(transparent)]
    Load(#[from] scene_io::LoadError),
    #[error(transparent)]
    Image(#[from] scene_io::ImageError),
    #[error("rendering failed: {0}")]
    Render(#[from] renderer::DataError),
    #[error("encoding a PNG: {0}")]
    Encode(#[from] image::ImageError),
    #[error("{0}")]
    Camera(String),
    /// The plotting library's own error, as it words it (its types are generic per backend).
    #[error("drawing: {0}")]
    Draw(String),
    #[error("nothing to plot")]
    NothingToPlot,
    #[error("{path}: {source}")]
    Folder {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("{0}: no .gltf or .glb files")]
    NoScenes(std::path::PathBuf),
}

impl LabError {
    /// For `map_err` on a plotting call.
    pub fn draw(e: impl std::fmt::Display) -> LabError {
        LabError::Draw(e.to_string())
    }
}
