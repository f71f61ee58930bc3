//! magg's renderer core: everything needed to turn a scene into pixels, and nothing that
//! touches a file or a socket.
//!
//! The shape data lives in [`chunk::Chunk`]s (flat byte blocks with their own BVH) that the
//! renderer reads through the [`source::SceneData`] trait, so the same code renders from
//! memory in one process and from a demand-filled cache on a render node.

pub mod accel;
pub mod bsdf;
pub mod bvh;
pub mod camera;
pub mod chunk;
pub mod demo;
pub mod denoise;
mod diffuse_wave;
pub mod integrator;
pub mod light;
pub mod material;
pub mod math;
pub mod ray;
pub mod region;
pub mod render;
pub mod sampler;
pub mod scene;
pub mod simd;
pub mod source;
#[cfg(test)]
mod testing;
pub mod texture;
pub mod trace;
pub mod triangle;

pub use camera::{Camera, Projection};
pub use integrator::IntegratorKind;
pub use render::{Image, MAX_IMAGE_SIDE, Rect, RenderSettings};
pub use scene::{
    MakeBlock, PrepareOptions, SceneDesc, SceneHeader, prepare, prepare_flat, prepare_with,
};
pub use source::{DataError, MemoryData, SceneData};
