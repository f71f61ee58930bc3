//! Where the scene comes from: a glTF file, or the built-in demo.

use std::path::PathBuf;

use renderer::{MemoryData, PrepareOptions, SceneDesc, SceneHeader, demo};

#[derive(Clone, Debug, PartialEq)]
pub enum SceneSource {
    Demo,
    File(PathBuf),
}

impl std::fmt::Display for SceneSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SceneSource::Demo => f.write_str("built-in demo scene"),
            SceneSource::File(p) => write!(f, "{}", p.display()),
        }
    }
}

/// A scene ready to render, with what the loader had to say about it.
pub struct LoadedScene {
    pub scene: SceneHeader,
    pub data: MemoryData,
    pub warnings: Vec<String>,
    pub triangles: u64,
}

/// Reads a scene description (the host's "reads the scene from disk"), with the
/// environment set when the user gave one.
pub fn read_scene(
    source: &SceneSource,
    environment: Option<renderer::light::Environment>,
) -> Result<(SceneDesc, Vec<String>), scene_io::LoadError> {
    let (mut desc, warnings) = match source {
        SceneSource::Demo => (demo::demo_scene(), Vec::new()),
        SceneSource::File(path) => {
            let loaded = scene_io::load_gltf(path)?;
            (loaded.desc, loaded.warnings)
        }
    };
    if environment.is_some() {
        desc.environment = environment;
    }
    Ok((desc, warnings))
}

/// Loads and prepares a scene (chunks, both BVH levels, lights, texture tiles).
pub fn load_scene(
    source: &SceneSource,
    opts: &PrepareOptions,
    environment: Option<renderer::light::Environment>,
) -> Result<LoadedScene, scene_io::LoadError> {
    let (desc, warnings) = read_scene(source, environment)?;
    let (scene, data) = crate::large_pages::prepare(desc, opts);
    let triangles = scene.triangle_count();
    Ok(LoadedScene {
        scene,
        data,
        warnings,
        triangles,
    })
}
