//! Pinhole cameras as glTF defines them: looking down their local -Z, +Y up.

use glam::{Mat3, Vec3};
use serde::{Deserialize, Serialize};

use crate::ray::Ray;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Projection {
    /// Vertical field of view in radians.
    Perspective { yfov: f32 },
    /// Half the height of the view in scene units (glTF's `ymag`); the width follows the
    /// image's aspect ratio.
    Orthographic { ymag: f32 },
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub name: String,
    pub position: Vec3,
    /// Columns: camera right, up, backward (the camera looks down -Z), orthonormal.
    pub orientation: Mat3,
    pub projection: Projection,
    /// Width over height the camera was made for, when the scene says (glTF's
    /// `aspectRatio`); the image size decides when it is absent.
    #[serde(default)]
    pub aspect_ratio: Option<f32>,
}

/// A camera's rays for one image size, with what every ray shares worked out once (the
/// field of view's tangent is a libm call, and a pixel casts many rays).
#[derive(Clone, Copy, Debug)]
pub struct CameraRays<'a> {
    camera: &'a Camera,
    width: f32,
    height: f32,
    aspect: f32,
    /// Half the view's height at distance 1 (perspective) or in scene units (orthographic).
    half_height: f32,
}

impl CameraRays<'_> {
    /// The ray through image position (x, y) in pixels, (0, 0) the top-left corner.
    #[inline]
    pub fn ray(&self, x: f32, y: f32) -> Ray {
        let c = self.camera;
        let (h, aspect) = (self.half_height, self.aspect);
        let sx = 2.0 * x / self.width - 1.0;
        let sy = 1.0 - 2.0 * y / self.height;
        match c.projection {
            Projection::Perspective { .. } => {
                let d = Vec3::new(sx * h * aspect, sy * h, -1.0);
                Ray::infinite(c.position, (c.orientation * d).normalize())
            }
            Projection::Orthographic { .. } => {
                let o = Vec3::new(sx * h * aspect, sy * h, 0.0);
                Ray::infinite(c.position + c.orientation * o, c.orientation * -Vec3::Z)
            }
        }
    }
}

impl Camera {
    /// The rays of an image of `width` x `height` pixels.
    pub fn rays(&self, width: u32, height: u32) -> CameraRays<'_> {
        CameraRays {
            camera: self,
            width: width as f32,
            height: height as f32,
            aspect: width as f32 / height as f32,
            half_height: match self.projection {
                Projection::Perspective { yfov } => (yfov * 0.5).tan(),
                Projection::Orthographic { ymag } => ymag,
            },
        }
    }

    /// The ray through image position (x, y) in pixels, (0, 0) the top-left corner.
    #[inline]
    pub fn ray(&self, width: u32, height: u32, x: f32, y: f32) -> Ray {
        self.rays(width, height).ray(x, y)
    }

    /// A camera that looks at `target` from `eye`, with +Y kept up where possible.
    pub fn look_at(name: &str, eye: Vec3, target: Vec3, projection: Projection) -> Camera {
        let back = (eye - target).normalize_or(Vec3::Z);
        let up_hint = if back.cross(Vec3::Y).length_squared() < 1e-8 {
            Vec3::Z
        } else {
            Vec3::Y
        };
        let right = up_hint.cross(back).normalize();
        let up = back.cross(right);
        Camera {
            name: name.to_string(),
            position: eye,
            orientation: Mat3::from_cols(right, up, back),
            projection,
            aspect_ratio: None,
        }
    }

    /// A perspective camera that frames a box (given by its corners) from the front, slightly
    /// above and to the side, for scenes that bring no camera of their own.
    pub fn framing(min: Vec3, max: Vec3, aspect: f32) -> Camera {
        let center = (min + max) * 0.5;
        let radius = ((max - min).length() * 0.5).max(f32::MIN_POSITIVE * 1e10);
        let yfov = 40f32.to_radians();
        // Distance at which the bounding sphere fits both the vertical and horizontal view.
        let half = (yfov * 0.5).tan();
        let fit = half.min(half * aspect).atan();
        let dist = radius / fit.sin();
        let dir = Vec3::new(0.35, 0.3, 1.0).normalize();
        Camera::look_at(
            "automatic",
            center + dir * dist,
            center,
            Projection::Perspective { yfov },
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centre_ray_looks_down_minus_z() {
        let c = Camera {
            name: String::new(),
            position: Vec3::ZERO,
            orientation: Mat3::IDENTITY,
            projection: Projection::Perspective { yfov: 1.0 },
            aspect_ratio: None,
        };
        let r = c.ray(100, 50, 50.0, 25.0);
        assert!((Vec3::from(r.dir) - -Vec3::Z).length() < 1e-6);
        // Top-left corner points up and left.
        let r = c.ray(100, 50, 0.0, 0.0);
        assert!(r.dir.x < 0.0 && r.dir.y > 0.0);
    }

    #[test]
    fn shared_setup_gives_the_same_rays() {
        for projection in [
            Projection::Perspective { yfov: 0.7 },
            Projection::Orthographic { ymag: 2.5 },
        ] {
            let c = Camera::look_at("c", Vec3::new(1.0, 2.0, 3.0), Vec3::ZERO, projection);
            let rays = c.rays(64, 48);
            for (x, y) in [(0.0, 0.0), (31.7, 12.25), (63.99, 47.5)] {
                let (a, b) = (rays.ray(x, y), c.ray(64, 48, x, y));
                assert_eq!((a.origin, a.dir), (b.origin, b.dir));
            }
        }
    }

    #[test]
    fn framing_sees_the_box() {
        let c = Camera::framing(Vec3::splat(-1.0), Vec3::splat(1.0), 1.5);
        let r = c.ray(150, 100, 75.0, 50.0);
        // The centre ray passes close to the box centre.
        let to_c = -Vec3::from(r.origin);
        let closest = (to_c - Vec3::from(r.dir) * to_c.dot(Vec3::from(r.dir))).length();
        assert!(closest < 1e-3);
    }
}
