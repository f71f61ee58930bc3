#!/usr/bin/env python3
"""Instructions a ray query costs, counted by callgrind: stable on a shared, noisy machine,
where wall times of one build against another cannot be told apart below 10%.

    python3 bench/kernel_counts.py [--host target/release/magg-host] [--out DIR]
        [--mesh GLB --rays-dir DIR] [--skip-rays] [--skip-cornell] [--skip-embree]

Two measurements, each printed as a markdown table:

1. `magg-host bench rays --repeat 1` on the ray sets of `bench/peers/embree.py --quick`
   (run that first; it writes the 99,044-triangle landscape and three ray files into
   bench/peers/out). With `--repeat 1` the bench casts every ray four times: once untimed and
   once timed in one process, the same through a render node's cache. The count a query is
   (instructions of the run - instructions of the same run with one ray) / (4 x rays), so
   loading and building cancel out; it is the mean of the two data paths.
   The same rays are counted through Intel Embree too, when `bench/peers/embree.py` has made
   its virtual environment (`bench/peers/.venv-embree`): `rtcIntersect1` / `rtcOccluded1` on
   the same landscape, the instructions of the Embree library alone (its build cancels out
   the same way), in the AVX2 code it picks under valgrind, which cannot run AVX-512: the
   same instruction set as magg's build. The binding's own loop over the rays (Cython, about
   60 instructions a ray) is left out of Embree's count; magg's count holds its bench loop
   (about 20).
2. The Cornell box (`tests/data/scenes/cornell`), 64x64 at 16 spp on one thread, in one
   process: the instructions of a closest-hit and of a shadow query (the inclusive count of
   `Tracer::closest` and `Tracer::occluded` over their calls), once as the file is (one chunk
   per mesh) and once with its non-emitting meshes merged into one mesh (a copy written into
   OUT), which is what merging small meshes into spatial chunks would give it.

Needs valgrind (`callgrind`, `callgrind_annotate`); nothing is installed.
"""

import argparse
import base64
import copy
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def callgrind(cmd, out_file=None, prefix=()):
    """Runs `cmd` under callgrind (itself run by `prefix`, e.g. taskset); its total instruction
    count."""
    target = out_file or os.devnull
    run = subprocess.run([*prefix, "valgrind", "--tool=callgrind",
                          f"--callgrind-out-file={target}", *cmd],
                         capture_output=True, text=True)
    if run.returncode != 0:
        sys.exit(f"failed ({run.returncode}): {' '.join(cmd)}\n{run.stderr[-2000:]}")
    m = re.search(r"I\s+refs:\s+([\d,]+)", run.stderr)
    if not m:
        sys.exit(f"no instruction count from callgrind for: {' '.join(cmd)}")
    return int(m.group(1).replace(",", ""))


def query_costs(profile):
    """Per function name fragment, (inclusive instructions, calls) from a callgrind profile."""
    # Run away from the sources: found relative to the current folder, they make it print
    # self costs per source file instead of each function's inclusive cost.
    text = subprocess.run(["callgrind_annotate", "--tree=caller", "--inclusive=yes", profile],
                          capture_output=True, text=True, check=True,
                          cwd=os.path.dirname(os.path.abspath(profile))).stdout
    found = {}
    calls = 0
    for line in text.splitlines():
        caller = re.match(r"\s*[\d,]+ \([^)]*\)\s+<\s.*\(([\d,]+)x\)", line)
        if caller:
            calls += int(caller.group(1).replace(",", ""))
            continue
        own = re.match(r"\s*([\d,]+) \([^)]*\)\s+\*\s+(.*)$", line)
        if own:
            for name in ("Tracer<D>::closest [", "Tracer<D>::occluded ["):
                if name in own.group(2) and calls:
                    ir, n = found.get(name, (0, 0))
                    found[name] = (ir + int(own.group(1).replace(",", "")), n + calls)
        calls = 0
    return found


def ray_sets(args):
    rays_dir = args.rays_dir
    mesh = args.mesh
    if mesh is None:
        meshes = sorted(f for f in os.listdir(rays_dir) if f.startswith("landscape-")
                        and f.endswith(".glb")) if os.path.isdir(rays_dir) else []
        quick = [m for m in meshes
                 if json.load(open(os.path.join(rays_dir, m[:-4] + ".json"))).get("triangles", 0)
                 < 200_000] if meshes else []
        if not quick:
            sys.exit(f"no --quick landscape in {rays_dir}: run python3 bench/peers/embree.py "
                     "--quick first")
        mesh = os.path.join(rays_dir, quick[0])
    sets = {}
    for name in ("primary", "random", "diffuse"):
        files = sorted(f for f in os.listdir(rays_dir)
                       if f.startswith(f"rays-{name}-100000-") and f.endswith(".bin"))
        if files:
            sets[name] = os.path.join(rays_dir, files[0])
    if not sets:
        sys.exit(f"no ray files of 100,000 rays in {rays_dir}: run python3 "
                 "bench/peers/embree.py --quick first")
    return mesh, sets


