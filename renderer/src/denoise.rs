//! An edge-aware denoiser for a finished image: a biased tool, off unless asked for (the
//! built-in demo scene turns it on and says so).
//!
//! It exists for the first picture a user sees: at a few dozen samples a path-traced image
//! is noisy, and the noise of smooth lighting on flat walls is what the eye reads as "not
//! done". The filter smooths that lighting while keeping edges and textures, guided by what
//! the camera sees, which has no noise:
//!
//! * **Guides**, traced here once per image (a few rays a pixel, through mirrors and glass to
//!   the first rough surface, as denoisers for path tracers commonly do): the surface's
//!   albedo, its shading normal, its position and the size of a pixel there.
//! * **Edge-avoiding à-trous wavelet filtering** (Dammertz, Sewtz, Hanika and Lensch, 2010),
//!   with the luminance weights scaled by a spatial variance estimate as in SVGF (Schied et
//!   al., 2017): three passes of a 5x5 kernel whose taps spread 1, 2 and 4 pixels apart, each
//!   tap weighted down where the normals differ, where the neighbour lies off this pixel's
//!   tangent plane or far from its point, where the albedos differ (so textures stay sharp),
//!   or where its brightness differs by more than the noise explains.
//!
//! Pixels on or beside a light's surface are left as they are.
//!
//! Everything here is a deterministic function of the image and the scene: the same bytes
//! whichever process rendered which pixels, and whatever the number of threads.

use glam::{Vec3, Vec3A};

use crate::{
    camera::Camera,
    material,
    math::{luminance, offset_ray_origin},
    ray::Ray,
    render::Image,
    sampler::Sampler,
    scene::SceneHeader,
    source::{DataError, SceneData},
    trace::{AlphaKey, Tracer},
};

/// Guide rays per pixel along each axis (a stratified grid), so that a pixel on an edge gets
/// the mix of both sides its colour has.
const GUIDE_GRID: u32 = 2;
/// Mirror and glass bounces a guide ray follows before it takes the surface it is on.
const GUIDE_SPECULAR_BOUNCES: u32 = 4;
/// Filter passes; the last one's taps are 2^(PASSES-1) pixels apart. Three beat five on the
/// demo scene at 32 and 64 spp (relMSE 4.48e-3 against 4.62e-3 at 32).
const PASSES: u32 = 3;
/// The B3-spline kernel of the à-trous transform.
const KERNEL: [f32; 5] = [1.0 / 16.0, 1.0 / 4.0, 3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0];
/// How sharply normals must agree: weight (n_p . n_q)^NORMAL_POWER (a power of two).
const NORMAL_POWER_LOG2: u32 = 7;
/// Distance of a neighbour from this pixel's tangent plane that costs a factor e, in pixel
/// footprints per pixel of separation.
const PLANE_SCALE: f32 = 1.0;
/// Distance between two pixels' surface points that costs a factor e, in pixel footprints
/// per pixel of separation (what keeps apart points of one plane seen through a curved
/// mirror, far apart on the plane but neighbours in the image).
const DISTANCE_SCALE: f32 = 3.0;
/// Luminance difference that costs a factor e, in standard deviations of the noise. (With
/// the 3x3 noise estimate, 6 against SVGF's 4 took the demo scene at 24 spp from relMSE
/// 4.29e-3 to 3.98e-3, and DamagedHelmet at 4 spp stayed at 2.54e-3.)
const LUMINANCE_SCALE: f32 = 6.0;
/// The noise estimate looks this many pixels each way: 3x3 (7x7, SVGF's, measured 4.69e-3
/// against 4.29e-3 on the demo at 24 spp: a wider window takes more of the light's own
/// variation, at shadows' and caustics' edges, for noise).
const VARIANCE_RADIUS: i32 = 1;
/// Albedo difference (RGB distance) between two pixels that costs a factor e: textures'
/// edges stay sharp. (Dividing the albedo out instead, to filter the light alone across
/// such edges, was measured worse on the demo scene: four guide rays a pixel do not see
/// the same mix of a fine texture as its samples did, and a wrong albedo scales the light.)
const ALBEDO_SCALE: f32 = 0.1;

