//! The command line, as a user meets it: the first command renders the demo scene, and
//! every mistake is one clear line with a non-zero exit and no file left behind.

mod common;
use common::*;

use std::path::Path;

#[test]
fn render_with_no_scene_writes_the_demo_image() {
    let dir = scratch("demo");
    let out = dir.join("magg.png");
    let o = run(host()
        .args([
            "render", "--width", "64", "--height", "48", "--spp", "2", "-o",
        ])
        .arg(&out));
    assert!(o.status.success(), "{}", stderr(&o));
    let img = image::open(&out).expect("a PNG was written");
    assert_eq!((img.width(), img.height()), (64, 48));
}

/// A width alone keeps the default size's 4:3 shape where the camera gives no aspect ratio
/// (the demo's): `--width 160` rendered 160x480.
#[test]
fn a_width_alone_keeps_four_by_three() {
    let dir = scratch("width-alone");
    for (width, height) in [(160, 120), (7, 6)] {
        let out = dir.join(format!("{width}.png"));
        let o = run(host()
            .args(["render", "--in-process", "--spp", "1", "--width"])
            .arg(width.to_string())
            .arg("-o")
            .arg(&out));
        assert!(o.status.success(), "{}", stderr(&o));
        let img = image::open(&out).expect("a PNG was written");
        assert_eq!((img.width(), img.height()), (width, height));
    }
}

/// The README's first command on a fresh clone: `cargo run` builds `magg-host` alone, so a
/// render that spawns its nodes must need no other executable (they run the host's own).
#[test]
fn a_lone_host_executable_spawns_its_own_nodes() {
    let dir = scratch("lone-host");
    let exe = dir.join("magg-host");
    std::fs::copy(env!("CARGO_BIN_EXE_magg-host"), &exe).unwrap();
    let out = dir.join("magg.png");
    // `run` starts the copy again while Linux still calls it busy (see there).
    let o = run(std::process::Command::new(&exe)
        .current_dir(&dir)
        .env("MAGG_LOG", "warn")
        .args([
            "render", "--spawn", "tiny", "--width", "32", "--height", "24", "--spp", "2", "-o",
        ])
        .arg(&out));
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(out.exists());
}

#[test]
fn stats_file_reports_the_work() {
    let dir = scratch("stats");
    let out = dir.join("a.exr");
    let stats = dir.join("s.json");
    let o = run(host()
        .args([
            "render", "--width", "32", "--height", "32", "--spp", "3", "-o",
        ])
        .arg(&out)
        .arg("--stats")
        .arg(&stats));
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
    assert_eq!(v["samples"], 32 * 32 * 3);
    assert!(v["rays"]["total"].as_u64().unwrap() >= 32 * 32 * 3);
    assert!(v["seconds"]["render"].as_f64().unwrap() > 0.0);
    assert!(v["samples_per_second"].as_f64().unwrap() > 0.0);
    records_add_up(&v, 32 * 32);
    // The plots of its records, beside the stats.
    let o = run(host().arg("plot").arg(&stats));
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(dir.join("s.timeline.png").is_file());
    assert!(dir.join("s.nodes.png").is_file());
}

/// The per-subscreen records of a `--stats` file add up to the render's totals.
fn records_add_up(v: &serde_json::Value, pixels: u64) {
    let records = v["subscreens"].as_array().unwrap();
    let sum = |key: &str| {
        records
            .iter()
            .map(|r| r[key].as_u64().unwrap())
            .sum::<u64>()
    };
    assert_eq!(sum("pixels"), pixels);
    assert_eq!(sum("samples"), v["samples"].as_u64().unwrap());
    assert_eq!(sum("rays"), v["rays"]["total"].as_u64().unwrap());
    for r in records {
        assert!(r["start_s"].as_f64().unwrap() <= r["end_s"].as_f64().unwrap());
    }
    assert!(
        records
            .iter()
            .any(|r| !r["chunks"].as_array().unwrap().is_empty()),
        "the demo scene's geometry is touched"
    );
    assert_eq!(
        v["chunk_bytes"].as_array().unwrap().len() as u64,
        v["chunks"].as_u64().unwrap()
    );
}

/// In one process, a record per tile, by the thread that rendered it, nothing fetched.
#[test]
fn in_process_stats_record_every_tile() {
    let dir = scratch("stats-in-process");
    let out = dir.join("a.png");
    let stats = dir.join("s.json");
    let o = run(host()
        .args(["render", "--in-process", "--threads", "2"])
        .args(["--width", "40", "--height", "24", "--spp", "2", "-o"])
        .arg(&out)
        .arg("--stats")
        .arg(&stats));
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
    records_add_up(&v, 40 * 24);
    let records = v["subscreens"].as_array().unwrap();
    // 16x16 tiles: three across, two down.
    assert_eq!(records.len(), 6);
    for r in records {
        assert!(r["node"].as_u64().unwrap() < 2, "{r}");
        assert_eq!(r["fetched_via"], "none");
        assert_eq!(r["fetches"], 0);
        assert!(r["cpu_s"].as_f64().unwrap() > 0.0, "{r}");
    }
    let o = run(host().arg("plot").arg(&stats).arg("-o").arg(dir.join("p")));
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(dir.join("p/s.timeline.png").is_file());
    assert!(dir.join("p/s.nodes.png").is_file());
    // `-o` names a folder: onto a file it said only "File exists (os error 17)".
    let o = run(host().arg("plot").arg(&stats).arg("-o").arg(&stats));
    one_clear_line(
        &o,
        &["plot -o FILE"],
        "not a folder (plot -o names the folder",
    );
    // A render run in its folder names its image there (`-o NAME.png`); plotted from the
    // folder above, the image is found beside the stats file (it was looked for in the
    // folder above, after half the pictures were drawn).
    let o = run(host()
        .current_dir(&dir)
        .args([
            "render",
            "--in-process",
            "--quiet",
            "--width",
            "8",
            "--height",
            "8",
        ])
        .args(["--spp", "1", "-o", "plot-beside.png", "--stats", "b.json"]));
    assert!(o.status.success(), "{}", stderr(&o));
    let above = dir.parent().unwrap();
    let name = dir.file_name().unwrap();
    let o = run(host()
        .current_dir(above)
        .arg("plot")
        .arg(Path::new(name).join("b.json")));
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(dir.join("b.nodes.png").is_file());
    // A stats file whose image is nowhere: said as a missing file, and nothing drawn.
    std::fs::remove_file(dir.join("plot-beside.png")).unwrap();
    std::fs::remove_file(dir.join("b.timeline.png")).unwrap();
    let o = run(host().arg("plot").arg(dir.join("b.json")));
    one_clear_line(&o, &["plot"], "looked for here and beside it");
    assert!(!dir.join("b.timeline.png").exists());
}

