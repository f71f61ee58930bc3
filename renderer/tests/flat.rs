//! One process walks the top-level tree and every chunk's tree as one
//! ([`renderer::MemoryData::flatten`]). These tests hold it to the two-level walk a render
//! node does: the same hits to the bit, the same shadow answers, the same chunks recorded as
//! entered, the same image bytes.

use std::sync::atomic::AtomicBool;

use glam::{Vec3, Vec3A};
use renderer::{
    IntegratorKind, MemoryData, PrepareOptions, RenderSettings, SceneDesc, SceneHeader,
    demo::demo_scene,
    ray::Ray,
    render::render_image,
    sampler::Sampler,
    source::Touched,
    trace::{AlphaKey, Tracer},
};

/// A point uniform in the box from `lo` to `hi`, drawn from the renderer's own sampler (a
/// deterministic generator; these tests need no more of it).
fn within(g: &mut Sampler, lo: Vec3, hi: Vec3) -> Vec3 {
    lo + (hi - lo) * Vec3::new(g.get_1d(), g.get_1d(), g.get_1d())
}

/// The scene prepared twice: as a render node walks it (two levels) and flattened.
fn both(desc: SceneDesc, chunk_triangles: usize) -> (SceneHeader, MemoryData, MemoryData) {
    let (scene, two_levels) = renderer::prepare(desc, &PrepareOptions { chunk_triangles });
    let mut flat = two_levels.clone();
    assert!(flat.flatten(&scene), "the scene fits one tree");
    assert!(flat.flat.is_some() && two_levels.flat.is_none());
    (scene, two_levels, flat)
}

/// Rays from inside and around the scene's box in every direction, some of them short
/// (shadow rays end at a point), and rays aimed at the box from outside.
fn rays(scene: &SceneHeader, n: usize) -> Vec<Ray> {
    let (lo, hi) = (scene.bounds_min, scene.bounds_max);
    let pad = (hi - lo) * 0.25;
    let mut g = Sampler::new(1991, 0, 0, 0);
    (0..n)
        .map(|i| {
            let origin = within(&mut g, lo - pad, hi + pad);
            let target = within(&mut g, lo, hi);
            let dir = match i % 3 {
                0 => target - origin,
                _ => Vec3::new(g.get_1d() - 0.5, g.get_1d() - 0.5, g.get_1d() - 0.5),
            };
            let tmax = if i % 4 == 0 { 1.0 } else { f32::INFINITY };
            Ray::new(Vec3A::from(origin), Vec3A::from(dir), tmax)
        })
        .collect()
}

fn scenes() -> Vec<(&'static str, SceneDesc)> {
    // The demo scene's materials are single-sided: hits are taken chunk by chunk (culled
    // back faces). Made double-sided, every surface takes every hit.
    let mut solid = demo_scene();
    for m in &mut solid.materials {
        m.double_sided = true;
    }
    vec![("demo", demo_scene()), ("demo, double-sided", solid)]
}

#[test]
fn one_tree_finds_what_two_levels_find() {
    for (name, desc) in scenes() {
        // Chunks of one four-triangle block (whose trees the walks skip), small chunks, and
        // the default.
        for chunk_triangles in [4, 64, 4096] {
            let (scene, two_levels, flat) = both(desc.clone(), chunk_triangles);
            let key = AlphaKey::new(&Sampler::new(0, 0, 0, 0), 0);
            let (a, b) = (Tracer::new(&scene, &two_levels), Tracer::new(&scene, &flat));
            let mut hits = 0;
            for (i, ray) in rays(&scene, 4000).iter().enumerate() {
                let found = |t: &Tracer<'_, MemoryData>| {
                    t.closest(ray, key).unwrap().map(|h| {
                        let th = h.tri_hit;
                        (
                            h.chunk.header().chunk_id,
                            h.tri,
                            [th.t, th.b0, th.b1, th.b2].map(f32::to_bits),
                        )
                    })
                };
                let want = found(&a);
                hits += usize::from(want.is_some());
                assert_eq!(
                    found(&b),
                    want,
                    "{name}, chunks of {chunk_triangles}: ray {i} {ray:?}"
                );
                assert_eq!(
                    b.occluded(ray, key).unwrap(),
                    a.occluded(ray, key).unwrap(),
                    "{name}, chunks of {chunk_triangles}: shadow ray {i} {ray:?}"
                );
            }
            assert!(hits > 1000, "{name}: most rays hit something ({hits})");
        }
    }
}

#[test]
fn chunks_entered_are_recorded_as_the_two_levels_record_them() {
    let (scene, two_levels, flat) = both(demo_scene(), 64);
    let key = AlphaKey::new(&Sampler::new(0, 0, 0, 0), 0);
    let chunks = scene.chunks.len();
    let (ta, tb) = (Touched::new(chunks, 0), Touched::new(chunks, 0));
    let (wa, wb) = (ta.watching(&two_levels), tb.watching(&flat));
    let (a, b) = (Tracer::new(&scene, &wa), Tracer::new(&scene, &wb));
    let mut entered = 0;
    for (i, ray) in rays(&scene, 2000).iter().enumerate() {
        a.closest(ray, key).unwrap();
        b.closest(ray, key).unwrap();
        let want = ta.take().0;
        entered += want.len();
        assert_eq!(tb.take().0, want, "closest-hit ray {i} {ray:?}");
        a.occluded(ray, key).unwrap();
        b.occluded(ray, key).unwrap();
        assert_eq!(tb.take().0, ta.take().0, "shadow ray {i} {ray:?}");
    }
    assert!(entered > 1000, "rays enter chunks ({entered})");
}

#[test]
fn images_are_the_same_bytes_walked_as_one_tree() {
    let (scene, two_levels, flat) = both(demo_scene(), 256);
    let camera = scene.camera(None, 40.0 / 30.0).unwrap();
    let cancel = AtomicBool::new(false);
    for integrator in [IntegratorKind::Path, IntegratorKind::Whitted] {
        let s = RenderSettings {
            width: 40,
            height: 30,
            spp: 4,
            seed: 3,
            integrator,
            ..RenderSettings::default()
        };
        let render = |data: &MemoryData| {
            render_image(&scene, data, &camera, &s, 2, 8, &cancel, &|_, _| {})
                .unwrap()
                .0
        };
        let bits = |img: renderer::Image| -> Vec<[u32; 3]> {
            img.pixels.iter().map(|p| p.map(f32::to_bits)).collect()
        };
        assert_eq!(
            bits(render(&flat)),
            bits(render(&two_levels)),
            "{integrator:?}"
        );
    }
}
