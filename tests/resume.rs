//! Resume: a render killed mid-way (kill -9: no chance to tidy up) continues from its
//! checkpoint `OUT.partial`, in one process or on a cluster of another shape, and ends in
//! the same bytes as an uninterrupted render; a checkpoint of other settings is refused.

mod common;
use common::*;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const SIZE: [&str; 6] = ["--width", "64", "--height", "48", "--spp", "1024"];

fn scene() -> PathBuf {
    data().join("scenes/cornell/cornell.gltf")
}

/// Finished scan lines in a checkpoint file (its layout is in `host::checkpoint`): the magic,
/// a u32 header length, the header, then one byte per line.
fn lines_finished(partial: &Path, height: usize) -> usize {
    let Ok(b) = std::fs::read(partial) else {
        return 0;
    };
    let len = u32::from_le_bytes(b[8..12].try_into().unwrap()) as usize;
    b[12 + len..12 + len + height]
        .iter()
        .filter(|&&x| x == 1)
        .count()
}

/// Starts a render that writes its checkpoint after every tile, waits until the checkpoint
/// holds some finished lines, and kills the host (and any nodes) with SIGKILL.
fn killed_mid_render(out: &Path, mode: &[&str]) {
    let mut render = Logged::start(
        host()
            .arg("render")
            .arg(scene())
            .args(SIZE)
            .args(mode)
            .args(["--checkpoint-every", "0", "--quiet", "-o"])
            .arg(out),
    );
    let partial = PathBuf::from(format!("{}.partial", out.display()));
    let deadline = Instant::now() + Duration::from_secs(120);
    while lines_finished(&partial, 48) == 0 {
        assert!(
            Instant::now() < deadline,
            "no checkpoint appeared: {}",
            render.log()
        );
        assert!(
            render.child.try_wait().unwrap().is_none(),
            "the render ended before it could be killed: {}",
            render.log()
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    for pid in children_of(render.pid()) {
        let _ = rustix::process::kill_process(
            rustix::process::Pid::from_raw(pid as i32).unwrap(),
            rustix::process::Signal::KILL,
        );
    }
    render.kill9();
    assert!(!out.exists(), "a killed render wrote its image");
    let kept = lines_finished(&partial, 48);
    assert!((1..48).contains(&kept), "{kept} lines kept");
}

fn finish(out: &Path, mode: &[&str]) -> String {
    let o = run(host()
        .arg("render")
        .arg(scene())
        .args(SIZE)
        .args(mode)
        .args(["--resume", "--quiet", "-o"])
        .arg(out));
    assert!(o.status.success(), "{}", stderr(&o));
    stderr(&o)
}

fn uninterrupted(dir: &Path) -> PathBuf {
    let reference = dir.join("reference.pfm");
    let o = run(host()
        .arg("render")
        .arg(scene())
        .args(SIZE)
        .args(["--in-process", "--quiet", "-o"])
        .arg(&reference));
    assert!(o.status.success(), "{}", stderr(&o));
    reference
}

#[test]
fn a_killed_in_process_render_resumes_to_the_same_bytes() {
    let dir = scratch("resume-in-process");
    let out = dir.join("image.pfm");
    killed_mid_render(&out, &["--in-process"]);
    let partial = dir.join("image.pfm.partial");
    let o = run(host()
        .arg("render")
        .arg(scene())
        .args(SIZE)
        .args(["--in-process", "--quiet", "-o"])
        .arg(&out));
    assert!(
        !o.status.success(),
        "started over a checkpoint without --resume"
    );
    assert!(stderr(&o).contains("--resume"), "{}", stderr(&o));
    finish(&out, &["--in-process"]);
    assert!(
        !partial.exists(),
        "the checkpoint outlived the finished image"
    );
    same_bytes(&out, &uninterrupted(&dir));
}

#[test]
fn a_checkpoint_of_other_settings_is_refused_with_the_reason() {
    let dir = scratch("resume-mismatch");
    let out = dir.join("image.pfm");
    killed_mid_render(&out, &["--in-process"]);
    let o = run(host()
        .arg("render")
        .arg(scene())
        .args(["--width", "64", "--height", "48", "--spp", "64"])
        .args(["--in-process", "--resume", "--quiet", "-o"])
        .arg(&out));
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("spp was 1024, this render has 64"),
        "{}",
        stderr(&o)
    );
    let o = run(host()
        .arg("render")
        .args(SIZE)
        .args(["--in-process", "--resume", "--quiet", "-o"])
        .arg(&out));
    assert!(!o.status.success());
    assert!(stderr(&o).contains("another scene"), "{}", stderr(&o));
    assert!(
        dir.join("image.pfm.partial").exists(),
        "a refused resume lost the checkpoint"
    );
}

#[test]
fn a_killed_cluster_render_resumes_in_one_process_to_the_same_bytes() {
    let dir = scratch("resume-cluster");
    let out = dir.join("image.pfm");
    killed_mid_render(&out, &["--spawn", "tiny"]);
    finish(&out, &["--in-process"]);
    same_bytes(&out, &uninterrupted(&dir));
}

#[test]
fn a_killed_render_resumes_on_a_cluster_of_another_shape_to_the_same_bytes() {
    let dir = scratch("resume-reshaped");
    let out = dir.join("image.pfm");
    killed_mid_render(&out, &["--spawn", "tiny"]);
    finish(&out, &["--spawn", "grid:2x1x2"]);
    assert!(!dir.join("image.pfm.partial").exists());
    same_bytes(&out, &uninterrupted(&dir));
}
