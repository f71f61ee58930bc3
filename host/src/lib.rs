//! The host role (the paper's HP): reads the scene from disk, hands the work out, and saves
//! the image. For now it renders in its own process; the cluster modes build on the same
//! scene loading, settings and output.

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
pub mod spawn;
pub mod stats;

pub use inprocess::{RenderConfig, RenderError, render_in_process};
pub use scene_source::{SceneSource, load_scene};
