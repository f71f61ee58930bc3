//! The built-in demo scene, made in code so that the first command needs no file: a closed
//! room lit by an area light in its ceiling, with a mirror sphere, a glass sphere and a
//! textured floor. It shows what the renderer does: soft shadows, reflection, refraction,
//! caustics (with `path`) and texture mapping.

use glam::{Vec2, Vec3, Vec4};

use crate::{
    camera::{Camera, Projection},
    chunk::MeshData,
    material::{Material, TexRef, UvTransform},
    scene::{SceneDesc, TextureDesc},
    texture::{Filter, Wrap},
};

fn quad(corners: [Vec3; 4], material: u32, uv_scale: f32) -> MeshData {
    // Corners counter-clockwise seen from the side the quad faces.
    let n = (corners[1] - corners[0])
        .cross(corners[2] - corners[0])
        .normalize();
    MeshData {
        positions: corners.to_vec(),
        normals: vec![n; 4],
        uv0: vec![
            Vec2::new(0.0, uv_scale),
            Vec2::new(uv_scale, uv_scale),
            Vec2::new(uv_scale, 0.0),
            Vec2::new(0.0, 0.0),
        ],
        triangles: vec![[0, 1, 2], [0, 2, 3]],
        material,
        ..Default::default()
    }
}

/// A UV sphere with smooth normals.
pub fn sphere(center: Vec3, radius: f32, segments: u32, rings: u32, material: u32) -> MeshData {
    let mut m = MeshData {
        material,
        ..Default::default()
    };
    for r in 0..=rings {
        let v = r as f32 / rings as f32;
        let theta = v * std::f32::consts::PI;
        for s in 0..=segments {
            let u = s as f32 / segments as f32;
            // The seam's last column repeats the first exactly (sin(2 pi) is not 0 in f32),
            // so the sphere is closed.
            let phi = if s == segments {
                0.0
            } else {
                u * std::f32::consts::TAU
            };
            let n = Vec3::new(
                theta.sin() * phi.cos(),
                theta.cos(),
                -theta.sin() * phi.sin(),
            );
            m.positions.push(center + n * radius);
            m.normals.push(n);
            m.uv0.push(Vec2::new(u, v));
        }
    }
    let w = segments + 1;
    for r in 0..rings {
        for s in 0..segments {
            let a = r * w + s;
            let b = a + w;
            if r != 0 {
                m.triangles.push([a, b, a + 1]);
            }
            if r != rings - 1 {
                m.triangles.push([a + 1, b, b + 1]);
            }
        }
    }
    m
}

fn checker(size: u32) -> TextureDesc {
    let mut rgba = Vec::with_capacity((size * size * 4) as usize);
    for y in 0..size {
        for x in 0..size {
            let odd = ((x * 8 / size) + (y * 8 / size)) % 2 == 1;
            let c: [u8; 4] = if odd {
                [40, 60, 90, 255]
            } else {
                [225, 215, 190, 255]
            };
            rgba.extend_from_slice(&c);
        }
    }
    TextureDesc {
        name: "checker".into(),
        width: size,
        height: size,
        rgba,
        wrap_s: Wrap::Repeat,
        wrap_t: Wrap::Repeat,
        filter: Filter::Linear,
        texels_of: None,
    }
}

