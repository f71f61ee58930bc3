#!/usr/bin/env python3
"""The Cornell box, magg against Mitsuba 3, in one run.

Usage (from anywhere; the script finds the repository from its own path):

    python3 bench/peers/mitsuba.py                 # 16, 64, 256, 1024 spp
    python3 bench/peers/mitsuba.py --quick         # 16 and 64 spp only
    python3 bench/peers/mitsuba.py --spp 16,256 --repeat 3 --skip-scalar
    python3 bench/peers/mitsuba.py --magg-mode cluster   # magg's default 86-process cluster

Set-up, done by the script itself on its first run:
  * Debian's `libllvm19` (apt-get, as root or through sudo) when it is missing: Mitsuba's
    `llvm_*` variants JIT-compile through LLVM, and with Debian 12's default LLVM 14/15 the
    JIT aborts ("Cannot select fminimum"). `DRJIT_LIBLLVM_PATH` is pointed at its
    `libLLVM.so.19.1`.
  * a virtual environment `bench/peers/.venv-mitsuba` with the pinned versions in `PINS`
    (Mitsuba 3.9.1, the version the shared reference image was rendered with). The script
    then re-executes itself inside it.

What it does:
  1. Converts the glTF scene (`--scene`) to a Mitsuba scene from the file's own numbers: the
     node hierarchy (matrix or TRS), mesh positions, normals and indices from the accessors,
     the camera's yfov and world transform, base colours, emissive factor x strength,
     double-sidedness. Every surface is Lambertian (`diffuse`, wrapped in `twosided` where the
     glTF material is double-sided); an emissive mesh gets a one-sided `area` emitter.
     Integrator `path` with Mitsuba's defaults (max_depth -1, i.e. unbounded, Russian roulette
     from depth 5), `independent` sampler, `box` pixel filter, linear RGB `hdrfilm`.
  2. For each renderer and sample count (`--spp`), renders the scene once (`--repeat N`: N
     times, median times; the renderers take turns, one run each a round, so that load from
     elsewhere falls on all of them alike) and measures
       - wall time: the whole command a user waits for. Mitsuba: a fresh Python process that
         imports mitsuba, sets the variant, converts and loads the scene, renders and writes
         the EXR (one untimed warm-up per variant first, so the LLVM kernel cache is warm;
         a timed run that still compiled a kernel, at a sample count the warm-up did not
         cover, is run again).
         magg: `magg-host render ... --in-process` (or the cluster, `--magg-mode cluster`).
       - render-only time: Mitsuba: `mi.render` plus the evaluation it forces (Dr.Jit is
         lazy: the timed region ends once the image is a NumPy array); magg: `seconds.render`
         of its `--stats` JSON.
       - CPU time (user + system) of the whole command: on a shared machine, how much of
         the cores a run actually got.
       - relMSE against the reference (`--reference`), computed here in NumPy:
         mean over pixels and channels of (a - b)^2 / (b^2 + 0.01); cross-checked once with
         `magg-host compare`.
     Both renderers use all cores (Mitsuba's LLVM backend and scalar variant use their own
     thread pools at their defaults; magg's `--threads` default is all cores).
  3. Prints one markdown table (a row per renderer, variant and spp: times, relMSE, time x
     relMSE) and a summary (efficiency time x relMSE at the largest spp, and the estimated
     time to reach relMSE 1e-2 and 1e-3, with ratios magg / Mitsuba), and writes it to
     `OUT/mitsuba-table.md`, with the raw numbers in `OUT/mitsuba-results.json` and the
     images in `OUT/mitsuba-images/`. The table names the CPU by family, model and widest
     vector instructions: Mitsuba's LLVM kernels are compiled for the CPU they run on (16
     lanes with AVX-512, 8 without) and magg for x86-64-v3 everywhere, so ratios compare
     only between CPUs of the same vector width.

The reference's own README gives Mitsuba's errors against it (16 spp 1.1e-2, 64 spp 2.7e-3,
256 spp 7.0e-4, 1024 spp 1.8e-4); the Mitsuba rows here should match them, which checks the
conversion.
"""

from __future__ import annotations

import argparse
import base64
import datetime
import json
import math
import os
import platform
import re
import resource
import shlex
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
# This file is named mitsuba.py: drop its folder from the import path so that `import mitsuba`
# finds the package, not this script.
sys.path = [p for p in sys.path if Path(p or ".").resolve() != HERE]
REPO = HERE.parents[1]
VENV = HERE / ".venv-mitsuba"
# Mitsuba 3.9.1 is what rendered the shared reference; drjit 1.5.0 is the version it requires
# (pinned here too so the environment is fully determined); numpy 2.2.x supports Python 3.10-3.13.
PINS = ["mitsuba==3.9.1", "drjit==1.5.0", "numpy==2.2.6"]

DEFAULT_SCENE = REPO / "tests/data/scenes/cornell/cornell.gltf"
DEFAULT_REFERENCE = REPO / "tests/data/references/cornell/cornell_ref.exr"
DEFAULT_MAGG = REPO / "target/release/magg-host"
DEFAULT_OUT = REPO / "bench/peers/out"
DEFAULT_SPP = [16, 64, 256, 1024]
QUICK_SPP = [16, 64]
TARGETS = [1e-2, 1e-3]

# Mitsuba's `path` integrator defaults, set explicitly so the output can state them.
MITSUBA_MAX_DEPTH = -1
MITSUBA_RR_DEPTH = 5


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# Bootstrap: LLVM 19 and the virtual environment
# ---------------------------------------------------------------------------------------------


