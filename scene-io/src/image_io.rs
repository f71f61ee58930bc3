//! Image files, chosen by extension:
//!
//! * `.png`: 8-bit sRGB. Linear values are clamped to [0, 1], encoded with the sRGB transfer
//!   function and rounded; no tone mapping, so what the renderer computed is what a viewer
//!   shows, up to the clamp.
//! * `.exr` (OpenEXR, 32-bit float RGB) and `.pfm` (portable float map, little-endian, rows
//!   bottom-up as the format says): linear values, untouched.
//!
//! Files are written whole or not at all: into a temporary file beside the target, then
//! renamed over it, so a reader never sees half an image and a failure leaves nothing behind.

use std::{
    fs,
    io::Write,
    path::{Path, PathBuf},
};

use renderer::Image;

#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("{path}: unknown image format (use .png, .exr or .pfm)")]
    UnknownFormat { path: PathBuf },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Encode { path: PathBuf, message: String },
    #[error("{path}: not a valid image: {message}")]
    Decode { path: PathBuf, message: String },
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Png,
    Exr,
    Pfm,
}

impl Format {
    pub fn of(path: &Path) -> Option<Format> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "png" => Some(Format::Png),
            "exr" => Some(Format::Exr),
            "pfm" => Some(Format::Pfm),
            _ => None,
        }
    }
}

/// sRGB transfer function (IEC 61966-2-1) of a linear value in [0, 1].
pub fn linear_to_srgb(c: f32) -> f32 {
    if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

pub fn to_srgb8(c: f32) -> u8 {
    let c = if c.is_finite() {
        c.clamp(0.0, 1.0)
    } else {
        0.0
    };
    (linear_to_srgb(c) * 255.0 + 0.5).floor().clamp(0.0, 255.0) as u8
}

/// Encodes an image into the bytes of a file of the given format.
pub fn encode(image: &Image, format: Format) -> Result<Vec<u8>, String> {
    match format {
        Format::Png => {
            let mut rgb = Vec::with_capacity(image.pixels.len() * 3);
            for p in &image.pixels {
                rgb.extend(p.iter().map(|&c| to_srgb8(c)));
            }
            let mut out = Vec::new();
            let enc = image::codecs::png::PngEncoder::new(&mut out);
            image::ImageEncoder::write_image(
                enc,
                &rgb,
                image.width,
                image.height,
                image::ExtendedColorType::Rgb8,
            )
            .map_err(|e| e.to_string())?;
            Ok(out)
        }
        Format::Pfm => {
            let mut out = format!("PF\n{} {}\n-1.0\n", image.width, image.height).into_bytes();
            for row in (0..image.height as usize).rev() {
                for p in &image.pixels[row * image.width as usize..(row + 1) * image.width as usize]
                {
                    for c in p {
                        out.extend_from_slice(&c.to_le_bytes());
                    }
                }
            }
            Ok(out)
        }
        Format::Exr => {
            use exr::prelude::*;
            let w = image.width as usize;
            let channels = SpecificChannels::rgb(|Vec2(x, y): Vec2<usize>| {
                let p = image.pixels[y * w + x];
                (p[0], p[1], p[2])
            });
            // Lossless ZIP in increasing line order, written by one thread: the same pixels
            // always give the same file bytes (parallel writers may order blocks freely).
            let img = exr::image::Image::from_encoded_channels(
                (w, image.height as usize),
                Encoding::SMALL_LOSSLESS,
                channels,
            );
            let mut cursor = std::io::Cursor::new(Vec::new());
            img.write()
                .non_parallel()
                .to_buffered(&mut cursor)
                .map_err(|e| e.to_string())?;
            Ok(cursor.into_inner())
        }
    }
}

/// Writes `image` to `path` atomically, in the format its extension names.
pub fn write_image(path: &Path, image: &Image) -> Result<(), ImageError> {
    let format = Format::of(path).ok_or_else(|| ImageError::UnknownFormat { path: path.into() })?;
    let bytes = encode(image, format).map_err(|message| ImageError::Encode {
        path: path.into(),
        message,
    })?;
    write_atomic(path, &bytes)
}

/// Writes bytes to `path` via a temporary file in the same folder and a rename, so that a
/// reader never sees half a file and a failure leaves the old one. What the rename would
/// replace rather than write to is written the way the user meant: a device or a pipe
/// (`--stats /dev/null`, `--stats /dev/stdout`, a FIFO a script reads) is written directly
/// (a rename replaced `/dev/null` itself with a regular file, for the whole machine where
/// run as root), and a symbolic link's target gets the new file (the link stays).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ImageError> {
    let io = |source| ImageError::Io {
        path: path.into(),
        source,
    };
    // Asked of the path as given: the kernel follows links, `/proc/self/fd` ones included.
    if let Ok(meta) = fs::metadata(path)
        && !meta.is_file()
        && !meta.is_dir()
    {
        let written = fs::OpenOptions::new()
            .write(true)
            .open(path)
            .and_then(|mut f| f.write_all(bytes));
        return written.map_err(io);
    }
    let target = link_target(path).map_err(io)?;
    let path = target.as_path();
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
    let result = (|| {
        let mut f = fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        fs::rename(&tmp, path)
    })();
    if let Err(e) = result {
        let _ = fs::remove_file(&tmp);
        return Err(io(e));
    }
    Ok(())
}