EMBREE_PYTHON = os.path.join(ROOT, "bench", "peers", ".venv-embree", "bin", "python")

# Run by the Embree environment's Python under callgrind: builds the scene as embree.py does
# (the first query commits it), then casts RAYS[:N] once with the query QUERY.
EMBREE_CAST = """
import sys
sys.path.insert(0, sys.argv[1])
import numpy as np
import embree
embree.np = np
verts, tris = embree.check_glb(sys.argv[2])
o, d = embree.read_rays(sys.argv[3])
n = int(sys.argv[4])
scene, _, _ = embree.build_scene(np.ascontiguousarray(verts), tris, False)
scene.run(np.ascontiguousarray(o[:n]), np.ascontiguousarray(d[:n]),
          dists=np.full(n, np.inf, np.float32), query=sys.argv[5])
"""


def embree_library_instructions(script, mesh, rays, n, query, tmp):
    """Instructions executed inside the Embree library while casting rays[:n] (the whole
    run: loading, building, casting)."""
    profile = os.path.join(tmp, "embree.callgrind")
    # One CPU, as embree.py runs it: TBB then starts no worker threads, whose work-stealing
    # would make the build's count differ from run to run.
    pin = ["taskset", "-c", "0"] if shutil.which("taskset") else []
    callgrind([EMBREE_PYTHON, script, os.path.join(ROOT, "bench", "peers"), mesh, rays, str(n),
               query], profile, prefix=pin)
    text = subprocess.run(["callgrind_annotate", "--threshold=100", profile],
                          capture_output=True, text=True, check=True,
                          cwd=os.path.dirname(os.path.abspath(profile))).stdout
    total = 0
    for line in text.splitlines():
        m = re.match(r"\s*([\d,]+) \(", line)
        if m and "libembree4" in line:
            total += int(m.group(1).replace(",", ""))
    if not total:
        sys.exit("callgrind_annotate named no function of the Embree library")
    return total


def measure_rays(args, tmp):
    mesh, sets = ray_sets(args)
    one = os.path.join(tmp, "one-ray.bin")
    with open(one, "wb") as f:
        f.write(struct.pack("<6f", 0.0, 0.0, 0.0, 0.0, 0.0, 1.0))

    def bench(rays, extra=()):
        return callgrind([args.host, "bench", "rays", mesh, rays, "--repeat", "1", *extra])

    embree = None
    if not args.skip_embree and os.path.exists(EMBREE_PYTHON):
        embree = os.path.join(tmp, "embree_cast.py")
        with open(embree, "w") as f:
            f.write(EMBREE_CAST)
    elif not args.skip_embree:
        print(f"(no {EMBREE_PYTHON}: run python3 bench/peers/embree.py --quick to count Embree "
              "too)\n")

    # One run with one ray per kind of query, as for magg below: it holds the build, which
    # every set's run repeats.
    embree_base = {}

    def embree_query(path, n, query):
        if embree is None:
            return None
        if query not in embree_base:
            embree_base[query] = embree_library_instructions(embree, mesh, one, 1, query, tmp)
        total = embree_library_instructions(embree, mesh, path, n, query, tmp)
        return (total - embree_base[query]) / (n - 1)

    print(f"Ray queries on {os.path.basename(mesh)} (callgrind, `bench rays --repeat 1`)\n")
    print("| set | rays | instructions a query | Embree (AVX2) | magg / Embree |")
    print("|---|---:|---:|---:|---:|")
    base = bench(one)
    any_base = bench(one, ["--any-hit"])

    def row(label, n, magg, theirs):
        if theirs is None:
            print(f"| {label} | {n:,} | {magg:,.0f} | | |")
        else:
            print(f"| {label} | {n:,} | {magg:,.0f} | {theirs:,.0f} | {magg / theirs:.2f} |")

    for name, path in sets.items():
        n = os.path.getsize(path) // 24
        total = bench(path)
        row(name, n, (total - base) / (4 * n), embree_query(path, n, "DISTANCE"))
        if name == "random":
            total = bench(path, ["--any-hit"])
            row("random, any hit", n, (total - any_base) / (4 * n),
                embree_query(path, n, "OCCLUDED"))
    print(f"\nThe whole command with one ray (loading and building): {base:,} instructions.\n")


