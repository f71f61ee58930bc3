//! The image does not depend on how the screen is divided or who renders it: the same seed
//! gives the same bytes for any tile size, thread count or rectangle.

use std::sync::atomic::AtomicBool;

use renderer::{
    IntegratorKind, PrepareOptions, Rect, RenderSettings,
    demo::demo_scene,
    render::{Image, render_image, render_rect},
};

fn settings(integrator: IntegratorKind) -> RenderSettings {
    RenderSettings {
        width: 48,
        height: 36,
        spp: 4,
        seed: 7,
        integrator,
        max_depth: 16,
        ..RenderSettings::default()
    }
}

#[test]
fn same_bytes_for_any_tiling_threads_and_rectangles() {
    let (scene, data) = renderer::prepare(demo_scene(), &PrepareOptions::default());
    let camera = scene.camera(None, 48.0 / 36.0).unwrap();
    let cancel = AtomicBool::new(false);
    for integrator in [IntegratorKind::Path, IntegratorKind::Whitted] {
        let s = settings(integrator);
        let (reference, _) =
            render_image(&scene, &data, &camera, &s, 1, 48, &cancel, &|_, _| {}).unwrap();
        for (threads, tile) in [(2, 16), (3, 7), (4, 1), (5, 13)] {
            let (img, _) = render_image(
                &scene,
                &data,
                &camera,
                &s,
                threads,
                tile,
                &cancel,
                &|_, _| {},
            )
            .unwrap();
            assert_eq!(
                img, reference,
                "{integrator}: {threads} threads, tiles of {tile}"
            );
        }
        // Odd rectangles rendered on their own, assembled.
        let mut assembled = Image::new(s.width, s.height);
        for rect in [
            Rect {
                x: 0,
                y: 0,
                width: 48,
                height: 5,
            },
            Rect {
                x: 0,
                y: 5,
                width: 11,
                height: 31,
            },
            Rect {
                x: 11,
                y: 5,
                width: 37,
                height: 31,
            },
        ] {
            let mut buf = vec![[0.0; 3]; rect.pixel_count()];
            render_rect(&scene, &data, &camera, &s, rect, &mut buf, &cancel).unwrap();
            assembled.put_rect(rect, &buf);
        }
        assert_eq!(assembled, reference, "{integrator}: assembled rectangles");
    }
}

#[test]
fn chunk_size_does_not_change_the_picture_beyond_ties() {
    // Different chunkings build different trees; the nearest hit is the same surface, so
    // the images agree to within float noise of the hit point.
    let s = settings(IntegratorKind::Whitted);
    let cancel = AtomicBool::new(false);
    let mut images = Vec::new();
    for chunk_triangles in [64, 4096] {
        let (scene, data) = renderer::prepare(demo_scene(), &PrepareOptions { chunk_triangles });
        let camera = scene.camera(None, 48.0 / 36.0).unwrap();
        images.push(
            render_image(&scene, &data, &camera, &s, 2, 16, &cancel, &|_, _| {})
                .unwrap()
                .0,
        );
    }
    let diff: f64 = images[0]
        .pixels
        .iter()
        .zip(&images[1].pixels)
        .map(|(a, b)| (0..3).map(|c| (a[c] - b[c]).abs() as f64).sum::<f64>())
        .sum::<f64>()
        / (images[0].pixels.len() * 3) as f64;
    assert!(diff < 1e-3, "mean abs difference {diff}");
}
