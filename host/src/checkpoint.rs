//! The checkpoint of a render in progress, so that nothing finished is lost to a crash, a
//! Ctrl-C, a power cut or the loss of the only fork node.
//!
//! Beside the output `OUT` the host keeps `OUT.partial`: the finished scan lines and what
//! they were rendered from (a hash of the scene description and preparation options, the
//! settings and the camera). `magg-host render ... --resume` reads it back and renders only
//! the rows it lacks, on any cluster or in one process; since every pixel depends only on
//! the scene, the settings and the pixel, the final image is the same bytes as an
//! uninterrupted render. A checkpoint made from anything else is refused with what differs.
//!
//! The file is replaced atomically (written beside, synced, renamed), ends with a SHA-256 of
//! everything before it, and is read with every length checked, so a torn or foreign file
//! is an error that says so, never a wrong image.
//!
//! Layout, little-endian: the 8-byte magic `MAGGPART`; a u32 length and that many bytes of
//! JSON (the key, the image size, the format version); one byte per scan line, 1 where the
//! line is finished; the finished lines' pixels in order, `width * 3` f32 each; the SHA-256.

use std::{
    io::Write,
    path::{Path, PathBuf},
    time::Duration,
};

use renderer::{Camera, Image, PrepareOptions, RenderSettings, SceneDesc};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

const MAGIC: &[u8; 8] = b"MAGGPART";
const FORMAT: u32 = 1;
/// The header is a few hundred bytes; more is not a checkpoint.
const MAX_HEADER: usize = 1 << 20;

/// How often a render in progress replaces its checkpoint, by default: often enough that a
/// crash loses little, rarely enough that writing it costs nothing to speak of.
pub const DEFAULT_INTERVAL: Duration = Duration::from_secs(10);

/// What the pixels of a render depend on. Two renders with equal keys make the same bytes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CheckpointKey {
    /// SHA-256 of the scene description as the host read it (environment included), in hex.
    pub scene_sha256: String,
    pub chunk_triangles: usize,
    /// The settings and the camera, as JSON values, so that a mismatch can be named field by
    /// field.
    pub settings: serde_json::Value,
    pub camera: serde_json::Value,
}

/// SHA-256 of a scene description, in hex: what a checkpoint's scene is known by.
pub fn scene_digest(desc: &SceneDesc) -> String {
    digest_of_encoded(&protocol::encode_value(desc))
}

/// [`scene_digest`] of a description already encoded with `protocol::encode_value` (as the
/// cluster render does to send it), so that it is not encoded twice.
pub fn digest_of_encoded(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

impl CheckpointKey {
    pub fn new(
        scene_sha256: String,
        prepare: &PrepareOptions,
        settings: &RenderSettings,
        camera: &Camera,
    ) -> CheckpointKey {
        CheckpointKey {
            scene_sha256,
            chunk_triangles: prepare.chunk_triangles,
            settings: serde_json::to_value(settings).unwrap_or_default(),
            camera: serde_json::to_value(camera).unwrap_or_default(),
        }
    }

    /// The first difference from `other`, in words; `None` if the keys are equal.
    fn difference(&self, other: &CheckpointKey) -> Option<String> {
        if self.scene_sha256 != other.scene_sha256 {
            return Some("it was made from another scene (or another --environment)".into());
        }
        if self.chunk_triangles != other.chunk_triangles {
            return Some(format!(
                "it was made with --chunk-triangles {}, this render has {}",
                self.chunk_triangles, other.chunk_triangles
            ));
        }
        for (what, a, b) in [
            ("setting", &self.settings, &other.settings),
            ("camera", &self.camera, &other.camera),
        ] {
            if a == b {
                continue;
            }
            let field = match (a.as_object(), b.as_object()) {
                (Some(x), Some(y)) => {
                    x.iter().find(|(k, v)| y.get(*k) != Some(*v)).map(|(k, v)| {
                        format!(
                            "{what} {k} was {v}, this render has {}",
                            y.get(k).unwrap_or(&serde_json::Value::Null)
                        )
                    })
                }
                _ => None,
            };
            return Some(field.unwrap_or_else(|| format!("the {what}s differ")));
        }
        None
    }
}

#[derive(Serialize, Deserialize)]
struct Header {
    format: u32,
    key: CheckpointKey,
    width: u32,
    height: u32,
}

/// Why a checkpoint could not be read, used or written.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: not a magg checkpoint, or damaged ({why})", path.display())]
    Damaged { path: PathBuf, why: String },
    #[error("{}: made by checkpoint format {found}, this build reads format {FORMAT}", path.display())]
    Format { path: PathBuf, found: u32 },
    #[error("{}: cannot resume from it: {why}", path.display())]
    Mismatch { path: PathBuf, why: String },
    #[error(
        "{}: holds an interrupted render; add --resume to continue it, or delete the file to start again",
        path.display()
    )]
    Exists { path: PathBuf },
}

