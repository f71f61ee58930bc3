//! The lab: what measures magg rather than runs it. Benchmarks (`bench`, `raybench`,
//! `whittedbench`), the paper's experiments (`experiment`, `runs`, `balance`,
//! `convergence`), the simulator run on a render's stats (`simulate`), the gallery of shared
//! scenes, plots (`plot`; `timeline` draws one render from its stats' records) and image
//! comparison. It stands apart from the roles so that the host, fork node and render node
//! libraries carry only what a cluster needs; it uses them the way a user would (whole
//! renders, real clusters, the render node's cache).

pub mod all;
pub mod balance;
pub mod bench;
pub mod compare;
pub mod convergence;
pub mod experiment;
pub mod gallery;
pub mod plot;
pub mod raybench;
pub mod runs;
pub mod scaling;
pub mod simulate;
pub mod timeline;
pub mod validate;
pub mod whittedbench;

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
    #[error(transparent)]
    Camera(#[from] renderer::scene::SceneError),
    /// The plotting library's own error, as it words it (its types are generic per backend).
    #[error("drawing: {0}")]
    Draw(String),
    #[error(transparent)]
    Run(#[from] runs::RunError),
    #[error("{} against the reference: {source}", path.display())]
    Compare {
        path: std::path::PathBuf,
        source: compare::SizeMismatch,
    },
    #[error(transparent)]
    Simulate(#[from] simulate::SimulateError),
    #[error("nothing to plot")]
    NothingToPlot,
    #[error("{path}: {source}")]
    Folder {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    /// A `--stats` file that cannot be plotted, and why.
    #[error("{path}: {reason}")]
    Stats {
        path: std::path::PathBuf,
        reason: String,
    },
    #[error("{0}: no .gltf or .glb files")]
    NoScenes(std::path::PathBuf),
    /// Settings a measurement cannot be made with, and why.
    #[error("{0}")]
    Settings(String),
}

impl LabError {
    /// For `map_err` on a plotting call.
    pub fn draw(e: impl std::fmt::Display) -> LabError {
        LabError::Draw(e.to_string())
    }

    /// For `map_err` on a file or folder operation under `path`.
    pub fn folder(path: &std::path::Path) -> impl Fn(std::io::Error) -> LabError + Copy + '_ {
        move |source| LabError::Folder {
            path: path.to_path_buf(),
            source,
        }
    }
}
