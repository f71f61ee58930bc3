//! Textures, stored as square tiles so that a render node fetches only the parts of an image
//! its rays touch (the paper's texture data, moved on demand like shape data).
//!
//! Texels are 8-bit RGBA as the image files hold them. Colour textures are decoded from sRGB
//! per texel, before filtering, by whoever samples them: the same image can be both a colour
//! and a data texture, so the texture itself does not know its colour space.

use std::sync::LazyLock;

use glam::{Vec2, Vec4};
use serde::{Deserialize, Serialize};

use crate::{
    region::Region,
    source::{DataError, SceneData},
};

/// Texels along the side of a tile: 64 x 64 x 4 bytes = 16 KiB a tile.
pub const TILE_SIZE: u32 = 64;
pub const TILE_TEXELS: usize = (TILE_SIZE * TILE_SIZE) as usize;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum Wrap {
    #[default]
    Repeat,
    MirroredRepeat,
    ClampToEdge,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum Filter {
    Nearest,
    #[default]
    Linear,
}

/// A texture as the scene header carries it: everything but its texels.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TextureInfo {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub wrap_s: Wrap,
    pub wrap_t: Wrap,
    pub filter: Filter,
    /// Global id of this texture's first tile; tiles are numbered row by row.
    pub first_tile: u32,
    /// Mean texel value (linear for data, sRGB-decoded in `average_srgb`), used to weigh
    /// emissive triangles by their power without sampling the texture.
    pub average_linear: [f32; 4],
    pub average_srgb: [f32; 4],
}

impl TextureInfo {
    pub fn tiles_x(&self) -> u32 {
        self.width.div_ceil(TILE_SIZE)
    }
    pub fn tiles_y(&self) -> u32 {
        self.height.div_ceil(TILE_SIZE)
    }
    pub fn tile_count(&self) -> u32 {
        self.tiles_x() * self.tiles_y()
    }
}

/// One tile's texels, RGBA8 packed little-endian in a u32, row-major, always full size
/// (edge tiles are padded by repeating their last texel).
#[derive(Clone, Debug, PartialEq)]
pub struct Tile {
    /// Its own, or in place in a card's mapped memory ([`Region`]).
    pub texels: Region<u32>,
}

impl Tile {
    pub fn from_words(words: Box<[u32]>) -> Result<Tile, DataError> {
        Tile::from_region(Region::own(words))
    }

    /// A tile wherever its texels lie: any texel value is a colour, so the size is all
    /// there is to check.
    pub fn from_region(words: Region<u32>) -> Result<Tile, DataError> {
        if words.len() != TILE_TEXELS {
            return Err(DataError::Corrupt(format!(
                "texture tile has {} texels, expected {TILE_TEXELS}",
                words.len()
            )));
        }
        Ok(Tile { texels: words })
    }

    pub fn as_bytes(&self) -> &[u8] {
        bytemuck::cast_slice(&self.texels)
    }
}

/// Cuts an RGBA8 image into tiles.
pub fn make_tiles(width: u32, height: u32, rgba: &[u8]) -> Vec<Tile> {
    let tx = width.div_ceil(TILE_SIZE);
    let ty = height.div_ceil(TILE_SIZE);
    let mut tiles = Vec::with_capacity((tx * ty) as usize);
    for ty_i in 0..ty {
        for tx_i in 0..tx {
            let mut texels = vec![0u32; TILE_TEXELS];
            for y in 0..TILE_SIZE {
                let sy = (ty_i * TILE_SIZE + y).min(height - 1);
                for x in 0..TILE_SIZE {
                    let sx = (tx_i * TILE_SIZE + x).min(width - 1);
                    let i = ((sy * width + sx) * 4) as usize;
                    texels[(y * TILE_SIZE + x) as usize] =
                        u32::from_le_bytes([rgba[i], rgba[i + 1], rgba[i + 2], rgba[i + 3]]);
                }
            }
            tiles.push(Tile {
                texels: texels.into(),
            });
        }
    }
    tiles
}

