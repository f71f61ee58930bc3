#!/usr/bin/env python3
"""Two builds of magg-host against each other on the same rays, runs taking turns: what one
kernel change does to the rate, where the shared machine's noise (10% and more between runs
a minute apart) would drown a comparison of runs made at different times.

    python3 bench/rays_ab.py BASE HEAD [--rounds 3] [--repeat 3] [--core 0] [--any-hit]
        [--path in-process|cache]

BASE and HEAD are magg-host binaries (copy one aside before building the other). The rays are
those the last `bench/peers/embree.py` run made (its `out/embree-results.json` names the mesh
and the ray files; run it first). Each round runs `bench rays --repeat N` of BASE then HEAD on
one core, for every set; the table gives the best in-process rate of each over all rounds and
HEAD's over BASE's (above 1: HEAD is faster). Hit files of the two are compared byte for byte
too: a kernel change that is only faster must not move a single hit. Nothing is installed.
"""

import ab_pair
import filecmp
import json
import os
import subprocess
import sys
import tempfile

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "peers", "out")


def rate(exe, mesh, rays, repeat, core, any_hit, hits, path):
    """The best rate of one `bench rays` run on `path` ("in_process" or "cache"), from the
    report it writes."""
    report = hits + ".json"
    cmd = ["taskset", "-c", str(core), exe, "bench", "rays", mesh, rays,
           "--repeat", str(repeat), "--hits", hits, "--json", report]
    if any_hit:
        cmd.append("--any-hit")
    run = subprocess.run(cmd, capture_output=True, text=True)
    if run.returncode != 0:
        sys.exit(f"failed ({run.returncode}): {' '.join(cmd)}\n{run.stderr[-2000:]}")
    try:
        with open(report) as f:
            return float(json.load(f)[path]["best_mrays"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        sys.exit(f"no {path} rate in {report} ({e}) from: {' '.join(cmd)}")


def main():
    ap = ab_pair.parser(__doc__)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--core", type=int, default=0)
    ap.add_argument("--any-hit", action="store_true", help="any-hit queries instead of closest")
    ap.add_argument("--path", choices=("in-process", "cache"), default="in-process",
                    help="whose rate: one process's or a render node's cache path")
    args = ap.parse_args()
    ab_pair.check_executables(args)
    results = os.path.join(OUT, "embree-results.json")
    try:
        with open(results) as f:
            made = json.load(f)
    except (OSError, ValueError) as e:
        sys.exit(f"cannot read {results} ({e}): run bench/peers/embree.py first")
    mesh = os.path.join(OUT, made["mesh"]["file"])
    sets = [(s["set"], os.path.join(OUT, s["file"])) for s in made["sets"]
            if not s["set"].endswith("any-hit")]
    print(f"{len(sets)} ray sets on {made['mesh']['file']} ({made['mesh']['triangles']:,} "
          f"triangles), {args.rounds} rounds taking turns, `--repeat {args.repeat}`, core "
          f"{args.core}{', any hit' if args.any_hit else ''}, {args.path} path\n")
    print("| set | BASE best M rays/s | HEAD best M rays/s | HEAD / BASE | hits |")
    print("|---|---:|---:|---:|---|")
    path = args.path.replace("-", "_")
    with tempfile.TemporaryDirectory() as tmp:
        for name, rays in sets:
            best = {"base": 0.0, "head": 0.0}
            for _ in range(args.rounds):
                for side in ("base", "head"):
                    exe = getattr(args, side)
                    hits = os.path.join(tmp, f"{side}.f32")
                    best[side] = max(best[side], rate(exe, mesh, rays, args.repeat, args.core,
                                                      args.any_hit, hits, path))
            same = filecmp.cmp(os.path.join(tmp, "base.f32"), os.path.join(tmp, "head.f32"),
                               shallow=False)
            print(f"| {name} | {best['base']:.2f} | {best['head']:.2f} | "
                  f"{best['head'] / best['base']:.3f} | {'same bytes' if same else 'DIFFER'} |",
                  flush=True)


if __name__ == "__main__":
    main()
