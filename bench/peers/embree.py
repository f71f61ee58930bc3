#!/usr/bin/env python3
"""Ray casting on one core: magg against Intel Embree (through the `embreex` binding).

Usage (from anywhere; everything it needs it installs itself):

    python3 bench/peers/embree.py                 # 1.0-1.1 M triangles, 1 M rays a set, 5 repeats
    python3 bench/peers/embree.py --quick         # ~100 k triangles, 100 k rays: a smoke run
    python3 bench/peers/embree.py --skip-magg     # Embree only
    options: --repeat N  --rounds R  --rays N  --magg PATH  --out DIR  --core C  --robust

On its first run the script makes the virtual environment `bench/peers/.venv-embree`
(`python3 -m venv`), pip-installs `embreex` (pinned) and `numpy` into it, and re-executes
itself with that environment's Python. Nothing is installed by hand.

What it does
------------
1. Makes a deterministic mesh (fixed seeds): a heightfield landscape of sines and Gaussian
   hills, and a few dozen spheres (spherified cubes) and boxes of a few thousand triangles
   each, of varied sizes and orientations, some partly buried. Full size: 1,016,720
   triangles (--quick: 99,044). It is written as binary glTF 2.0 (GLB): one mesh with one triangle primitive,
   a float VEC3 POSITION accessor with min/max, UINT32 indices, one node, one scene; no
   material, camera or normals. The file is read back and checked against the spec
   (header, chunk padding, byteLengths, alignment, min/max) on every run.
2. Writes four ray sets:
   - `primary`: a pinhole camera above and in front of the landscape looking down at it
     obliquely; one ray per pixel of a square image of isqrt(N)^2 pixels (1000x1000 for
     N = 1 M), in scan-line order (top row first, left to right); the top rows see sky.
   - `random`: origins uniform in the mesh's bounding box, directions uniform on the sphere.
   - `diffuse`: one diffuse bounce from each primary ray that hits (Embree's closest hit):
     hit point = origin + t*dir, the hit triangle's geometric normal flipped to face the
     incoming ray, a cosine-weighted direction about it, and the origin moved off the
     surface along that normal by 1e-4 x the bounding-box diagonal (so tnear = 0 works).
     So this set has as many rays as primary rays that hit.
   - `escaping`: rays that start one bounding-box diagonal out from the box's centre and
     point straight away from it: each query tests the root's box and ends, so their rate
     is the fixed cost of a query (not one of the issue's targets; it says how much of the
     other sets' time that cost is).
   The mesh and the ray files are cached in the output folder under names keyed by their
   generation parameters, and made again only when absent.
3. Traces each set with Embree on one core and times it, then runs
   `magg-host bench rays` on the same files on the same core, set by set and, with
   `--rounds R`, R times over, the two taking turns (a shared machine's speed moves by a
   third within minutes; runs taken in turns meet it in the same state, where all of one
   peer's runs and then all of the other's did not), and prints one markdown table
   comparing them (best over every round, each round's ratio below it; also written to
   OUT/embree-table.md, and every figure to OUT/embree-results.json), the BVH build
   times, up to 5 example rays per set that Embree hits and magg misses, and the CPU by
   family, model and widest vector instructions (Embree picks its code for the CPU; magg
   is built for x86-64-v3).

File formats (all little-endian, no header)
-------------------------------------------
- Ray file (`rays-SET-*.bin`): per ray 6 x float32: origin x y z, direction x y z (unit
  length). Every ray has tnear = 0 and tfar = +infinity.
- Hit file (`*.f32`): per ray one float32, the distance to the closest hit, +infinity on
  a miss; in `--any-hit` mode 1.0 for a hit (no distance is computed), +infinity on a miss.
- Mesh: `landscape-KEY.glb`, glTF 2.0 binary, y up.

What exactly is measured on the Embree side
-------------------------------------------
embreex 4.4.0.post1 wraps Embree 4.4.0 (TBB tasking, AVX2 kernels on an AVX2 machine,
backface culling off). Its package ships no .pyx, but the compiled `rtcore_scene` module
imports exactly rtcNewScene, rtcSetSceneFlags, rtcCommitScene, rtcIntersect1,
rtcOccluded1 and rtcReleaseScene (and no TBB symbols), with rtcCommitScene, rtcIntersect1
and rtcOccluded1 all called from `EmbreeScene.run` (checked with `nm -D` and `objdump`).
So `EmbreeScene.run(origins, dirs, dists=..., query=...)` is a plain serial Cython loop over
the rays calling the single-ray API once per ray, with default arguments (NULL):
rtcIntersect1 for query='DISTANCE' (the closest hit, t written back into `dists`),
rtcOccluded1 for query='OCCLUDED' (any hit; it returns 0 for a hit, -1 for a miss). No
packet (rtcIntersect4/8/16) or stream API is used. embreex does not set the FTZ/DAZ
floating-point modes that Embree recommends; neither does this script.

- BVH build: embreex commits lazily, inside the first `run()` call (`is_committed` goes
  from 0 to 1). The script times that first call with a single ray and subtracts the
  median time of a few more single-ray calls (microseconds), which leaves rtcCommitScene.
  It does this on `--repeat` freshly made scenes and reports best and median. Making the
  geometry (TriangleMesh: copying vertices and indices into Embree's buffers) is timed
  apart and is not part of the build figure.
- Rays/s: the timed region is the one `scene.run(...)` call. Inside it: the Python call
  and buffer acquisition of the arrays, the Cython loop filling an RTCRayHit/RTCRay per
  ray from the (n, 3) float32 origin and direction arrays, the Embree call per ray, and
  storing the result. Outside it: reading the file and making contiguous float32 arrays,
  and allocating the tfar array (`dists`, filled with +inf, handed in so that run() does
  not allocate it; for 'OCCLUDED' run() still allocates its int32 result array). Best and
  median over `--repeat` runs in each of `--rounds` rounds, after one untimed pass a set
  (which gives the hits the others must repeat exactly).
- Embree's default (non-robust) intersector is not watertight: a ray through an edge shared
  by two triangles can slip between them. Unless `--robust` is given, an untimed pass with
  RTC_SCENE_FLAG_ROBUST counts such rays per set (`robust_hits_default_misses` in the JSON),
  so that they can be told apart from magg's own misses.

One core
--------
The measuring process pins itself to one CPU (`os.sched_setaffinity(0, {C})`, `--core C`,
default 0, before numpy or Embree are loaded) and magg runs as `taskset -c C ...`.
embreex always creates its device with rtcNewDevice(NULL) (no config string can be
passed, so "threads=1" is not possible through it); Embree then sizes its TBB pool from
TBB's default concurrency, which oneTBB takes from the process's affinity mask: the script
checks that TBB reports max_concurrency 1, and every thread Embree could start would be
confined to that one CPU anyway. OPENBLAS_NUM_THREADS/OMP_NUM_THREADS are set to 1 so that
numpy starts no helper threads either.

magg's side
-----------
`MAGG rays MESH.glb RAYS.bin --hits HITS.f32 --repeat N --json OUT.json [--any-hit]`, where
MAGG is `target/release/magg-host bench` (`--magg PATH` replaces the binary; when the
default binary is missing, `cargo build --release --bin magg-host` is run first, on all
CPUs). Its JSON: {"triangles", "chunks", "build_seconds", "rays", "hits", "any_hit",
"in_process": {"best_mrays", "median_mrays", "repeats"}, "cache": {...the same through a
render node's cache with every chunk resident}}. Should magg lack the subcommand, the
script says so and prints the Embree figures alone.
"""