def find_libllvm19() -> str | None:
    """The path of libLLVM.so.19.1 from Debian's libllvm19 package, if it is installed."""
    try:
        r = subprocess.run(["dpkg", "-L", "libllvm19"], capture_output=True, text=True)
    except FileNotFoundError:
        return None
    if r.returncode != 0:
        return None
    libs = [l for l in r.stdout.split() if re.search(r"/libLLVM(-19)?\.so\.19(\.\d+)*$", l)]
    libs.sort(key=lambda p: (not p.endswith("libLLVM.so.19.1"), p))
    return next((p for p in libs if Path(p).exists()), None)


def ensure_libllvm19() -> str:
    """Installs libllvm19 with apt-get when missing; sets and returns DRJIT_LIBLLVM_PATH."""
    given = os.environ.get("DRJIT_LIBLLVM_PATH")
    if given and Path(given).exists():
        return given
    path = find_libllvm19()
    if path is None:
        if shutil.which("apt-get") is None:
            sys.exit("error: Mitsuba's llvm variants need LLVM 19 (libllvm19), and there is no "
                     "apt-get here to install it; set DRJIT_LIBLLVM_PATH to a libLLVM 19")
        sudo = [] if os.geteuid() == 0 else ["sudo"]
        if sudo and shutil.which("sudo") is None:
            sys.exit("error: installing libllvm19 needs root (or sudo)")
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
        install = sudo + ["apt-get", "install", "-y", "--no-install-recommends", "libllvm19"]
        log("installing Debian's libllvm19 (LLVM 19 for Mitsuba's llvm_* variants): "
            + " ".join(install))
        if subprocess.run(install, env=env).returncode != 0:
            # A fresh machine may have no (or stale) package lists.
            subprocess.run(sudo + ["apt-get", "update"], env=env, check=True)
            subprocess.run(install, env=env, check=True)
        path = find_libllvm19()
        if path is None:
            sys.exit("error: libllvm19 is installed but no libLLVM.so.19* found in `dpkg -L libllvm19`")
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path


def in_venv() -> bool:
    return Path(sys.prefix).resolve() == VENV.resolve()


def bootstrap() -> None:
    """Makes sure LLVM 19 and the venv exist; re-executes this script inside the venv."""
    ensure_libllvm19()
    if in_venv():
        return
    python = VENV / "bin" / "python"
    stamp = VENV / ".pins"
    if not python.exists():
        log(f"creating the virtual environment {VENV}")
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
    if not stamp.exists() or stamp.read_text().split() != PINS:
        log("pip install " + " ".join(PINS))
        subprocess.run([str(python), "-m", "pip", "install", "--disable-pip-version-check",
                        "--progress-bar", "off", *PINS], check=True)
        stamp.write_text("\n".join(PINS) + "\n")
    os.execv(str(python), [str(python), str(Path(__file__).resolve()), *sys.argv[1:]])


# ---------------------------------------------------------------------------------------------
# glTF reading (numbers only: everything the Cornell box uses, and the usual generality)
# ---------------------------------------------------------------------------------------------

COMPONENT_DTYPES = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def load_gltf(path: Path) -> tuple[dict, list[bytes]]:
    """The glTF JSON and its buffers (data URIs, external files, or a .glb's BIN chunk)."""
    raw = path.read_bytes()
    glb_bin = None
    if raw[:4] == b"glTF":
        _, _, length = struct.unpack_from("<III", raw, 0)
        off, doc = 12, None
        while off < length:
            clen, ctype = struct.unpack_from("<II", raw, off)
            chunk = raw[off + 8: off + 8 + clen]
            if ctype == 0x4E4F534A:  # JSON
                doc = json.loads(chunk)
            elif ctype == 0x004E4942:  # BIN
                glb_bin = chunk
            off += 8 + clen
    else:
        doc = json.loads(raw)
    buffers = []
    for b in doc.get("buffers", []):
        uri = b.get("uri")
        if uri is None:
            data = glb_bin
        elif uri.startswith("data:"):
            data = base64.b64decode(uri.split(",", 1)[1])
        else:
            from urllib.parse import unquote
            data = (path.parent / unquote(uri)).read_bytes()
        buffers.append(data[: b["byteLength"]])
    return doc, buffers


