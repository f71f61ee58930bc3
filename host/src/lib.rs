//! The host role (the paper's HP): reads the scene from disk, renders it in this process
//! (`inprocess`) or hands the work out to a cluster (`distributed`, `cluster`, `spawn`), and
//! saves the image. The lab (benchmarks, experiments, plots) is the `lab` crate, beside it.

pub mod checkpoint;
pub mod cluster;
pub mod distributed;
pub mod inprocess;
pub mod large_pages;
pub mod progress;
mod recovery;
pub mod scene_source;
pub mod schedule;
pub mod spawn;
pub mod stats;

pub use inprocess::{RenderConfig, RenderError, render_in_process};
pub use scene_source::{SceneSource, load_scene};