/// What the camera sees at one pixel, without noise.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GuidePixel {
    pub albedo: Vec3,
    /// Unit, facing the camera (zero where nothing was hit).
    pub normal: Vec3,
    pub position: Vec3,
    /// The width of a pixel at `position`, in scene units.
    pub footprint: f32,
    /// The share of the pixel's guide rays that found a light's surface. Such pixels, and
    /// their neighbours, are left as they are and lend nothing to others: a light's
    /// brightness is no noise, its image in a mirror lies on the same plane as what
    /// surrounds it, and four guide rays may miss a light that covers part of a pixel.
    pub emitter: f32,
}

/// The guides of a whole image.
#[derive(Clone, Debug, PartialEq)]
pub struct Guides {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<GuidePixel>,
}

/// Traces the guides of a `width` x `height` image of `camera`'s view, on `threads` threads.
pub fn guides<D: SceneData + Sync>(
    scene: &SceneHeader,
    data: &D,
    camera: &Camera,
    width: u32,
    height: u32,
    threads: usize,
) -> Result<Guides, DataError> {
    let rays = camera.rays(width, height);
    // Where a ray that leaves the scene is taken to end (an empty scene's bounds are not
    // finite).
    let far = (scene.bounds_max - scene.bounds_min).length().max(1.0) * 1e3;
    let far = if far.is_finite() { far } else { 1e6 };
    let row_guides = |y: u32, out: &mut [GuidePixel]| -> Result<(), DataError> {
        let t = Tracer::new(scene, data);
        for (x, px) in (0..width).zip(out.iter_mut()) {
            let mut sum = GuidePixel::default();
            let mut positions = [Vec3::ZERO; (GUIDE_GRID * GUIDE_GRID) as usize];
            let mut through_specular = false;
            for j in 0..GUIDE_GRID {
                for i in 0..GUIDE_GRID {
                    let (u, v) = (
                        (i as f32 + 0.5) / GUIDE_GRID as f32,
                        (j as f32 + 0.5) / GUIDE_GRID as f32,
                    );
                    let (fx, fy) = (x as f32 + u, y as f32 + v);
                    let ray = rays.ray(fx, fy);
                    let beside = rays.ray(fx + 1.0, fy);
                    let spread = (
                        (beside.origin - ray.origin).length(),
                        (beside.dir - ray.dir).length(),
                    );
                    let sampler = Sampler::new(0, x, y, j * GUIDE_GRID + i);
                    let (g, specular) = guide_sample(&t, ray, &sampler, spread, far)?;
                    through_specular |= specular;
                    positions[(j * GUIDE_GRID + i) as usize] = g.position;
                    sum.albedo += g.albedo;
                    sum.normal += g.normal;
                    sum.position += g.position;
                    sum.footprint += g.footprint;
                    sum.emitter += g.emitter;
                }
            }
            let n = (GUIDE_GRID * GUIDE_GRID) as f32;
            let position = sum.position / n;
            let mut footprint = sum.footprint / n;
            if through_specular {
                // A curved mirror or lens magnifies: how far apart the guide rays landed
                // says how wide the pixel is there (on a plane seen head on, the grid's
                // points lie sqrt(2)/4 of a pixel from their mean).
                let spread = (positions
                    .iter()
                    .map(|q| (*q - position).length_squared())
                    .sum::<f32>()
                    / n)
                    .sqrt()
                    * (4.0 / std::f32::consts::SQRT_2);
                footprint = footprint.max(spread);
            }
            *px = GuidePixel {
                albedo: sum.albedo / n,
                normal: sum.normal.normalize_or_zero(),
                position,
                footprint,
                emitter: sum.emitter / n,
            };
        }
        Ok(())
    };
    let mut pixels = vec![GuidePixel::default(); width as usize * height as usize];
    let w = width as usize;
    let results: Vec<Result<(), DataError>> = if w == 0 {
        Vec::new()
    } else {
        for_bands(&mut pixels, w, threads, |first_row, band| {
            for (r, row) in band.chunks_mut(w).enumerate() {
                row_guides((first_row + r) as u32, row)?;
            }
            Ok(())
        })
    };
    results.into_iter().collect::<Result<(), DataError>>()?;
    Ok(Guides {
        width,
        height,
        pixels,
    })
}

