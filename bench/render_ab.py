#!/usr/bin/env python3
"""Two builds of magg-host rendering the same command, runs taking turns: what a change to the
cluster (its start, the scene's way to the fork nodes) does to the time to the image, where
the shared machine's noise would drown a comparison of runs made at different times.

    python3 bench/render_ab.py BASE HEAD [--pairs 10] -- RENDER ARGS...

BASE and HEAD are magg-host binaries (copy one aside before building the other). A render
that spawns its cluster starts its own executable in every role, so each side runs its own
build throughout. Each pair runs `BASE render --quiet RENDER ARGS -o OUT` then the same with
HEAD; a run is timed from its start to its image written (the output file's modification
time, as `bench/cluster_targets.py` times them). Prints every run, the median of each side
and HEAD's over BASE's, and whether the last images of the two are the same bytes (they
must be). Nothing is installed.

Example (the spheres on the 86-process cluster at cache 100%):

    python3 bench/render_ab.py /tmp/base target/release/magg-host -- \\
        ../shared/scenes/khronos/MetalRoughSpheresNoTextures/glTF/MetalRoughSpheresNoTextures.gltf \\
        --width 320 --height 240 --spp 64 --integrator path --cache 100
"""

import ab_pair
import filecmp
import os
import statistics
import subprocess
import sys
import tempfile
import time


def run(exe, args, out):
    """Seconds from the start of one render to its image written."""
    if os.path.exists(out):
        os.remove(out)
    cmd = [exe, "render", "--quiet", *args, "-o", out]
    start = time.time()
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0 or not os.path.exists(out):
        sys.exit(f"failed ({done.returncode}): {' '.join(cmd)}\n{done.stderr[-2000:]}")
    return os.path.getmtime(out) - start


def main():
    ap = ab_pair.parser(__doc__)
    ap.add_argument("--pairs", type=int, default=10)
    argv = sys.argv[1:]
    if "--" not in argv:
        sys.exit("give the render's scene and options after --")
    cut = argv.index("--")
    a = ap.parse_args(argv[:cut])
    render = argv[cut + 1:]
    if not render:
        sys.exit("give the render's scene and options after --")
    ab_pair.check_executables(a)
    times = {"base": [], "head": []}
    with tempfile.TemporaryDirectory() as tmp:
        outs = {side: os.path.join(tmp, f"{side}.png") for side in times}
        for i in range(a.pairs):
            for side in ("base", "head"):
                t = run(getattr(a, side), render, outs[side])
                times[side].append(t)
                print(f"pair {i + 1}: {side} {t:.3f} s", flush=True)
        same = filecmp.cmp(outs["base"], outs["head"], shallow=False)
    med = {side: statistics.median(v) for side, v in times.items()}
    print()
    for side in ("base", "head"):
        print(f"{side}: median {med[side]:.3f} s ({' / '.join(f'{t:.3f}' for t in times[side])})")
    print(f"head / base: {med['head'] / med['base']:.3f}; images: "
          f"{'same bytes' if same else 'DIFFERENT'}")
    if not same:
        sys.exit(1)


if __name__ == "__main__":
    main()