/// `OUT.partial` for the output `OUT`.
pub fn path_for(output: &Path) -> PathBuf {
    let mut name = output.as_os_str().to_os_string();
    name.push(".partial");
    PathBuf::from(name)
}

/// The finished scan lines of a render and their pixels.
#[derive(Clone, Debug)]
pub struct Checkpoint {
    pub key: CheckpointKey,
    pub image: Image,
    /// Per scan line, whether it is finished (its pixels in `image` are final).
    pub rows_done: Vec<bool>,
}

impl Checkpoint {
    /// A render with nothing finished yet.
    pub fn empty(key: CheckpointKey, width: u32, height: u32) -> Checkpoint {
        Checkpoint {
            key,
            image: Image::new(width, height),
            rows_done: vec![false; height as usize],
        }
    }

    /// Takes a finished rectangle's pixels; `pending[y]` counts the pixels of line `y` not
    /// yet in, and a line is finished when it reaches 0.
    pub fn put_rect(&mut self, rect: renderer::Rect, pixels: &[[f32; 3]], pending: &mut [u32]) {
        self.image.put_rect(rect, pixels);
        for y in rect.y..rect.y + rect.height {
            let left = &mut pending[y as usize];
            *left = left.saturating_sub(rect.width);
            if *left == 0 {
                self.rows_done[y as usize] = true;
            }
        }
    }

    /// Per line, the pixels not yet in (0 for finished lines): the `pending` of `put_rect`.
    pub fn pending(&self) -> Vec<u32> {
        self.rows_done
            .iter()
            .map(|&d| if d { 0 } else { self.image.width })
            .collect()
    }

    pub fn rows_finished(&self) -> usize {
        self.rows_done.iter().filter(|&&d| d).count()
    }

    /// Replaces the file at `path` with this checkpoint, atomically: a reader (or a crash)
    /// sees the old file or the new one, never a mix.
    pub fn write(&self, path: &Path) -> Result<(), CheckpointError> {
        write(path, &self.key, &self.image, &self.rows_done)
    }

    /// Reads and checks a checkpoint file's bytes (its key is not compared here).
    fn decode(path: &Path, bytes: &[u8]) -> Result<Checkpoint, CheckpointError> {
        let damaged = |why: &str| CheckpointError::Damaged {
            path: path.to_path_buf(),
            why: why.to_string(),
        };
        if bytes.len() < MAGIC.len() + 4 + 32 || &bytes[..8] != MAGIC {
            return Err(damaged("no magg checkpoint header"));
        }
        let (body, digest) = bytes.split_at(bytes.len() - 32);
        if Sha256::digest(body).as_slice() != digest {
            return Err(damaged(
                "its checksum does not match: the file was cut short or changed",
            ));
        }
        let len = u32::from_le_bytes(body[8..12].try_into().unwrap_or_default()) as usize;
        if len > MAX_HEADER || 12 + len > body.len() {
            return Err(damaged("header length out of range"));
        }
        let header: Header = serde_json::from_slice(&body[12..12 + len])
            .map_err(|e| damaged(&format!("header: {e}")))?;
        if header.format != FORMAT {
            return Err(CheckpointError::Format {
                path: path.to_path_buf(),
                found: header.format,
            });
        }
        let (w, h) = (header.width as usize, header.height as usize);
        let most = renderer::MAX_IMAGE_SIDE as usize;
        if w == 0 || h == 0 || w > most || h > most {
            return Err(damaged("image size out of range"));
        }
        let rest = &body[12 + len..];
        if rest.len() < h {
            return Err(damaged("the scan-line table is cut short"));
        }
        let (table, mut pixels) = rest.split_at(h);
        if table.iter().any(|&b| b > 1) {
            return Err(damaged(
                "the scan-line table holds values other than 0 and 1",
            ));
        }
        let rows_done: Vec<bool> = table.iter().map(|&b| b == 1).collect();
        let finished = rows_done.iter().filter(|&&d| d).count();
        if pixels.len() != finished * w * 12 {
            return Err(damaged(
                "the pixel data does not match the finished scan lines",
            ));
        }
        let mut image = Image::new(header.width, header.height);
        for (y, _) in rows_done.iter().enumerate().filter(|(_, d)| **d) {
            let (row, more) = pixels.split_at(w * 12);
            pixels = more;
            for (p, c) in image.pixels[y * w..(y + 1) * w]
                .iter_mut()
                .zip(row.chunks_exact(12))
            {
                for (k, v) in c.chunks_exact(4).enumerate() {
                    p[k] = f32::from_le_bytes(v.try_into().unwrap_or_default());
                }
            }
        }
        Ok(Checkpoint {
            key: header.key,
            image,
            rows_done,
        })
    }