/// Runs `work` on bands of whole rows of `buf` (`width` wide) on up to `threads` threads.
fn for_bands<T: Send, R: Send>(
    buf: &mut [T],
    width: usize,
    threads: usize,
    work: impl Fn(usize, &mut [T]) -> R + Sync,
) -> Vec<R> {
    let rows = buf.len() / width.max(1);
    let threads = threads.clamp(1, rows.max(1));
    let band_rows = rows.div_ceil(threads).max(1);
    std::thread::scope(|s| {
        let work = &work;
        let handles: Vec<_> = buf
            .chunks_mut(band_rows * width)
            .enumerate()
            .map(|(b, band)| s.spawn(move || work(b * band_rows, band)))
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().expect("a denoiser thread panicked"))
            .collect()
    })
}

/// One guide ray: through mirrors and glass to the first surface that scatters.
fn guide_sample<D: SceneData>(
    t: &Tracer<D>,
    mut ray: Ray,
    sampler: &Sampler<'_>,
    (origin_spread, dir_spread): (f32, f32),
    far: f32,
) -> Result<(GuidePixel, bool), DataError> {
    let scene = t.scene;
    let mut travelled = 0.0f32;
    let mut tint = Vec3::ONE;
    for bounce in 0..=GUIDE_SPECULAR_BOUNCES {
        let dir = Vec3::from(ray.dir).normalize();
        let Some(hit) = t.closest(&ray, AlphaKey::new(sampler, bounce))? else {
            // The world around the scene: its light is filtered as it is, as on a far wall.
            let g = GuidePixel {
                albedo: tint,
                normal: -dir,
                position: Vec3::from(ray.origin) + dir * far,
                footprint: origin_spread + dir_spread * (travelled + far),
                emitter: 0.0,
            };
            return Ok((g, bounce > 0));
        };
        let m = &scene.materials[hit.chunk.header().material as usize];
        let s = hit
            .chunk
            .surface_reading(hit.tri, &hit.tri_hit, || m.reads());
        let params = material::shading_params(scene, t.data, m, &s)?;
        travelled += hit.tri_hit.t * ray.dir.length();
        let wo = -dir;
        let bsdf = crate::bsdf::Bsdf::new(&params, s.ng, wo);
        let normal = {
            let n = bsdf.shading_normal();
            if n.dot(wo) < 0.0 { -n } else { n }
        };
        let take = |albedo: Vec3, emitter: f32| {
            let g = GuidePixel {
                albedo: tint * albedo,
                normal,
                position: Vec3::from(s.p),
                footprint: origin_spread + dir_spread * travelled,
                emitter,
            };
            (g, bounce > 0)
        };
        if params.emission.max_element() > 0.0 {
            return Ok(take(Vec3::ONE, 1.0));
        }
        if !bsdf.is_pure_delta() || bounce == GUIDE_SPECULAR_BOUNCES {
            return Ok(take(params.base_color.clamp(Vec3::ZERO, Vec3::ONE), 0.0));
        }
        // A mirror or glass: follow its stronger continuation.
        let [a, b] = bsdf.specular_paths(wo, true);
        let (wi, weight, _) = if b.1.max_element() > a.1.max_element() {
            b
        } else {
            a
        };
        if weight.max_element() <= 0.0 {
            return Ok(take(params.base_color.clamp(Vec3::ZERO, Vec3::ONE), 0.0));
        }
        tint *= weight.clamp(Vec3::ZERO, Vec3::ONE);
        let ng = Vec3A::from(bsdf.geometric_normal());
        let origin = offset_ray_origin(s.p, s.p_error, ng, wi.into());
        ray = Ray::new(origin, wi.into(), f32::INFINITY);
    }
    unreachable!("the last bounce returns")
}

