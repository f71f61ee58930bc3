//! The path tracer converges to what an independent unbiased renderer (Mitsuba 3) computes
//! for the Cornell box: relative MSE falls as 1/spp (or faster) and reaches the bar of
//! `tests/data/references/cornell/README.md` at 1024 spp; channel means agree within 1%.

mod common;
use common::*;

fn render_cornell(spp: u32, dir: &std::path::Path) -> renderer::Image {
    let scene = data().join("scenes/cornell/cornell.gltf");
    let out = dir.join(format!("cornell-{spp}.exr"));
    let o = run(host()
        .arg("render")
        .arg(&scene)
        .args([
            "--width", "256", "--height", "256", "--seed", "11", "--quiet", "--spp",
        ])
        .arg(spp.to_string())
        .arg("-o")
        .arg(&out));
    assert!(o.status.success(), "{}", stderr(&o));
    scene_io::read_image(&out).unwrap()
}

#[test]
fn cornell_box_converges_to_the_mitsuba_reference() {
    let dir = scratch("cornell");
    let reference =
        scene_io::read_image(&data().join("references/cornell/cornell_ref.exr")).unwrap();
    let mut errors = Vec::new();
    for spp in [16, 64, 1024] {
        let img = render_cornell(spp, &dir);
        let c = lab::compare::compare(&img, &reference).unwrap();
        eprintln!(
            "{spp} spp: relMSE {:.3e}, means {:?} vs {:?}",
            c.rel_mse, c.mean_a, c.mean_b
        );
        for d in c.mean_rel_diff {
            assert!(
                d.abs() < 0.01,
                "{spp} spp: channel mean off by {:.2}%",
                d * 100.0
            );
        }
        errors.push(c.rel_mse);
    }
    // 1/spp: each step of 4x (16 -> 64) and 16x (64 -> 1024) cuts the error about as much.
    let r1 = errors[0] / errors[1];
    let r2 = errors[1] / errors[2];
    assert!(
        (3.0..5.5).contains(&r1),
        "16->64 spp cut relMSE by {r1:.2}, expected about 4"
    );
    assert!(
        (11.0..22.0).contains(&r2),
        "64->1024 spp cut relMSE by {r2:.2}, expected about 16"
    );
    assert!(
        errors[2] < 2.5e-4,
        "1024 spp relMSE {:.3e} is above the 2.5e-4 bar",
        errors[2]
    );
}