import argparse
import gc
import hashlib
import importlib.util
import json
import math
import os
import shutil
import struct
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
VENV = HERE / ".venv-embree"
EMBREEX_PIN = "embreex==4.4.0.post1"
# numpy is pinned too: its random streams and float maths are then the same on every
# reinstall, so the cached files stay what their names say.
NUMPY_PIN = "numpy==2.4.6" if sys.version_info >= (3, 11) else "numpy<2.3"
STAGE_ENV = "MAGG_EMBREE_BENCH_IN_VENV"

# Bump when the generators change: it is part of every cache key.
GEN_VERSION = 1
FULL_MESH = dict(terrain_n=640, objects=48, subdiv=(14, 22), seed=1991)
QUICK_MESH = dict(terrain_n=200, objects=12, subdiv=(9, 13), seed=1991)
HALF_SIZE = 100.0  # the landscape spans [-100, 100] in x and z
RAY_SEEDS = dict(random=7, diffuse=11, escaping=13)
# Above the landscape's near edge (z = +100), looking down along -z: the top rows reach
# just past the far edge (sky over its low parts), the bottom rows land inside it.
CAMERA = dict(eye=(0.0, 70.0, 130.0), pitch_deg=33.0, vfov_deg=45.0)
SETS = ("primary", "random", "diffuse", "escaping")


def log(msg):
    print(f"[embree.py {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------------------
# Stage 1: the virtual environment.


def in_venv():
    return Path(sys.prefix).resolve() == VENV.resolve()


def ensure_venv_and_reexec():
    py = VENV / "bin" / "python"
    stamp = VENV / ".installed"
    wanted = f"{EMBREEX_PIN} {NUMPY_PIN}"
    if not (py.exists() and stamp.exists() and stamp.read_text().strip() == wanted):
        log(f"making {VENV} and installing {wanted}")
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
        subprocess.run(
            [str(py), "-m", "pip", "install", "--disable-pip-version-check", "-q",
             EMBREEX_PIN, NUMPY_PIN],
            check=True,
        )
        stamp.write_text(wanted + "\n")
    env = dict(os.environ)
    env[STAGE_ENV] = "1"
    # Set before numpy loads: OpenBLAS would otherwise start helper threads.
    env["OPENBLAS_NUM_THREADS"] = "1"
    env["OMP_NUM_THREADS"] = "1"
    os.execve(str(py), [str(py), str(Path(__file__).resolve()), *sys.argv[1:]], env)


# ----------------------------------------------------------------------------------------
# Stage 2 (inside the venv): everything else. numpy and embreex are imported in main().

np = None


def key_of(params):
    return hashlib.sha1(json.dumps(params, sort_keys=True).encode()).hexdigest()[:10]


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_atomic(path, data):
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
    tmp.replace(path)


def normalize(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# --- mesh ---------------------------------------------------------------------------


def grid_triangles(na, nb):
    """Two triangles per cell of an (na+1) x (nb+1) vertex grid, vertex (a, b) at
    a*(nb+1)+b. With the grid's a step U and b step V, both face along U x V."""
    a, b = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
    v00 = (a * (nb + 1) + b).ravel()
    v10 = v00 + (nb + 1)
    v01 = v00 + 1
    v11 = v10 + 1
    t = np.empty((2 * na * nb, 3), np.int64)
    t[0::2] = np.stack([v00, v10, v01], axis=1)
    t[1::2] = np.stack([v10, v11, v01], axis=1)
    return t


_cube_cache = {}


def cube_lattice(s):
    """The surface of an s x s x s lattice cube: integer vertex coordinates in [0, s]^3
    (shared between faces, so the mesh is closed) and outward-facing triangles."""
    if s in _cube_cache:
        return _cube_cache[s]
    a, b = np.meshgrid(np.arange(s + 1), np.arange(s + 1), indexing="ij")
    points, tris, base = [], [], 0
    cell = grid_triangles(s, s)
    for axis in range(3):
        for side in (0, s):
            # e_u x e_v = +e_axis for the cyclic order; swapping them faces the other way.
            u, v = (axis + 1) % 3, (axis + 2) % 3
            if side == 0:
                u, v = v, u
            p = np.empty((s + 1, s + 1, 3), np.int64)
            p[..., axis] = side
            p[..., u] = a
            p[..., v] = b
            points.append(p.reshape(-1, 3))
            tris.append(cell + base)
            base += (s + 1) ** 2
    uniq, inverse = np.unique(np.concatenate(points), axis=0, return_inverse=True)
    result = (uniq, inverse.reshape(-1)[np.concatenate(tris)])
    _cube_cache[s] = result
    return result


class Rand:
    """Uniform doubles only (PCG64's `random()`), whose stream numpy keeps stable."""

    def __init__(self, seed):
        self.g = np.random.Generator(np.random.PCG64(seed))

    def u(self, lo=0.0, hi=1.0, size=None):
        return lo + (hi - lo) * self.g.random(size)


def make_terrain_height(rng):
    waves = []
    for k in range(1, 7):
        ang = rng.u(0, 2 * math.pi)
        freq = 2 * math.pi / (2 * HALF_SIZE) * k * rng.u(0.7, 1.3)
        waves.append((freq * math.cos(ang), freq * math.sin(ang), 7.0 / k**1.3,
                      rng.u(0, 2 * math.pi)))
    hills = [(rng.u(-80, 80), rng.u(-80, 80), rng.u(-6, 22), rng.u(10, 30)) for _ in range(7)]

    def height(x, z):
        h = np.zeros(np.broadcast(x, z).shape)
        for fx, fz, amp, phase in waves:
            h += amp * np.sin(fx * x + fz * z + phase)
        for cx, cz, amp, sigma in hills:
            h += amp * np.exp(-((x - cx) ** 2 + (z - cz) ** 2) / (2 * sigma**2))
        return h

    return height


def rotation(yaw, tilt):
    cy, sy, ct, st = math.cos(yaw), math.sin(yaw), math.cos(tilt), math.sin(tilt)
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, ct, -st], [0, st, ct]])
    return ry @ rx