fn expect_error(args: &[&str], out: &std::path::Path, needle: &str) {
    let o = run(host().args(args).arg("-o").arg(out));
    one_clear_line(&o, args, needle);
    assert!(!out.exists(), "{args:?} left {} behind", out.display());
}

/// A failure of the command `what` ran, said on one line that mentions `needle`, no panic.
fn one_clear_line(o: &std::process::Output, what: &[&str], needle: &str) {
    assert!(!o.status.success(), "{what:?} should fail");
    let err = stderr(o);
    assert!(
        err.contains(needle),
        "{what:?}: {err:?} should mention {needle:?}"
    );
    assert!(!err.contains("panicked"), "{what:?} panicked: {err}");
    assert_eq!(
        err.trim().lines().count(),
        1,
        "{what:?}: one line expected, got {err:?}"
    );
}

#[test]
fn mistakes_are_one_clear_line() {
    let dir = scratch("errors");
    let png = dir.join("x.png");
    expect_error(
        &["render", "/no/such/scene.gltf"],
        &png,
        "/no/such/scene.gltf",
    );
    expect_error(&["render", "--width", "0"], &png, "width");
    expect_error(&["render", "--spp", "0"], &png, "spp");
    expect_error(&["render"], &dir.join("x.bmp"), "unknown image format");
    expect_error(
        &["render"],
        &dir.join("no-such-dir/x.png"),
        "does not exist",
    );
    expect_error(
        &["render"],
        Path::new("/etc/hostname/x.png"),
        "does not exist",
    );
    // An output or stats path that is a folder: said before the render, not after it.
    let folder = dir.join("folder.png");
    std::fs::create_dir_all(&folder).unwrap();
    let o = run(host()
        .args(["render", "--width", "8", "--height", "8", "-o"])
        .arg(&folder));
    assert!(
        !o.status.success() && stderr(&o).contains("is a folder"),
        "{}",
        stderr(&o)
    );
    expect_error(
        &["render", "--stats", folder.to_str().unwrap()],
        &png,
        "is a folder",
    );
    // A preset beside a size it would silently override.
    expect_error(
        &["render", "--preset", "vga", "--width", "100"],
        &png,
        "cannot be used with",
    );
    expect_error(&["render", "--cache", "0"], &png, "--cache");
    expect_error(&["render", "--cache", "500"], &png, "--cache");
    expect_error(&["render", "--time-scale", "-1"], &png, "--time-scale");
    expect_error(&["render", "--spawn", "grid:0x0x0"], &png, "grid");
    expect_error(
        &["render", "--spawn", "no-such-topology"],
        &png,
        "no-such-topology",
    );
    expect_error(&["render", "--environment", "red"], &png, "red");
    expect_error(&["render", "--at-work", "0"], &png, "a number above 0");
    expect_error(
        &["render", "--coherent-rays", "maybe"],
        &png,
        "auto, on or off",
    );
    // A camera the scene lacks is the user's choice, not a broken header (it said "invalid
    // scene header").
    expect_error(
        &["render", "--in-process", "--camera", "nope"],
        &png,
        r#"error: no camera named "nope"; the scene has ["demo"] (and "auto" frames the scene)"#,
    );
    // One file written twice, or over an input: the second write replaced the first.
    let scene = dir.join("scene.gltf");
    std::fs::copy(data().join("scenes/cornell/cornell.gltf"), &scene).unwrap();
    let scene_bytes = std::fs::read(&scene).unwrap();
    let png_stats = png.to_str().unwrap().to_string();
    expect_error(
        &["render", "--in-process", "--stats", &png_stats],
        &png,
        "the image (-o) and the statistics (--stats) would be the same file",
    );
    expect_error(
        &[
            "render",
            scene.to_str().unwrap(),
            "--stats",
            scene.to_str().unwrap(),
        ],
        &png,
        "the statistics (--stats) and the scene would be the same file",
    );
    assert_eq!(std::fs::read(&scene).unwrap(), scene_bytes);
    let recorded = dir.join("recorded.json");
    std::fs::write(&recorded, "{}").unwrap();
    let o = run(host()
        .arg("simulate")
        .arg(&recorded)
        .arg("--json")
        .arg(&recorded));
    one_clear_line(&o, &["simulate"], "would be the same file");
    assert_eq!(std::fs::read(&recorded).unwrap(), b"{}");
    // Over the files a scene reads: `-o` onto its texture, `--stats` onto its buffer and a
    // gallery's sheet onto a texture each replaced the file (and the scene no longer loaded).
    let textured = dir.join("textured");
    std::fs::create_dir_all(&textured).unwrap();
    let src = data().join("scenes/khronos/BoxTextured/glTF");
    for f in ["BoxTextured.gltf", "BoxTextured0.bin", "CesiumLogoFlat.png"] {
        std::fs::copy(src.join(f), textured.join(f)).unwrap();
    }
    let boxed = textured.join("BoxTextured.gltf");
    let (texture, buffer) = (
        textured.join("CesiumLogoFlat.png"),
        textured.join("BoxTextured0.bin"),
    );
    let kept = [&texture, &buffer].map(|f| std::fs::read(f).unwrap());
    let render = |flag: &str, onto: &std::path::Path| {
        let mut cmd = host();
        cmd.args(["render", "--in-process"]).arg(&boxed);
        if flag == "--stats" {
            cmd.arg("-o").arg(textured.join("box.png"));
        }
        run(cmd.arg(flag).arg(onto))
    };
    one_clear_line(
        &render("-o", &texture),
        &["render -o TEXTURE"],
        "the image (-o) and a file the scene reads would be the same file",
    );
    one_clear_line(
        &render("--stats", &buffer),
        &["render --stats BUFFER"],
        "the statistics (--stats) and a file the scene reads would be the same file",
    );
    let o = run(host().arg("gallery").arg(&textured).arg("-o").arg(&texture));
    one_clear_line(
        &o,
        &["gallery -o TEXTURE"],
        "the sheet (-o) and a file a scene reads would be the same file",
    );
    assert_eq!([&texture, &buffer].map(|f| std::fs::read(f).unwrap()), kept);
    // Values that were silently clamped or taken, and a scene file named that is not there
    // (it was skipped without a word).
    for (flag, value) in [
        ("--size", "0"),
        ("--size", "100000"),
        ("--spp", "0"),
        ("--columns", "0"),
    ] {
        let o = run(host()
            .args(["gallery", "."])
            .args([flag, value])
            .arg("-o")
            .arg(&png));
        one_clear_line(
            &o,
            &["gallery", flag, value],
            &format!("'{value}' for '{flag}"),
        );
    }
    let o = run(host().args(["bench", "--cornell", "/no/such/cornell.gltf"]));
    one_clear_line(&o, &["bench"], "/no/such/cornell.gltf: no such scene file");
    // Flags that cannot go together, of which one was silently ignored (`--topology tiny`
    // alone spawned the 86 processes of magg).
    expect_error(
        &["render", "--topology", "tiny"],
        &png,
        "required arguments were not provided: --listen",
    );
    expect_error(
        &["render", "--listen", "127.0.0.1:0", "--spawn", "tiny"],
        &png,
        "'--listen <LISTEN>' cannot be used with '--spawn <SPAWN>'",
    );
    // A cluster's flags beside --in-process did nothing without a word: said, and the
    // render goes on (the same command with and without --in-process is how a cluster's
    // image is checked).
    let o = run(host()
        .args([
            "render",
            "--in-process",
            "--width",
            "8",
            "--height",
            "8",
            "--spp",
            "1",
        ])
        .args(["--cache", "5", "--at-work=all", "--threads", "1", "-o"])
        .arg(&png));
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stderr(&o)
            .contains("--cache, --at-work only a cluster reads: in one process they do nothing"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_file(&png).unwrap();
    expect_error(
        &["render", "--in-process", "--spawn", "tiny"],
        &png,
        "'--in-process' cannot be used with '--spawn <SPAWN>'",
    );
    expect_error(
        &[
            "render",
            "--secret",
            "12345678",
            "--secret-file",
            "magg-secret",
        ],
        &png,
        "'--secret <SECRET>' cannot be used with '--secret-file <SECRET_FILE>'",
    );
    // Numbers beyond what any use needs, which overflowed a deadline, a duration or an
    // allocation and ended in a panic or an abort.
    let huge = "18446744073709551615";
    expect_error(
        &["render", "--checkpoint-every", "1e30"],
        &png,
        "1e30 seconds: give 0 to 31536000 (a year)",
    );
    expect_error(
        &["render", "--checkpoint-every", "inf"],
        &png,
        "inf seconds: give 0",
    );
    expect_error(
        &["render", "--join-timeout", huge],
        &png,
        "seconds: give 0 to 31536000 (a year)",
    );
    expect_error(
        &["render", "--threads", huge],
        &png,
        "threads: give 1 to 4096",
    );
    expect_error(&["render", "--render-threads", "0"], &png, "1..=4096");
    expect_error(
        &["render", "--time-scale", "1e300"],
        &png,
        "at most 1000000, not 1e300",
    );
    expect_error(
        &["render", "--subscreens", "4294967295"],
        &png,
        "4294967295 subscreens: give 1 to 1000000",
    );
    expect_error(
        &["render", "--chunk-triangles", "4294967296"],
        &png,
        "4294967296 triangles: give 1 to 4294967295",
    );
    let o = run(host().args(["bench", "--triangles", huge]));
    let err = stderr(&o);
    assert!(
        !o.status.success() && err.contains("triangles: give 1 to 100000000"),
        "{err}"
    );
    for node in [
        env!("CARGO_BIN_EXE_magg-render-node"),
        env!("CARGO_BIN_EXE_magg-fork-node"),
    ] {
        let args = ["--join", "127.0.0.1:1", "--timeout", huge];
        let o = run(std::process::Command::new(node).args(args));
        one_clear_line(&o, &args, "seconds: give 0 to 31536000 (a year)");
    }
    // A file that is not glTF at all.
    let junk = dir.join("junk.gltf");
    std::fs::write(&junk, b"this is not json").unwrap();
    expect_error(&["render", junk.to_str().unwrap()], &png, "junk.gltf");
    // At the default log level as well: the cluster starts while the scene is read, and says
    // so only once it has been read, so a scene that cannot be read is still one line.
    let o = run(host()
        .env_remove("MAGG_LOG")
        .args(["render", junk.to_str().unwrap(), "-o"])
        .arg(&png));
    let err = stderr(&o);
    assert!(!o.status.success() && err.contains("junk.gltf"), "{err}");
    assert_eq!(
        err.trim().lines().count(),
        1,
        "one line expected, got {err:?}"
    );
    assert!(!png.exists());
    // With nodes started by hand, it is reported at once, not once they have all joined.
    let began = std::time::Instant::now();
    let o = run(host()
        .env("MAGG_SECRET", "a secret for a cluster that never forms")
        .args(["render", junk.to_str().unwrap(), "--listen", "127.0.0.1:0"])
        .args(["--topology", "tiny", "-o"])
        .arg(&png));
    let err = stderr(&o);
    assert!(!o.status.success() && err.contains("junk.gltf"), "{err}");
    assert!(
        began.elapsed() < std::time::Duration::from_secs(30),
        "waited {:?} for nodes that never came",
        began.elapsed()
    );
}

/// A listen address the host cannot listen at is refused before a secret is written: one
/// that does not parse, a port out of range, a port another process holds. No secret file
/// is left behind for the nodes of a cluster that never started, and one already there (a
/// running host's, which its nodes read) is not replaced.
#[test]
fn a_listen_address_that_cannot_be_writes_no_secret() {
    let dir = scratch("listen-address");
    let secret = dir.join("magg-secret");
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let taken = taken.local_addr().unwrap().to_string();
    let listen = |addr: &str| {
        run(host()
            .current_dir(&dir)
            .env_remove("MAGG_SECRET")
            .args(["render", "--listen", addr, "-o"])
            .arg(dir.join("x.png")))
    };
    for addr in ["nonsense", "127.0.0.1:99999", taken.as_str()] {
        let what = ["render", "--listen", addr];
        one_clear_line(&listen(addr), &what, &format!("cannot listen at {addr}"));
        assert!(
            !secret.exists(),
            "{what:?} wrote a secret for a cluster that could not start"
        );
    }
    std::fs::write(&secret, "the secret of a host already running").unwrap();
    assert!(!listen(&taken).status.success());
    assert_eq!(
        std::fs::read_to_string(&secret).unwrap(),
        "the secret of a host already running"
    );
    // A host that listens with a secret file there from before uses that secret: its nodes
    // join with it, and the file stays as it was (a new secret replaced it, whatever it was).
    let mut host = Logged::start(
        host()
            .current_dir(&dir)
            .env_remove("MAGG_SECRET")
            .env("MAGG_LOG", "info")
            .args([
                "render", "--quiet", "--width", "8", "--height", "8", "--spp", "1",
            ])
            .args(["--listen", "127.0.0.1:0", "--topology", "grid:1x1x1", "-o"])
            .arg(dir.join("x.png")),
    );
    let addr = host.join_address();
    // Written here with the default mode (0644 under the usual umask): others may read it,
    // which is said.
    for said in [
        "using the cluster secret in magg-secret, left by an earlier run",
        "magg-secret can be read by others than you (mode ",
    ] {
        assert!(host.log().contains(said), "{}", host.log());
    }
    let _nodes = join_one_of_each(
        &addr,
        |args| {
            let mut c = std::process::Command::new(args[0]);
            c.args(&args[1..]);
            c
        },
        |c| c.arg("--secret-file").arg(&secret),
    );
    assert_eq!(
        host.wait_exit(std::time::Duration::from_secs(60)),
        Some(Some(0)),
        "{}",
        host.log()
    );
    assert!(dir.join("x.png").exists());
    assert_eq!(
        std::fs::read_to_string(&secret).unwrap(),
        "the secret of a host already running"
    );
    // One that holds no secret (too short to be one) is said, naming the file.
    std::fs::write(&secret, "short").unwrap();
    let o = listen("127.0.0.1:0");
    one_clear_line(
        &o,
        &["render", "--listen"],
        "the cluster secret in magg-secret",
    );
    assert_eq!(std::fs::read_to_string(&secret).unwrap(), "short");
}

/// A log filter that does not parse is said once, and the command goes on at `info` (it
/// fell back silently).
#[test]
fn a_log_filter_that_is_not_one_is_said() {
    let dir = scratch("log-filter");
    let out = dir.join("l.png");
    let o = run(host()
        .args(["--log", "info,=[", "render", "--in-process", "--width", "8"])
        .args(["--height", "8", "--spp", "1", "-o"])
        .arg(&out));
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains(r#"the log filter "info,=[" is not one"#),
        "{err}"
    );
    assert!(out.exists());
}

#[test]
fn a_required_unknown_extension_is_refused_by_name() {
    let dir = scratch("iridescence");
    let scene = data().join("scenes/khronos/IridescenceSuzanne/glTF-Binary/IridescenceSuzanne.glb");
    expect_error(
        &["render", scene.to_str().unwrap()],
        &dir.join("x.png"),
        "KHR_materials_iridescence",
    );
}

/// The lab's whole-render experiment starts this executable again for each run and reads
/// the figures back from their `--stats`; the cluster run's image must equal the in-process one.
#[test]
fn experiment_overhead_runs_both_renders_and_compares_bytes() {
    let dir = scratch("overhead");
    let scene = data().join("scenes/cornell/cornell.gltf");
    let o = run(host()
        .args(["experiment", "overhead", "--out"])
        .arg(&dir)
        .args(["--cluster", "--spawn tiny", "--"])
        .arg(&scene)
        .args(["--width", "24", "--height", "16", "--spp", "2"]));
    assert!(o.status.success(), "{}", stderr(&o));
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(table.contains("images identical: true"), "{table}");
    assert!(table.contains("cluster, 6 processes"), "{table}");
    same_bytes(&dir.join("in-process.pfm"), &dir.join("cluster.pfm"));
    let stats: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("cluster.json")).unwrap()).unwrap();
    assert_eq!(stats["processes"], 6);
    // A render that fails is said once as an error ("error: render ... failed: error: ...").
    let o = run(host()
        .args(["experiment", "overhead", "--out"])
        .arg(&dir)
        .args(["--", "/no/such/scene.gltf"]));
    let err = stderr(&o);
    assert!(!o.status.success());
    assert!(err.contains("/no/such/scene.gltf"), "{err}");
    assert_eq!(err.matches("error:").count(), 1, "{err}");
}

