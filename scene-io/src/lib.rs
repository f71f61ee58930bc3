//! Files in and out: glTF 2.0 scenes become [`renderer::SceneDesc`]s, rendered images become
//! PNG, OpenEXR or PFM files. Everything here treats its input as hostile: a malformed file
//! is an error naming the file and the problem, never a panic.

pub mod gltf_load;
pub mod image_io;

pub use gltf_load::{LoadError, Loaded, files_named, load_gltf};
pub use image_io::{ImageError, read_image, write_image};