def read_accessor(doc: dict, buffers: list[bytes], index: int):
    """An accessor's elements as a float64 (or integer) array of shape (count, components)."""
    import numpy as np

    acc = doc["accessors"][index]
    if "sparse" in acc:
        raise NotImplementedError("sparse accessors")
    dtype = np.dtype(COMPONENT_DTYPES[acc["componentType"]])
    ncomp = TYPE_SIZES[acc["type"]]
    count = acc["count"]
    if "bufferView" not in acc:
        return np.zeros((count, ncomp), dtype)
    view = doc["bufferViews"][acc["bufferView"]]
    data = buffers[view["buffer"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    elem = dtype.itemsize * ncomp
    stride = view.get("byteStride") or elem
    out = np.ndarray((count, ncomp), dtype, buffer=data, offset=start, strides=(stride, dtype.itemsize))
    out = np.array(out)  # own the memory
    if acc.get("normalized"):
        out = np.maximum(out / float(np.iinfo(dtype).max), -1.0)
    return out


def node_matrix(node: dict):
    """A node's local 4x4 transform: its `matrix` (column-major) or T * R * S."""
    import numpy as np

    if "matrix" in node:
        return np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T
    t = node.get("translation", [0.0, 0.0, 0.0])
    x, y, z, w = node.get("rotation", [0.0, 0.0, 0.0, 1.0])
    s = node.get("scale", [1.0, 1.0, 1.0])
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    m = np.eye(4)
    m[:3, :3] = r @ np.diag(s)
    m[:3, 3] = t
    return m


def world_matrices(doc: dict) -> list[tuple[int, object]]:
    """(node index, world matrix) for every node of the default scene, parents first."""
    import numpy as np

    scene = doc["scenes"][doc.get("scene", 0)]
    out, stack = [], [(i, np.eye(4)) for i in reversed(scene["nodes"])]
    while stack:
        i, parent = stack.pop()
        node = doc["nodes"][i]
        world = parent @ node_matrix(node)
        out.append((i, world))
        stack.extend((c, world) for c in reversed(node.get("children", [])))
    return out


def convert_gltf(path: Path) -> dict:
    """The scene in world space: triangle meshes with their materials, and the camera.

    Returns {"meshes": [{name, positions (n,3), normals (n,3) or None, faces (m,3),
    base_color (3), emission (3), double_sided}], "camera": {eye, target, up, yfov_deg,
    aspect, znear}, "warnings": [...]}.
    """
    import numpy as np

    doc, buffers = load_gltf(path)
    warnings: list[str] = []
    meshes, camera = [], None
    for node_index, world in world_matrices(doc):
        node = doc["nodes"][node_index]
        name = node.get("name", f"node{node_index}")
        if "camera" in node and camera is None:
            cam = doc["cameras"][node["camera"]]
            if cam["type"] != "perspective":
                raise NotImplementedError(f"camera type {cam['type']}")
            p = cam["perspective"]
            # A glTF camera looks down its local -Z with +Y up; carry those through the world
            # transform and let Mitsuba's look_at build its own frame (it looks down +Z).
            eye = world @ np.array([0.0, 0.0, 0.0, 1.0])
            forward = world @ np.array([0.0, 0.0, -1.0, 0.0])
            up = world @ np.array([0.0, 1.0, 0.0, 0.0])
            camera = {
                "name": name,
                "eye": (eye[:3] / eye[3]).tolist(),
                "target": (eye[:3] / eye[3] + forward[:3] / np.linalg.norm(forward[:3])).tolist(),
                "up": (up[:3] / np.linalg.norm(up[:3])).tolist(),
                "yfov_deg": math.degrees(p["yfov"]),
                "aspect": p.get("aspectRatio"),
                "znear": p.get("znear", 0.01),
            }
        if "mesh" not in node:
            continue
        lin = world[:3, :3]
        normal_matrix = np.linalg.inv(lin).T
        # A mirroring transform turns counter-clockwise (front) faces clockwise.
        mirrored = np.linalg.det(lin) < 0
        for k, prim in enumerate(doc["meshes"][node["mesh"]]["primitives"]):
            if prim.get("mode", 4) != 4:
                warnings.append(f"{name}: primitive {k} is not a triangle list; skipped")
                continue
            pos = read_accessor(doc, buffers, prim["attributes"]["POSITION"]).astype(np.float64)
            pos = pos @ lin.T + world[:3, 3]
            normals = None
            if "NORMAL" in prim["attributes"]:
                n = read_accessor(doc, buffers, prim["attributes"]["NORMAL"]).astype(np.float64)
                n = n @ normal_matrix.T
                normals = n / np.linalg.norm(n, axis=1, keepdims=True)
            if "indices" in prim:
                faces = read_accessor(doc, buffers, prim["indices"]).reshape(-1, 3).astype(np.int64)
            else:
                faces = np.arange(len(pos), dtype=np.int64).reshape(-1, 3)
            if mirrored:
                faces = faces[:, [0, 2, 1]]
            mat = doc["materials"][prim["material"]] if "material" in prim else {}
            pbr = mat.get("pbrMetallicRoughness", {})
            ext = mat.get("extensions", {})
            if "baseColorTexture" in pbr or "emissiveTexture" in mat:
                warnings.append(f"{name}: textures are ignored (factors only)")
            spec = ext.get("KHR_materials_specular", {}).get("specularFactor", 1.0)
            if pbr.get("metallicFactor", 1.0) != 0 or spec != 0:
                warnings.append(f"{name}: not purely diffuse in glTF (metallic or specular); "
                                "rendered as Lambertian")
            strength = ext.get("KHR_materials_emissive_strength", {}).get("emissiveStrength", 1.0)
            meshes.append({
                "name": f"{name}_{k}" if k else name,
                "positions": pos,
                "normals": normals,
                "faces": faces,
                "base_color": list(pbr.get("baseColorFactor", [1, 1, 1, 1])[:3]),
                "emission": [c * strength for c in mat.get("emissiveFactor", [0, 0, 0])],
                "double_sided": bool(mat.get("doubleSided", False)),
            })
    if camera is None:
        raise ValueError(f"{path}: no camera")
    return {"meshes": meshes, "camera": camera, "warnings": warnings}


def face_normals(mesh: dict):
    """Unit geometric normals by the right-hand rule on the winding (glTF's and Mitsuba's front)."""
    import numpy as np

    p = mesh["positions"][mesh["faces"]]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def write_ply(path: Path, mesh: dict) -> None:
    """A binary PLY of the mesh (world-space float32 positions, optional normals)."""
    import numpy as np

    pos = mesh["positions"].astype("<f4")
    cols = [pos]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(pos)}",
              "property float x", "property float y", "property float z"]
    if mesh["normals"] is not None:
        cols.append(mesh["normals"].astype("<f4"))
        header += ["property float nx", "property float ny", "property float nz"]
    header += [f"element face {len(mesh['faces'])}", "property list uchar int vertex_indices",
               "end_header"]
    faces = np.zeros(len(mesh["faces"]), np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
    faces["n"] = 3
    faces["i"] = mesh["faces"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(np.ascontiguousarray(np.hstack(cols)).tobytes())
        f.write(faces.tobytes())


def mitsuba_scene_dict(mi, desc: dict, width: int, height: int, spp: int, tmpdir: Path) -> dict:
    """The Mitsuba scene dictionary for a converted glTF scene."""
    cam = desc["camera"]
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": MITSUBA_MAX_DEPTH, "rr_depth": MITSUBA_RR_DEPTH},
        "sensor": {
            "type": "perspective",
            "fov_axis": "y",
            "fov": cam["yfov_deg"],
            "near_clip": cam["znear"],
            "to_world": mi.ScalarTransform4f.look_at(
                origin=cam["eye"], target=cam["target"], up=cam["up"]),
            "sampler": {"type": "independent", "sample_count": spp},
            "film": {
                "type": "hdrfilm", "width": width, "height": height,
                "pixel_format": "rgb", "component_format": "float32",
                "rfilter": {"type": "box"},
            },
        },
    }
    for i, m in enumerate(desc["meshes"]):
        ply = tmpdir / f"mesh{i}.ply"
        write_ply(ply, m)
        bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": m["base_color"]}}
        if m["double_sided"]:
            bsdf = {"type": "twosided", "material": bsdf}
        shape = {
            "type": "ply",
            "filename": str(ply),
            # glTF: without NORMAL the mesh is flat-shaded; Mitsuba would otherwise compute
            # smooth vertex normals.
            "face_normals": m["normals"] is None,
            "bsdf": bsdf,
        }
        if any(c > 0 for c in m["emission"]):
            # Mitsuba's area emitter is one-sided, emitting on the side of the geometric
            # normal from the winding: the same front face as glTF's counter-clockwise one.
            shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": m["emission"]}}
        scene[f"shape{i}_{re.sub(r'[^A-Za-z0-9_]', '_', m['name'])}"] = shape
    return scene


# ---------------------------------------------------------------------------------------------
# The Mitsuba worker: one fresh process per render, timed from outside as a user waits
# ---------------------------------------------------------------------------------------------


def count_cached_kernels() -> int:
    """Kernels in Dr.Jit's on-disk LLVM kernel cache: a run that adds any compiled them."""
    cache = Path.home() / ".drjit"
    return sum(1 for _ in cache.glob("*.llvm.*")) if cache.is_dir() else 0


def worker_main(argv: list[str]) -> None:
    p = argparse.ArgumentParser(prog="mitsuba.py --worker")
    p.add_argument("--variant", required=True)
    p.add_argument("--scene", type=Path, required=True)
    p.add_argument("--spp", type=int, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, required=True)
    p.add_argument("--height", type=int, required=True)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--timing", type=Path, required=True)
    a = p.parse_args(argv)

    kernels_before = count_cached_kernels()
    t0 = time.perf_counter()
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    mi.set_variant(a.variant)
    t1 = time.perf_counter()
    desc = convert_gltf(a.scene)
    with tempfile.TemporaryDirectory(prefix="magg-mitsuba-") as tmp:
        scene = mi.load_dict(mitsuba_scene_dict(mi, desc, a.width, a.height, a.spp, Path(tmp)))
    t2 = time.perf_counter()
    image = mi.render(scene, spp=a.spp, seed=a.seed)
    # Dr.Jit is lazy: mi.render only records the computation (llvm variants). Evaluating it
    # and copying it out to NumPy is what actually renders, so it belongs in the timed region.
    dr.eval(image)
    pixels = np.array(image, dtype=np.float32)
    t3 = time.perf_counter()
    mi.Bitmap(pixels[..., :3]).write(str(a.output))
    t4 = time.perf_counter()
    light_normals = [face_normals(m).mean(axis=0).round(6).tolist()
                     for m in desc["meshes"] if any(c > 0 for c in m["emission"])]
    a.timing.write_text(json.dumps({
        "import_s": t1 - t0, "load_s": t2 - t1, "render_s": t3 - t2, "write_s": t4 - t3,
        "in_process_total_s": t4 - t0,
        "kernels_compiled": count_cached_kernels() - kernels_before, "mitsuba": mi.__version__, "drjit": dr.__version__,
        "light_normals": light_normals, "warnings": desc["warnings"], "camera": desc["camera"],
    }))


# ---------------------------------------------------------------------------------------------
# Images and errors
# ---------------------------------------------------------------------------------------------


def read_pfm(path: Path):
    """A PFM as an (h, w, 3) float32 array, top row first (PFM stores rows bottom-up)."""
    import numpy as np

    with open(path, "rb") as f:
        kind = f.readline().strip()
        w, h = (int(v) for v in f.readline().split())
        scale = float(f.readline())
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    channels = 3 if kind == b"PF" else 1
    img = data[: w * h * channels].reshape(h, w, channels)[::-1].astype(np.float32)
    return np.repeat(img, 3, axis=2) if channels == 1 else img


def read_image(path: Path):
    """An EXR or PFM as an (h, w, 3) linear float32 array, top row first."""
    import numpy as np

    if path.suffix.lower() == ".pfm":
        return read_pfm(path)
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    bmp = mi.Bitmap(str(path))
    arr = np.array(bmp, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    # EXR channels come back in Mitsuba's order (R, G, B[, A]); a single channel is grey.
    return np.repeat(arr[..., :1], 3, axis=2) if arr.shape[2] == 1 else arr[..., :3]


def rel_mse(a, b) -> float:
    """mean over pixels and channels of (a - b)^2 / (b^2 + 0.01), as the reference README."""
    import numpy as np

    if a.shape != b.shape:
        raise ValueError(f"image is {a.shape}, reference {b.shape}")
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    return float(np.mean((a64 - b64) ** 2 / (b64 ** 2 + 0.01)))


# ---------------------------------------------------------------------------------------------
# Running the renderers
# ---------------------------------------------------------------------------------------------


def timed_run(cmd: list[str]) -> tuple[subprocess.CompletedProcess, float, float]:
    """Runs a command; returns it, its wall time and its CPU time (user + system, children
    included). CPU time shows how much of the two cores a run got on a shared machine."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return r, wall, cpu


def run_mitsuba(args, variant: str, spp: int, out_image: Path, width: int, height: int,
                retry_cold: bool = True) -> dict:
    timing = out_image.with_suffix(".timing.json")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--variant", variant,
           "--scene", str(args.scene), "--spp", str(spp), "--seed", str(args.seed),
           "--width", str(width), "--height", str(height), "-o", str(out_image),
           "--timing", str(timing)]
    r, wall, cpu = timed_run(cmd)
    if r.returncode != 0:
        sys.exit(f"error: Mitsuba {variant} at {spp} spp failed:\n{r.stdout}{r.stderr}")
    info = json.loads(timing.read_text())
    timing.unlink()
    if info["kernels_compiled"] > 0 and retry_cold:
        # The kernel depends on the sample count (Dr.Jit bakes some of it in), so the warm-up
        # at one spp need not have compiled it: this run was the warm-up, time the next one.
        log(f"Mitsuba {variant} {spp} spp compiled {info['kernels_compiled']} new kernel(s); "
            "running it again with the cache warm")
        return run_mitsuba(args, variant, spp, out_image, width, height, retry_cold=False)
    return {"wall_s": wall, "render_s": info["render_s"], "cpu_s": cpu, "detail": info}


def image_tag(renderer: str, variant: str) -> str:
    return "magg" if renderer == "magg" else f"mitsuba-{variant}"


def magg_command(args, spp: int, out_image: Path, stats: Path, width: int, height: int) -> list[str]:
    cmd = [str(args.magg), "render", str(args.scene), "-o", str(out_image),
           "--width", str(width), "--height", str(height), "--spp", str(spp),
           "--seed", str(args.seed), "--stats", str(stats), "--quiet"]
    if args.magg_mode == "in-process":
        cmd.append("--in-process")
    return cmd + shlex.split(args.magg_args)


def run_magg(args, spp: int, out_image: Path, width: int, height: int) -> dict:
    stats = out_image.with_suffix(".stats.json")
    cmd = magg_command(args, spp, out_image, stats, width, height)
    r, wall, cpu = timed_run(cmd)
    if r.returncode != 0:
        sys.exit(f"error: {shlex.join(cmd)} failed:\n{r.stdout}{r.stderr}")
    s = json.loads(stats.read_text())
    return {"wall_s": wall, "render_s": s["seconds"]["render"], "cpu_s": cpu, "command": shlex.join(cmd),
            "detail": {"seconds": s.get("seconds"), "threads": s.get("threads"),
                       "mode": s.get("mode"), "samples_per_second": s.get("samples_per_second"),
                       "bad_samples": s.get("bad_samples"), "processes": s.get("processes")}}


def magg_compare(args, image: Path, reference: Path) -> float | None:
    r = subprocess.run([str(args.magg), "compare", str(image), str(reference)],
                       capture_output=True, text=True)
    m = re.search(r"relMSE\s+([0-9.eE+-]+)", r.stdout)
    return float(m.group(1)) if m else None


def magg_depth_note(args) -> str:
    """magg's path length settings, read from its --help and its integrator's source."""
    depth = None
    r = subprocess.run([str(args.magg), "render", "--help"], capture_output=True, text=True)
    # "[default: 64]", or "[default: 64 for path, 16 for whitted]": the path tracer's.
    m = re.search(r"--max-depth[^\[]*\[default:\s*(\d+)", r.stdout, re.S)
    if m:
        depth = m.group(1)
    extra = shlex.split(args.magg_args)
    if "--max-depth" in extra and extra.index("--max-depth") + 1 < len(extra):
        depth = extra[extra.index("--max-depth") + 1]
    rr = None
    src = REPO / "renderer/src/integrator.rs"
    if src.exists():
        m = re.search(r"if bounce >= (\d+) \{\s*let q", src.read_text())
        rr = m.group(1) if m else None
    note = f"max depth {depth or '(its default)'} bounces"
    note += f", Russian roulette from bounce {rr}" if rr else ", with Russian roulette"
    return note


# ---------------------------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------------------------


def time_to_reach(points: list[tuple[float, float]], target: float) -> tuple[float, str] | None:
    """Time to reach relMSE `target`, from (time, relMSE) points in sweep order.

    log(time) is interpolated linearly against log(relMSE) between the two consecutive points
    that bracket the target; when none does, it is extrapolated from the nearest two (the last
    two for a lower target, the first two for a higher one), and the note says so.
    """
    pts = [(t, e) for t, e in points if t > 0 and e > 0]
    if len(pts) < 2:
        return None
    for (t0, e0), (t1, e1) in zip(pts, pts[1:]):
        if min(e0, e1) <= target <= max(e0, e1) and e0 != e1:
            return _loglog(t0, e0, t1, e1, target), ""
    low = target < min(e for _, e in pts)
    (t0, e0), (t1, e1) = pts[-2:] if low else pts[:2]
    if e0 == e1:
        return None
    return _loglog(t0, e0, t1, e1, target), "extrapolated"


def _loglog(t0, e0, t1, e1, target) -> float:
    slope = (math.log(t1) - math.log(t0)) / (math.log(e1) - math.log(e0))
    return math.exp(math.log(t0) + slope * (math.log(target) - math.log(e0)))


def target_label(target: float) -> str:
    """1e-2 rather than 0.01."""
    exp = math.log10(target)
    return f"1e{round(exp)}" if abs(exp - round(exp)) < 1e-9 else f"{target:g}"


def fmt(x, digits=3) -> str:
    if x is None:
        return "n/a"
    if isinstance(x, str):
        return x
    if x == 0:
        return "0"
    if abs(x) >= 1e4 or abs(x) < 0.1:
        return f"{x:.{digits - 1}e}"
    return f"{x:#.{digits}g}" if abs(x) < 100 else f"{x:.0f}"


KIND_LABELS = {"wall": "wall time", "render": "render time", "cpu": "CPU time"}


def runs_table(rows: list[dict]) -> list[str]:
    """Every run: times, relMSE and time x relMSE (also cycles.py's)."""
    lines = ["| renderer | variant | spp | wall (s) | render (s) | CPU (s) | relMSE | wall x relMSE | render x relMSE |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['renderer']} | {r['variant']} | {r['spp']} | {r['wall_s']:.2f} | "
                     f"{r['render_s']:.2f} | {r['cpu_s']:.2f} | {fmt(r['rel_mse'])} | {fmt(r['wall_s'] * r['rel_mse'])} | "
                     f"{fmt(r['render_s'] * r['rel_mse'])} |")
    return lines


def summary_table(rows: list[dict], renderers: list[tuple[str, str]], peer_prefix: str,
                  kinds=("wall", "render"), extra=None, short=lambda k: k):
    """One column per renderer, then magg over each peer (renderers named PEER_PREFIX...):
    time x relMSE at the largest spp and the time of each of KINDS to each target. EXTRA(runs)
    adds entries to a renderer's summary. Returns the table's lines, its footnote's lines, the
    summary and the ratios (also cycles.py's)."""
    summary: dict = {}
    for key in renderers:
        rs = sorted((r for r in rows if (r["renderer"], r["variant"]) == key), key=lambda r: r["spp"])
        if not rs:
            continue
        last = rs[-1]
        s = {"largest_spp": last["spp"],
             "wall_x_relmse": last["wall_s"] * last["rel_mse"],
             "render_x_relmse": last["render_s"] * last["rel_mse"]}
        if extra:
            s.update(extra(rs))
        for target in TARGETS:
            for kind in kinds:
                est = time_to_reach([(r[f"{kind}_s"], r["rel_mse"]) for r in rs], target)
                s[f"{kind}_s_to_{target:g}"] = est[0] if est else None
                s[f"{kind}_s_to_{target:g}_note"] = est[1] if est else "too few points"
        summary[f"{key[0]} {key[1]}"] = s
    magg_key = next((k for k in summary if k.startswith("magg")), None)
    peer_keys = [k for k in summary if k.startswith(peer_prefix)]
    metrics = [("wall_x_relmse", "wall x relMSE at the largest spp (s)"),
               ("render_x_relmse", "render x relMSE at the largest spp (s)")]
    for target in TARGETS:
        for kind in kinds:
            metrics.append((f"{kind}_s_to_{target:g}",
                            f"{KIND_LABELS[kind]} to relMSE {target_label(target)} (s)"))
    ratios: dict = {}
    lines = ["", "Summary (lower is better; ratio < 1: magg is faster or more efficient):", ""]
    head = ["metric"] + [f"{k} ({summary[k]['largest_spp']} spp)" for k in summary]
    if magg_key:
        head += [f"magg / {short(k)}" for k in peer_keys]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("| --- |" + " ---: |" * (len(head) - 1))
    extrapolated = False
    for metric, label in metrics:
        cells = [label]
        for k in summary:
            note = summary[k].get(f"{metric}_note", "")
            extrapolated |= note == "extrapolated"
            cells.append(fmt(summary[k][metric]) + (" *" if note == "extrapolated" else ""))
        if magg_key:
            for k in peer_keys:
                a, b = summary[magg_key][metric], summary[k][metric]
                ratio = a / b if a is not None and b else None
                ratios.setdefault(k, {})[metric] = ratio
                cells.append(fmt(ratio))
        lines.append("| " + " | ".join(cells) + " |")
    footnote = []
    if extrapolated:
        footnote = ["", "\\* extrapolated from the two nearest sweep points (no two points bracket "
                        "the target); others interpolated log(time) against log(relMSE)."]
    return lines, footnote, summary, ratios


def build_tables(rows: list[dict], renderers: list[tuple[str, str]], meta: dict) -> tuple[str, dict]:
    lines = []
    lines.append(f"# Cornell box: magg against Mitsuba {meta['versions']['mitsuba']}")
    lines.append("")
    lines.append(f"{meta['width']}x{meta['height']} pixels, scene `{meta['scene']}`, reference "
                 f"`{meta['reference']}`; {meta['machine']}. relMSE = mean over pixels and "
                 "channels of (a - b)^2 / (b^2 + 0.01). Wall: the whole command a user waits for "
                 "(Mitsuba: a fresh Python process that imports mitsuba, converts and loads the "
                 "scene, renders, writes the EXR; kernel cache warm). Render: the render alone "
                 "(Mitsuba: mi.render and its evaluation; magg: `seconds.render` of --stats). "
                 "CPU: user + system time of the whole command (near 2 x wall when it had both "
                 "cores to itself; less means other work on the machine took some). "
                 + (f"Median of {meta['repeat']} runs." if meta["repeat"] > 1 else "One run each."))
    lines.append("")
    v = meta["versions"]
    lines.append(f"Versions: Mitsuba {v['mitsuba']} (drjit {v['drjit']}, libllvm19 {v['libllvm19']}), "
                 f"Python {v['python']}, NumPy {v['numpy']}"
                 + (f"; {' '.join(v['magg'].split()[:4])}" if v.get("magg") else "") + ".")
    lines.append("")
    lines.append("Path lengths: " + "; ".join(f"{k}: {v}" for k, v in meta["depth"].items()) + ".")
    lines.append("")
    wide = meta["avx512"]
    lines.append("Vector width: Mitsuba's LLVM kernels are compiled for this CPU, "
                 + ("16 lanes (AVX-512)" if wide else "8 lanes (no AVX-512)")
                 + "; magg is built for x86-64-v3 (8-lane AVX2) on every CPU. Ratios against "
                 "Mitsuba compare only between CPUs of the same vector width.")
    lines.append("")
    lines += runs_table(rows)
    table, footnote, summary, ratios = summary_table(
        rows, renderers, "Mitsuba", short=lambda k: k.replace("Mitsuba ", ""))
    lines += table + footnote
    return "\n".join(lines) + "\n", {"per_renderer": summary, "magg_over_mitsuba": ratios}


# ---------------------------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------------------------


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--spp", default=",".join(map(str, DEFAULT_SPP)),
                   help="comma-separated sample counts (default %(default)s)")
    p.add_argument("--quick", action="store_true", help="16 and 64 spp only")
    p.add_argument("--repeat", type=int, default=1, help="runs per (renderer, spp); median times")
    p.add_argument("--seed", type=int, default=0, help="sampler seed of every render")
    p.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    p.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE)
    p.add_argument("--magg", type=Path, default=DEFAULT_MAGG, help="the magg-host binary")
    p.add_argument("--magg-mode", choices=["in-process", "cluster"], default="in-process",
                   help="in-process (--in-process) or magg's default 86-process local cluster")
    p.add_argument("--magg-args", default="", help="extra flags for `magg-host render`, e.g. \"--threads 1\" "
                        "(a single flag: --magg-args=--adaptive)")
    p.add_argument("--skip-magg", action="store_true")
    p.add_argument("--skip-scalar", action="store_true", help="leave out Mitsuba scalar_rgb")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    a = p.parse_args()
    a.spp_list = QUICK_SPP if a.quick else sorted({int(s) for s in a.spp.split(",") if s.strip()})
    if not a.spp_list or min(a.spp_list) < 1 or a.repeat < 1:
        p.error("--spp needs positive sample counts, --repeat at least 1")
    a.scene, a.reference, a.out = a.scene.resolve(), a.reference.resolve(), a.out.resolve()
    return a


def cpu_fields() -> dict[str, str]:
    """The first processor's fields in /proc/cpuinfo (empty where it cannot be read)."""
    try:
        first = Path("/proc/cpuinfo").read_text().split("\n\n", 1)[0]
    except OSError:
        return {}
    return {k.strip(): v.strip() for k, _, v in (l.partition(":") for l in first.splitlines())}


def has_avx512(fields: dict[str, str]) -> bool:
    return "avx512f" in fields.get("flags", "").split()


def cpu_identity(fields: dict[str, str] | None = None) -> str:
    """The processor as /proc/cpuinfo tells it: its model name, family, model and stepping
    (a hypervisor may show every AMD EPYC by one name), and its widest vector instructions.
    Mitsuba's LLVM variants compile their kernels for the CPU they run on (Dr.Jit's kernels
    here carry `"target-cpu"="znver3"` and `-avx512f`): 16 lanes with AVX-512, 8 without.
    magg and the other peers are built for one instruction set. So a ratio against Mitsuba
    depends on whether the CPU has AVX-512; compare ratios only across like CPUs."""
    f = cpu_fields() if fields is None else fields
    if not f:
        return platform.processor() or "unknown CPU"
    vector = ("AVX-512" if has_avx512(f) else "AVX2, no AVX-512"
              if "avx2" in f.get("flags", "").split() else "no AVX2")
    ident = ", ".join(f"{k} {f[k]}" for k in ("cpu family", "model", "stepping") if f.get(k))
    return f"{f.get('model name') or 'unknown CPU'}: {ident}; {vector}"


def machine_note(fields: dict[str, str] | None = None) -> str:
    return f"{os.cpu_count()} cores ({cpu_identity(fields)})"


def main() -> None:
    args = parse_args()
    import mitsuba as mi
    import drjit as dr
    import numpy as np

    for path, what in [(args.scene, "scene"), (args.reference, "reference")]:
        if not path.exists():
            sys.exit(f"error: no {what} at {path}")
    if not args.skip_magg and not args.magg.exists():
        sys.exit(f"error: no magg binary at {args.magg} (cargo build --release, or --skip-magg)")

    reference = read_image(args.reference)
    height, width = reference.shape[:2]
    checks: dict = {}
    # The EXR and PFM readers must agree on the reference (orientation, channels).
    pfm = args.reference.with_suffix(".pfm")
    if args.reference.suffix.lower() == ".exr" and pfm.exists():
        checks["reference_exr_vs_pfm_relmse"] = rel_mse(read_image(pfm), reference)

    images = args.out / "mitsuba-images"
    images.mkdir(parents=True, exist_ok=True)
    variants = ["llvm_ad_rgb"] + ([] if args.skip_scalar else ["scalar_rgb"])
    renderers = [("Mitsuba", v) for v in variants]
    if not args.skip_magg:
        renderers.append(("magg", args.magg_mode + (" " + args.magg_args if args.magg_args else "")))

    # Untimed warm-ups: Mitsuba's LLVM kernel cache (and the page cache for every program).
    log(f"warm-up runs at {args.spp_list[0]} spp (untimed)")
    for v in variants:
        warm = run_mitsuba(args, v, args.spp_list[0], images / f"warmup-{v}.exr", width, height)
        checks.setdefault("light_normals", warm["detail"]["light_normals"])
        checks.setdefault("mitsuba_camera", warm["detail"]["camera"])
        checks.setdefault("conversion_warnings", warm["detail"]["warnings"])
        (images / f"warmup-{v}.exr").unlink()
    if not args.skip_magg:
        warm = images / "warmup-magg.exr"
        run_magg(args, args.spp_list[0], warm, width, height)
        for p in images.glob("warmup-magg*"):
            p.unlink()
    log(f"light mesh normal(s) (emitting side): {checks['light_normals']}")

    rows = []
    for spp in args.spp_list:
        # Runs of the renderers take turns (round by round), so that a spell of load from
        # elsewhere on this shared machine falls on each of them alike: the ratios compare
        # runs made under the same conditions, not one renderer's quiet minutes with
        # another's busy ones.
        runs = {key: [] for key in renderers}
        for _ in range(args.repeat):
            for renderer, variant in renderers:
                out_image = images / f"{image_tag(renderer, variant)}-{spp}spp.exr"
                if renderer == "magg":
                    run = run_magg(args, spp, out_image, width, height)
                else:
                    run = run_mitsuba(args, variant, spp, out_image, width, height)
                runs[(renderer, variant)].append(run)
        for renderer, variant in renderers:
            out_image = images / f"{image_tag(renderer, variant)}-{spp}spp.exr"
            rs = runs[(renderer, variant)]
            # Same seed each repeat: the image (so relMSE) is the same; only times vary.
            err = rel_mse(read_image(out_image), reference)
            row = {
                "renderer": renderer, "variant": variant, "spp": spp,
                "wall_s": statistics.median(r["wall_s"] for r in rs),
                "render_s": statistics.median(r["render_s"] for r in rs),
                "cpu_s": statistics.median(r["cpu_s"] for r in rs),
                "rel_mse": err, "image": str(out_image),
                "wall_s_runs": [r["wall_s"] for r in rs],
                "render_s_runs": [r["render_s"] for r in rs],
                "cpu_s_runs": [r["cpu_s"] for r in rs],
                "detail": rs[-1]["detail"],
            }
            if "command" in rs[-1]:
                row["command"] = rs[-1]["command"]
            rows.append(row)
            log(f"{renderer:7s} {variant:12s} {spp:5d} spp: wall {row['wall_s']:7.2f} s, "
                f"render {row['render_s']:7.2f} s, CPU {row['cpu_s']:7.2f} s, relMSE {err:.3e}")

    # Cross-check the NumPy relMSE against magg's own `compare`, once (on the first images).
    if not args.skip_magg:
        for r in rows[: len(renderers)]:
            theirs = magg_compare(args, Path(r["image"]), args.reference)
            checks.setdefault("magg_compare", []).append(
                {"image": r["image"], "numpy_relmse": r["rel_mse"], "magg_compare_relmse": theirs})

    depth = {"Mitsuba": f"path, max_depth {MITSUBA_MAX_DEPTH} (unbounded), "
                        f"Russian roulette from depth {MITSUBA_RR_DEPTH} (its defaults)"}
    if not args.skip_magg:
        depth["magg"] = "path tracer (NEE + MIS), " + magg_depth_note(args) + " (its defaults)"
    magg_version = None
    if not args.skip_magg:
        v = subprocess.run([str(args.magg), "--version"], capture_output=True, text=True)
        magg_version = v.stdout.strip() or None
    llvm_pkg = subprocess.run(["dpkg-query", "-W", "-f=${Version}", "libllvm19"],
                              capture_output=True, text=True).stdout.strip()
    cpu = cpu_fields()
    meta = {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "scene": str(args.scene), "reference": str(args.reference),
        "width": width, "height": height, "spp": args.spp_list, "repeat": args.repeat,
        "seed": args.seed, "machine": machine_note(cpu), "avx512": has_avx512(cpu),
        "platform": platform.platform(),
        "versions": {"mitsuba": mi.__version__, "drjit": dr.__version__, "numpy": np.__version__,
                     "python": platform.python_version(), "libllvm19": llvm_pkg,
                     "DRJIT_LIBLLVM_PATH": os.environ.get("DRJIT_LIBLLVM_PATH"),
                     "magg": magg_version},
        "depth": depth, "magg_mode": None if args.skip_magg else args.magg_mode,
        "magg_args": args.magg_args,
    }
    table, summary = build_tables(rows, renderers, meta)
    checks_lines = ["", "Checks:", ""]
    checks_lines.append(f"- emitting side of the light (mean face normal, Mitsuba's front = glTF's "
                        f"counter-clockwise): {checks.get('light_normals')}")
    if "reference_exr_vs_pfm_relmse" in checks:
        checks_lines.append(f"- reference EXR vs PFM relMSE: {checks['reference_exr_vs_pfm_relmse']:.3g}")
    for c in checks.get("magg_compare", []):
        checks_lines.append(f"- relMSE of {Path(c['image']).name}: NumPy {c['numpy_relmse']:.6e}, "
                            f"`magg-host compare` {fmt(c['magg_compare_relmse'], 7)}")
    for w in checks.get("conversion_warnings", []):
        checks_lines.append(f"- conversion warning: {w}")
    table += "\n".join(checks_lines) + "\n"
    print(table)

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "mitsuba-table.md").write_text(table)
    (args.out / "mitsuba-results.json").write_text(json.dumps(
        {"meta": meta, "runs": rows, "summary": summary, "checks": checks}, indent=2) + "\n")
    log(f"wrote {args.out / 'mitsuba-table.md'} and {args.out / 'mitsuba-results.json'}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        worker_main(sys.argv[2:])
    else:
        bootstrap()
        main()