/// `experiment load-balance` on the smallest cluster: static division gives one subscreen
/// per render node, the three runs give the same bytes, and the CSV, chart and report exist.
#[test]
fn experiment_load_balance_writes_times_per_render_node() {
    let dir = scratch("load-balance");
    let scene = data().join("scenes/cornell/cornell.gltf");
    let o = run(host()
        .args(["experiment", "load-balance", "--subscreens", "12", "--out"])
        .arg(&dir)
        .args(["--cluster", "--spawn tiny", "--"])
        .arg(&scene)
        .args(["--width", "24", "--height", "16", "--spp", "2"]));
    assert!(o.status.success(), "{}", stderr(&o));
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(
        table.contains("| static | 4 |"),
        "tiny has 4 render nodes: {table}"
    );
    assert!(table.contains("| dynamic | 12 |"), "{table}");
    assert!(
        !table.contains("NO"),
        "every run must give the same image: {table}"
    );
    for f in ["load-balance.csv", "load-balance.png", "report.md"] {
        assert!(dir.join(f).is_file(), "{f} missing");
    }
    let csv = std::fs::read_to_string(dir.join("load-balance.csv")).unwrap();
    // A header and 4 render nodes for each of the 3 runs.
    assert_eq!(csv.lines().count(), 1 + 3 * 4, "{csv}");
}