static SRGB_TO_LINEAR: LazyLock<[f32; 256]> = LazyLock::new(|| {
    let mut t = [0.0; 256];
    for (i, v) in t.iter_mut().enumerate() {
        let c = i as f32 / 255.0;
        *v = if c <= 0.04045 {
            c / 12.92
        } else {
            ((c + 0.055) / 1.055).powf(2.4)
        };
    }
    t
});

pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

#[inline]
fn decode(texel: u32, srgb: bool) -> Vec4 {
    let [r, g, b, a] = texel.to_le_bytes();
    if srgb {
        let lut = &*SRGB_TO_LINEAR;
        Vec4::new(
            lut[r as usize],
            lut[g as usize],
            lut[b as usize],
            a as f32 / 255.0,
        )
    } else {
        Vec4::new(r as f32, g as f32, b as f32, a as f32) / 255.0
    }
}

#[inline]
fn wrap(i: i64, n: u32, mode: Wrap) -> u32 {
    let n = n as i64;
    let v = match mode {
        // A coordinate already inside needs no division (texture coordinates in [0, 1]).
        Wrap::Repeat if (0..n).contains(&i) => i,
        Wrap::Repeat => i.rem_euclid(n),
        Wrap::ClampToEdge => i.clamp(0, n - 1),
        Wrap::MirroredRepeat => {
            let period = 2 * n;
            let m = i.rem_euclid(period);
            if m < n { m } else { period - 1 - m }
        }
    };
    v as u32
}

/// `wrap(i + 1, n, mode)` given `at = wrap(i, n, mode)`: for repeat, the next texel without
/// a second division.
#[inline]
fn wrap_next(i: i64, at: u32, n: u32, mode: Wrap) -> u32 {
    match mode {
        Wrap::Repeat if at + 1 < n => at + 1,
        Wrap::Repeat => 0,
        _ => wrap(i + 1, n, mode),
    }
}

/// Reads one texel through the data source (which may fetch its tile).
#[inline]
fn texel<D: SceneData>(data: &D, tex: &TextureInfo, x: u32, y: u32) -> Result<u32, DataError> {
    let tile_id = tex.first_tile + (y / TILE_SIZE) * tex.tiles_x() + x / TILE_SIZE;
    let tile = data.tile(tile_id)?;
    Ok(tile.texels[((y % TILE_SIZE) * TILE_SIZE + x % TILE_SIZE) as usize])
}

/// Samples `tex` at `uv` (glTF convention: (0, 0) is the top-left of the image), decoding
/// sRGB first when `srgb`. Non-finite coordinates read texel (0, 0).
pub fn sample<D: SceneData>(
    data: &D,
    tex: &TextureInfo,
    uv: Vec2,
    srgb: bool,
) -> Result<Vec4, DataError> {
    let uv = if uv.is_finite() { uv } else { Vec2::ZERO };
    // Keep coordinates in a range where f32 -> i64 conversion is exact enough; wrapping is
    // periodic so only clamped modes care, and they clamp anyway.
    let uv = uv.clamp(Vec2::splat(-1e6), Vec2::splat(1e6));
    let x = uv.x as f64 * tex.width as f64;
    let y = uv.y as f64 * tex.height as f64;
    match tex.filter {
        Filter::Nearest => {
            let xi = wrap(x.floor() as i64, tex.width, tex.wrap_s);
            let yi = wrap(y.floor() as i64, tex.height, tex.wrap_t);
            Ok(decode(texel(data, tex, xi, yi)?, srgb))
        }
        Filter::Linear => {
            let (xf, yf) = (x - 0.5, y - 0.5);
            let (x0, y0) = (xf.floor(), yf.floor());
            let (fx, fy) = ((xf - x0) as f32, (yf - y0) as f32);
            let (x0, y0) = (x0 as i64, y0 as i64);
            let xa = wrap(x0, tex.width, tex.wrap_s);
            let xb = wrap_next(x0, xa, tex.width, tex.wrap_s);
            let ya = wrap(y0, tex.height, tex.wrap_t);
            let yb = wrap_next(y0, ya, tex.height, tex.wrap_t);
            let [t00, t10, t01, t11] =
                if xa / TILE_SIZE == xb / TILE_SIZE && ya / TILE_SIZE == yb / TILE_SIZE {
                    // The usual case: all four texels in one tile, fetched once.
                    let tile = data
                        .tile(tex.first_tile + (ya / TILE_SIZE) * tex.tiles_x() + xa / TILE_SIZE)?;
                    let at = |x: u32, y: u32| {
                        tile.texels[((y % TILE_SIZE) * TILE_SIZE + x % TILE_SIZE) as usize]
                    };
                    [at(xa, ya), at(xb, ya), at(xa, yb), at(xb, yb)]
                } else {
                    [
                        texel(data, tex, xa, ya)?,
                        texel(data, tex, xb, ya)?,
                        texel(data, tex, xa, yb)?,
                        texel(data, tex, xb, yb)?,
                    ]
                };
            let [t00, t10, t01, t11] = [
                decode(t00, srgb),
                decode(t10, srgb),
                decode(t01, srgb),
                decode(t11, srgb),
            ];
            let top = t00 * (1.0 - fx) + t10 * fx;
            let bottom = t01 * (1.0 - fx) + t11 * fx;
            Ok(top * (1.0 - fy) + bottom * fy)
        }
    }
}