/// The denoised image: `image` filtered with the guides of the same view and size, on
/// `threads` threads (the result does not depend on how many).
///
/// # Panics
/// If the guides are not of `image`'s size.
pub fn denoise(image: &Image, guides: &Guides, threads: usize) -> Image {
    assert_eq!(
        (image.width, image.height),
        (guides.width, guides.height),
        "guides of another image size"
    );
    let (w, h) = (image.width as usize, image.height as usize);
    if w == 0 || h == 0 {
        return image.clone();
    }
    let g = &guides.pixels;
    // Finite colours only: a NaN pixel must not spread.
    let mut colour: Vec<Vec3> = image
        .pixels
        .iter()
        .map(|c| {
            let c = Vec3::from(*c);
            if c.is_finite() { c } else { Vec3::ZERO }
        })
        .collect();
    // Pixels on or beside a light are left as they are and lend nothing to others: a light's
    // brightness is no noise, and the guide rays may miss a light that covers part of a
    // pixel.
    let mut frozen = vec![false; w * h];
    for (p, gp) in g.iter().enumerate() {
        if gp.emitter > 0.0 {
            let (x, y) = (p % w, p / w);
            for qy in y.saturating_sub(1)..(y + 2).min(h) {
                for qx in x.saturating_sub(1)..(x + 2).min(w) {
                    frozen[qy * w + qx] = true;
                }
            }
        }
    }
    let grid = Grid {
        w,
        h,
        guides: g,
        frozen: &frozen,
    };
    let mut variance = spatial_variance(&colour, &grid, threads);
    for pass in 0..PASSES {
        let step = 1usize << pass;
        let blurred = blur3(&variance, w, h);
        let mut filtered: Vec<(Vec3, f32)> = vec![(Vec3::ZERO, 0.0); w * h];
        for_bands(&mut filtered, w, threads, |first_row, band| {
            for (i, slot) in band.iter_mut().enumerate() {
                let p = first_row * w + i;
                *slot = filter_pixel(p, step, &colour, &variance, &blurred, &grid);
            }
        });
        (colour, variance) = filtered.into_iter().unzip();
    }
    Image {
        width: image.width,
        height: image.height,
        pixels: colour.iter().map(|c| c.to_array()).collect(),
    }
}

/// An image's guides with its size, and which pixels the filter leaves alone.
#[derive(Clone, Copy)]
struct Grid<'a> {
    w: usize,
    h: usize,
    guides: &'a [GuidePixel],
    frozen: &'a [bool],
}

/// How much two pixels may share colour by what the camera sees there: the weight of their
/// normals' agreement, and an exponent (to be negated) for the neighbour's distance from this
/// pixel's tangent plane and from this pixel's point (`pixels` apart on the image) and for
/// their albedos' difference.
#[inline]
fn geometry_weight(p: &GuidePixel, q: &GuidePixel, pixels: f32) -> (f32, f32) {
    let mut wn = p.normal.dot(q.normal).max(0.0);
    for _ in 0..NORMAL_POWER_LOG2 {
        wn *= wn;
    }
    let d = q.position - p.position;
    let scale = p.footprint * pixels + 1e-20;
    let plane = p.normal.dot(d).abs() / (PLANE_SCALE * scale);
    let apart = d.length_squared() / (DISTANCE_SCALE * DISTANCE_SCALE * scale * scale);
    let albedo = (q.albedo - p.albedo).length_squared() / (ALBEDO_SCALE * ALBEDO_SCALE);
    (wn, plane + apart + albedo)
}

