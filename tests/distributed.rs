//! Rendering on real clusters of processes gives the same bytes as one process, whatever the
//! topology, transfer mode, cache size, subscreen count or redivision; and no process
//! outlives the render.

mod common;
use common::*;

use std::path::{Path, PathBuf};

fn render(args: &[&str], out: &Path, stats: Option<&Path>) -> std::process::Output {
    let mut cmd = host();
    cmd.arg("render")
        .args(args)
        .arg("--quiet")
        .arg("-o")
        .arg(out);
    if let Some(s) = stats {
        cmd.arg("--stats").arg(s);
    }
    run(&mut cmd)
}

fn helmet() -> PathBuf {
    data().join("scenes/khronos/DamagedHelmet/glTF-Binary/DamagedHelmet.glb")
}

#[test]
fn magg_cluster_with_a_five_percent_cache_matches_one_process() {
    let dir = scratch("magg-demand");
    let scene = helmet();
    let scene = scene.to_str().unwrap();
    let size = ["--width", "200", "--height", "150", "--spp", "4"];
    let reference = dir.join("ref.exr");
    let o = render(
        &[&[scene, "--in-process"][..], &size].concat(),
        &reference,
        None,
    );
    assert!(o.status.success(), "{}", stderr(&o));

    let out = dir.join("cluster.exr");
    let stats = dir.join("stats.json");
    let o = render(
        &[
            &[
                scene,
                "--spawn",
                "magg",
                "--transfer",
                "demand",
                "--cache",
                "5",
            ][..],
            &size,
        ]
        .concat(),
        &out,
        Some(&stats),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    same_bytes(&out, &reference);

    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
    assert_eq!(v["processes"], 86);
    let nodes = v["nodes"].as_array().unwrap();
    let renderers: Vec<&serde_json::Value> =
        nodes.iter().filter(|n| n["role"] == "Render").collect();
    assert_eq!(renderers.len(), 80);
    // Every render node ran its rendering loop: it rendered, or at least asked for work and
    // waited for it.
    for n in &renderers {
        assert!(
            n["subscreens"].as_u64().unwrap() >= 1 || n["idle_s"].as_f64().unwrap() > 0.0,
            "render node {} never asked for work",
            n["node"]
        );
    }
    // The 80 render nodes share this machine: no more of them worked than it has CPUs (the
    // default without a link model), and those that did kept working, so that no more
    // nodes than that touched the scene.
    assert_eq!(v["at_work"], "auto");
    let cpus = std::thread::available_parallelism().unwrap().get();
    let rendered = renderers
        .iter()
        .filter(|n| n["subscreens"].as_u64().unwrap() >= 1)
        .count();
    if cpus < 80 {
        let limits = v["machine_limits"].as_array().unwrap();
        assert_eq!(limits.len(), 1, "{limits:?}");
        assert_eq!(limits[0]["nodes"].as_array().unwrap().len(), 80);
        let at_work = limits[0]["at_work"].as_u64().unwrap() as usize;
        assert!(at_work < 80, "{limits:?}");
        assert!(
            (1..=at_work).contains(&rendered),
            "{rendered} render nodes rendered, {at_work} at most at work"
        );
    }
    let t = &v["totals"];
    // Every counter the summary shows is filled in for a cluster as for one process.
    assert_eq!(v["rays"]["camera"].as_u64().unwrap(), 200 * 150 * 4);
    assert!(v["rays"]["secondary"].as_u64().unwrap() > 0);
    assert!(v["rays"]["shadow"].as_u64().unwrap() > 0);
    assert_eq!(v["bad_samples"].as_u64().unwrap(), 0);
    assert!(v["peak_rss_bytes"].as_u64().unwrap() > 0);
    assert!(t["cache_peak_bytes"].as_u64().unwrap() > 0);
    assert!(t["cache_misses"].as_u64().unwrap() > 0);
    assert!(
        t["cache_evictions"].as_u64().unwrap() > 0,
        "a 5% cache must evict"
    );
    // Coherent rays are `auto` by default: every render node read its cards' memory in
    // place, where a miss copies nothing, so no path was put aside (tested over TCP in
    // `coherent_rays_wait_only_where_a_miss_crosses_a_socket`).
    assert_eq!(v["coherent_rays"], "auto");
    assert_eq!(v["shared_memory_nodes"], 80);
    assert_eq!(t["paths_deferred"].as_u64().unwrap(), 0, "{t}");
    assert_eq!(v["ask_ahead"], true, "the default");
    // With links of no delay model, requests for work go straight to the host: they do not
    // cross the fork nodes (which still carry pixels on their way to the host, as many as
    // the render nodes at work make cross them): every one came over the render node's own
    // connection.
    assert_eq!(v["ask_via"], "control", "the default without a link model");
    let subscreens = v["subscreen_count"].as_u64().unwrap();
    assert_eq!(v["requests_via"]["mesh"], 0, "{}", v["requests_via"]);
    assert!(
        v["requests_via"]["control"].as_u64().unwrap() >= subscreens,
        "{} for {subscreens} subscreens",
        v["requests_via"]
    );
    let fetched =
        t["bytes_fetched_dma"].as_u64().unwrap() + t["bytes_fetched_serial"].as_u64().unwrap();
    // What batch transfer would move: every chunk's and tile's words to each render node.
    let data_bytes: f64 = ["chunk_bytes", "tile_bytes"]
        .iter()
        .flat_map(|k| v[k].as_array().unwrap())
        .map(|b| b.as_f64().unwrap())
        .sum();
    assert!(
        v["cache_bytes"].as_f64().unwrap() > 0.05 * data_bytes,
        "the budget counts chunks ready to walk, more than their words"
    );
    assert!(
        (fetched as f64) < 80.0 * data_bytes * 0.25,
        "fetched {fetched} bytes; batch would move {} ",
        80.0 * data_bytes
    );
    for m in v["members"].as_array().unwrap() {
        let pid = m["pid"].as_u64().unwrap();
        assert!(
            exited(pid),
            "process {pid} ({}) outlived the render",
            m["role"]
        );
    }
}

#[test]
fn tiny_cluster_matches_in_every_mode() {
    // The demo scene, denoised by default: the host filters the finished image, so the
    // filter's output is compared too.
    let dir = scratch("tiny-modes");
    let size = [
        "--width", "96", "--height", "64", "--spp", "3", "--seed", "5",
    ];
    let reference = in_process_to(&dir.join("ref.pfm"), &size);
    let small_cache = [
        "--transfer",
        "demand",
        "--cache",
        "8",
        "--chunk-triangles",
        "128",
        "--subscreens",
        "5",
    ];
    let modes: Vec<Vec<&str>> = vec![
        vec!["--transfer", "batch", "--subscreens", "1"],
        vec!["--transfer", "batch", "--subscreens", "7"],
        vec!["--transfer", "batch", "--subscreens", "500"],
        // The paper's way: a node asks for its next subscreen only once it has finished one,
        // and asks through the mesh.
        vec![
            "--ask-ahead",
            "off",
            "--ask-via",
            "mesh",
            "--subscreens",
            "40",
            "--adaptive",
        ],
        vec![
            "--transfer",
            "demand",
            "--cache",
            "40",
            "--chunk-triangles",
            "256",
            "--subscreens",
            "3",
            "--adaptive",
        ],
        vec![
            "--transfer",
            "demand",
            "--cache",
            "30",
            "--chunk-triangles",
            "512",
            "--subscreens",
            "40",
            "--adaptive",
            "--render-threads",
            "2",
        ],
        // A cache of a few chunks: paths wait for what it lacks (coherent rays), or each
        // miss is fetched at once.
        small_cache.to_vec(),
        [&small_cache[..], &["--coherent-rays", "off"]].concat(),
        // Paths wait for data even where it is read in place.
        [&small_cache[..], &["--coherent-rays", "on"]].concat(),
        // One node of the four at work, or every one.
        [&small_cache[..], &["--at-work", "1"]].concat(),
        [&small_cache[..], &["--at-work", "all"]].concat(),
        vec![
            "--transfer",
            "demand",
            "--cache",
            "100",
            "--demand-via",
            "serial",
            "--link-model",
            "paper",
            "--time-scale",
            "0.01",
        ],
    ];
    for (i, mode) in modes.iter().enumerate() {
        let out = dir.join(format!("m{i}.pfm"));
        let stats = dir.join(format!("m{i}.json"));
        let o = render(
            &[&["--spawn", "tiny"][..], mode, &size].concat(),
            &out,
            Some(&stats),
        );
        assert!(o.status.success(), "{mode:?}: {}", stderr(&o));
        same_bytes(&out, &reference);
        // Requests for work came the way asked for (the mesh where the paper's links are
        // modelled or where asked, else each render node's own connection), and only that way.
        let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
        let (asked, other) = match v["ask_via"].as_str().unwrap() {
            "mesh" => ("mesh", "control"),
            _ => ("control", "mesh"),
        };
        let via = &v["requests_via"];
        assert!(via[asked].as_u64().unwrap() > 0, "{mode:?}: {via}");
        assert_eq!(via[other], 0, "{mode:?}: {via}");
    }
}

/// With `--coherent-rays auto` (the default), paths wait for data where a miss crosses a
/// socket, and not where it is read in place in shared memory; the image is the same bytes
/// either way.
#[test]
fn coherent_rays_wait_only_where_a_miss_crosses_a_socket() {
    let dir = scratch("coherent-auto");
    let size = [
        "--width", "64", "--height", "48", "--spp", "2", "--seed", "3",
    ];
    let reference = in_process_to(&dir.join("ref.pfm"), &size);
    let small_cache = [
        "--spawn",
        "tiny",
        "--cache",
        "8",
        "--chunk-triangles",
        "128",
    ];
    for (transport, deferring) in [("tcp", true), ("auto", false)] {
        let out = dir.join(format!("{transport}.pfm"));
        let stats = dir.join(format!("{transport}.json"));
        let o = render(
            &[&small_cache[..], &["--dma-transport", transport], &size].concat(),
            &out,
            Some(&stats),
        );
        assert!(o.status.success(), "{transport}: {}", stderr(&o));
        same_bytes(&out, &reference);
        let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
        assert_eq!(v["coherent_rays"], "auto");
        // Nodes waiting on sockets fill each other's waits: every one of them works. Reading
        // in place, no more than the machine's CPUs.
        let limited = !v["machine_limits"].as_array().unwrap().is_empty();
        let cpus = std::thread::available_parallelism().unwrap().get();
        assert_eq!(limited, !deferring && cpus < 4, "{transport}: {v}");
        let t = &v["totals"];
        assert!(t["cache_evictions"].as_u64().unwrap() > 0, "{t}");
        let deferred = t["paths_deferred"].as_u64().unwrap();
        assert_eq!(deferred > 0, deferring, "{transport}: {t}");
        assert_eq!(
            t["deferred_fetches"].as_u64().unwrap() > 0,
            deferring,
            "{transport}: {t}"
        );
    }
}

#[test]
fn adaptive_redivision_splits_subscreens() {
    let dir = scratch("adaptive");
    let stats = dir.join("s.json");
    let out = dir.join("a.pfm");
    // Two subscreens for four nodes: the idle ones must be given halves.
    let o = render(
        &[
            "--spawn",
            "tiny",
            "--width",
            "64",
            "--height",
            "64",
            "--spp",
            "8",
            "--subscreens",
            "2",
            "--adaptive",
            // Every node at work, as in the paper, however few CPUs the machine has.
            "--at-work",
            "all",
        ],
        &out,
        Some(&stats),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
    // A cache that holds the whole scene (the default) makes no path wait: rows are taken
    // one at a time, and so can be given back.
    assert_eq!(v["coherent_rays"], "off");
    assert!(
        v["subscreens_split"].as_u64().unwrap() >= 2,
        "{}",
        v["subscreens_split"]
    );
    let busy = v["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|n| n["subscreens"].as_u64().unwrap_or(0) > 0)
        .count();
    assert!(busy >= 3, "only {busy} render nodes got work");
}

/// Every subscreen a cluster rendered has a record (where, who, when, what it cost, which
/// chunks and tiles it touched, what was fetched for it) that adds up to the render's
/// totals, and `magg-host plot` draws them.
#[test]
fn cluster_stats_record_every_subscreen_and_plot_them() {
    let dir = scratch("records");
    let stats = dir.join("s.json");
    let out = dir.join("r.pfm");
    let (w, h) = (64u64, 48u64);
    let o = render(
        &[
            "--spawn",
            "tiny",
            "--width",
            "64",
            "--height",
            "48",
            "--spp",
            "2",
            "--transfer",
            "demand",
            "--cache",
            "40",
            "--chunk-triangles",
            "256",
            "--subscreens",
            "9",
            "--adaptive",
        ],
        &out,
        Some(&stats),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
    let records = v["subscreens"].as_array().unwrap();
    let sum = |key: &str| {
        records
            .iter()
            .map(|r| r[key].as_u64().unwrap())
            .sum::<u64>()
    };
    assert_eq!(sum("pixels"), w * h, "every pixel in exactly one record");
    assert_eq!(sum("rays"), v["rays"]["total"].as_u64().unwrap());
    assert_eq!(sum("samples"), v["samples"].as_u64().unwrap());
    let t = &v["totals"];
    assert_eq!(
        sum("fetched_bytes"),
        t["bytes_fetched_dma"].as_u64().unwrap() + t["bytes_fetched_serial"].as_u64().unwrap()
    );
    assert_eq!(sum("fetches"), t["cache_misses"].as_u64().unwrap());
    let chunk_count = v["chunk_bytes"].as_array().unwrap().len();
    assert_eq!(chunk_count as u64, v["chunks"].as_u64().unwrap());
    let render_s = v["seconds"]["render"].as_f64().unwrap();
    for r in records {
        let (pixels, width, height) = (
            r["pixels"].as_u64().unwrap(),
            r["width"].as_u64().unwrap(),
            r["height"].as_u64().unwrap(),
        );
        assert_eq!(pixels, width * height, "{r}");
        let (start, end) = (r["start_s"].as_f64().unwrap(), r["end_s"].as_f64().unwrap());
        assert!(0.0 <= start && start <= end && end <= render_s + 0.5, "{r}");
        assert!(r["cpu_s"].as_f64().unwrap() > 0.0, "{r}");
        let chunks = r["chunks"].as_array().unwrap();
        // More rays than camera rays: some ray hit a surface, so its chunk was touched.
        if r["rays"].as_u64().unwrap() > r["samples"].as_u64().unwrap() {
            assert!(!chunks.is_empty(), "{r}");
        }
        assert!(
            chunks
                .iter()
                .all(|c| (c.as_u64().unwrap() as usize) < chunk_count)
        );
        let via = r["fetched_via"].as_str().unwrap();
        match r["fetches"].as_u64().unwrap() {
            0 => assert_eq!(via, "none"),
            _ => assert_eq!(via, "dma"),
        }
        let node = r["node"].as_u64().unwrap();
        assert!(
            v["nodes"]
                .as_array()
                .unwrap()
                .iter()
                .any(|n| n["node"] == node && n["role"] == "Render"),
            "{r}"
        );
    }
    assert!(
        records.iter().any(|r| r["fetches"].as_u64().unwrap() > 0),
        "a 40% cache starts empty: someone fetched"
    );

    let plots = dir.join("plots");
    let o = run(host().arg("plot").arg(&stats).arg("-o").arg(&plots));
    assert!(o.status.success(), "{}", stderr(&o));
    for f in ["s.timeline.png", "s.nodes.png"] {
        let png = std::fs::read(plots.join(f)).unwrap();
        assert!(png.starts_with(b"\x89PNG"), "{f}");
    }
}

#[test]
fn a_cache_smaller_than_a_chunk_is_a_clear_error() {
    let dir = scratch("tiny-cache");
    let out = dir.join("x.png");
    let o = render(
        &[
            "--spawn", "tiny", "--cache", "0.01", "--width", "8", "--height", "8", "--spp", "1",
        ],
        &out,
        None,
    );
    assert!(!o.status.success());
    assert!(stderr(&o).contains("largest chunk"), "{}", stderr(&o));
    assert!(!out.exists());
}

#[test]
fn interrupting_the_host_stops_every_process() {
    let dir = scratch("ctrl-c");
    let out = dir.join("never.png");
    let mut host = Logged::start(
        render_on_spawned_tiny()
            .args(["--spp", "4096", "--width", "200", "--height", "200", "-o"])
            .arg(&out),
    );
    // Interrupt once the render is under way: the first pixels have reached the host.
    host.wait_for(
        "MAGG_EVENT pixels node=",
        std::time::Duration::from_secs(60),
    )
    .unwrap_or_else(|| panic!("the render did not begin: {}", host.log()));
    let kids = children_of(host.pid());
    assert_eq!(kids.len(), 5, "the host should have started 5 nodes");
    let _ = rustix::process::kill_process(
        rustix::process::Pid::from_raw(host.pid() as i32).unwrap(),
        rustix::process::Signal::INT,
    );
    let code = host.wait_exit(std::time::Duration::from_secs(30));
    assert_eq!(code, Some(Some(130)), "{}", host.log());
    assert!(!out.exists(), "no image after an interrupt");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    for k in kids {
        while !exited(k) && std::time::Instant::now() < deadline {
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        assert!(exited(k), "node process {k} outlived the host");
    }
}

/// A spawning host interrupted while its nodes join stops at once and leaves no node behind
/// (it waited for the join timeout). The nodes are held (SIGSTOP) as they start, so the
/// cluster cannot form before the interrupt however fast the machine.
#[test]
fn interrupting_a_spawning_host_while_its_nodes_join_stops_every_process() {
    use std::time::{Duration, Instant};
    let dir = scratch("ctrl-c-forming");
    let out = dir.join("never.png");
    let mut host = Logged::start(
        host()
            .args(["--log", "info", "render", "--quiet", "--spawn", "tiny"])
            .args(["--join-timeout", "120", "-o"])
            .arg(&out),
    );
    let mut held = Held(Vec::new());
    let until = Instant::now() + Duration::from_secs(30);
    while held.0.len() < 5 && Instant::now() < until {
        for kid in children_of(host.pid()) {
            if node_role(kid).is_some() && !held.0.contains(&kid) {
                held.hold(kid);
            }
        }
    }
    assert_eq!(held.0.len(), 5, "the host should have started 5 nodes");
    assert!(
        host.wait_for("subscreens on", Duration::from_secs(1))
            .is_none(),
        "the cluster formed before its nodes were held: {}",
        host.log()
    );
    signal(host.pid() as u64, rustix::process::Signal::INT);
    let code = host.wait_exit(Duration::from_secs(20));
    assert_eq!(code, Some(Some(130)), "{}", host.log());
    assert!(
        host.log()
            .contains("interrupted; the cluster was stopped and no image was written"),
        "{}",
        host.log()
    );
    assert!(!out.exists(), "no image after an interrupt");
    for &kid in &held.0 {
        assert!(exited(kid), "node process {kid} outlived the host");
    }
}

/// The local subscreen order changes who renders what, never a pixel.
#[test]
fn local_subscreen_order_matches_one_process() {
    let dir = scratch("local-order");
    let scene = helmet();
    let scene = scene.to_str().unwrap();
    let size = ["--width", "96", "--height", "72", "--spp", "2"];
    let reference = dir.join("ref.pfm");
    let o = render(
        &[&[scene, "--in-process"][..], &size].concat(),
        &reference,
        None,
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let out = dir.join("cluster.pfm");
    let stats = dir.join("stats.json");
    let cluster = [
        scene, "--spawn", "tiny", "--order", "local", "--cache", "20",
    ];
    let o = render(&[&cluster[..], &size].concat(), &out, Some(&stats));
    assert!(o.status.success(), "{}", stderr(&o));
    same_bytes(&out, &reference);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
    assert_eq!(v["order"], "local");
}