    /// Reads the checkpoint at `path` for a render with `key`; refuses one made from
    /// anything else, saying what differs.
    pub fn resume(path: &Path, key: &CheckpointKey) -> Result<Checkpoint, CheckpointError> {
        let bytes = std::fs::read(path).map_err(|source| CheckpointError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let c = Checkpoint::decode(path, &bytes)?;
        if let Some(why) = c.key.difference(key) {
            return Err(CheckpointError::Mismatch {
                path: path.to_path_buf(),
                why,
            });
        }
        let (w, h) = (
            key.settings["width"].as_u64().unwrap_or(0),
            key.settings["height"].as_u64().unwrap_or(0),
        );
        if (c.image.width as u64, c.image.height as u64) != (w, h) {
            return Err(CheckpointError::Mismatch {
                path: path.to_path_buf(),
                why: format!(
                    "its image is {}x{}, this render's {w}x{h}",
                    c.image.width, c.image.height
                ),
            });
        }
        Ok(c)
    }
}

/// The file's bytes, the digest last.
fn encode(key: &CheckpointKey, image: &Image, rows_done: &[bool]) -> Vec<u8> {
    let header = serde_json::to_vec(&Header {
        format: FORMAT,
        key: key.clone(),
        width: image.width,
        height: image.height,
    })
    .unwrap_or_default();
    let w = image.width as usize;
    let mut out = Vec::with_capacity(64 + header.len() + rows_done.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    out.extend_from_slice(&header);
    out.extend(rows_done.iter().map(|&d| u8::from(d)));
    for (y, _) in rows_done.iter().enumerate().filter(|(_, d)| **d) {
        for p in &image.pixels[y * w..(y + 1) * w] {
            for c in p {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
    let digest = Sha256::digest(&out);
    out.extend_from_slice(&digest);
    out
}

/// Replaces the file at `path` with the checkpoint of `image`, whose lines flagged in
/// `rows_done` are finished, atomically: a reader (or a crash) sees the old file or the new
/// one, never a mix.
pub fn write(
    path: &Path,
    key: &CheckpointKey,
    image: &Image,
    rows_done: &[bool],
) -> Result<(), CheckpointError> {
    let io = |source| CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut tmp = path.as_os_str().to_os_string();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    let mut f = std::fs::File::create(&tmp).map_err(io)?;
    f.write_all(&encode(key, image, rows_done)).map_err(io)?;
    f.sync_all().map_err(io)?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(io)?;
    // The rename itself survives a power cut once the folder is synced.
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty())
        && let Ok(d) = std::fs::File::open(dir)
    {
        let _ = d.sync_all();
    }
    Ok(())
}

/// The checkpoint a render starts from: the one at `path` when resuming (or an empty one,
/// with a note, when there is none yet); refuses to start over a checkpoint without
/// `--resume`, which would lose its finished lines.
pub fn start(
    path: &Path,
    resume: bool,
    key: CheckpointKey,
    width: u32,
    height: u32,
) -> Result<Checkpoint, CheckpointError> {
    let exists = path.exists();
    match (resume, exists) {
        (true, true) => {
            let c = Checkpoint::resume(path, &key)?;
            tracing::info!(
                "resuming from {}: {} of {} scan lines finished",
                path.display(),
                c.rows_finished(),
                height
            );
            Ok(c)
        }
        (true, false) => {
            tracing::warn!(
                "no checkpoint at {}: rendering from the start",
                path.display()
            );
            Ok(Checkpoint::empty(key, width, height))
        }
        (false, true) => Err(CheckpointError::Exists {
            path: path.to_path_buf(),
        }),
        (false, false) => Ok(Checkpoint::empty(key, width, height)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(spp: u32) -> CheckpointKey {
        let desc = renderer::demo::demo_scene();
        let settings = RenderSettings {
            width: 8,
            height: 5,
            spp,
            ..RenderSettings::default()
        };
        let camera = Camera::framing(glam::Vec3::ZERO, glam::Vec3::ONE, 8.0 / 5.0);
        CheckpointKey::new(
            scene_digest(&desc),
            &PrepareOptions::default(),
            &settings,
            &camera,
        )
    }

    fn some_rows(k: CheckpointKey) -> Checkpoint {
        let mut c = Checkpoint::empty(k, 8, 5);
        for y in [0usize, 3] {
            c.rows_done[y] = true;
            for x in 0..8 {
                c.image.pixels[y * 8 + x] = [x as f32 * 0.5, y as f32, -1.25e-7];
            }
        }
        c
    }

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("magg-checkpoint-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d.join("out.png.partial")
    }

    #[test]
    fn a_written_checkpoint_reads_back_the_same_rows_and_bits() {
        let path = scratch("roundtrip");
        let c = some_rows(key(4));
        c.write(&path).unwrap();
        let back = Checkpoint::resume(&path, &key(4)).unwrap();
        assert_eq!(back.rows_done, c.rows_done);
        assert_eq!(back.rows_finished(), 2);
        let bits = |i: &Image| {
            i.pixels
                .iter()
                .flatten()
                .map(|v| v.to_bits())
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(&back.image), bits(&c.image));
    }

    #[test]
    fn other_settings_or_another_scene_are_refused_with_the_difference() {
        let path = scratch("mismatch");
        some_rows(key(4)).write(&path).unwrap();
        let e = Checkpoint::resume(&path, &key(8)).unwrap_err().to_string();
        assert!(e.contains("spp was 4, this render has 8"), "{e}");
        let mut other = key(4);
        other.scene_sha256 = "00".into();
        let e = Checkpoint::resume(&path, &other).unwrap_err().to_string();
        assert!(e.contains("another scene"), "{e}");
    }

    #[test]
    fn a_damaged_or_foreign_file_is_refused() {
        let path = scratch("damaged");
        some_rows(key(4)).write(&path).unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        let n = bytes.len();
        bytes[n / 2] ^= 1;
        std::fs::write(&path, &bytes).unwrap();
        let e = Checkpoint::resume(&path, &key(4)).unwrap_err().to_string();
        assert!(e.contains("checksum"), "{e}");
        std::fs::write(&path, &bytes[..n - 40]).unwrap();
        assert!(Checkpoint::resume(&path, &key(4)).is_err());
        std::fs::write(&path, b"P6 not a checkpoint at all, just text").unwrap();
        let e = Checkpoint::resume(&path, &key(4)).unwrap_err().to_string();
        assert!(e.contains("not a magg checkpoint"), "{e}");
    }

    #[test]
    fn starting_over_a_checkpoint_needs_resume() {
        let path = scratch("exists");
        let c = start(&path, false, key(4), 8, 5).unwrap();
        assert_eq!(c.rows_finished(), 0);
        let c = start(&path, true, key(4), 8, 5).unwrap();
        assert_eq!(c.rows_finished(), 0, "no file yet: from the start");
        some_rows(key(4)).write(&path).unwrap();
        let e = start(&path, false, key(4), 8, 5).unwrap_err().to_string();
        assert!(e.contains("--resume"), "{e}");
        assert_eq!(start(&path, true, key(4), 8, 5).unwrap().rows_finished(), 2);
    }

    #[test]
    fn the_partial_file_sits_beside_the_output() {
        assert_eq!(
            path_for(Path::new("a/b.png")),
            PathBuf::from("a/b.png.partial")
        );
    }
}
