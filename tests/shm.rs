//! The card's shared memory for real: on one machine a render node's DMA reads go through
//! the fork node's shared-memory segment, with TCP forced they cross sockets, and either way
//! (also with the delay model on) the image is the same bytes as one process; the stats say
//! which transport carried how much, chunks are walked in place in the mapping (so a render
//! node's own memory stays within its budget), every fork node took its card's share as the
//! segment the first fork node wrote, and no segment outlives the fork node that wrote it.

mod common;
use common::*;

use std::path::Path;

fn helmet() -> String {
    data()
        .join("scenes/khronos/DamagedHelmet/glTF-Binary/DamagedHelmet.glb")
        .to_str()
        .unwrap()
        .to_string()
}

/// Renders on a spawned cluster of three cards of two render nodes and returns the stats.
fn cluster(dir: &Path, name: &str, args: &[&str], reference: &Path) -> serde_json::Value {
    let out = dir.join(format!("{name}.png"));
    let stats = dir.join(format!("{name}.json"));
    let o = run(host()
        .args(["render", "--quiet", "--spawn", "grid:3x1x2"])
        .args(args)
        .arg("-o")
        .arg(&out)
        .arg("--stats")
        .arg(&stats));
    assert!(o.status.success(), "{name}: {}", stderr(&o));
    same_bytes(&out, reference);
    serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap()
}

fn u(v: &serde_json::Value) -> u64 {
    v.as_u64().unwrap()
}

/// Every fork node of the (one-machine) cluster took its card's share as the segment the
/// first fork node wrote, and together they hold the whole scene.
fn shares_came_as_segments(v: &serde_json::Value) {
    let forks: Vec<&serde_json::Value> = (v["nodes"].as_array().unwrap().iter())
        .filter(|n| n["role"] == "Fork")
        .collect();
    let items: Vec<u64> = (forks.iter())
        .map(|n| u(&n["share_items_in_segment"]))
        .collect();
    assert_eq!(items.len(), 3, "three cards");
    assert!(items.iter().all(|&i| i > 0), "items by card: {items:?}");
    let scene = u(&v["chunks"]) + u(&v["texture_tiles"]);
    assert_eq!(items.iter().sum::<u64>(), scene, "items by card: {items:?}");
}

/// No segment of the render's fork nodes is left in /dev/shm.
fn no_segment_left(v: &serde_json::Value) {
    let Ok(entries) = std::fs::read_dir("/dev/shm") else {
        return;
    };
    let names: Vec<String> = entries
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    for m in v["members"].as_array().unwrap() {
        let prefix = format!("magg-card-{}-", m["pid"]);
        assert!(
            !names.iter().any(|n| n.starts_with(&prefix)),
            "fork node {} left its segment: {names:?}",
            m["pid"]
        );
    }
}

#[test]
fn shared_memory_and_forced_tcp_give_the_bytes_of_one_process() {
    let _one = serial();
    let dir = scratch("shm");
    let scene = helmet();
    let render = [
        scene.as_str(),
        "--width",
        "96",
        "--height",
        "72",
        "--spp",
        "2",
    ];
    let reference = in_process(&dir, &render);
    let demand = ["--transfer", "demand", "--cache", "20"];

    let auto = cluster(&dir, "auto", &[&render[..], &demand].concat(), &reference);
    let renderers: Vec<&serde_json::Value> = auto["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|n| n["role"] == "Render")
        .collect();
    assert_eq!(auto["dma_transport"], "auto");
    assert_eq!(auto["shared_memory_nodes"], renderers.len());
    let t = &auto["totals"];
    assert!(u(&t["bytes_fetched_shared"]) > 0, "{t}");
    // Every card is on this machine: every DMA byte came through shared memory.
    assert_eq!(u(&t["bytes_fetched_shared"]), u(&t["bytes_fetched_dma"]));
    for n in &renderers {
        assert!(u(&n["shared_segments"]) >= 1, "{n}");
        // Chunks are walked where they lie in the mapping, so the node's own memory holds
        // little beyond the tiles it copied, well within its budget.
        if u(&n["cache_misses"]) > 0 {
            assert!(u(&n["chunks_in_place"]) > 0, "{n}");
        }
        assert!(
            u(&n["peak_private_bytes"]) <= u(&auto["cache_bytes"]) + (8 << 20),
            "{n}"
        );
    }
    shares_came_as_segments(&auto);
    no_segment_left(&auto);

    let tcp = cluster(
        &dir,
        "tcp",
        &[&render[..], &demand, &["--dma-transport", "tcp"]].concat(),
        &reference,
    );
    assert_eq!(tcp["dma_transport"], "tcp");
    assert_eq!(tcp["shared_memory_nodes"], 0);
    let t = &tcp["totals"];
    assert_eq!(u(&t["bytes_fetched_shared"]), 0);
    assert!(u(&t["bytes_fetched_dma"]) > 0);
    for n in tcp["nodes"].as_array().unwrap() {
        assert_eq!(u(&n["chunks_in_place"]), 0, "{n}");
    }
    // Render nodes do not read the segments, but fork nodes still serve from them.
    shares_came_as_segments(&tcp);
    no_segment_left(&tcp);

    // With the paper's delays the fork node still times each shared-memory read.
    let delayed = cluster(
        &dir,
        "delayed",
        &[
            &render[..],
            &demand,
            &["--link-model", "paper", "--time-scale", "0.001"],
        ]
        .concat(),
        &reference,
    );
    assert!(u(&delayed["totals"]["bytes_fetched_shared"]) > 0);
    no_segment_left(&delayed);
}
