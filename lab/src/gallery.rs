//! `magg-host gallery DIR -o sheet.png`: every scene of a folder rendered small, on one
//! contact sheet with its name underneath, to check many scenes at a glance (wrong-handed
//! normal maps, upside-down textures, missing transforms show up there).

use std::{
    path::{Path, PathBuf},
    sync::atomic::AtomicBool,
};

use plotters::prelude::*;
use renderer::{IntegratorKind, PrepareOptions, RenderSettings, render::render_image};

#[derive(Clone, Debug)]
pub struct GalleryConfig {
    pub dir: PathBuf,
    pub output: PathBuf,
    pub size: u32,
    pub spp: u32,
    pub integrator: IntegratorKind,
    pub columns: u32,
    pub threads: usize,
}

/// One tile of the sheet: a scene's picture, or why there is none.
pub struct Entry {
    pub name: String,
    pub pixels: Option<Vec<[f32; 3]>>,
    pub note: String,
    pub bad_samples: u64,
}

/// Every `.gltf` and `.glb` under `dir`, in name order, each folder walked once however
/// many links lead to it: a link to a folder above it (`ln -s . again`) made the walk go
/// round until the system's limit on links, listing the same scenes dozens of times, and
/// two such links never ended.
pub fn scene_files(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    let mut walked = std::collections::HashSet::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        // A folder's identity is its device and inode, whichever path reached it.
        let id = {
            use std::os::unix::fs::MetadataExt;
            let m = std::fs::metadata(&d)?;
            (m.dev(), m.ino())
        };
        if !walked.insert(id) {
            continue;
        }
        for e in std::fs::read_dir(&d)? {
            let p = e?.path();
            if p.is_dir() {
                stack.push(p);
            } else if matches!(
                p.extension()
                    .and_then(|e| e.to_str())
                    .map(str::to_ascii_lowercase)
                    .as_deref(),
                Some("gltf" | "glb")
            ) {
                out.push(p);
            }
        }
    }
    out.sort_by_key(|p| p.file_name().map(|n| n.to_string_lossy().to_lowercase()));
    Ok(out)
}

/// Renders one scene small; never fails, the entry says what went wrong.
pub fn render_entry(path: &Path, c: &GalleryConfig) -> Entry {
    let name = path
        .file_stem()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let loaded = match scene_io::load_gltf(path) {
        Ok(l) => l,
        Err(e) => {
            let why = match &e {
                scene_io::LoadError::UnsupportedRequiredExtension { extension, .. } => {
                    format!("refused: requires {extension}")
                }
                other => other.to_string(),
            };
            return Entry {
                name,
                pixels: None,
                note: why,
                bad_samples: 0,
            };
        }
    };
    let (scene, data) = renderer::prepare(loaded.desc, &PrepareOptions::default());
    let settings = RenderSettings {
        width: c.size,
        height: c.size,
        spp: c.spp,
        integrator: c.integrator,
        max_depth: 32,
        ..RenderSettings::default()
    };
    let camera = match scene.camera(None, 1.0) {
        Ok(cam) => cam,
        Err(e) => {
            return Entry {
                name,
                pixels: None,
                note: e.to_string(),
                bad_samples: 0,
            };
        }
    };
    match render_image(
        &scene,
        &data,
        &camera,
        &settings,
        c.threads,
        16,
        &AtomicBool::new(false),
        &|_, _| {},
    ) {
        Ok((img, stats)) => Entry {
            name,
            pixels: Some(img.pixels),
            note: if loaded.warnings.is_empty() {
                String::new()
            } else {
                format!("{} warning(s)", loaded.warnings.len())
            },
            bad_samples: stats.bad_samples,
        },
        Err(e) => Entry {
            name,
            pixels: None,
            note: e.to_string(),
            bad_samples: 0,
        },
    }
}

/// A contact sheet's longest side, as a render's.
const MAX_SHEET_SIDE: u64 = renderer::MAX_IMAGE_SIDE as u64;