/// Mean texel of an RGBA8 image, linear and sRGB-decoded (from per-channel histograms:
/// one increment per byte, then 256 products, however large the image).
pub fn averages(rgba: &[u8]) -> ([f32; 4], [f32; 4]) {
    let mut hist = [[0u64; 256]; 4];
    for px in rgba.chunks_exact(4) {
        for c in 0..4 {
            hist[c][px[c] as usize] += 1;
        }
    }
    let n = (rgba.len() / 4).max(1) as f64;
    let lut = &*SRGB_TO_LINEAR;
    let mut lin = [0f32; 4];
    let mut srgb = [0f32; 4];
    for c in 0..4 {
        let (mut l, mut s) = (0f64, 0f64);
        for (v, &count) in hist[c].iter().enumerate() {
            let count = count as f64;
            l += count * v as f64 / 255.0;
            s += count
                * if c < 3 {
                    lut[v] as f64
                } else {
                    v as f64 / 255.0
                };
        }
        lin[c] = (l / n) as f32;
        srgb[c] = (s / n) as f32;
    }
    (lin, srgb)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_modes() {
        assert_eq!(wrap(-1, 4, Wrap::Repeat), 3);
        assert_eq!(wrap(5, 4, Wrap::Repeat), 1);
        assert_eq!(wrap(-1, 4, Wrap::ClampToEdge), 0);
        assert_eq!(wrap(9, 4, Wrap::ClampToEdge), 3);
        assert_eq!(wrap(4, 4, Wrap::MirroredRepeat), 3);
        assert_eq!(wrap(-1, 4, Wrap::MirroredRepeat), 0);
        assert_eq!(wrap(8, 4, Wrap::MirroredRepeat), 0);
    }

    #[test]
    fn the_next_texel_is_the_wrap_of_the_next_coordinate() {
        for mode in [Wrap::Repeat, Wrap::ClampToEdge, Wrap::MirroredRepeat] {
            for n in [1u32, 2, 3, 64, 100] {
                for i in -300i64..300 {
                    let at = wrap(i, n, mode);
                    assert!(at < n, "{mode:?} {n} {i}");
                    assert_eq!(
                        wrap_next(i, at, n, mode),
                        wrap(i + 1, n, mode),
                        "{mode:?} {n} {i}"
                    );
                    if mode == Wrap::Repeat {
                        assert_eq!(at as i64, i.rem_euclid(n as i64));
                    }
                }
            }
        }
    }

    #[test]
    fn srgb_endpoints() {
        assert_eq!(SRGB_TO_LINEAR[0], 0.0);
        assert!((SRGB_TO_LINEAR[255] - 1.0).abs() < 1e-6);
        assert!((SRGB_TO_LINEAR[128] - 0.2158).abs() < 1e-3);
    }
}