def make_mesh(params):
    """Returns (vertices float32 (V, 3), indices uint32 (T, 3))."""
    rng = Rand(params["seed"])
    height = make_terrain_height(rng)
    n = params["terrain_n"]
    # a runs along +x and b along -z, so the grid's triangles face +y.
    xs = np.linspace(-HALF_SIZE, HALF_SIZE, n + 1)
    zs = np.linspace(HALF_SIZE, -HALF_SIZE, n + 1)
    x, z = np.meshgrid(xs, zs, indexing="ij")
    verts = [np.stack([x, height(x, z), z], axis=-1).reshape(-1, 3)]
    tris = [grid_triangles(n, n)]
    base = len(verts[0])

    lo, hi = params["subdiv"]
    for i in range(params["objects"]):
        s = int(rng.u(lo, hi + 1))
        lattice, ltris = cube_lattice(s)
        c = lattice / s * 2.0 - 1.0
        cx, cz = rng.u(-85, 85), rng.u(-85, 85)
        ground = float(height(np.float64(cx), np.float64(cz)))
        if i % 2 == 0:
            # A spherified cube: tan() evens out the cells before projecting on the sphere.
            r = math.exp(rng.u(math.log(2.5), math.log(12.0)))
            p = normalize(np.tan(c * (math.pi / 4))) * r
            lift = r * rng.u(-0.6, 0.9)  # below 0: partly buried
            rot = rotation(rng.u(0, 2 * math.pi), 0.0)
        else:
            half = np.array([rng.u(2, 9), rng.u(2, 9), rng.u(2, 9)])
            p = c * half
            lift = half[1] * rng.u(-0.7, 0.8)
            rot = rotation(rng.u(0, 2 * math.pi), rng.u(-0.35, 0.35))
        verts.append(p @ rot.T + np.array([cx, ground + lift, cz]))
        tris.append(ltris + base)
        base += len(p)
    v = np.concatenate(verts).astype(np.float32)
    t = np.concatenate(tris).astype(np.uint32)
    return v, t


# --- glTF ---------------------------------------------------------------------------

GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942


def glb_bytes(verts, tris):
    pos = verts.astype("<f4").tobytes()
    idx = tris.astype("<u4").tobytes()
    gltf = {
        "asset": {"version": "2.0", "generator": "magg bench/peers/embree.py"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 4}]}],
        "buffers": [{"byteLength": len(pos) + len(idx)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(pos), "target": 34962},
            {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx), "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "byteOffset": 0, "componentType": 5126, "count": len(verts),
             "type": "VEC3",
             # float(float32) is exact, so these equal the data's min/max bit for bit.
             "min": [float(m) for m in verts.min(axis=0)],
             "max": [float(m) for m in verts.max(axis=0)]},
            {"bufferView": 1, "byteOffset": 0, "componentType": 5125, "count": tris.size,
             "type": "SCALAR"},
        ],
    }
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    binary = pos + idx
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (struct.pack("<III", GLB_MAGIC, 2, total)
            + struct.pack("<II", len(js), JSON_CHUNK) + js
            + struct.pack("<II", len(binary), BIN_CHUNK) + binary)