/// Each pixel's luminance variance, estimated from its 3x3 neighbourhood of like geometry
/// (one image has one sample of each pixel's noise; neighbours stand in for more).
fn spatial_variance(colour: &[Vec3], grid: &Grid<'_>, threads: usize) -> Vec<f32> {
    let Grid {
        w,
        h,
        guides: g,
        frozen,
    } = *grid;
    let mut out = vec![0.0f32; w * h];
    for_bands(&mut out, w, threads, |first_row, band| {
        for (i, slot) in band.iter_mut().enumerate() {
            let p = first_row * w + i;
            let (px, py) = (p % w, p / w);
            let (mut sw, mut s1, mut s2) = (0.0f32, 0.0f32, 0.0f32);
            for dy in -VARIANCE_RADIUS..=VARIANCE_RADIUS {
                for dx in -VARIANCE_RADIUS..=VARIANCE_RADIUS {
                    let (qx, qy) = (px as i32 + dx, py as i32 + dy);
                    if qx < 0 || qy < 0 || qx >= w as i32 || qy >= h as i32 {
                        continue;
                    }
                    let q = qy as usize * w + qx as usize;
                    if frozen[q] && q != p {
                        continue;
                    }
                    let dist = ((dx * dx + dy * dy) as f32).sqrt();
                    let (wn, plane) = geometry_weight(&g[p], &g[q], dist.max(1.0));
                    let wt = wn * (-plane).exp();
                    let l = luminance(colour[q]);
                    sw += wt;
                    s1 += wt * l;
                    s2 += wt * l * l;
                }
            }
            let mean = s1 / sw;
            *slot = (s2 / sw - mean * mean).max(0.0);
        }
    });
    out
}

/// A 3x3 Gaussian blur of a variance image (its estimate is itself noisy).
fn blur3(v: &[f32], w: usize, h: usize) -> Vec<f32> {
    const K: [f32; 3] = [0.25, 0.5, 0.25];
    let mut out = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (mut s, mut sw) = (0.0, 0.0);
            for (j, ky) in K.iter().enumerate() {
                for (i, kx) in K.iter().enumerate() {
                    let (qx, qy) = (x as i32 + i as i32 - 1, y as i32 + j as i32 - 1);
                    if qx < 0 || qy < 0 || qx >= w as i32 || qy >= h as i32 {
                        continue;
                    }
                    let k = kx * ky;
                    s += k * v[qy as usize * w + qx as usize];
                    sw += k;
                }
            }
            out[y * w + x] = s / sw;
        }
    }
    out
}

