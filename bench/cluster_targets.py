#!/usr/bin/env python3
"""Issue 14's cluster targets, measured: wall times of the same render command in one
process and on the 86-process cluster, runs of every configuration interleaved (so that load
from elsewhere falls on all of them alike), the median of each, its ratio to in-process, and
what the render nodes fetched and kept in memory of their own. Every image must be the same
bytes as the in-process one; the script stops if one is not.

Two times per run: from the command's start to its image written (when the output file got
its final name: its modification time, read against the same clock; the issue's measure),
and to the command's exit. On 86 processes the host writes the image before it collects the
nodes' figures and stops them (about 0.1 s more); in one process little follows the image.
The targets are judged on the first, as the issue words them; both are printed.

    python3 bench/cluster_targets.py [--runs 3] [--host target/release/magg-host]
        [--scene PATH] [--cornell PATH] [--with-tcp-5]

It only runs `magg-host render` with `--stats` and reads the stats files: nothing is
installed. Targets (issue 14, item 4) are printed beside the figures as met or not.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MIB = 1 << 20


def find_scene():
    for base in (os.path.join(ROOT, "..", "shared", "scenes", "khronos"),
                 os.path.join(ROOT, "tests", "data", "scenes", "khronos")):
        p = os.path.join(base, "MetalRoughSpheresNoTextures", "glTF",
                         "MetalRoughSpheresNoTextures.gltf")
        if os.path.exists(p):
            return p
    return None


def render(host, args, out, stats):
    """Runs one render; returns (seconds to the image written, seconds to exit, stats)."""
    cmd = [host, "render", "--quiet", *args, "-o", out, "--stats", stats]
    # The file's modification time comes from the system clock: read the start on it too.
    t0 = time.time_ns()
    p = subprocess.run(cmd, capture_output=True, text=True)
    whole = (time.time_ns() - t0) / 1e9
    if p.returncode != 0:
        sys.exit(f"failed: {' '.join(cmd)}\n{p.stderr}")
    to_image = (os.stat(out).st_mtime_ns - t0) / 1e9
    if not 0 < to_image <= whole:
        sys.exit(f"{out}: its modification time is not within the run (the clock moved?)")
    with open(stats) as f:
        return to_image, whole, json.load(f)


def same_bytes(a, b):
    with open(a, "rb") as fa, open(b, "rb") as fb:
        return fa.read() == fb.read()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--host", default=os.path.join(ROOT, "target", "release", "magg-host"))
    ap.add_argument("--scene", default=find_scene())
    ap.add_argument("--cornell",
                    default=os.path.join(ROOT, "tests", "data", "scenes", "cornell", "cornell.gltf"))
    ap.add_argument("--with-tcp-5", action="store_true",
                    help="also cache 5%% over TCP (minutes a run on two cores)")
    a = ap.parse_args()
    if not a.scene or not os.path.exists(a.scene):
        sys.exit("MetalRoughSpheresNoTextures.gltf not found: pass --scene PATH")
    if not os.access(a.host, os.X_OK):
        sys.exit(f"{a.host} is not built: cargo build --release --bins")

    spheres = [a.scene, "--width", "320", "--height", "240", "--spp", "64",
               "--integrator", "path"]
    cornell = [a.cornell, "--width", "256", "--height", "256", "--spp", "256"]
    configs = [
        ("spheres", "in-process", spheres + ["--in-process"]),
        ("spheres", "86 processes, cache 100%", spheres + ["--cache", "100"]),
        # The paper's way, for comparison: every render node at work at once.
        ("spheres", "86 processes, cache 100%, all at work",
         spheres + ["--cache", "100", "--at-work", "all"]),
        ("spheres", "86 processes, cache 5%", spheres + ["--cache", "5"]),
        # The paper's way, for comparison: each miss fetched at once (no coherent rays).
        ("spheres", "86 processes, cache 5%, coherent rays off",
         spheres + ["--cache", "5", "--coherent-rays", "off"]),
        ("spheres", "86 processes, cache 100%, TCP only",
         spheres + ["--cache", "100", "--dma-transport", "tcp"]),
        ("cornell", "in-process", cornell + ["--in-process"]),
        ("cornell", "86 processes", cornell),
    ]
    if a.with_tcp_5:
        configs.insert(5, ("spheres", "86 processes, cache 5%, TCP only",
                           spheres + ["--cache", "5", "--dma-transport", "tcp"]))

    results = {(s, n): [] for s, n, _ in configs}
    with tempfile.TemporaryDirectory(prefix="magg-cluster-targets-") as tmp:
        reference = {}
        for run in range(a.runs):
            for scene, name, args in configs:
                key = (scene, name)
                out = os.path.join(tmp, f"{scene}-{len(results[key])}-{abs(hash(name))}.png")
                stats = os.path.join(tmp, "stats.json")
                to_image, whole, st = render(a.host, args, out, stats)
                ref = reference.setdefault(scene, out)
                if not same_bytes(out, ref):
                    sys.exit(f"{scene} {name}: the image differs from the in-process one")
                results[key].append((to_image, whole, st))
                print(f"run {run + 1}: {scene:8} {name:40} {to_image:7.2f} s to the image,"
                      f" {whole:7.2f} s to exit", flush=True)

    def median(key, which=0):
        return statistics.median(r[which] for r in results[key])

    print()
    print("| scene | run | s to the image (each run) | median s | x in-process |"
          " s to exit, median | x in-process | fetched by render nodes |"
          " render nodes' own memory, max |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for scene, name, _ in configs:
        key = (scene, name)
        walls = " / ".join(f"{r[0]:.2f}" for r in results[key])
        base = median((scene, "in-process"))
        base_whole = median((scene, "in-process"), 1)
        st = results[key][-1][2]
        nodes = [n for n in st.get("nodes", []) if n.get("role") == "Render"]
        fetched = st["totals"]["bytes_fetched_dma"] + st["totals"]["bytes_fetched_serial"] \
            if "totals" in st else 0
        private = max((n.get("peak_private_bytes", 0) for n in nodes), default=0)
        budget = st.get("cache_bytes", 0)
        mem = f"{private / MIB:.1f} MiB (budget {budget / MIB:.1f})" if nodes else "-"
        print(f"| {scene} | {name} | {walls} | {median(key):.2f} | {median(key) / base:.2f} |"
              f" {median(key, 1):.2f} | {median(key, 1) / base_whole:.2f} |"
              f" {fetched / MIB:.0f} MiB | {mem} |")

    def ratio(scene, name, which=0):
        return median((scene, name), which) / median((scene, "in-process"), which)

    def fetched(name):
        st = results[("spheres", name)][-1][2]["totals"]
        return st["bytes_fetched_dma"] + st["bytes_fetched_serial"]

    worst_private = max(
        (n.get("peak_private_bytes", 0) - results[k][-1][2].get("cache_bytes", 0)
         for k in results for _, _, st in results[k][-1:]
         for n in st.get("nodes", []) if n.get("role") == "Render"), default=0)
    def times(scene, name):
        return ratio(scene, name), ratio(scene, name, 1)

    # (what, measured to the image, measured to exit (None where not a time), bar)
    targets = [
        ("spheres, 86 processes at cache 100% within 1.5x in-process",
         *times("spheres", "86 processes, cache 100%"), 1.5),
        ("spheres, 86 processes at cache 5% within 2x in-process",
         *times("spheres", "86 processes, cache 5%"), 2.0),
        ("spheres, bytes fetched at 5% at most 2x those at 100%",
         fetched("86 processes, cache 5%") / max(fetched("86 processes, cache 100%"), 1), None,
         2.0),
        ("spheres, TCP only at cache 100% within 3x in-process",
         *times("spheres", "86 processes, cache 100%, TCP only"), 3.0),
        ("Cornell box, 86 processes within 1.10x in-process",
         *times("cornell", "86 processes"), 1.10),
        ("render node's own memory at most its budget + 8 MiB (excess, MiB)",
         worst_private / MIB, None, 8.0),
    ]
    print()
    print("| target | measured | to exit | bar | met |")
    print("|---|---:|---:|---:|---|")
    for what, value, whole, bar in targets:
        whole = "-" if whole is None else f"{whole:.2f}"
        print(f"| {what} | {value:.2f} | {whole} | {bar:.2f} | {'yes' if value <= bar else 'no'} |")


if __name__ == "__main__":
    main()