def check_glb(path):
    """Reads a GLB back and checks it against the glTF 2.0 spec and this benchmark's
    promises. Returns (vertices, indices (T, 3)). Raises AssertionError on a fault."""
    data = Path(path).read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert magic == GLB_MAGIC and version == 2, "GLB header"
    assert length == len(data), "GLB length field"
    jlen, jtype = struct.unpack_from("<II", data, 12)
    assert jtype == JSON_CHUNK and jlen % 4 == 0, "JSON chunk header"
    jbytes = data[20:20 + jlen]
    assert len(jbytes) - len(jbytes.rstrip(b" ")) <= 3, "JSON padding"
    gltf = json.loads(jbytes)
    off = 20 + jlen
    blen, btype = struct.unpack_from("<II", data, off)
    assert btype == BIN_CHUNK and blen % 4 == 0, "BIN chunk header"
    assert off + 8 + blen == len(data), "trailing bytes after BIN chunk"
    binary = data[off + 8:off + 8 + blen]

    assert gltf["asset"]["version"] == "2.0"
    assert len(gltf["buffers"]) == 1 and "uri" not in gltf["buffers"][0]
    buf_len = gltf["buffers"][0]["byteLength"]
    assert buf_len <= blen <= buf_len + 3, "buffer byteLength vs BIN chunk"
    assert binary[buf_len:] == b"\0" * (blen - buf_len), "BIN padding"
    for key in ("materials", "cameras", "textures", "images", "skins", "animations"):
        assert key not in gltf, f"unexpected {key}"
    assert gltf["scene"] == 0 and gltf["scenes"] == [{"nodes": [0]}]
    assert gltf["nodes"] == [{"mesh": 0}]
    assert len(gltf["meshes"]) == 1 and len(gltf["meshes"][0]["primitives"]) == 1
    prim = gltf["meshes"][0]["primitives"][0]
    assert prim.get("mode", 4) == 4 and list(prim["attributes"]) == ["POSITION"]
    assert "material" not in prim

    def view(acc_index, ctype, atype, ncomp, dtype):
        acc = gltf["accessors"][acc_index]
        assert acc["componentType"] == ctype and acc["type"] == atype
        bv = gltf["bufferViews"][acc["bufferView"]]
        assert bv["buffer"] == 0 and "byteStride" not in bv
        assert bv["byteOffset"] + bv["byteLength"] <= buf_len
        start = bv["byteOffset"] + acc.get("byteOffset", 0)
        size = np.dtype(dtype).itemsize
        assert acc.get("byteOffset", 0) % size == 0 and start % size == 0, "alignment"
        nbytes = acc["count"] * ncomp * size
        assert acc.get("byteOffset", 0) + nbytes <= bv["byteLength"]
        arr = np.frombuffer(binary, dtype, acc["count"] * ncomp, start)
        return acc, arr.reshape(acc["count"], ncomp)

    pacc, verts = view(prim["attributes"]["POSITION"], 5126, "VEC3", 3, "<f4")
    assert np.array_equal(np.array(pacc["min"], np.float32), verts.min(axis=0)), "min"
    assert np.array_equal(np.array(pacc["max"], np.float32), verts.max(axis=0)), "max"
    assert np.isfinite(verts).all()
    _, idx = view(prim["indices"], 5125, "SCALAR", 1, "<u4")
    assert idx.size % 3 == 0 and int(idx.max()) < len(verts), "indices"
    return verts, idx.reshape(-1, 3)


def ensure_mesh(out, params):
    key = key_of({"gen": GEN_VERSION, **params})
    path = out / f"landscape-{key}.glb"
    if not path.exists():
        t0 = time.perf_counter()
        verts, tris = make_mesh(params)
        write_atomic(path, glb_bytes(verts, tris))
        log(f"made {path.name}: {len(tris):,} triangles, {len(verts):,} vertices "
            f"in {time.perf_counter() - t0:.1f} s")
        write_atomic(path.with_suffix(".json"), json.dumps(
            {"params": params, "gen_version": GEN_VERSION, "triangles": len(tris),
             "vertices": len(verts), "sha256": sha256(path)}, indent=1).encode())
    verts, tris = check_glb(path)
    log(f"mesh {path.name}: {len(tris):,} triangles, valid GLB")
    return key, path, np.ascontiguousarray(verts), tris


# --- rays ---------------------------------------------------------------------------


def primary_rays(n, bbox_lo, bbox_hi):
    side = math.isqrt(n)
    eye = np.array(CAMERA["eye"])
    pitch = math.radians(CAMERA["pitch_deg"])
    fwd = np.array([0.0, -math.sin(pitch), -math.cos(pitch)])
    right = normalize(np.cross(fwd, [0.0, 1.0, 0.0]))
    up = np.cross(right, fwd)
    tan_half = math.tan(math.radians(CAMERA["vfov_deg"]) / 2)
    pix = (np.arange(side) + 0.5) / side * 2.0 - 1.0
    sy, sx = np.meshgrid(-pix * tan_half, pix * tan_half, indexing="ij")  # row-major
    d = normalize(fwd + sx[..., None] * right + sy[..., None] * up).reshape(-1, 3)
    o = np.broadcast_to(eye, d.shape)
    return o, d


def random_rays(n, bbox_lo, bbox_hi, seed):
    rng = Rand(seed)
    o = bbox_lo + (bbox_hi - bbox_lo) * rng.u(size=(n, 3))
    return o, sphere_directions(rng, n)


def sphere_directions(rng, n):
    """`n` directions uniform on the unit sphere, drawn from `rng`."""
    zc = rng.u(-1.0, 1.0, n)
    phi = rng.u(0.0, 2 * math.pi, n)
    r = np.sqrt(np.maximum(0.0, 1.0 - zc * zc))
    return np.stack([r * np.cos(phi), r * np.sin(phi), zc], axis=1)


def escaping_rays(n, bbox_lo, bbox_hi, seed):
    """Rays that meet nothing at once: each starts one bounding-box diagonal out from the box's
    centre and points straight away from it, so a query tests the root's box and ends. Their
    rate is the fixed cost of a query (setting the ray up, one node test, the call and the
    loop around it), which every ray of the other sets pays too; not one of the issue's
    targets, a measure of where the time goes."""
    d = sphere_directions(Rand(seed), n)
    centre = (bbox_lo + bbox_hi) / 2
    o = centre + d * float(np.linalg.norm(bbox_hi - bbox_lo))
    return o, d


def diffuse_rays(prim_o, prim_d, tfar, prim_id, verts, tris, eps, seed):
    """One cosine-weighted bounce from every primary ray that hit."""
    hit = prim_id >= 0
    o, d = prim_o[hit].astype(np.float64), prim_d[hit].astype(np.float64)
    p = o + tfar[hit].astype(np.float64)[:, None] * d
    tri = tris[prim_id[hit]]
    v0, v1, v2 = (verts[tri[:, k]].astype(np.float64) for k in range(3))
    n = np.cross(v1 - v0, v2 - v0)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[np.einsum("ij,ij->i", n, d) > 0] *= -1.0
    # An orthonormal basis about n (Duff et al. 2017, "Building an Orthonormal Basis,
    # Revisited"): no branch, no division by a near-zero.
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t1 = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t2 = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    rng = Rand(seed)
    r1, r2 = rng.u(size=len(n)), rng.u(size=len(n))
    phi, sin_t = 2 * math.pi * r1, np.sqrt(r2)
    local = (sin_t * np.cos(phi), sin_t * np.sin(phi), np.sqrt(np.maximum(0.0, 1.0 - r2)))
    new_d = normalize(local[0][:, None] * t1 + local[1][:, None] * t2 + local[2][:, None] * n)
    return p + eps * n, new_d


