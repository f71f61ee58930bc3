//! Comparing two linear images the way renderer papers do: relative mean squared error and
//! per-channel means.

use renderer::Image;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Comparison {
    /// mean over pixels and channels of (a - b)^2 / (b^2 + 0.01).
    pub rel_mse: f64,
    pub mean_a: [f64; 3],
    pub mean_b: [f64; 3],
    /// (mean_a - mean_b) / mean_b per channel.
    pub mean_rel_diff: [f64; 3],
}

/// Two images that cannot be compared pixel by pixel.
#[derive(Debug, thiserror::Error)]
#[error("image sizes differ: {0}x{1} vs {2}x{3}")]
pub struct SizeMismatch(pub u32, pub u32, pub u32, pub u32);

/// Compares `a` against the reference `b`. Errors if the sizes differ.
pub fn compare(a: &Image, b: &Image) -> Result<Comparison, SizeMismatch> {
    if a.width != b.width || a.height != b.height {
        return Err(SizeMismatch(a.width, a.height, b.width, b.height));
    }
    let mut sum = 0f64;
    for (pa, pb) in a.pixels.iter().zip(&b.pixels) {
        for c in 0..3 {
            let (x, y) = (pa[c] as f64, pb[c] as f64);
            sum += (x - y) * (x - y) / (y * y + 0.01);
        }
    }
    let rel_mse = sum / (a.pixels.len().max(1) * 3) as f64;
    let (ma, mb) = (a.channel_means(), b.channel_means());
    let mean_rel_diff = [0, 1, 2].map(|c| {
        if mb[c] != 0.0 {
            (ma[c] - mb[c]) / mb[c]
        } else {
            0.0
        }
    });
    Ok(Comparison {
        rel_mse,
        mean_a: ma,
        mean_b: mb,
        mean_rel_diff,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_images_have_zero_error() {
        let mut a = Image::new(2, 2);
        a.pixels[1] = [0.5, 0.2, 0.1];
        let c = compare(&a, &a).unwrap();
        assert_eq!(c.rel_mse, 0.0);
        let mut b = a.clone();
        b.pixels[1][0] = 0.6;
        let c = compare(&b, &a).unwrap();
        let expected = (0.01 / (0.25 + 0.01)) / 12.0;
        assert!((c.rel_mse - expected).abs() < 1e-5 * expected);
    }
}