def merged_cornell(src, dst):
    """A copy of the Cornell box with every non-emitting mesh merged into one (the first
    one's material), positions only: the geometry rays meet is the same."""
    g = json.load(open(src))
    blob = None
    uri = g["buffers"][0].get("uri", "")
    if uri.startswith("data:"):
        blob = base64.b64decode(uri.split(",", 1)[1])
    else:
        blob = open(os.path.join(os.path.dirname(src), uri), "rb").read()

    def positions(acc):
        a = g["accessors"][acc]
        view = g["bufferViews"][a["bufferView"]]
        at = view.get("byteOffset", 0) + a.get("byteOffset", 0)
        stride = view.get("byteStride", 12)
        return [struct.unpack_from("<3f", blob, at + stride * i) for i in range(a["count"])]

    def triangles(prim):
        pts = positions(prim["attributes"]["POSITION"])
        if "indices" not in prim:
            return pts
        a = g["accessors"][prim["indices"]]
        view = g["bufferViews"][a["bufferView"]]
        at = view.get("byteOffset", 0) + a.get("byteOffset", 0)
        fmt = {5121: "B", 5123: "H", 5125: "I"}[a["componentType"]]
        size = struct.calcsize(fmt)
        return [pts[struct.unpack_from("<" + fmt, blob, at + size * i)[0]]
                for i in range(a["count"])]

    def emits(prim):
        m = g["materials"][prim.get("material", 0)]
        return any(c > 0 for c in m.get("emissiveFactor", [0, 0, 0]))

    for n in g["nodes"]:
        if "mesh" in n and any(k in n for k in ("matrix", "translation", "rotation", "scale")):
            sys.exit("the merged copy expects meshes placed without node transforms")
    merged, lights, material = [], [], None
    for mesh in g["meshes"]:
        for prim in mesh["primitives"]:
            if emits(prim):
                lights.append((triangles(prim), prim.get("material")))
            else:
                merged += triangles(prim)
                material = prim.get("material") if material is None else material
    parts = [(merged, material)] + lights
    data, views, accessors, meshes = b"", [], [], []
    for i, (pts, mat) in enumerate(parts):
        views.append({"buffer": 0, "byteOffset": len(data), "byteLength": 12 * len(pts)})
        data += b"".join(struct.pack("<3f", *p) for p in pts)
        accessors.append({"bufferView": i, "componentType": 5126, "count": len(pts),
                          "type": "VEC3", "min": [min(p[k] for p in pts) for k in range(3)],
                          "max": [max(p[k] for p in pts) for k in range(3)]})
        prim = {"attributes": {"POSITION": i}}
        if mat is not None:
            prim["material"] = mat
        meshes.append({"name": f"part{i}", "primitives": [prim]})
    out = copy.deepcopy(g)
    out["buffers"] = [{"byteLength": len(data), "uri": "data:application/octet-stream;base64,"
                       + base64.b64encode(data).decode()}]
    out["bufferViews"], out["accessors"], out["meshes"] = views, accessors, meshes
    cameras = [n for n in g["nodes"] if "camera" in n]
    out["nodes"] = [{"name": f"part{i}", "mesh": i} for i in range(len(parts))] + cameras
    out["scenes"] = [{"nodes": list(range(len(out["nodes"])))}]
    out["scene"] = 0
    with open(dst, "w") as f:
        json.dump(out, f)
    return len(merged) // 3


def measure_cornell(args, tmp):
    src = os.path.join(ROOT, "tests", "data", "scenes", "cornell", "cornell.gltf")
    merged = os.path.join(args.out, "cornell-merged.gltf")
    os.makedirs(args.out, exist_ok=True)
    tris = merged_cornell(src, merged)
    print("Cornell box, 64x64, 16 spp, one thread, in one process (callgrind)\n")
    print("| scene | closest-hit queries | instructions a closest-hit query | shadow queries |"
          " instructions a shadow query |")
    print("|---|---:|---:|---:|---:|")
    for label, scene in (("one chunk per mesh", src),
                         (f"non-emitting meshes merged ({tris} triangles)", merged)):
        profile = os.path.join(tmp, "cornell.callgrind")
        callgrind([args.host, "render", scene, "--in-process", "--width", "64", "--height", "64",
                   "--spp", "16", "--threads", "1", "-o", os.path.join(tmp, "c.pfm")], profile)
        costs = query_costs(profile)
        c_ir, c_n = costs.get("Tracer<D>::closest [", (0, 0))
        o_ir, o_n = costs.get("Tracer<D>::occluded [", (0, 0))
        if not c_n or not o_n:
            sys.exit("callgrind_annotate named no Tracer::closest / occluded calls")
        print(f"| {label} | {c_n:,} | {c_ir / c_n:,.0f} | {o_n:,} | {o_ir / o_n:,.0f} |")
    print()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--host", default=os.path.join(ROOT, "target", "release", "magg-host"))
    ap.add_argument("--out", default=os.path.join(ROOT, "bench", "out"))
    ap.add_argument("--mesh", help="the landscape GLB (default: the --quick one in --rays-dir)")
    ap.add_argument("--rays-dir", default=os.path.join(ROOT, "bench", "peers", "out"))
    ap.add_argument("--skip-rays", action="store_true")
    ap.add_argument("--skip-cornell", action="store_true")
    ap.add_argument("--skip-embree", action="store_true",
                    help="count magg's queries only, even where Embree's environment exists")
    args = ap.parse_args()
    for tool in ("valgrind", "callgrind_annotate"):
        if shutil.which(tool) is None:
            sys.exit(f"{tool} is not installed (Debian: apt-get install valgrind)")
    if not os.path.exists(args.host):
        sys.exit(f"no {args.host}: build it first (cargo build --release)")
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_rays:
            measure_rays(args, tmp)
        if not args.skip_cornell:
            measure_cornell(args, tmp)


if __name__ == "__main__":
    main()