def write_rays(path, o, d):
    rays = np.empty((len(d), 6), "<f4")
    rays[:, :3] = o
    # Normalised again in float32 so each stored direction is as close to unit as can be.
    d32 = d.astype(np.float32)
    rays[:, 3:] = d32 / np.linalg.norm(d32, axis=1, keepdims=True)
    write_atomic(path, rays.tobytes())


def read_rays(path):
    rays = np.fromfile(path, "<f4").reshape(-1, 6)
    return np.ascontiguousarray(rays[:, :3]), np.ascontiguousarray(rays[:, 3:])


# --- Embree -------------------------------------------------------------------------


def embree_info():
    """Embree's version and settings, and TBB's concurrency, through the libraries that
    the embreex wheel bundles (ctypes; embreex itself exposes none of this)."""
    import ctypes
    import glob
    import embreex

    libs = Path(embreex.__file__).resolve().parent.parent / "embreex.libs"
    info = {"embreex": embreex.__version__}
    try:
        lib = ctypes.CDLL(glob.glob(str(libs / "libembree4*.so*"))[0])
        lib.rtcNewDevice.restype = ctypes.c_void_p
        lib.rtcNewDevice.argtypes = [ctypes.c_char_p]
        lib.rtcGetDeviceProperty.restype = ctypes.c_ssize_t
        lib.rtcGetDeviceProperty.argtypes = [ctypes.c_void_p, ctypes.c_int]
        lib.rtcReleaseDevice.argtypes = [ctypes.c_void_p]
        dev = lib.rtcNewDevice(None)
        prop = lambda p: int(lib.rtcGetDeviceProperty(dev, p))  # noqa: E731
        v = prop(0)  # RTC_DEVICE_PROPERTY_VERSION, e.g. 40400
        info["embree"] = f"{v // 10000}.{v // 100 % 100}.{v % 100}"
        info["tasking"] = {0: "internal", 1: "TBB", 2: "PPL"}.get(prop(128), "?")
        info["backface_culling"] = bool(prop(65))
        lib.rtcReleaseDevice(dev)
    except (IndexError, OSError, AttributeError) as e:
        info["embree"] = f"unknown ({e})"
    try:
        tbb = ctypes.CDLL(glob.glob(str(libs / "libtbb*.so*"))[0])
        f = getattr(tbb, "_ZN3tbb6detail2r115max_concurrencyEPKNS0_2d115task_arena_baseE")
        f.restype, f.argtypes = ctypes.c_int, [ctypes.c_void_p]
        info["tbb_max_concurrency"] = f(None)
    except (IndexError, OSError, AttributeError) as e:
        info["tbb_max_concurrency"] = f"unknown ({e})"
    return info


def timed(fn):
    gc.disable()
    try:
        t0 = time.perf_counter()
        result = fn()
        return result, time.perf_counter() - t0
    finally:
        gc.enable()


def build_scene(verts, tris, robust):
    """A committed Embree scene; returns (scene, upload seconds, commit seconds)."""
    from embreex import mesh_construction, rtcore_scene

    scene = rtcore_scene.EmbreeScene(robust=robust)
    _, upload = timed(lambda: mesh_construction.TriangleMesh(scene, verts, tris))
    assert scene.is_committed == 0
    o = np.zeros((1, 3), np.float32)
    d = np.array([[0.0, -1.0, 0.0]], np.float32)
    # The first run() commits the scene (builds the BVH) before its one ray.
    _, first = timed(lambda: scene.run(o, d, dists=np.full(1, np.inf, np.float32),
                                       query="DISTANCE"))
    assert scene.is_committed == 1
    single = [timed(lambda: scene.run(o, d, dists=np.full(1, np.inf, np.float32),
                                      query="DISTANCE"))[1] for _ in range(5)]
    return scene, upload, first - float(np.median(single))


def trace(scene, o, d, any_hit=False):
    dists = np.full(len(o), np.inf, np.float32)
    query = "OCCLUDED" if any_hit else "DISTANCE"
    result, seconds = timed(lambda: scene.run(o, d, dists=dists, query=query))
    return (result >= 0 if any_hit else result), seconds


def stats(rays, seconds):
    return {"best_mrays": rays / min(seconds) / 1e6,
            "median_mrays": rays / float(np.median(seconds)) / 1e6,
            "seconds": seconds}


# --- magg ---------------------------------------------------------------------------


class MaggUnavailable(Exception):
    pass


def prepare_magg(args, all_cpus):
    """The magg-host binary, built if it is the default one and missing; checks that it
    has the `bench rays` subcommand. Raises MaggUnavailable with the reason."""
    if args.magg:
        binary = Path(shutil.which(args.magg) or args.magg).resolve()
        if not binary.exists():
            raise MaggUnavailable(f"{binary} does not exist")
    else:
        binary = REPO / "target" / "release" / "magg-host"
        if not binary.exists():
            cmd = ["cargo", "build", "--release", "--bin", "magg-host"]
            log(f"{binary} is missing: {' '.join(cmd)}")
            try:
                # On all CPUs: this process is pinned to one, and children inherit that.
                done = subprocess.run(cmd, cwd=REPO,
                                      preexec_fn=lambda: os.sched_setaffinity(0, all_cpus))
            except FileNotFoundError:
                raise MaggUnavailable("cargo is not installed, and magg-host is not built")
            if done.returncode != 0 or not binary.exists():
                raise MaggUnavailable(f"`{' '.join(cmd)}` failed (exit {done.returncode})")
    # Not plain `bench`: without a subcommand, today's magg-host runs its whole benchmark.
    probe = subprocess.run([str(binary), "bench", "rays", "--help"], capture_output=True,
                           text=True, timeout=120)
    if probe.returncode != 0:
        why = [l for l in (probe.stderr or probe.stdout).splitlines() if l.strip()][:2]
        raise MaggUnavailable(
            f"`{binary.name} bench rays` is not available (exit {probe.returncode}: "
            f"{' / '.join(why)}); this magg-host has no `bench rays` subcommand yet")
    return binary


def pinned(cmd, core):
    return (["taskset", "-c", str(core)] if shutil.which("taskset") else []) + cmd