/// `experiment error` renders the Cornell box at 1, 2 and 4 spp against the repository's
/// reference: the error falls as samples double, and the CSV, plot and report exist.
#[test]
fn experiment_error_measures_falling_error_against_the_reference() {
    let dir = scratch("error");
    let o = run(host()
        .args(["experiment", "error", "--max-spp", "4", "--scene"])
        .arg(data().join("scenes/cornell/cornell.gltf"))
        .arg("--reference")
        .arg(data().join("references/cornell/cornell_ref.exr"))
        .arg("--peers")
        .arg(dir.join("none.json"))
        .arg("--out")
        .arg(&dir));
    assert!(o.status.success(), "{}", stderr(&o));
    for f in ["error.csv", "error.png", "report.md"] {
        assert!(dir.join(f).is_file(), "{f} missing");
    }
    let csv = std::fs::read_to_string(dir.join("error.csv")).unwrap();
    let errors: Vec<f64> = csv
        .lines()
        .skip(1)
        .map(|l| l.rsplit(',').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(errors.len(), 3, "{csv}");
    assert!(errors[0] > errors[1] && errors[1] > errors[2], "{csv}");
}

/// `experiment validate` renders its four cases on real processes and simulates each from
/// the render's own records: every row has a measurement and a positive prediction.
#[test]
fn experiment_validate_predicts_every_case() {
    let dir = scratch("validate");
    let o = run(host()
        .args([
            "experiment",
            "validate",
            "--width",
            "32",
            "--height",
            "32",
            "--spp",
            "2",
        ])
        .arg("--scene")
        .arg(data().join("scenes/cornell/cornell.gltf"))
        .arg("--out")
        .arg(&dir));
    assert!(o.status.success(), "{}", stderr(&o));
    let csv = std::fs::read_to_string(dir.join("validate.csv")).unwrap();
    let rows: Vec<Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').skip(2).map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 9, "{csv}");
    assert!(
        rows.iter()
            .all(|r| r[0] > 0.0 && r[1] > 0.0 && r[2].is_finite()),
        "{csv}"
    );
    assert!(dir.join("report.md").is_file());
}

/// `experiment links` on the smallest cluster: every table and plot is written, and the
/// measured one-packet times exist for the distances the card has.
#[test]
fn experiment_links_writes_its_tables_and_plots() {
    let dir = scratch("links");
    let o = run(host()
        .args(["experiment", "links", "--spawn", "tiny", "--sizes", "640"])
        .args(["--count", "1", "--probes", "2", "--out"])
        .arg(&dir));
    assert!(o.status.success(), "{}", stderr(&o));
    for f in [
        "one_way.csv",
        "transfers.csv",
        "links.json",
        "fig1.5-one-node.png",
        "fig1.6-many-nodes.png",
    ] {
        assert!(dir.join(f).is_file(), "{f} missing");
    }
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("links.json")).unwrap()).unwrap();
    let one_way = report["one_way"].as_array().unwrap();
    assert!(!one_way.is_empty());
    assert!(one_way.iter().all(|o| o["samples"] == 2), "{one_way:?}");
    assert!(report["raw"]["one_hop_round_trip_us"].as_f64().unwrap() > 0.0);
}