/// One à-trous tap set around pixel `p` with taps `step` pixels apart: the filtered colour
/// and the variance of its luminance.
#[inline]
fn filter_pixel(
    p: usize,
    step: usize,
    colour: &[Vec3],
    variance: &[f32],
    blurred_variance: &[f32],
    grid: &Grid<'_>,
) -> (Vec3, f32) {
    let Grid {
        w,
        h,
        guides: g,
        frozen,
    } = *grid;
    let (px, py) = ((p % w) as i32, (p / w) as i32);
    let gp = &g[p];
    if frozen[p] {
        return (colour[p], variance[p]);
    }
    let lp = luminance(colour[p]);
    let sigma = LUMINANCE_SCALE * blurred_variance[p].sqrt() + 1e-6;
    let (mut sum, mut sw, mut sv) = (Vec3::ZERO, 0.0f32, 0.0f32);
    for (j, ky) in KERNEL.iter().enumerate() {
        let dy = j as i32 - 2;
        let qy = py + dy * step as i32;
        if qy < 0 || qy >= h as i32 {
            continue;
        }
        for (i, kx) in KERNEL.iter().enumerate() {
            let dx = i as i32 - 2;
            let qx = px + dx * step as i32;
            if qx < 0 || qx >= w as i32 {
                continue;
            }
            let q = qy as usize * w + qx as usize;
            if frozen[q] {
                continue;
            }
            let wt = if q == p {
                kx * ky
            } else {
                let dist = step as f32 * ((dx * dx + dy * dy) as f32).sqrt();
                let (wn, plane) = geometry_weight(gp, &g[q], dist);
                let lum = (lp - luminance(colour[q])).abs() / sigma;
                kx * ky * wn * (-(plane + lum)).exp()
            };
            sum += wt * colour[q];
            sw += wt;
            sv += wt * wt * variance[q];
        }
    }
    (sum / sw, sv / (sw * sw))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat_guides(w: u32, h: u32) -> Guides {
        Guides {
            width: w,
            height: h,
            pixels: (0..w * h)
                .map(|i| GuidePixel {
                    albedo: Vec3::splat(0.5),
                    normal: Vec3::Z,
                    position: Vec3::new((i % w) as f32, (i / w) as f32, 0.0),
                    footprint: 1.0,
                    emitter: 0.0,
                })
                .collect(),
        }
    }

    /// A deterministic noise in [-1, 1].
    fn noise(i: u32) -> f32 {
        let h = (i as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        ((h >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }

    #[test]
    fn smooths_noise_on_a_flat_wall_and_keeps_its_mean() {
        let (w, h) = (64u32, 48u32);
        let g = flat_guides(w, h);
        let image = Image {
            width: w,
            height: h,
            pixels: (0..w * h).map(|i| [0.5 + 0.2 * noise(i); 3]).collect(),
        };
        let out = denoise(&image, &g, 2);
        let err = |im: &Image| {
            im.pixels.iter().map(|p| (p[0] - 0.5).powi(2)).sum::<f32>() / im.pixels.len() as f32
        };
        let mean =
            |im: &Image| im.pixels.iter().map(|p| p[0]).sum::<f32>() / im.pixels.len() as f32;
        assert!(
            err(&out) < err(&image) / 20.0,
            "{} vs {}",
            err(&out),
            err(&image)
        );
        assert!((mean(&out) - mean(&image)).abs() < 0.01);
    }

    #[test]
    fn keeps_an_edge_between_two_walls() {
        // Two walls at right angles meet at x = 32: light from one must not bleed into the
        // other, however different their brightness.
        let (w, h) = (64u32, 16u32);
        let mut g = flat_guides(w, h);
        for (i, p) in g.pixels.iter_mut().enumerate() {
            if i as u32 % w >= 32 {
                p.normal = Vec3::X;
            }
        }
        let image = Image {
            width: w,
            height: h,
            pixels: (0..w * h)
                .map(|i| if i % w < 32 { [0.1; 3] } else { [2.0; 3] })
                .collect(),
        };
        let out = denoise(&image, &g, 3);
        for (a, b) in out.pixels.iter().zip(&image.pixels) {
            assert!((a[0] - b[0]).abs() < 1e-4 * b[0], "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn keeps_texture_detail() {
        // A checkerboard under even light comes back as it was: no check lends colour to
        // another.
        let (w, h) = (32u32, 32u32);
        let mut g = flat_guides(w, h);
        for (i, p) in g.pixels.iter_mut().enumerate() {
            let (x, y) = (i as u32 % w, i as u32 / w);
            p.albedo = if (x / 4 + y / 4) % 2 == 0 {
                Vec3::splat(0.8)
            } else {
                Vec3::splat(0.1)
            };
        }
        let image = Image {
            width: w,
            height: h,
            pixels: g
                .pixels
                .iter()
                .map(|p| (p.albedo * 1.5).to_array())
                .collect(),
        };
        let out = denoise(&image, &g, 1);
        for (a, b) in out.pixels.iter().zip(&image.pixels) {
            assert!((a[0] - b[0]).abs() < 1e-4, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn the_same_bytes_on_any_number_of_threads_and_nan_does_not_spread() {
        let (w, h) = (40u32, 30u32);
        let g = flat_guides(w, h);
        let mut image = Image {
            width: w,
            height: h,
            pixels: (0..w * h).map(|i| [1.0 + noise(i), 1.0, 0.5]).collect(),
        };
        image.pixels[100] = [f32::NAN, 1.0, 1.0];
        let one = denoise(&image, &g, 1);
        assert!(one.pixels.iter().all(|p| p.iter().all(|c| c.is_finite())));
        for threads in [2, 3, 7, 64] {
            assert_eq!(denoise(&image, &g, threads), one, "{threads} threads");
        }
    }
}