def run_magg(binary, mesh, rays_path, n_rays, tag, args, out, any_hit=False):
    hits_path, json_path = out / f"magg-hits-{tag}.f32", out / f"magg-{tag}.json"
    for p in (hits_path, json_path):
        p.unlink(missing_ok=True)  # never read a stale result
    cmd = [str(binary), "bench", "rays", str(mesh), str(rays_path), "--hits", str(hits_path),
           "--repeat", str(args.repeat), "--json", str(json_path)]
    if any_hit:
        cmd.append("--any-hit")
    cmd = pinned(cmd, args.core)
    log("running " + " ".join(cmd))
    # Already pinned (taskset, and inherited affinity); the preexec keeps it so without taskset.
    done = subprocess.run(cmd, capture_output=True, text=True,
                          preexec_fn=lambda: os.sched_setaffinity(0, {args.core}))
    (out / f"magg-{tag}.log").write_text(done.stdout + done.stderr)
    if done.returncode != 0:
        tail = [l for l in (done.stderr or done.stdout).splitlines() if l.strip()][-5:]
        raise MaggUnavailable(f"magg failed on {tag} (exit {done.returncode}): "
                              + " / ".join(tail))
    report = json.loads(json_path.read_text())
    for k in ("triangles", "build_seconds", "rays", "in_process", "cache"):
        if k not in report:
            raise MaggUnavailable(f"magg's JSON for {tag} has no '{k}'")
    hits = np.fromfile(hits_path, "<f4")
    if len(hits) != n_rays or report["rays"] != n_rays:
        raise MaggUnavailable(f"magg traced {report['rays']} rays and wrote {len(hits)} hits "
                              f"for {tag}, not {n_rays}")
    return report, hits, cmd


# --- comparison and report ----------------------------------------------------------


def agreement(embree_hit, embree_t, magg_t, any_hit):
    """embree_hit: bool per ray; embree_t: closest distances (inf on miss)."""
    magg_hit = np.isfinite(magg_t)
    res = {"hit_agree": float(np.mean(embree_hit == magg_hit)),
           "embree_only_hits": int(np.sum(embree_hit & ~magg_hit)),
           "magg_only_hits": int(np.sum(~embree_hit & magg_hit))}
    if not any_hit:
        both = embree_hit & magg_hit
        close = np.zeros(len(magg_t), bool)
        a, b = embree_t[both].astype(np.float64), magg_t[both].astype(np.float64)
        close[both] = np.abs(a - b) <= 1e-4 * np.maximum(np.abs(a), np.abs(b))
        res["t_agree"] = float(np.mean(close | (~embree_hit & ~magg_hit)))
    return res


def fmt(x, spec):
    return "—" if x is None else format(x, spec)


def pct(share):
    return "—" if share is None else f"{100 * share:.4f}%"


def cpu_identity() -> str:
    """The processor, as bench/peers/mitsuba.py describes it (model, family, model number,
    stepping, widest vector instructions): a hypervisor may show different CPUs by one name."""
    spec = importlib.util.spec_from_file_location("magg_peer_mitsuba", HERE / "mitsuba.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.cpu_identity()


def table(rows, build, triangles):
    head = ("| set | rays | hit (Embree) | Embree best Mrays/s | Embree median Mrays/s "
            "| magg best Mrays/s | magg cache best Mrays/s | magg/Embree (best) "
            "| hit/miss agree | t agree (1e-4 rel) |")
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        m = r.get("magg") or {}
        ip, ca = m.get("in_process", {}), m.get("cache", {})
        ratio = ip["best_mrays"] / r["embree"]["best_mrays"] if ip else None
        agree = r.get("agreement") or {}
        lines.append(
            f"| {r['set']} | {r['rays']:,} | {100 * r['hit_share']:.2f}% "
            f"| {r['embree']['best_mrays']:.3f} | {r['embree']['median_mrays']:.3f} "
            f"| {fmt(ip.get('best_mrays'), '.3f')} | {fmt(ca.get('best_mrays'), '.3f')} "
            f"| {fmt(ratio, '.2f')} "
            f"| {pct(agree.get('hit_agree'))} | {pct(agree.get('t_agree'))} |")
    eb = build["embree"]
    line = (f"\nBVH build on one core ({triangles:,} triangles): Embree rtcCommitScene "
            f"{eb['best_seconds']:.3f} s best, {eb['median_seconds']:.3f} s median")
    if build.get("magg"):
        mb = build["magg"]
        line += (f"; magg {mb['best_seconds']:.3f} s best, {mb['median_seconds']:.3f} s "
                 f"median; magg/Embree {mb['best_seconds'] / eb['best_seconds']:.2f}x "
                 f"(best over best)")
    else:
        line += "; magg —"
    note = ("\nmagg/Embree (best): magg's best in-process M rays/s over Embree's best "
            "(above 1: magg is faster); the build ratio is of seconds (above 1: magg is slower).")
    return "\n".join(lines) + "\n" + line + note + "\n"


def rounds_text(rows):
    """With more than one round: each round's magg/Embree, set by set (the table's ratio is
    the best over the best)."""
    if not any(len(r["round_ratios"]) > 1 for r in rows):
        return ""
    lines = ["", "magg/Embree in each round (best of `--repeat` runs each, taken in turns):"]
    for r in rows:
        ratios = r["round_ratios"]
        lines.append(f"- {r['set']}: " + ", ".join(f"{x:.2f}" for x in ratios))
    return "\n".join(lines) + "\n"


def examples_text(rows):
    vec = lambda v: "(" + ", ".join(f"{x:.9g}" for x in v) + ")"  # noqa: E731
    out = []
    for r in rows:
        for e in r.get("examples", []):
            out.append(f"- {r['set']} #{e['index']}: origin {vec(e['origin'])} "
                       f"dir {vec(e['dir'])}, Embree t {e['embree_t']:.9g}")
    if not out:
        return ""
    return "\nRays that Embree hits and magg misses (up to 5 a set):\n" + "\n".join(out) + "\n"


# --- main ---------------------------------------------------------------------------


def parse_args():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=None, help="timed runs a set (default 5; 3 with --quick)")
    ap.add_argument("--rounds", type=int, default=1,
                    help="rounds taking turns: in each, every set is timed with Embree and "
                         "then with magg (default 1); best over all rounds")
    ap.add_argument("--rays", type=int, default=None, help="rays a set (default 1,000,000; 100,000 with --quick)")
    ap.add_argument("--magg", metavar="PATH", help="the magg-host binary (default target/release/magg-host)")
    ap.add_argument("--skip-magg", action="store_true", help="Embree only")
    ap.add_argument("--quick", action="store_true", help="~100 k triangles, 100 k rays: a smoke run")
    ap.add_argument("--out", type=Path, default=HERE / "out", help="output and cache folder")
    ap.add_argument("--core", type=int, default=0, help="the CPU to run on (default 0)")
    ap.add_argument("--robust", action="store_true", help="Embree's RTC_SCENE_FLAG_ROBUST")
    args = ap.parse_args()
    if args.repeat is None:
        args.repeat = 3 if args.quick else 5
    if args.rays is None:
        args.rays = 100_000 if args.quick else 1_000_000
    if args.repeat < 1 or args.rays < 1 or args.rounds < 1:
        ap.error("--repeat, --rounds and --rays must be at least 1")
    return args