/// Where a write to `path` should land: `path` itself, or, for a symbolic link (a chain of
/// them, even one that ends at a file not yet there), the path it finally names.
pub fn link_target(path: &Path) -> std::io::Result<PathBuf> {
    let mut at = path.to_path_buf();
    // The kernel's own limit on links followed in one lookup.
    for _ in 0..40 {
        match fs::symlink_metadata(&at) {
            Ok(m) if m.file_type().is_symlink() => {
                let next = fs::read_link(&at)?;
                at = match at.parent() {
                    Some(dir) if next.is_relative() => dir.join(next),
                    _ => next,
                };
            }
            _ => return Ok(at),
        }
    }
    Err(std::io::Error::other(
        "too many levels of symbolic links (a loop?)",
    ))
}

/// Reads an image written by magg or another renderer (PNG is sRGB-decoded to linear).
pub fn read_image(path: &Path) -> Result<Image, ImageError> {
    let format = Format::of(path).ok_or_else(|| ImageError::UnknownFormat { path: path.into() })?;
    // A file that is not there (or cannot be opened) is said as such, not as "not a valid
    // image", which is what the decoders make of it.
    fs::File::open(path).map_err(|source| ImageError::Io {
        path: path.into(),
        source,
    })?;
    let decode = |message: String| ImageError::Decode {
        path: path.into(),
        message,
    };
    match format {
        Format::Pfm => {
            let bytes = fs::read(path).map_err(|source| ImageError::Io {
                path: path.into(),
                source,
            })?;
            decode_pfm(&bytes).map_err(|e| decode(e.to_string()))
        }
        Format::Png => {
            let img = image::open(path)
                .map_err(|e| decode(e.to_string()))?
                .to_rgb8();
            let (w, h) = img.dimensions();
            let pixels = img
                .pixels()
                .map(|p| {
                    p.0.map(|c| renderer::texture::srgb_to_linear(c as f32 / 255.0))
                })
                .collect();
            Ok(Image {
                width: w,
                height: h,
                pixels,
            })
        }
        Format::Exr => {
            use exr::prelude::*;
            // The reader allocates the pixels for the size the header declares before it
            // reads any: a header is checked first, as a render's size is.
            const MAX_READ_SIDE: usize = renderer::MAX_IMAGE_SIDE as usize;
            let meta = exr::meta::MetaData::read_from_file(path, false)
                .map_err(|e| decode(e.to_string()))?;
            if let Some(size) = (meta.headers.iter().map(|h| h.layer_size))
                .find(|s| s.0 > MAX_READ_SIDE || s.1 > MAX_READ_SIDE)
            {
                return Err(decode(format!(
                    "a layer of {}x{} pixels: at most {MAX_READ_SIDE} a side",
                    size.0, size.1
                )));
            }
            let img = read_first_rgba_layer_from_file(
                path,
                |res: Vec2<usize>, _| (res.0, vec![[0f32; 3]; res.0 * res.1]),
                |(w, px): &mut (usize, Vec<[f32; 3]>),
                 pos: Vec2<usize>,
                 (r, g, b, _a): (f32, f32, f32, f32)| {
                    px[pos.1 * *w + pos.0] = [r, g, b];
                },
            )
            .map_err(|e| decode(e.to_string()))?;
            let size = img.layer_data.size;
            Ok(renderer::Image {
                width: size.0 as u32,
                height: size.1 as u32,
                pixels: img.layer_data.channel_data.pixels.1,
            })
        }
    }
}