/// The demo scene.
pub fn demo_scene() -> SceneDesc {
    let white = Material::diffuse("white", Vec3::new(0.75, 0.74, 0.72));
    let red = Material::diffuse("red", Vec3::new(0.63, 0.07, 0.05));
    let green = Material::diffuse("green", Vec3::new(0.12, 0.45, 0.09));
    let floor = Material {
        base_color_tex: Some(TexRef {
            texture: 0,
            tex_coord: 0,
            transform: Some(UvTransform {
                offset: Vec2::ZERO,
                rotation: 0.0,
                scale: Vec2::splat(0.5),
            }),
        }),
        ..Material::diffuse("floor", Vec3::ONE)
    };
    let light = Material {
        name: "light".into(),
        base_color: Vec4::new(0.0, 0.0, 0.0, 1.0),
        metallic: 0.0,
        specular: 0.0,
        emissive: Vec3::new(14.0, 12.0, 9.0),
        double_sided: false,
        ..Material::default()
    };
    let mirror = Material {
        name: "mirror".into(),
        base_color: Vec4::new(0.95, 0.95, 0.95, 1.0),
        metallic: 1.0,
        roughness: 0.0,
        ..Material::default()
    };
    let glass = Material::glass("glass");
    let materials = vec![white, red, green, floor, light, mirror, glass];
    let (w, r, g, f, l, mi, gl) = (0, 1, 2, 3, 4, 5, 6);

    let (x0, x1, y0, y1, z0, z1) = (-2.0f32, 2.0f32, 0.0f32, 3.0f32, -2.5f32, 2.5f32);
    let p = Vec3::new;
    let mut meshes = vec![
        // Floor (faces up), textured; ceiling (faces down); walls facing inwards.
        quad(
            [p(x0, y0, z1), p(x1, y0, z1), p(x1, y0, z0), p(x0, y0, z0)],
            f,
            5.0,
        ),
        quad(
            [p(x0, y1, z0), p(x1, y1, z0), p(x1, y1, z1), p(x0, y1, z1)],
            w,
            1.0,
        ),
        quad(
            [p(x0, y0, z0), p(x1, y0, z0), p(x1, y1, z0), p(x0, y1, z0)],
            w,
            1.0,
        ),
        quad(
            [p(x1, y0, z1), p(x0, y0, z1), p(x0, y1, z1), p(x1, y1, z1)],
            w,
            1.0,
        ),
        quad(
            [p(x0, y0, z1), p(x0, y0, z0), p(x0, y1, z0), p(x0, y1, z1)],
            r,
            1.0,
        ),
        quad(
            [p(x1, y0, z0), p(x1, y0, z1), p(x1, y1, z1), p(x1, y1, z0)],
            g,
            1.0,
        ),
        // The light, just below the ceiling, facing down.
        quad(
            [
                p(-0.6, y1 - 0.01, -0.6),
                p(0.6, y1 - 0.01, -0.6),
                p(0.6, y1 - 0.01, 0.6),
                p(-0.6, y1 - 0.01, 0.6),
            ],
            l,
            1.0,
        ),
    ];
    meshes.push(sphere(p(-0.85, 0.65, -1.1), 0.65, 64, 32, mi));
    meshes.push(sphere(p(0.8, 0.6, -0.2), 0.6, 64, 32, gl));

    let eye = p(0.0, 1.5, 2.3);
    let target = p(0.0, 0.9, -1.0);
    let camera = Camera::look_at(
        "demo",
        eye,
        target,
        Projection::Perspective {
            yfov: 55f32.to_radians(),
        },
    );

    SceneDesc {
        meshes,
        materials,
        textures: vec![checker(256)],
        lights: Vec::new(),
        cameras: vec![camera],
        environment: None,
    }
}

/// A scene made to make a Whitted tracer run away: `count` concentric glass spheres (each a
/// closed surface of its own), the outermost of radius 1, seen from close by, lit by a point
/// light above a diffuse floor. Every surface splits a ray into a reflected and a refracted
/// branch, and total internal reflection between the shells keeps branches strong.
pub fn glass_shells(count: u32) -> SceneDesc {
    let glass = Material::glass("glass");
    let floor = Material::diffuse("floor", Vec3::splat(0.7));
    let mut meshes: Vec<MeshData> = (0..count)
        .map(|i| {
            let radius = 1.0 - 0.9 * i as f32 / count.max(1) as f32;
            sphere(Vec3::ZERO, radius, 32, 16, 0)
        })
        .collect();
    meshes.push(quad(
        [
            Vec3::new(-10.0, -1.0, 10.0),
            Vec3::new(10.0, -1.0, 10.0),
            Vec3::new(10.0, -1.0, -10.0),
            Vec3::new(-10.0, -1.0, -10.0),
        ],
        1,
        1.0,
    ));
    let camera = Camera::look_at(
        "shells",
        Vec3::new(0.4, 0.6, 2.6),
        Vec3::ZERO,
        Projection::Perspective {
            yfov: 45f32.to_radians(),
        },
    );
    SceneDesc {
        meshes,
        materials: vec![glass, floor],
        textures: Vec::new(),
        lights: vec![crate::light::Light::Point {
            position: Vec3::new(1.0, 4.0, 2.0),
            intensity: Vec3::splat(40.0),
        }],
        cameras: vec![camera],
        environment: None,
    }
}