def main():
    args = parse_args()
    if not in_venv():
        if os.environ.get(STAGE_ENV):
            sys.exit(f"re-running inside {VENV} did not land in it (sys.prefix {sys.prefix})")
        ensure_venv_and_reexec()
    all_cpus = os.sched_getaffinity(0)
    if args.core not in all_cpus:
        sys.exit(f"--core {args.core} is not among this process's CPUs {sorted(all_cpus)}")
    # Pinned before numpy and Embree load, so that TBB sizes its pool for one CPU.
    os.sched_setaffinity(0, {args.core})
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    global np
    import numpy
    np = numpy

    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    info = embree_info()
    log(f"embreex {info['embreex']}, Embree {info['embree']}, tasking {info.get('tasking')}, "
        f"TBB max concurrency {info['tbb_max_concurrency']}, on CPU {args.core}")
    if info["tbb_max_concurrency"] != 1:
        log("WARNING: TBB would use more than one thread; the figures are not single-core")

    mesh_params = QUICK_MESH if args.quick else FULL_MESH
    mesh_key, mesh_path, verts, tris = ensure_mesh(out, mesh_params)
    if not args.quick:
        assert len(tris) >= 1_000_000
    lo, hi = verts.min(axis=0).astype(np.float64), verts.max(axis=0).astype(np.float64)
    diag = float(np.linalg.norm(hi - lo))

    # magg first (it may have to be built, on all CPUs) so nothing runs beside the timings.
    binary, magg_error = None, None
    if args.skip_magg:
        magg_error = "skipped (--skip-magg)"
    else:
        try:
            binary = prepare_magg(args, all_cpus)
        except (MaggUnavailable, OSError, subprocess.TimeoutExpired) as e:
            magg_error = str(e)
            log(f"magg: {magg_error}; the table shows Embree alone")

    # Embree build, `--repeat` times on fresh scenes; the last one traces the rays.
    tris32 = np.ascontiguousarray(tris.astype(np.int32))
    uploads, commits, scene = [], [], None
    for _ in range(args.repeat):
        scene = None  # free the previous scene first
        gc.collect()
        scene, upload, commit = build_scene(verts, tris32, args.robust)
        uploads.append(upload)
        commits.append(commit)
    info["threads_after_build"] = len(os.listdir("/proc/self/task"))
    log(f"Embree build: rtcCommitScene {min(commits):.3f} s best, geometry upload "
        f"{min(uploads):.3f} s; threads in this process: {info['threads_after_build']}")

    # Ray files (cached). The diffuse set needs Embree's primary hits.
    ray_paths = {}
    for name in SETS:
        params = {"gen": GEN_VERSION, "mesh": mesh_key, "set": name, "rays": args.rays,
                  "seed": RAY_SEEDS.get(name)}
        if name == "diffuse":
            params.update(embreex=info["embreex"], robust=args.robust, eps=1e-4)
        if name in ("primary", "diffuse"):
            params["camera"] = CAMERA
        path = out / f"rays-{name}-{args.rays}-{key_of(params)}.bin"
        ray_paths[name] = path
        if path.exists():
            continue
        t0 = time.perf_counter()
        if name == "primary":
            o, d = primary_rays(args.rays, lo, hi)
        elif name == "random":
            o, d = random_rays(args.rays, lo, hi, RAY_SEEDS["random"])
        elif name == "escaping":
            o, d = escaping_rays(args.rays, lo, hi, RAY_SEEDS["escaping"])
        else:
            po, pd = read_rays(ray_paths["primary"])
            hit = scene.run(po, pd, dists=np.full(len(po), np.inf, np.float32),
                            query="DISTANCE", output=1)
            o, d = diffuse_rays(po, pd, hit["tfar"], hit["primID"], verts, tris,
                                1e-4 * diag, RAY_SEEDS["diffuse"])
        write_rays(path, o, d)
        log(f"made {path.name}: {len(d):,} rays in {time.perf_counter() - t0:.1f} s")

    # Embree's hits: one untimed pass a set (which also warms the caches, as magg's bench
    # does); the timings are taken in the rounds below, each set's beside magg's.
    rows, embree_t, embree_results = [], {}, {}
    # Each set read once: the rounds trace the same arrays again.
    rays = {name: read_rays(ray_paths[name]) for name in SETS}
    for name, any_hit in [(s, False) for s in SETS] + [("random", True)]:
        o, d = rays[name]
        res, _ = trace(scene, o, d, any_hit)
        tag = name + ("-any-hit" if any_hit else "")
        embree_results[tag] = res
        row = {"set": tag, "file": ray_paths[name].name, "rays": len(o), "_seconds": [],
               "_magg_runs": [], "round_ratios": []}
        if any_hit:
            hit = res
            # Any-hit must find a hit exactly where closest-hit does.
            row["embree_occluded_vs_closest_mismatch"] = int(
                np.sum(hit != np.isfinite(embree_t["random"])))
        else:
            embree_t[name] = res
            hit = np.isfinite(res)
            res.astype("<f4").tofile(out / f"embree-hits-{name}.f32")
        row["hit_share"] = float(np.mean(hit))
        row["_hit"] = hit
        rows.append(row)

    # Embree's default intersector is not watertight: a ray through a shared edge can slip
    # between two triangles. An untimed pass with RTC_SCENE_FLAG_ROBUST counts those rays,
    # to tell them apart from magg's misses.
    if not args.robust:
        robust_scene, _, _ = build_scene(verts, tris32, True)
        for row in rows:
            name = row["set"].removesuffix("-any-hit")
            o, d = rays[name]
            hit, _ = trace(robust_scene, o, d, row["set"].endswith("-any-hit"))
            if not row["set"].endswith("-any-hit"):
                hit = np.isfinite(hit)
            row["robust_hits_default_misses"] = int(np.sum(hit & ~row["_hit"]))
            row["default_hits_robust_misses"] = int(np.sum(~hit & row["_hit"]))
        log("Embree robust mode hits where the default misses: " + ", ".join(
            f"{r['set']} {r['robust_hits_default_misses']}" for r in rows))
        robust_scene = None
        gc.collect()

    # The rounds: each set timed with Embree (`--repeat` runs) and then with magg on the same
    # files, so that both meet the machine in the same state (a shared machine's speed moves
    # by a third within minutes; taking turns set by set keeps that out of the ratio).
    magg_builds, magg_cmds = [], []
    for rnd in range(args.rounds):
        for row in rows:
            any_hit = row["set"].endswith("-any-hit")
            name = row["set"].removesuffix("-any-hit")
            o, d = rays[name]
            seconds = []
            for _ in range(args.repeat):
                res, sec = trace(scene, o, d, any_hit)
                assert np.array_equal(res, embree_results[row["set"]]), "Embree not deterministic"
                seconds.append(sec)
            row["_seconds"] += seconds
            e_best = len(o) / min(seconds) / 1e6
            log(f"round {rnd + 1}: Embree {row['set']}: {e_best:.3f} M rays/s best")
            if binary is None:
                continue
            try:
                report, mt, cmd = run_magg(binary, mesh_path, ray_paths[name], row["rays"],
                                           row["set"], args, out, any_hit)
            except (MaggUnavailable, OSError, ValueError, KeyError, TypeError) as e:
                magg_error = (f"{type(e).__name__}: {e}" if not isinstance(e, MaggUnavailable)
                              else str(e))
                log(f"magg: {magg_error}")
                binary = None
                continue
            magg_cmds.append(" ".join(cmd))
            magg_builds.append(report["build_seconds"])
            row["_magg_runs"].append(report)
            row["round_ratios"].append(report["in_process"]["best_mrays"] / e_best)
            if rnd == 0:
                row["agreement"] = agreement(row["_hit"], embree_t[name], mt, any_hit)
                missed = np.flatnonzero(row["_hit"] & ~np.isfinite(mt))[:5]
                row["examples"] = [{"index": int(i), "origin": o[i].tolist(),
                                    "dir": d[i].tolist(),
                                    "embree_t": float(embree_t[name][i])} for i in missed]
            elif not np.array_equal(mt, row["_magg_hits"]):
                magg_error = f"magg's hits for {row['set']} changed between rounds"
                log(f"magg: {magg_error}")
            row["_magg_hits"] = mt
            log(f"round {rnd + 1}: magg {row['set']}: "
                f"{report['in_process']['best_mrays']:.3f} M rays/s best "
                f"({row['round_ratios'][-1]:.2f} of Embree's), hit/miss agree "
                f"{100 * row['agreement']['hit_agree']:.4f}%")
    scene = None
    gc.collect()
    for row in rows:
        row["embree"] = stats(row["rays"], row.pop("_seconds"))
        runs = row.pop("_magg_runs")
        row.pop("_magg_hits", None)
        if runs:
            # The best of every round's report, and the median of the rounds' medians.
            best = dict(max(runs, key=lambda r: r["in_process"]["best_mrays"]))
            for path in ("in_process", "cache"):
                best[path] = dict(best[path])
                best[path]["best_mrays"] = max(r[path]["best_mrays"] for r in runs)
                best[path]["median_mrays"] = float(np.median(
                    [r[path]["median_mrays"] for r in runs]))
                best[path]["repeats"] = sum(r[path]["repeats"] for r in runs)
            best["rounds"] = len(runs)
            row["magg"] = best

    build = {"embree": {"best_seconds": min(commits), "median_seconds": float(np.median(commits)),
                        "seconds": commits, "geometry_upload_seconds": uploads}}
    if magg_builds:
        build["magg"] = {"best_seconds": min(magg_builds),
                         "median_seconds": float(np.median(magg_builds)),
                         "seconds": magg_builds,
                         "note": "build_seconds of each magg invocation"}
    for row in rows:
        del row["_hit"]
    cpu = cpu_identity()
    md = (table(rows, build, len(tris)) + rounds_text(rows) + examples_text(rows)
          + f"\nCPU: {cpu} (Embree picks its code for the CPU it runs on: AVX-512 "
          "where there is AVX-512; magg is built for x86-64-v3 everywhere).\n")
    if magg_error:
        md += f"\nmagg: {magg_error}\n"
    print(md)
    (out / "embree-table.md").write_text(md)
    results = {
        "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "cpu": cpu,
        "core": args.core, "repeat": args.repeat, "rounds": args.rounds, "quick": args.quick,
        "robust": args.robust,
        "embree_info": info, "numpy": np.__version__,
        "mesh": {"file": mesh_path.name, "params": mesh_params, "triangles": len(tris),
                 "vertices": len(verts), "bbox": [lo.tolist(), hi.tolist()], "diagonal": diag},
        "build": build, "sets": rows, "magg_commands": magg_cmds, "magg_error": magg_error,
    }
    (out / "embree-results.json").write_text(json.dumps(results, indent=1))
    log(f"wrote {out / 'embree-table.md'} and {out / 'embree-results.json'}")


if __name__ == "__main__":
    main()