/// `magg-host simulate` on a stats file of per-subscreen records (written here, as a
/// cluster render writes them): the prediction beside the measured time, the same again as
/// JSON, and what is wrong with a file it cannot use in one line.
#[test]
fn simulate_predicts_a_recorded_render_and_another_machine() {
    let dir = scratch("simulate");
    let record = |i: u32| {
        format!(
            r#"{{"node": {}, "x": 0, "y": {i}, "width": 16, "height": 1, "start_s": 0.0,
                "end_s": 0.05, "cpu_s": 0.05, "pixels": 16, "samples": 16, "rays": 16,
                "chunks": [{}], "tiles": [0], "fetched_bytes": 0, "fetches": 0,
                "fetched_via": "dma"}}"#,
            2 + i % 4,
            i % 3
        )
    };
    let records: Vec<String> = (0..8).map(record).collect();
    let stats = format!(
        r#"{{"width": 16, "height": 8, "topology": "tiny", "link_model": "Paper",
            "time_scale": 0.01, "transfer": "Demand", "cache_percent": 100.0, "adaptive": false,
            "seconds": {{"render": 0.11}}, "subscreens": [{}],
            "chunk_bytes": [3000, 5000, 7000], "tile_bytes": [16384]}}"#,
        records.join(",")
    );
    let file = dir.join("stats.json");
    std::fs::write(&file, stats).unwrap();
    let json = dir.join("prediction.json");
    let o = run(host().arg("simulate").arg(&file).arg("--json").arg(&json));
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("predicted render time 0.1"), "{out}");
    assert!(out.contains("measured 0.1100 s"), "{out}");
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(v["result"]["render_nodes"], 4);
    // Read by `| head -0`: the summary goes nowhere, and the prediction file is written all
    // the same (an exit at the first line the closed stdout refused lost it, with status 0);
    // the recorded render may give its own overheads.
    let again = dir.join("prediction-again.json");
    let o = into_closed_stdout(
        host()
            .arg("simulate")
            .arg(&file)
            .arg("--overheads-from")
            .arg(&file)
            .arg("--json")
            .arg(&again),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(again.is_file(), "no prediction behind a closed stdout");
    // The same costs on the 1000-node machine, 2000 subscreens: no measurement to compare.
    let o = run(host().arg("simulate").arg(&file).args([
        "--topology",
        "magg1000",
        "--subscreens",
        "2000",
    ]));
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("1000 render nodes"), "{out}");
    assert!(!out.contains("measured"), "{out}");
    // A stats file from before the records.
    std::fs::write(&file, r#"{"width": 16, "subscreens": 8}"#).unwrap();
    let o = run(host().arg("simulate").arg(&file));
    assert!(!o.status.success());
    let err = stderr(&o);
    assert!(err.contains("no per-subscreen records"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
}

/// A render on a topology file's machine, whose name is no preset, keeps the topology whole
/// in its stats, and `simulate` replays the render on it without being told the machine
/// (it could not find a machine called `pair` before).
#[test]
fn simulate_replays_a_render_on_a_topology_file() {
    let dir = scratch("simulate-file");
    let topology = dir.join("pair.toml");
    std::fs::write(
        &topology,
        "name = \"pair\"\n[grid]\ncards = 1\nrows = 1\ncols = 2\n",
    )
    .unwrap();
    let stats = dir.join("stats.json");
    let o = run(host()
        .arg("render")
        .arg(data().join("scenes/cornell/cornell.gltf"))
        .args(["--width", "16", "--height", "8", "--spp", "1", "--spawn"])
        .arg(&topology)
        .arg("--stats")
        .arg(&stats)
        .arg("-o")
        .arg(dir.join("pair.png")));
    assert!(o.status.success(), "{}", stderr(&o));
    // Gone, as a file may be by the time its render is simulated.
    std::fs::remove_file(&topology).unwrap();
    let o = run(host().arg("simulate").arg(&stats));
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains("2 render nodes") && out.contains("measured"),
        "{out}"
    );
}

/// A topology file's `[model] link` and `time_scale` and its `cluster_id` hold unless a flag
/// gives another, and the stats record what the render used. The command line's defaults
/// replaced all three: the file's paper links ran as none at scale 1 (and the stats'
/// `topology_file` said 1), and the host took nodes of the default id, not the file's.
#[test]
fn a_topology_files_model_and_cluster_id_hold_unless_a_flag_is_given() {
    let dir = scratch("topology-own");
    let file = dir.join("own.toml");
    std::fs::write(
        &file,
        "name = \"own\"\ncluster_id = \"other\"\n[grid]\ncards = 1\nrows = 1\ncols = 1\n\
         [model]\nlink = \"paper\"\ntime_scale = 0.5\nbase_us = 100.0\n",
    )
    .unwrap();
    let render = |flags: &[&str], name: &str| -> serde_json::Value {
        let stats = dir.join(format!("{name}.json"));
        let o = run(host()
            .arg("render")
            .arg(data().join("scenes/cornell/cornell.gltf"))
            .args(["--quiet", "--width", "8", "--height", "4", "--spp", "1"])
            .arg("--spawn")
            .arg(&file)
            .args(flags)
            .arg("--stats")
            .arg(&stats)
            .arg("-o")
            .arg(dir.join(format!("{name}.png"))));
        assert!(o.status.success(), "{}", stderr(&o));
        serde_json::from_str(&std::fs::read_to_string(&stats).unwrap()).unwrap()
    };
    let kept = |s: &serde_json::Value, link: &str, scale: &str| {
        assert_eq!(
            s["link_model"].as_str(),
            Some(link),
            "{}",
            s["topology_file"]
        );
        let file = s["topology_file"].as_str().unwrap();
        for line in [
            format!("link = \"{}\"", link.to_lowercase()),
            format!("time_scale = {scale}"),
            "base_us = 100.0".into(),
            "cluster_id = \"other\"".into(),
        ] {
            assert!(file.lines().any(|l| l == line), "{line:?} in {file}");
        }
    };
    let own = render(&[], "own");
    kept(&own, "Paper", "0.5");
    assert_eq!(own["time_scale"].as_f64(), Some(0.5));
    let flags = render(&["--link-model", "none", "--time-scale", "0.25"], "flags");
    kept(&flags, "None", "0.25");
    assert_eq!(flags["time_scale"].as_f64(), Some(0.25));
    // Nodes started by hand join only with the file's id.
    let mut host = Logged::start(
        host()
            .env("MAGG_SECRET", "a topology file's own cluster id")
            .env_remove("MAGG_CLUSTER_ID")
            .env("MAGG_LOG", "info")
            .args([
                "render", "--quiet", "--width", "8", "--height", "4", "--spp", "1",
            ])
            .args(["--listen", "127.0.0.1:0", "--topology"])
            .arg(&file)
            .arg("-o")
            .arg(dir.join("listen.png")),
    );
    let addr = host.join_address();
    let node = |role: &str, id: Option<&str>| {
        let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_magg-host"));
        c.args([
            role,
            "--join",
            &addr,
            "--listen",
            "127.0.0.1:0",
            "--log",
            "warn",
        ])
        .env("MAGG_SECRET", "a topology file's own cluster id")
        .env_remove("MAGG_CLUSTER_ID");
        if let Some(id) = id {
            c.args(["--cluster-id", id]);
        }
        Logged::start(&mut c)
    };
    let mut stranger = node("render-node", None);
    assert_ne!(
        stranger.wait_exit(std::time::Duration::from_secs(60)),
        Some(Some(0)),
        "{}",
        stranger.log()
    );
    assert!(
        stranger
            .log()
            .contains(r#"this is cluster "other", not "magg""#),
        "{}",
        stranger.log()
    );
    let _members = [
        node("fork-node", Some("other")),
        node("render-node", Some("other")),
    ];
    assert_eq!(
        host.wait_exit(std::time::Duration::from_secs(60)),
        Some(Some(0)),
        "{}",
        host.log()
    );
}

/// `experiment speedup` at a tiny size: a recording, measured points on real processes (1, 2
/// and 8 render nodes) each beside its prediction, simulated curves to 1000 render nodes,
/// and every finding of the paper checked in the report.
#[test]
fn experiment_speedup_measures_simulates_and_checks_the_findings() {
    let dir = scratch("speedup");
    let o = run(host()
        .args(["experiment", "speedup", "--width", "40", "--height", "30"])
        .arg("--scene")
        .arg(data().join("scenes/cornell/cornell.gltf"))
        .arg("--out")
        .arg(&dir)
        .args(["--", "--spp", "1", "--integrator", "whitted"]));
    assert!(o.status.success(), "{}", stderr(&o));
    let csv = std::fs::read_to_string(dir.join("speedup.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    let measured: Vec<_> = rows.iter().filter(|r| r[0] == "measured").collect();
    assert_eq!(measured.len(), 6, "{csv}");
    assert!(
        measured
            .iter()
            .all(|r| r[4].parse::<f64>().unwrap() > 0.0 && r[5].parse::<f64>().unwrap() > 0.0),
        "{csv}"
    );
    // T(1)/T(1) is 1 on every simulated curve.
    assert!(
        rows.iter()
            .filter(|r| r[0] == "simulated" && r[3] == "1")
            .all(|r| (r[4].parse::<f64>().unwrap() - 1.0).abs() < 1e-9),
        "{csv}"
    );
    assert!(
        rows.iter().any(|r| r[0] == "simulated" && r[3] == "1000"),
        "{csv}"
    );
    let report = std::fs::read_to_string(dir.join("report.md")).unwrap();
    assert_eq!(
        report.matches("| yes |").count() + report.matches("| no |").count(),
        8,
        "{report}"
    );
    for png in ["speedup-1.png", "speedup-2.png", "speedup-measured.png"] {
        assert!(dir.join(png).is_file(), "{png}");
    }
}

/// relMSE of `image` against `reference`, as `magg-host compare` reports it.
fn rel_mse(image: &Path, reference: &Path) -> f64 {
    let o = run(host().arg("compare").arg(image).arg(reference));
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    out.lines()
        .find_map(|l| l.strip_prefix("relMSE "))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no relMSE in {out:?}"))
}

/// The demo scene is denoised unless told not to (a biased filter, on for the demo alone):
/// 8 samples a pixel denoised come much nearer a 256-sample render than 8 samples as
/// sampled (same clamping), and a scene file is left as sampled unless `--denoise on` is
/// given.
#[test]
fn the_demo_is_denoised_and_scene_files_are_not_unless_asked() {
    let dir = scratch("denoise");
    let render = |name: &str, extra: &[&str]| {
        let size = ["--width", "80", "--height", "60", "--clamp-indirect", "4"];
        in_process_to(&dir.join(name), &[&size[..], extra].concat())
    };
    let converged = render(
        "converged.pfm",
        &["--spp", "256", "--seed", "9", "--denoise", "off"],
    );
    let raw = render("raw.pfm", &["--spp", "8", "--denoise", "off"]);
    let denoised = render("denoised.pfm", &["--spp", "8"]);
    let (e_raw, e_denoised) = (rel_mse(&raw, &converged), rel_mse(&denoised, &converged));
    assert!(
        e_denoised < e_raw / 2.5,
        "denoised relMSE {e_denoised:.3e}, as sampled {e_raw:.3e}"
    );

    let cornell = data().join("scenes/cornell/cornell.gltf");
    let cornell = cornell.to_str().unwrap();
    // (The clamp given above changes nothing here: the Cornell box has no caustics.)
    let plain = render("cornell.pfm", &[cornell, "--spp", "2"]);
    let off = render(
        "cornell-off.pfm",
        &[cornell, "--spp", "2", "--denoise", "off"],
    );
    let on = render(
        "cornell-on.pfm",
        &[cornell, "--spp", "2", "--denoise", "on"],
    );
    same_bytes(&plain, &off);
    assert_ne!(std::fs::read(&plain).unwrap(), std::fs::read(&on).unwrap());
}

/// `magg-host compare A B | head -1`: a reader that goes away before the figures are
/// written is no error, and no panic.
#[test]
fn compare_into_a_closed_pipe_is_no_error() {
    let dir = scratch("compare-pipe");
    let image = in_process_to(
        &dir.join("a.pfm"),
        &["--width", "16", "--height", "16", "--spp", "1"],
    );
    let o = into_closed_stdout(host().arg("compare").arg(&image).arg(&image));
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!stderr(&o).contains("panicked"), "{}", stderr(&o));
}

/// Runs `cmd` with its stdout a pipe whose reader is gone before the first line
/// (`| head -0`).
fn into_closed_stdout(cmd: &mut std::process::Command) -> std::process::Output {
    let mut child = cmd
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    child.wait_with_output().unwrap()
}

/// `magg-host render ... 2>&1 | head -1`, or stderr on a full disk: the log and the last
/// line cannot be written, and the image is written all the same (it panicked at the first
/// log line, before the render, with nothing saved). Likewise results to a full stdout are
/// one line on stderr and exit 1, not a panic.
#[test]
fn a_closed_or_full_stderr_loses_no_image() {
    let dir = scratch("closed-stderr");
    let full = || {
        std::fs::OpenOptions::new()
            .write(true)
            .open("/dev/full")
            .unwrap()
    };
    for (name, cluster) in [("in-process", false), ("cluster", true)] {
        let render = |out: &Path| {
            let mut c = host();
            c.env("MAGG_LOG", "info")
                .args(["render", "--width", "16", "--height", "16", "--spp", "1"])
                .args(if cluster {
                    &["--spawn", "tiny"][..]
                } else {
                    &["--in-process"][..]
                })
                .arg("-o")
                .arg(out);
            c
        };
        // Its reader gone before the first line: every write meets a broken pipe.
        let out = dir.join(format!("{name}-pipe.png"));
        let mut child = render(&out)
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        drop(child.stderr.take());
        let status = child.wait().unwrap();
        assert!(status.success(), "{name}: {status}");
        assert!(out.exists(), "{name}: no image behind a closed stderr");
        let out = dir.join(format!("{name}-full.png"));
        let status = render(&out).stderr(full()).status().unwrap();
        assert!(status.success(), "{name}: {status}");
        assert!(
            out.exists(),
            "{name}: no image with stderr on a full device"
        );
    }
    let image = dir.join("in-process-full.png");
    let o = host()
        .arg("compare")
        .arg(&image)
        .arg(&image)
        .stdout(full())
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("writing the results to standard output"),
        "{}",
        stderr(&o)
    );
    assert!(!stderr(&o).contains("panicked"), "{}", stderr(&o));
}

/// SIGTERM (what `docker stop` and service managers send) stops a render with its finished
/// lines kept, and the exit status says which signal it was: 143, as a shell reports a
/// process SIGTERM ended (it said 130, Ctrl-C's, for both).
#[test]
fn sigterm_stops_a_render_with_status_143() {
    let dir = scratch("sigterm");
    let out = dir.join("long.png");
    let mut render = Logged::start(
        host()
            .env("MAGG_LOG", "info")
            .args([
                "render",
                "--in-process",
                "--threads",
                "1",
                "--denoise",
                "off",
            ])
            .args(["--width", "256", "--height", "256", "--spp", "4096", "-o"])
            .arg(&out),
    );
    render
        .wait_for("spp (path)", std::time::Duration::from_secs(30))
        .unwrap_or_else(|| panic!("the render did not begin: {}", render.log()));
    let _ = rustix::process::kill_process(
        rustix::process::Pid::from_raw(render.pid() as i32).unwrap(),
        rustix::process::Signal::TERM,
    );
    let code = render.wait_exit(std::time::Duration::from_secs(60));
    assert_eq!(code, Some(Some(143)), "{}", render.log());
    assert!(
        render.log().contains("SIGTERM: stopping the render"),
        "{}",
        render.log()
    );
    assert!(!out.exists(), "no image from a stopped render");
    assert!(dir.join("long.png.partial").exists(), "{}", render.log());
}

/// A stop while the scene is still loading ends the command at once, with nothing written
/// (there is nothing to keep yet): it waited for the load and preparation to end, half a
/// minute for 16,000 copies of a mesh.
#[test]
fn a_stop_while_loading_ends_at_once() {
    let dir = scratch("stop-loading");
    // 3,000 copies of a 2,048-triangle sphere: 6 M triangles, seconds to load and prepare.
    let n = 32u32;
    let (mut positions, mut indices) = (Vec::new(), Vec::new());
    for j in 0..=n {
        for i in 0..=n {
            let (t, p) = (
                std::f32::consts::PI * j as f32 / n as f32,
                std::f32::consts::TAU * i as f32 / n as f32,
            );
            positions.extend([t.sin() * p.cos(), t.cos(), t.sin() * p.sin()]);
        }
    }
    for j in 0..n {
        for i in 0..n {
            let a = j * (n + 1) + i;
            indices.extend([a, a + n + 1, a + 1, a + 1, a + n + 1, a + n + 2]);
        }
    }
    let mut buf: Vec<u8> = indices.iter().flat_map(|i| i.to_le_bytes()).collect();
    let index_bytes = buf.len();
    buf.extend(positions.iter().flat_map(|v| v.to_le_bytes()));
    let copies = 3000;
    let nodes: Vec<String> = (0..copies)
        .map(|i| {
            format!(
                r#"{{"mesh":0,"translation":[{},0,-4]}}"#,
                (i % 7) as f32 * 0.01
            )
        })
        .collect();
    let roots: Vec<String> = (0..copies).map(|i| i.to_string()).collect();
    let scene = dir.join("copies.gltf");
    let bin = dir.join("copies.bin");
    std::fs::write(&bin, &buf).unwrap();
    std::fs::write(
        &scene,
        format!(
            r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[{roots}]}}],
            "nodes":[{nodes}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":1}},"indices":0}}]}}],
            "buffers":[{{"byteLength":{len},"uri":"copies.bin"}}],
            "bufferViews":[{{"buffer":0,"byteLength":{index_bytes}}},
                           {{"buffer":0,"byteOffset":{index_bytes},"byteLength":{pb}}}],
            "accessors":[{{"bufferView":0,"componentType":5125,"count":{ni},"type":"SCALAR"}},
                         {{"bufferView":1,"componentType":5126,"count":{nv},"type":"VEC3",
                           "min":[-1,-1,-1],"max":[1,1,1]}}]}}"#,
            roots = roots.join(","),
            nodes = nodes.join(","),
            len = buf.len(),
            pb = buf.len() - index_bytes,
            ni = indices.len(),
            nv = positions.len() / 3,
        ),
    )
    .unwrap();
    let out = dir.join("copies.png");
    let began = std::time::Instant::now();
    let mut render = Logged::start(
        host()
            .env("MAGG_LOG", "info")
            .args(["render", "--in-process", "--width", "64", "--height", "48"])
            .arg(&scene)
            .arg("-o")
            .arg(&out),
    );
    // Once the command catches SIGTERM (before that the signal would simply kill it), well
    // before the scene is loaded.
    let catches_term = || {
        let status = std::fs::read_to_string(format!("/proc/{}/status", render.pid()));
        status.ok().and_then(|s| {
            let mask = s
                .lines()
                .find_map(|l| l.strip_prefix("SigCgt:"))?
                .trim()
                .to_string();
            Some(u64::from_str_radix(&mask, 16).ok()? & (1 << (15 - 1)) != 0)
        }) == Some(true)
    };
    while !catches_term() {
        assert!(
            began.elapsed() < std::time::Duration::from_secs(60),
            "SIGTERM never caught: {}",
            render.log()
        );
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    let _ = rustix::process::kill_process(
        rustix::process::Pid::from_raw(render.pid() as i32).unwrap(),
        rustix::process::Signal::TERM,
    );
    let code = render.wait_exit(std::time::Duration::from_secs(120));
    let log = render.log();
    assert_eq!(code, Some(Some(143)), "{log}");
    assert!(
        log.contains("SIGTERM: stopped before rendering began; nothing was written"),
        "after {:.1} s: {log}",
        began.elapsed().as_secs_f64()
    );
    assert!(!out.exists() && !dir.join("copies.png.partial").exists());
}

/// compare with a reference whose mean is 0 says so instead of a relative difference (it
/// printed +0.000% for 0.5 against 0), and an image holding NaN is an error naming it (it
/// printed relMSE NaN and exited 0).
#[test]
fn compare_says_what_it_cannot_measure() {
    let dir = scratch("compare-edges");
    let write = |name: &str, value: f32| {
        let mut img = renderer::Image::new(2, 2);
        img.pixels.iter_mut().for_each(|p| *p = [value; 3]);
        let path = dir.join(name);
        scene_io::image_io::write_image(&path, &img).unwrap();
        path
    };
    let (half, zero, nan) = (
        write("half.pfm", 0.5),
        write("zero.pfm", 0.0),
        write("nan.pfm", f32::NAN),
    );
    let o = run(host().arg("compare").arg(&half).arg(&zero));
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains("mean R: 0.50000 vs 0.00000 (the reference's mean is 0)"),
        "{out}"
    );
    let o = run(host().arg("compare").arg(&half).arg(&nan));
    one_clear_line(&o, &["compare"], "nan.pfm: 12 pixel values are not finite");
    assert!(o.stdout.is_empty());
}
