#!/usr/bin/env python3
"""Instructions a cluster render executes, process by process and thread by thread, against
one process rendering the same image: counted by callgrind, so stable on a shared machine
where wall times of the two move by 10% from one minute to the next.

    python3 bench/cluster_counts.py [--host target/release/magg-host] [--topology grid:1x1x2]
        [--scene tests/data/scenes/cornell/cornell.gltf] [--width 64 --height 64 --spp 16]

The cluster is started by hand, as on a LAN (`render --listen`, then a fork node and render
nodes joining it), every process under callgrind; one process renders the same with
`--in-process --threads 1`. The images must be the same bytes. Printed: each process's
threads and their instructions, then the instructions of the rendering threads of the
cluster against one process's, and of everything else (starting, the wire, the host's
bookkeeping) against one process's other threads.

What it cannot see: the kernel (process start, page faults, sockets), which is most of what
the cluster's start costs, and the machine's own effects (caches, preemption by the other
processes). Those show only in wall and CPU times (`bench/cluster_targets.py`). Keep the
topology small: each process under callgrind takes about 100 MB. Needs valgrind; nothing is
installed.
"""

import argparse
import glob
import os
import re
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SECRET = "cluster-counts secret"


def threads(prefix):
    """(thread number, instructions, renders) for each of one process's callgrind files."""
    rows = []
    for path in sorted(glob.glob(prefix + "-*")):
        with open(path, errors="replace") as f:
            text = f.read()
        total = re.search(r"^(?:summary|totals):\s+(\d+)", text, re.M)
        number = re.search(r"^thread:\s+(\d+)", text, re.M)
        if not total or not number:
            sys.exit(f"{path}: not a callgrind file of one thread")
        rows.append((int(number.group(1)), int(total.group(1)), "render_pixel" in text))
    if not rows:
        sys.exit(f"no callgrind output at {prefix}-*: did the process start?")
    return rows


def under_callgrind(out, cmd, log):
    return subprocess.Popen(
        ["valgrind", "--tool=callgrind", "--separate-threads=yes",
         f"--callgrind-out-file={out}", *cmd],
        stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "MAGG_SECRET": SECRET})


def wait_for(path, needle, proc, limit):
    """The first line of the log at `path` holding `needle`."""
    until = time.time() + limit
    while time.time() < until:
        with open(path, errors="replace") as f:
            for line in f:
                if needle in line:
                    return line
        if proc.poll() is not None:
            break
        time.sleep(0.2)
    with open(path, errors="replace") as f:
        sys.exit(f"no {needle!r} from the host:\n{f.read()[-3000:]}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--host", default=os.path.join(ROOT, "target", "release", "magg-host"))
    ap.add_argument("--topology", default="grid:1x1x2")
    ap.add_argument("--scene",
                    default=os.path.join(ROOT, "tests", "data", "scenes", "cornell", "cornell.gltf"))
    ap.add_argument("--width", default="64")
    ap.add_argument("--height", default="64")
    ap.add_argument("--spp", default="16")
    a = ap.parse_args()
    if not os.access(a.host, os.X_OK):
        sys.exit(f"{a.host} is not built: cargo build --release --bins")
    view = [a.scene, "--width", a.width, "--height", a.height, "--spp", a.spp, "--quiet"]

    with tempfile.TemporaryDirectory(prefix="magg-cluster-counts-") as tmp:
        one = os.path.join(tmp, "one.png")
        with open(os.path.join(tmp, "one.log"), "w") as log:
            p = under_callgrind(os.path.join(tmp, "one.cg"),
                                [a.host, "render", *view, "--in-process", "--threads", "1",
                                 "-o", one], log)
            if p.wait() != 0:
                sys.exit(f"the one-process render failed: see {log.name}")
        alone = threads(os.path.join(tmp, "one.cg"))

        host_log = os.path.join(tmp, "host.log")
        cluster = os.path.join(tmp, "cluster.png")
        procs = []
        try:
            cluster_run(a, tmp, view, host_log, cluster, procs)
        finally:
            # On any way out, no process of the cluster is left running (the host waits
            # ten minutes for nodes that may never come).
            for _, p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait()
        report(a, tmp, procs, alone, one, cluster)


def cluster_run(a, tmp, view, host_log, cluster, procs):
    """Starts the host and its nodes under callgrind and waits for the render to end."""
    with open(host_log, "w") as log:
        host = under_callgrind(os.path.join(tmp, "host.cg"),
                               [a.host, "render", *view, "--topology", a.topology,
                                "--listen", "127.0.0.1:0", "--join-timeout", "600",
                                "-o", cluster], log)
    procs.append(("host", host))
    # "waiting for NAME: 1 host + F fork nodes + R render nodes = ... to join at ADDR"
    line = wait_for(host_log, "to join at ", host, 300)
    addr = line.rsplit("to join at ", 1)[1].strip()
    m = re.search(r"(\d+) fork nodes? \+ (\d+) render nodes?", line)
    if not m:
        sys.exit(f"cannot tell the topology's nodes from: {line}")
    forks, renders = int(m.group(1)), int(m.group(2))
    for role, n in (("fork-node", forks), ("render-node", renders)):
        for i in range(n):
            name = f"{role}-{i + 1}"
            with open(os.path.join(tmp, name + ".log"), "w") as log:
                procs.append((name, under_callgrind(
                    os.path.join(tmp, name + ".cg"),
                    [a.host, role, "--join", addr, "--listen", "127.0.0.1:0",
                     "--log", "warn"], log)))
    if host.wait(timeout=1800) != 0:
        with open(host_log, errors="replace") as f:
            sys.exit(f"the cluster render failed:\n{f.read()[-3000:]}")
    for name, p in procs[1:]:
        if p.wait(timeout=120) != 0:
            sys.exit(f"{name} exited with {p.returncode}: see its log in {tmp}")


def report(a, tmp, procs, alone, one, cluster):
    """Prints each thread's count and the cluster's against one process's."""
    with open(one, "rb") as f1, open(cluster, "rb") as f2:
        if f1.read() != f2.read():
            sys.exit("the cluster's image differs from one process's")

    print(f"`{os.path.relpath(a.scene, ROOT)}` {a.width}x{a.height} at {a.spp} spp,"
          f" topology {a.topology}; the same image bytes both ways")
    print()
    print("| process | thread | renders | instructions |")
    print("|---|---:|---|---:|")
    render_sum = other_sum = 0
    for name, _ in procs:
        for number, total, renders_ in threads(os.path.join(tmp, name + ".cg")):
            print(f"| {name} | {number} | {'yes' if renders_ else ''} | {total:,} |")
            if renders_:
                render_sum += total
            else:
                other_sum += total
    one_render = sum(t for _, t, r in alone if r)
    one_other = sum(t for _, t, r in alone if not r)
    for number, total, renders_ in alone:
        print(f"| one process | {number} | {'yes' if renders_ else ''} | {total:,} |")
    print()
    print("| | cluster | one process | cluster / one process |")
    print("|---|---:|---:|---:|")
    print(f"| rendering threads | {render_sum:,} | {one_render:,} |"
          f" {render_sum / one_render:.4f} |")
    print(f"| everything else | {other_sum:,} | {one_other:,} |"
          f" {other_sum / max(one_other, 1):.2f} |")
    print(f"| all | {render_sum + other_sum:,} | {one_render + one_other:,} |"
          f" {(render_sum + other_sum) / (one_render + one_other):.4f} |")



if __name__ == "__main__":
    main()