/// What is wrong with a PFM file.
#[derive(Debug, thiserror::Error)]
pub enum PfmError {
    #[error("truncated header")]
    TruncatedHeader,
    #[error("header is not text")]
    HeaderNotText,
    #[error("header too long")]
    HeaderTooLong,
    #[error("bad magic {0:?}")]
    Magic(String),
    #[error("bad {0}")]
    Field(&'static str),
    #[error("image too large")]
    TooLarge,
    #[error("an image of {width}x{height}: no pixels")]
    NoPixels { width: u32, height: u32 },
    #[error("expected {0} bytes of pixels after the header")]
    TruncatedPixels(usize),
}

/// Parses a PFM file (colour "PF" or greyscale "Pf", either byte order).
pub fn decode_pfm(bytes: &[u8]) -> Result<Image, PfmError> {
    // Header: three whitespace-separated tokens after the magic, then one whitespace byte.
    let mut tokens = Vec::new();
    let mut i = 0;
    while tokens.len() < 4 {
        while i < bytes.len() && bytes[i].is_ascii_whitespace() {
            i += 1;
        }
        let start = i;
        while i < bytes.len() && !bytes[i].is_ascii_whitespace() {
            i += 1;
        }
        if start == i {
            return Err(PfmError::TruncatedHeader);
        }
        tokens.push(
            std::str::from_utf8(&bytes[start..i])
                .map_err(|_| PfmError::HeaderNotText)?
                .to_string(),
        );
        if start > 64 {
            return Err(PfmError::HeaderTooLong);
        }
    }
    i += 1;
    let channels = match tokens[0].as_str() {
        "PF" => 3,
        "Pf" => 1,
        m => return Err(PfmError::Magic(m.to_string())),
    };
    let w: u32 = tokens[1].parse().map_err(|_| PfmError::Field("width"))?;
    let h: u32 = tokens[2].parse().map_err(|_| PfmError::Field("height"))?;
    let scale: f32 = tokens[3].parse().map_err(|_| PfmError::Field("scale"))?;
    if w == 0 || h == 0 {
        return Err(PfmError::NoPixels {
            width: w,
            height: h,
        });
    }
    let little = scale < 0.0;
    let n = (w as usize)
        .checked_mul(h as usize)
        .and_then(|n| n.checked_mul(channels * 4))
        .ok_or(PfmError::TooLarge)?;
    let data = bytes.get(i..i + n).ok_or(PfmError::TruncatedPixels(n))?;
    let mut pixels = vec![[0f32; 3]; w as usize * h as usize];
    for (k, c) in data.chunks_exact(4).enumerate() {
        let arr = [c[0], c[1], c[2], c[3]];
        let v = if little {
            f32::from_le_bytes(arr)
        } else {
            f32::from_be_bytes(arr)
        };
        let px = k / channels;
        let (x, y_from_bottom) = (px % w as usize, px / w as usize);
        let row = h as usize - 1 - y_from_bottom;
        let p = &mut pixels[row * w as usize + x];
        if channels == 3 {
            p[k % 3] = v;
        } else {
            *p = [v; 3];
        }
    }
    Ok(Image {
        width: w,
        height: h,
        pixels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gradient() -> Image {
        let mut img = Image::new(5, 3);
        for (i, p) in img.pixels.iter_mut().enumerate() {
            *p = [i as f32 * 0.1, 1.0 - i as f32 * 0.05, 2.5];
        }
        img
    }

    #[test]
    fn same_pixels_same_file_bytes() {
        let img = gradient();
        for f in [Format::Png, Format::Exr, Format::Pfm] {
            assert_eq!(encode(&img, f).unwrap(), encode(&img, f).unwrap(), "{f:?}");
        }
    }

    #[test]
    fn pfm_and_exr_round_trip_exactly() {
        let dir = std::env::temp_dir().join(format!("magg-img-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let img = gradient();
        for name in ["a.pfm", "a.exr"] {
            let p = dir.join(name);
            write_image(&p, &img).unwrap();
            assert_eq!(read_image(&p).unwrap(), img, "{name}");
        }
        let _ = fs::remove_dir_all(&dir);
    }

    /// What a rename would replace instead of writing to: a link's target gets the file and
    /// the link stays; a pipe and a device are written directly and stay what they are (a
    /// rename had replaced them, `/dev/null` included, with regular files); a full device
    /// and a loop of links are errors.
    #[test]
    fn writes_land_in_what_links_pipes_and_devices_name() {
        use std::os::unix::fs::{FileTypeExt, symlink};
        let dir = std::env::temp_dir().join(format!("magg-write-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(dir.join("real")).unwrap();
        symlink("real/target.json", dir.join("link.json")).unwrap();
        symlink("link.json", dir.join("chain.json")).unwrap();
        write_atomic(&dir.join("chain.json"), b"through two links").unwrap();
        assert!(
            fs::symlink_metadata(dir.join("link.json"))
                .unwrap()
                .file_type()
                .is_symlink()
        );
        assert!(
            fs::symlink_metadata(dir.join("chain.json"))
                .unwrap()
                .file_type()
                .is_symlink()
        );
        assert_eq!(
            fs::read(dir.join("real/target.json")).unwrap(),
            b"through two links"
        );

        let fifo = dir.join("fifo");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        assert!(made.is_ok_and(|s| s.success()), "mkfifo failed");
        let (tx, rx) = std::sync::mpsc::channel();
        {
            let fifo = fifo.clone();
            std::thread::spawn(move || tx.send(fs::read(fifo).unwrap()));
        }
        // Through a link too, as `/dev/stdout` reaches a pipe.
        symlink("fifo", dir.join("to-fifo")).unwrap();
        write_atomic(&dir.join("to-fifo"), b"to a reader").unwrap();
        // A rename would leave the reader waiting: fail, not hang.
        let read = rx.recv_timeout(std::time::Duration::from_secs(10));
        assert_eq!(read.expect("the FIFO's reader got nothing"), b"to a reader");
        assert!(fs::symlink_metadata(&fifo).unwrap().file_type().is_fifo());

        write_atomic(Path::new("/dev/null"), b"nothing").unwrap();
        assert!(
            fs::metadata("/dev/null")
                .unwrap()
                .file_type()
                .is_char_device()
        );
        if Path::new("/dev/full").exists() {
            assert!(write_atomic(Path::new("/dev/full"), b"no room").is_err());
            assert!(
                fs::metadata("/dev/full")
                    .unwrap()
                    .file_type()
                    .is_char_device()
            );
        }

        symlink("loop-b", dir.join("loop-a")).unwrap();
        symlink("loop-a", dir.join("loop-b")).unwrap();
        let e = write_atomic(&dir.join("loop-a"), b"x")
            .unwrap_err()
            .to_string();
        assert!(e.contains("symbolic links"), "{e}");
        let _ = fs::remove_dir_all(&dir);
    }

    /// An EXR whose header declares a data window of a million pixels a side (12 TB of
    /// pixels, which the reader allocated and the process aborted on) is refused.
    #[test]
    fn an_exr_declaring_a_huge_image_is_refused() {
        let dir = std::env::temp_dir().join(format!("magg-img-huge-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let p = dir.join("huge.exr");
        write_image(&p, &gradient()).unwrap();
        let mut bytes = fs::read(&p).unwrap();
        // The attribute's name and type, its size (16), then x min, y min, x max, y max.
        let key = b"dataWindow\0box2i\0";
        let at = bytes.windows(key.len()).position(|w| w == key).unwrap() + key.len() + 4;
        for (k, v) in [0i32, 0, 999_999, 999_999].iter().enumerate() {
            bytes[at + 4 * k..at + 4 * k + 4].copy_from_slice(&v.to_le_bytes());
        }
        fs::write(&p, &bytes).unwrap();
        let e = read_image(&p).unwrap_err().to_string();
        assert!(
            e.contains("1000000x1000000 pixels: at most 32768 a side"),
            "{e}"
        );
        let _ = fs::remove_dir_all(&dir);
    }

    /// A PFM of no pixels is refused (compared, it gave a relMSE of 0).
    #[test]
    fn a_pfm_of_no_pixels_is_refused() {
        for header in ["PF\n0 0\n-1.0\n", "PF\n0 5\n-1.0\n", "Pf\n3 0\n1.0\n"] {
            let e = decode_pfm(header.as_bytes()).unwrap_err();
            assert!(matches!(e, PfmError::NoPixels { .. }), "{header:?}: {e}");
        }
    }

    #[test]
    fn png_is_srgb_clamped() {
        assert_eq!(to_srgb8(0.0), 0);
        assert_eq!(to_srgb8(1.0), 255);
        assert_eq!(to_srgb8(7.0), 255);
        assert_eq!(to_srgb8(f32::NAN), 0);
        assert_eq!(to_srgb8(0.2159), 128);
        assert_eq!(to_srgb8(0.2140), 127);
    }

    #[test]
    fn unwritable_target_leaves_nothing() {
        let p = Path::new("/nonexistent-dir-magg/x.png");
        assert!(matches!(
            write_image(p, &gradient()),
            Err(ImageError::Io { .. })
        ));
        assert!(matches!(
            write_image(Path::new("x.bmp"), &gradient()),
            Err(ImageError::UnknownFormat { .. })
        ));
    }

    #[test]
    fn truncated_pfm_is_an_error() {
        assert!(decode_pfm(b"PF\n2 2\n-1.0\n\0\0").is_err());
        assert!(decode_pfm(b"P6\n2 2\n").is_err());
        assert!(decode_pfm(b"PF\n99999999 99999999\n-1\n").is_err());
    }
}