/// Lays the entries out on a sheet and writes it as PNG.
pub fn write_sheet(entries: &[Entry], c: &GalleryConfig) -> Result<(), crate::LabError> {
    // More columns than pictures only widen the sheet with empty cells.
    let cols = c.columns.clamp(1, (entries.len() as u32).max(1));
    let rows = (entries.len() as u32).div_ceil(cols).max(1);
    let label = 34;
    // The sheet's sides in u64, so that a large --size or many pictures are refused below
    // instead of wrapping.
    let (cell_w, cell_h) = (u64::from(c.size) + 8, u64::from(c.size) + label);
    let (w64, h64) = (u64::from(cols) * cell_w + 8, u64::from(rows) * cell_h + 8);
    if w64 > MAX_SHEET_SIDE || h64 > MAX_SHEET_SIDE {
        return Err(crate::LabError::Settings(format!(
            "a contact sheet of {w64}x{h64} pixels ({} pictures of {} pixels, {cols} columns): \
             at most {MAX_SHEET_SIDE} a side; use a smaller --size or other --columns",
            entries.len(),
            c.size
        )));
    }
    let (w, h, cell_w, cell_h) = (w64 as u32, h64 as u32, cell_w as u32, cell_h as u32);
    let mut buf = vec![40u8; w as usize * h as usize * 3];
    for (i, e) in entries.iter().enumerate() {
        let (cx, cy) = (
            8 + (i as u32 % cols) * cell_w,
            8 + (i as u32 / cols) * cell_h,
        );
        if let Some(px) = &e.pixels {
            for y in 0..c.size {
                for x in 0..c.size {
                    let p = px[(y * c.size + x) as usize];
                    let at = (((cy + y) * w + cx + x) * 3) as usize;
                    for k in 0..3 {
                        buf[at + k] = scene_io::image_io::to_srgb8(p[k]);
                    }
                }
            }
        }
    }
    let have_font = crate::plot::ensure_font();
    if have_font {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        for (i, e) in entries.iter().enumerate() {
            let (cx, cy) = (
                (8 + (i as u32 % cols) * cell_w) as i32,
                (8 + (i as u32 / cols) * cell_h) as i32,
            );
            let style = ("sans-serif", 13).into_font().color(&WHITE);
            let name: String = e.name.chars().take(26).collect();
            root.draw_text(&name, &style, (cx, cy + c.size as i32 + 2))
                .map_err(crate::LabError::draw)?;
            let mut note = e.note.clone();
            if e.bad_samples > 0 {
                note = format!("{} NaN/inf samples! {note}", e.bad_samples);
            }
            if !note.is_empty() {
                let color = if e.pixels.is_none() || e.bad_samples > 0 {
                    RGBColor(255, 120, 100)
                } else {
                    RGBColor(180, 180, 180)
                };
                let small = ("sans-serif", 11).into_font().color(&color);
                let note: String = note.chars().take(32).collect();
                root.draw_text(&note, &small, (cx, cy + c.size as i32 + 17))
                    .map_err(crate::LabError::draw)?;
            }
        }
        root.present().map_err(crate::LabError::draw)?;
    }
    crate::plot::write_png(&c.output, w, h, &buf)
}

/// Renders every scene of the folder and writes the sheet; returns the entries.
pub fn gallery(c: &GalleryConfig, progress: &dyn Fn(&str)) -> Result<Vec<Entry>, crate::LabError> {
    let files = scene_files(&c.dir).map_err(|source| crate::LabError::Folder {
        path: c.dir.clone(),
        source,
    })?;
    if files.is_empty() {
        return Err(crate::LabError::NoScenes(c.dir.clone()));
    }
    // The sheet is written last: over a scene or its data, it would lose them after every
    // render had read them.
    let data: Vec<_> = files.iter().map(|f| scene_io::files_named(f)).collect();
    use host::inprocess::FileUse::{Read, Written};
    let named = std::iter::once(("the sheet (-o)", Some(c.output.as_path()), Written))
        .chain(files.iter().map(|f| ("a scene", Some(f.as_path()), Read)))
        .chain(
            data.iter()
                .flatten()
                .map(|p| ("a file a scene reads", Some(p.as_path()), Read)),
        );
    host::inprocess::refuse_same_files(&named.collect::<Vec<_>>())
        .map_err(crate::LabError::Settings)?;
    let mut entries = Vec::new();
    for f in &files {
        progress(&f.display().to_string());
        entries.push(render_entry(f, c));
    }
    write_sheet(&entries, c)?;
    Ok(entries)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(dir: &Path, size: u32, columns: u32) -> GalleryConfig {
        GalleryConfig {
            dir: dir.to_path_buf(),
            output: dir.join("sheet.png"),
            size,
            spp: 1,
            integrator: IntegratorKind::Path,
            columns,
            threads: 1,
        }
    }

    fn entry(size: u32) -> Entry {
        Entry {
            name: "a".into(),
            pixels: Some(vec![[0.5; 3]; (size * size) as usize]),
            note: String::new(),
            bad_samples: 0,
        }
    }

    /// A link back to the folder itself or to its parent lists each scene once (such links
    /// listed scenes dozens of times, or never ended).
    #[test]
    fn folders_reached_again_through_links_are_walked_once() {
        let dir = std::env::temp_dir().join(format!("magg-gallery-loop-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        std::fs::write(dir.join("a.gltf"), "{}").unwrap();
        std::fs::write(dir.join("sub/b.glb"), "").unwrap();
        std::os::unix::fs::symlink(".", dir.join("again")).unwrap();
        std::os::unix::fs::symlink("..", dir.join("sub/up")).unwrap();
        let names: Vec<String> = scene_files(&dir)
            .unwrap()
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["a.gltf", "b.glb"]);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// More columns than pictures make a sheet as wide as the pictures (a million columns
    /// wrapped the sheet's size and indexed past its buffer); a sheet too large to write is
    /// refused with its size, not allocated.
    #[test]
    fn columns_beyond_the_pictures_and_sheets_too_large_are_handled() {
        let dir = std::env::temp_dir().join(format!("magg-gallery-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let c = config(&dir, 4, 1_028_489);
        write_sheet(&[entry(4), entry(4)], &c).unwrap();
        let (w, h) = image::image_dimensions(&c.output).unwrap();
        assert_eq!((w, h), (2 * (4 + 8) + 8, 4 + 34 + 8));
        let e = write_sheet(&[entry(4)], &config(&dir, 40_000, 7)).unwrap_err();
        assert!(e.to_string().contains("at most 32768 a side"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
