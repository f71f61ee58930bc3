#!/usr/bin/env python3
"""Issue 12's first-picture target, measured: the README's first command (the built-in demo
scene on the default 86-process cluster, default flags) timed as a user waits for it, and its
error against a 4096-spp render of the same scene.

    python3 bench/first_command.py [--runs 3] [--spp 24 32] [--host target/release/magg-host]
        [--reference-spp 4096] [--clamped-reference] [--denoise off] [--out bench/out]

The unbiased reference (`--clamp-indirect 0 --denoise off`, another seed, so that its samples
are not the ones measured) is rendered once in one process and kept under `--out` (about 20
to 35 minutes on two cores at 4096 spp); `--clamped-reference` also renders one with the
runs' clamping, not denoised, against which an undenoised run's error is its noise alone. Each run is the first command with `--spp S` added where S
differs from the default (24 spp, denoised, indirect light clamped at 8), writing linear
floats (`-o X.pfm`: the first command's PNG is the same render, quantised); `--denoise off`
times the demo as sampled instead (64 spp by default then, clamped at 4). relMSE comes from
`magg-host compare`. Target (issue 12, item 4):
under 15 s with relMSE at most 5e-3 against the 4096-spp render.

It only runs `magg-host render` and `magg-host compare`: nothing is installed.
"""

import argparse
import os
import re
import statistics
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_SPP = {"on": 24, "off": 64}
DEMO_CLAMP = {"on": 8, "off": 4}
TARGET_SECONDS = 15.0
TARGET_REL_MSE = 5e-3


def run(cmd):
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"failed: {' '.join(cmd)}\n{p.stderr}")
    return p


def reference(host, out_dir, spp, clamp):
    """The demo at `spp`, not denoised, with indirect light clamped at `clamp` (0: unbiased)."""
    name = f"demo-ref-{spp}-{f'clamped-{clamp:g}' if clamp else 'unbiased'}.pfm"
    path = os.path.join(out_dir, name)
    if os.path.exists(path):
        return path
    print(f"rendering the reference {name} once (in one process, {spp} spp)...", flush=True)
    cmd = [host, "render", "--quiet", "--in-process", "--spp", str(spp), "--seed", "1",
           "--denoise", "off", "--clamp-indirect", f"{clamp:g}", "-o", path + ".tmp.pfm"]
    t0 = time.monotonic()
    run(cmd)
    os.replace(path + ".tmp.pfm", path)
    print(f"  {time.monotonic() - t0:.0f} s", flush=True)
    return path


def rel_mse(host, image, ref):
    out = run([host, "compare", image, ref]).stdout
    m = re.search(r"relMSE ([0-9.eE+-]+)", out)
    if not m:
        sys.exit(f"no relMSE in: {out}")
    return float(m.group(1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--spp", type=int, nargs="+")
    ap.add_argument("--denoise", choices=["on", "off"], default="on")
    ap.add_argument("--host", default=os.path.join(ROOT, "target", "release", "magg-host"))
    ap.add_argument("--reference-spp", type=int, default=4096)
    ap.add_argument("--clamped-reference", action="store_true")
    ap.add_argument("--out", default=os.path.join(ROOT, "bench", "out"))
    a = ap.parse_args()
    default_spp = DEFAULT_SPP[a.denoise]
    a.spp = a.spp or [default_spp]
    if not os.access(a.host, os.X_OK):
        sys.exit(f"{a.host} is not built: cargo build --release --bins")
    os.makedirs(a.out, exist_ok=True)

    refs = {"unbiased": reference(a.host, a.out, a.reference_spp, 0)}
    if a.clamped_reference:
        clamp = DEMO_CLAMP[a.denoise]
        refs[f"clamped at {clamp}"] = reference(a.host, a.out, a.reference_spp, clamp)

    walls = {s: [] for s in a.spp}
    errors = {}
    for r in range(a.runs):
        for spp in a.spp:
            image = os.path.join(a.out, f"first-command-{spp}-denoise-{a.denoise}.pfm")
            cmd = [a.host, "render", "--quiet", "-o", image]
            if a.denoise == "off":
                cmd += ["--denoise", "off"]
            if spp != default_spp:
                cmd += ["--spp", str(spp)]
            t0 = time.monotonic()
            run(cmd)
            wall = time.monotonic() - t0
            walls[spp].append(wall)
            print(f"run {r + 1}: {spp:5} spp {wall:7.2f} s", flush=True)
            if r == 0:
                # The image is the same bytes every run: its error once.
                errors[spp] = {k: rel_mse(a.host, image, ref) for k, ref in refs.items()}

    print()
    cols = " | ".join(f"relMSE vs {k} {a.reference_spp} spp" for k in refs)
    print(f"| spp | wall s (each run) | median s | {cols} | under {TARGET_SECONDS:.0f} s"
          f" and relMSE <= {TARGET_REL_MSE:g} (unbiased reference) |")
    print("|---:|---|---:|" + "---:|" * len(refs) + "---|")
    for spp in a.spp:
        med = statistics.median(walls[spp])
        each = " / ".join(f"{w:.2f}" for w in walls[spp])
        errs = " | ".join(f"{errors[spp][k]:.2e}" for k in refs)
        met = med < TARGET_SECONDS and errors[spp]["unbiased"] <= TARGET_REL_MSE
        print(f"| {spp} | {each} | {med:.2f} | {errs} | {'yes' if met else 'no'} |")


if __name__ == "__main__":
    main()
