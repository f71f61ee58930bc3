#!/usr/bin/env python3
"""The Cornell box, magg against Blender's Cycles, in one run.

Usage (from anywhere; the script finds the repository from its own path):

    python3 bench/peers/cycles.py                  # 1, 2, 4 ... 1024 spp
    python3 bench/peers/cycles.py --max-spp 64     # 1 to 64 spp
    python3 bench/peers/cycles.py --spp 16,256 --repeat 3 --skip-magg
    python3 bench/peers/cycles.py --table-only     # the tables again from OUT/cycles-results.json
    python3 bench/peers/cycles.py --magg-mode cluster   # magg's default 86-process cluster

Set-up, done by the script itself on its first run: a virtual environment
`bench/peers/.venv-cycles` made with Python 3.11 (PyPI's `bpy` wheels are built for exactly
one Python minor version, 3.11 for Blender 5.0; the script uses the Python it runs under when
that is 3.11, else a `python3.11` on the PATH) with the pinned versions in `PINS` (bpy 5.0.1,
Blender 5.0.1 as a Python module, about 380 MB; NumPy below 2). The script then re-executes
itself inside it.

What it does:
  1. For each sample count, a fresh Python process (the wall time is the whole command a user
     waits for) imports bpy, starts from Blender's empty factory settings, imports the glTF
     (`--scene`) with Blender's own glTF importer and renders it with Cycles:
       - camera: the glTF camera as imported (vertical fit, yfov 39.3077 degrees), made the
         scene camera, 256x256 pixels (the reference's size), clip start = znear;
       - Cycles on the CPU, `--threads` threads (default 2, this machine's cores);
       - box pixel filter 1 pixel wide (every sample uniform within its pixel, a pixel the
         plain mean of its samples, as the reference);
       - no denoising, no adaptive sampling, no clamping (sample_clamp_direct/indirect 0), no
         glossy filter (blur_glossy 0), no time limit; the seed fixed (`--seed`);
       - path lengths: max_bounces and every per-kind bound (diffuse, glossy, transmission,
         volume, transparent) 1024, Cycles' largest, so unbounded in practice; Cycles'
         own Russian roulette ends paths (always on; survival min(1, sqrt(max throughput))
         from the first bounce, min_light_bounces 0);
       - Cycles' defaults otherwise: sampling pattern (tabulated Sobol), light tree, light
         threshold 0.01 (a probabilistic, unbiased cut of weak light samples);
       - black world (the importer makes none; Blender's default world is grey);
       - the EXR is written as linear 32-bit float, the working space Linear Rec.709
         (linear sRGB primaries, as the glTF and the reference).
     What the importer does is checked against the glTF's own numbers, and the run stops if
     they differ: every material's Principled BSDF base colour, metallic 0, diffuse
     roughness 0 (Lambertian), Specular IOR Level = KHR_materials_specular's factor (0 here:
     no specular lobe, the diffuse keeps its whole albedo), emission colour x strength =
     emissiveFactor x KHR_materials_emissive_strength (radiance, W/(sr m^2)); the camera's
     eye, view direction, up and field of view; every mesh's world-space vertices (glTF's Y
     up is Blender's Z up: (x, y, z) -> (x, -z, y)).
     One fix to the import: Cycles emits from both sides of a surface, while glTF's
     single-sided light (doubleSided false) emits only from its front. The back of the
     Cornell box's light faces the ceiling 1 mm away, and that light leaking out of the gap
     brightened the image by 0.26% in every channel (256 spp, means against the
     reference's). So every single-sided emissive material gets its emission strength
     multiplied by (1 - Backfacing), and its emission sampling is set to front only.
  2. magg renders the same sample counts (`magg-host render ... --in-process`, or the
     cluster, `--magg-mode cluster`), one fresh command each; its render-only time is
     `seconds.render` of its `--stats` JSON.
  3. Every image's relMSE against the reference (`--reference`), computed here in NumPy:
     mean over pixels and channels of (a - b)^2 / (b^2 + 0.01), the formula of the
     reference's README and of `mitsuba.py` (the helpers are `mitsuba.py`'s own, loaded
     from it, so both scripts compute and interpolate the same way); cross-checked once
     with `magg-host compare`. Times: wall (the whole command, from outside), render (Cycles:
     `bpy.ops.render.render`, which includes Cycles' scene sync and BVH build, but not
     importing bpy and the glTF or writing the EXR) and CPU (user + system of the whole
     command: on a shared machine, how much of the cores a run actually got).
  4. Prints one markdown table (a row per renderer and spp) and a summary (time to relMSE
     1e-2 and 1e-3 read off each curve in log-log, ratios magg / Cycles), writes it to
     `OUT/cycles-table.md`, the raw numbers to `OUT/cycles-results.json` (the shape of
     `mitsuba-results.json`; `magg-host experiment error` plots its Cycles curve) and the
     images to `OUT/cycles-images/`.

If bpy cannot be imported (a system library it links against is missing), the script says
which and stops.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
VENV = HERE / ".venv-cycles"
# PyPI's bpy is Blender built as a Python module, for one Python minor version only.
PYTHON = (3, 11)
# bpy 5.0.1 is the newest Blender 5.0 on PyPI; NumPy 1.26.4 is the last release below 2
# (bpy's own Python code is built against NumPy 1.x).
PINS = ["bpy==5.0.1", "numpy==1.26.4"]

DEFAULT_SCENE = REPO / "tests/data/scenes/cornell/cornell.gltf"
DEFAULT_REFERENCE = REPO / "tests/data/references/cornell/cornell_ref.exr"
DEFAULT_MAGG = REPO / "target/release/magg-host"
DEFAULT_OUT = REPO / "bench/peers/out"
DEFAULT_MAX_SPP = 1024
TARGETS = [1e-2, 1e-3]
# Cycles' hard maximum for every bounce limit: with its Russian roulette, unbounded in practice.
CYCLES_MAX_BOUNCES = 1024
BOUNCE_PROPS = ["max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces",
                "volume_bounces", "transparent_max_bounces"]
VARIANT = "CPU"


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def load_mitsuba_helpers():
    """bench/peers/mitsuba.py as a module: relMSE, the log-log reading of a curve, magg's
    runs. Loading it runs nothing but its definitions (it imports Mitsuba only inside them)."""
    spec = importlib.util.spec_from_file_location("magg_peer_mitsuba", HERE / "mitsuba.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


M = load_mitsuba_helpers()


# ---------------------------------------------------------------------------------------------
# Bootstrap: the virtual environment
# ---------------------------------------------------------------------------------------------


def in_venv() -> bool:
    return Path(sys.prefix).resolve() == VENV.resolve()


def python311() -> str:
    """A Python 3.11 to make the environment with: this one, or python3.11 on the PATH."""
    if sys.version_info[:2] == PYTHON:
        return sys.executable
    found = shutil.which("python3.11")
    if found:
        return found
    sys.exit(f"error: PyPI's bpy 5.0 is built for Python 3.11 only; this is Python "
             f"{platform.python_version()} and there is no python3.11 on the PATH")


def check_bpy_imports(python: Path) -> None:
    """Stops with the reason when bpy cannot load (a system library it needs is missing)."""
    r = subprocess.run([str(python), "-c", "import bpy"], capture_output=True, text=True)
    if r.returncode == 0:
        return
    tail = "\n".join((r.stdout + r.stderr).strip().splitlines()[-5:])
    missing = [w for w in tail.replace(":", " ").split() if ".so" in w]
    hint = ""
    if missing:
        hint = (f"\nbpy links against {', '.join(sorted(set(missing)))}, which this system lacks; "
                "Blender's Linux build needs X11, Xrender, Xi, Xxf86vm, Xfixes, xkbcommon, SM "
                "and GL libraries even without a display (Debian: apt-get install libx11-6 "
                "libxrender1 libxi6 libxxf86vm1 libxfixes3 libxkbcommon0 libsm6 libgl1)")
    sys.exit(f"error: `import bpy` fails in {VENV}:\n{tail}{hint}")


def bootstrap() -> None:
    """Makes sure the venv exists with bpy importable; re-executes this script inside it."""
    if in_venv():
        return
    python = VENV / "bin" / "python"
    stamp = VENV / ".pins"
    if python.exists():
        r = subprocess.run([str(python), "-c", "import sys; print(sys.version_info[:2])"],
                           capture_output=True, text=True)
        if r.stdout.strip() != str(PYTHON):
            log(f"{VENV} is not Python 3.11 ({r.stdout.strip() or r.stderr.strip()}); making it again")
            shutil.rmtree(VENV)
    if not python.exists():
        base = python311()
        log(f"creating the virtual environment {VENV} with {base}")
        subprocess.run([base, "-m", "venv", str(VENV)], check=True)
    if not stamp.exists() or stamp.read_text().split() != PINS:
        log("pip install " + " ".join(PINS) + " (bpy is a download of about 380 MB)")
        subprocess.run([str(python), "-m", "pip", "install", "--disable-pip-version-check",
                        "--progress-bar", "off", *PINS], check=True)
        check_bpy_imports(python)
        stamp.write_text("\n".join(PINS) + "\n")
    os.execv(str(python), [str(python), str(Path(__file__).resolve()), *sys.argv[1:]])


def import_bpy():
    try:
        import bpy
    except ImportError as e:
        check_bpy_imports(Path(sys.executable))
        sys.exit(f"error: import bpy: {e}")
    return bpy


# ---------------------------------------------------------------------------------------------
# The scene in Blender: the glTF importer, checked against the file, and Cycles' settings
# ---------------------------------------------------------------------------------------------


def y_up_to_z_up(v):
    """glTF's frame (Y up) in Blender's (Z up), as Blender's glTF importer converts it."""
    return [v[0], -v[2], v[1]]


def close(a, b, tol=1e-5) -> bool:
    return all(abs(x - y) <= tol * max(1.0, abs(y)) for x, y in zip(a, b, strict=True))


def principled_of(mat):
    """The Principled BSDF that feeds the material's output, or None."""
    out = next((n for n in mat.node_tree.nodes
                if n.bl_idname == "ShaderNodeOutputMaterial" and n.is_active_output), None)
    if out is None or not out.inputs["Surface"].is_linked:
        return None
    node = out.inputs["Surface"].links[0].from_node
    return node if node.bl_idname == "ShaderNodeBsdfPrincipled" else None


def check_import(bpy, scene_path: Path) -> dict:
    """What Blender's importer made, against the glTF's own numbers (read by mitsuba.py's
    converter). Returns the findings; any difference in radiometry or geometry is an error."""
    import numpy as np

    doc, _ = M.load_gltf(scene_path)
    desc = M.convert_gltf(scene_path)
    errors: list[str] = []
    materials = []
    for i, gm in enumerate(doc.get("materials", [])):
        name = gm.get("name", f"material{i}")
        mat = bpy.data.materials.get(name)
        if mat is None:
            errors.append(f"material {name!r}: not imported")
            continue
        p = principled_of(mat)
        if p is None:
            errors.append(f"material {name!r}: no Principled BSDF at the output")
            continue
        pbr = gm.get("pbrMetallicRoughness", {})
        ext = gm.get("extensions", {})
        want = {
            "base_color": list(pbr.get("baseColorFactor", [1, 1, 1, 1])[:3]),
            "metallic": pbr.get("metallicFactor", 1.0),
            "specular_level": ext.get("KHR_materials_specular", {}).get("specularFactor", 1.0),
            "emission": [c * ext.get("KHR_materials_emissive_strength", {}).get("emissiveStrength", 1.0)
                         for c in gm.get("emissiveFactor", [0, 0, 0])],
        }
        strength = p.inputs["Emission Strength"].default_value
        got = {
            "base_color": list(p.inputs["Base Color"].default_value)[:3],
            "metallic": p.inputs["Metallic"].default_value,
            # glTF's specularFactor scales F0 as Specular IOR Level x 2 does in Principled v2.
            "specular_level": p.inputs["Specular IOR Level"].default_value * 2.0,
            "emission": [c * strength for c in list(p.inputs["Emission Color"].default_value)[:3]],
        }
        for key in want:
            w, g = want[key], got[key]
            if not close(w if isinstance(w, list) else [w], g if isinstance(g, list) else [g]):
                errors.append(f"material {name!r}: {key} {g} in Blender, {w} in the glTF")
        for sock in ("Base Color", "Metallic", "Emission Color", "Emission Strength",
                     "Specular IOR Level", "Diffuse Roughness", "Roughness"):
            if p.inputs[sock].is_linked:
                errors.append(f"material {name!r}: {sock} is driven by a node (a texture?)")
        if p.inputs["Diffuse Roughness"].default_value != 0:
            errors.append(f"material {name!r}: diffuse roughness is not 0 (not Lambertian)")
        for sock in ("Transmission Weight", "Coat Weight", "Sheen Weight", "Subsurface Weight"):
            if p.inputs[sock].default_value != 0:
                errors.append(f"material {name!r}: {sock} is not 0")
        materials.append({"name": name, "double_sided": bool(gm.get("doubleSided", False)),
                          **{k: [round(x, 6) for x in v] if isinstance(v, list) else round(v, 6)
                             for k, v in got.items()}})

    # Geometry: every glTF mesh's world-space vertices against the imported object's.
    meshes = []
    for m in desc["meshes"]:
        obj = bpy.data.objects.get(m["name"])
        if obj is None or obj.type != "MESH":
            errors.append(f"mesh {m['name']!r}: no Blender mesh object of that name")
            continue
        mw = np.array(obj.matrix_world)
        verts = np.array([list(v.co) + [1.0] for v in obj.data.vertices]) @ mw.T
        want = {tuple(np.round(y_up_to_z_up(p), 4)) for p in m["positions"]}
        got = {tuple(np.round(v[:3], 4)) for v in verts}
        if want != got:
            errors.append(f"mesh {m['name']!r}: vertices differ ({len(got)} in Blender, "
                          f"{len(want)} distinct in the glTF)")
        meshes.append(m["name"])

    # Camera: position, view direction, up, vertical field of view.
    cam = desc["camera"]
    cams = [o for o in bpy.data.objects if o.type == "CAMERA"]
    camera = {}
    if not cams:
        errors.append("no camera imported")
    else:
        obj = cams[0]
        mw = np.array(obj.matrix_world)
        eye = mw[:3, 3]
        forward = -mw[:3, 2] / np.linalg.norm(mw[:3, 2])
        up = mw[:3, 1] / np.linalg.norm(mw[:3, 1])
        want_forward = np.array(y_up_to_z_up(np.subtract(cam["target"], cam["eye"])))
        camera = {"eye": eye.round(6).tolist(), "forward": forward.round(6).tolist(),
                  "up": up.round(6).tolist(), "sensor_fit": obj.data.sensor_fit,
                  "yfov_deg": math.degrees(obj.data.angle_y)}
        if not (close(eye, y_up_to_z_up(cam["eye"]))
                and close(forward, want_forward / np.linalg.norm(want_forward))
                and close(up, y_up_to_z_up(cam["up"]))):
            errors.append(f"camera: Blender's {camera} against the glTF's {cam}")
        if obj.data.type != "PERSP" or abs(math.degrees(obj.data.angle_y) - cam["yfov_deg"]) > 1e-4:
            errors.append(f"camera: vertical field of view {math.degrees(obj.data.angle_y)} "
                          f"degrees in Blender, {cam['yfov_deg']} in the glTF")
    return {"errors": errors, "materials": materials, "meshes": meshes, "camera": camera,
            "glTF_camera": cam, "warnings": desc["warnings"]}


def emit_front_only(bpy, mat) -> None:
    """A glTF material that is not double-sided emits from its front only; Cycles' emission is
    two-sided. Multiplies the emission strength by (1 - Backfacing) and samples the front."""
    nt = mat.node_tree
    p = principled_of(mat)
    strength = p.inputs["Emission Strength"].default_value
    geometry = nt.nodes.new("ShaderNodeNewGeometry")
    front = nt.nodes.new("ShaderNodeMath")
    front.operation = "SUBTRACT"
    front.inputs[0].default_value = 1.0
    nt.links.new(geometry.outputs["Backfacing"], front.inputs[1])
    scaled = nt.nodes.new("ShaderNodeMath")
    scaled.operation = "MULTIPLY"
    scaled.inputs[1].default_value = strength
    nt.links.new(front.outputs[0], scaled.inputs[0])
    nt.links.new(scaled.outputs[0], p.inputs["Emission Strength"])
    mat.cycles.emission_sampling = "FRONT"


def setup_scene(bpy, a) -> dict:
    """Imports the glTF, checks it, and sets up Cycles as the module docs say."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=str(a.scene))
    found = check_import(bpy, a.scene)
    if found["errors"]:
        sys.exit("error: Blender's glTF import differs from the file:\n  "
                 + "\n  ".join(found["errors"]))
    doc, _ = M.load_gltf(a.scene)
    fixed = []
    for gm in doc.get("materials", []):
        mat = bpy.data.materials[gm["name"]]
        emits = any(c > 0 for c in gm.get("emissiveFactor", [0, 0, 0]))
        if emits and not gm.get("doubleSided", False):
            emit_front_only(bpy, mat)
            fixed.append(gm["name"])
        elif not gm.get("doubleSided", False) and any(
                c > 0 for c in gm.get("pbrMetallicRoughness", {}).get("baseColorFactor", [1, 1, 1])[:3]):
            found["warnings"].append(f"material {gm['name']!r}: single-sided in glTF, "
                                     "reflects on both sides in Cycles")
    found["front_only_emission"] = fixed

    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    sc.camera = next(o for o in bpy.data.objects if o.type == "CAMERA")
    sc.camera.data.clip_start = found["glTF_camera"]["znear"]
    r = sc.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = a.width, a.height, 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.threads_mode = "FIXED"
    r.threads = a.threads
    r.use_persistent_data = False
    c = sc.cycles
    c.device = "CPU"
    c.samples = a.spp
    c.seed = a.seed
    c.use_animated_seed = False
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.pixel_filter_type = "BOX"
    c.filter_width = 1.0
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.blur_glossy = 0.0
    c.time_limit = 0.0
    for prop in BOUNCE_PROPS:
        setattr(c, prop, CYCLES_MAX_BOUNCES)
    world = bpy.data.worlds.new("black")
    world.color = (0.0, 0.0, 0.0)
    for node in world.node_tree.nodes if world.node_tree else []:
        if node.type == "BACKGROUND":
            node.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
            node.inputs["Strength"].default_value = 0.0
    sc.world = world
    sc.view_settings.view_transform = "Standard"
    sc.view_settings.look = "None"
    sc.view_settings.exposure = 0.0
    sc.view_settings.gamma = 1.0
    s = r.image_settings
    s.file_format = "OPEN_EXR"
    s.color_mode = "RGB"
    s.color_depth = "32"
    s.exr_codec = "ZIP"
    found["settings"] = {
        "device": c.device, "threads": r.threads, "samples": c.samples, "seed": c.seed,
        "pixel_filter": f"{c.pixel_filter_type} {c.filter_width} px",
        "adaptive": c.use_adaptive_sampling, "denoising": c.use_denoising,
        "clamp": [c.sample_clamp_direct, c.sample_clamp_indirect], "blur_glossy": c.blur_glossy,
        "bounces": {p: getattr(c, p) for p in BOUNCE_PROPS},
        "min_light_bounces": c.min_light_bounces, "sampling_pattern": c.sampling_pattern,
        "light_tree": c.use_light_tree, "light_threshold": round(c.light_sampling_threshold, 6),
        "caustics": [c.caustics_reflective, c.caustics_refractive],
        "working_space": bpy.data.colorspace.working_space,
        "resolution": [r.resolution_x, r.resolution_y],
    }
    return found


# ---------------------------------------------------------------------------------------------
# The Cycles worker: one fresh process per render, timed from outside as a user waits
# ---------------------------------------------------------------------------------------------


def worker_main(argv: list[str]) -> None:
    p = argparse.ArgumentParser(prog="cycles.py --worker")
    p.add_argument("--scene", type=Path, required=True)
    p.add_argument("--spp", type=int, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, required=True)
    p.add_argument("--width", type=int, required=True)
    p.add_argument("--height", type=int, required=True)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--timing", type=Path, required=True)
    a = p.parse_args(argv)

    t0 = time.perf_counter()
    bpy = import_bpy()
    t1 = time.perf_counter()
    found = setup_scene(bpy, a)
    t2 = time.perf_counter()
    bpy.ops.render.render()
    t3 = time.perf_counter()
    bpy.data.images["Render Result"].save_render(str(a.output), scene=bpy.context.scene)
    t4 = time.perf_counter()
    a.timing.write_text(json.dumps({
        "import_s": t1 - t0, "load_s": t2 - t1, "render_s": t3 - t2, "write_s": t4 - t3,
        "in_process_total_s": t4 - t0, "blender": bpy.app.version_string,
        "blender_build": bpy.app.build_hash.decode(), **found,
    }))


# ---------------------------------------------------------------------------------------------
# Images
# ---------------------------------------------------------------------------------------------


def read_image(path: Path):
    """An EXR (through Blender's image loader) or PFM as an (h, w, 3) linear float32 array,
    top row first. Blender keeps float images as they are in the file (scene-linear) and
    stores rows bottom-up."""
    import numpy as np

    if path.suffix.lower() == ".pfm":
        return M.read_pfm(path)
    bpy = import_bpy()
    img = bpy.data.images.load(str(path), check_existing=False)
    try:
        if not img.is_float:
            raise ValueError(f"{path}: not a float image")
        w, h = img.size
        ch = img.channels
        buf = np.empty(w * h * ch, np.float32)
        img.pixels.foreach_get(buf)
    finally:
        bpy.data.images.remove(img)
    arr = buf.reshape(h, w, ch)[::-1]
    return np.repeat(arr[..., :1], 3, axis=2) if ch == 1 else np.ascontiguousarray(arr[..., :3])


def run_cycles(args, spp: int, out_image: Path, width: int, height: int) -> dict:
    timing = out_image.with_suffix(".timing.json")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker",
           "--scene", str(args.scene), "--spp", str(spp), "--seed", str(args.seed),
           "--threads", str(args.threads), "--width", str(width), "--height", str(height),
           "-o", str(out_image), "--timing", str(timing)]
    r, wall, cpu = M.timed_run(cmd)
    if r.returncode != 0:
        sys.exit(f"error: Cycles at {spp} spp failed:\n{r.stdout[-3000:]}{r.stderr[-3000:]}")
    info = json.loads(timing.read_text())
    timing.unlink()
    return {"wall_s": wall, "render_s": info["render_s"], "cpu_s": cpu, "detail": info}


# ---------------------------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------------------------


def slope(rows: list[dict]) -> float | None:
    """Least-squares slope of log relMSE against log spp over the rows from 16 spp up: -1 for
    an unbiased estimator with independent samples; flattening towards 0 means bias."""
    pts = [(math.log(r["spp"]), math.log(r["rel_mse"])) for r in rows if r["spp"] >= 16]
    if len(pts) < 2:
        return None
    mx = sum(x for x, _ in pts) / len(pts)
    my = sum(y for _, y in pts) / len(pts)
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    return sum((x - mx) * (y - my) for x, y in pts) / sxx if sxx else None


def build_tables(rows: list[dict], renderers: list[tuple[str, str]], meta: dict) -> tuple[str, dict]:
    lines = [f"# Cornell box: magg against Blender {meta['versions']['blender']} Cycles", ""]
    lines.append(f"{meta['width']}x{meta['height']} pixels, scene `{meta['scene']}`, reference "
                 f"`{meta['reference']}`; {meta['machine']}; load average before the runs "
                 f"{meta['load_average_before']}, after {meta['load_average_after']}. relMSE = "
                 "mean over pixels and channels of (a - b)^2 / (b^2 + 0.01). Wall: the whole "
                 "command a user waits for (Cycles: a fresh Python process that imports bpy, "
                 "imports the glTF, renders, writes the EXR). Render: the render alone (Cycles: "
                 "bpy.ops.render.render, scene sync included; magg: `seconds.render` of "
                 "--stats). CPU: user + system time of the whole command (near threads x wall "
                 "when it had the cores to itself). "
                 + (f"Median of {meta['repeat']} runs." if meta["repeat"] > 1 else "One run each."))
    lines.append("")
    v = meta["versions"]
    lines.append(f"Versions: Blender {v['blender']} (PyPI bpy {v['bpy']}, build {v['blender_build']}), "
                 f"Python {v['python']}, NumPy {v['numpy']}"
                 + (f"; {' '.join(v['magg'].split()[:4])}" if v.get("magg") else "") + ".")
    lines.append("")
    lines.append("Settings: " + "; ".join(f"{k}: {val}" for k, val in meta["depth"].items()) + ".")
    lines.append("")
    lines += M.runs_table(rows)
    table, footnote, summary, ratios = M.summary_table(
        rows, renderers, "Cycles", kinds=("wall", "render", "cpu"),
        extra=lambda rs: {"slope_from_16spp": slope(rs)})
    lines += table
    slopes = [f"{k} {summary[k]['slope_from_16spp']:.2f}" for k in summary
              if summary[k]["slope_from_16spp"] is not None]
    if slopes:
        lines += ["", "Slope of log relMSE against log spp from 16 spp up (-1: an unbiased "
                      "estimator with independent samples; towards 0: bias): "
                      + ", ".join(slopes) + "."]
    lines += footnote
    return "\n".join(lines) + "\n", {"per_renderer": summary, "magg_over_cycles": ratios}


# ---------------------------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------------------------


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--max-spp", type=int, default=DEFAULT_MAX_SPP,
                   help="the sweep: 1, 2, 4 ... up to this (default %(default)s)")
    p.add_argument("--spp", default="", help="comma-separated sample counts instead of the sweep")
    p.add_argument("--repeat", type=int, default=1, help="runs per (renderer, spp); median times")
    p.add_argument("--seed", type=int, default=0, help="sampler seed of every render")
    p.add_argument("--threads", type=int, default=2, help="Cycles' render threads (default %(default)s)")
    p.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    p.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE)
    p.add_argument("--magg", type=Path, default=DEFAULT_MAGG, help="the magg-host binary")
    p.add_argument("--magg-mode", choices=["in-process", "cluster"], default="in-process",
                   help="in-process (--in-process) or magg's default 86-process local cluster")
    p.add_argument("--magg-args", default="", help="extra flags for `magg-host render`, e.g. \"--threads 1\" "
                        "(a single flag: --magg-args=--adaptive)")
    p.add_argument("--skip-magg", action="store_true")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--table-only", action="store_true",
                   help="print and write the tables again from OUT/cycles-results.json; render nothing")
    a = p.parse_args()
    if a.spp.strip():
        a.spp_list = sorted({int(s) for s in a.spp.split(",") if s.strip()})
    else:
        a.spp_list = [1 << k for k in range(31) if (1 << k) <= a.max_spp]
    if not a.spp_list or min(a.spp_list) < 1 or a.repeat < 1 or a.threads < 1:
        p.error("--spp/--max-spp need positive sample counts, --repeat and --threads at least 1")
    a.scene, a.reference, a.out = a.scene.resolve(), a.reference.resolve(), a.out.resolve()
    return a


def load_average() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "unknown"


def main() -> None:
    args = parse_args()
    if args.table_only:
        table_only(args.out)
        return
    bpy = import_bpy()
    import numpy as np

    for path, what in [(args.scene, "scene"), (args.reference, "reference")]:
        if not path.exists():
            sys.exit(f"error: no {what} at {path}")
    if not args.skip_magg and not args.magg.exists():
        sys.exit(f"error: no magg binary at {args.magg} (cargo build --release, or --skip-magg)")

    reference = read_image(args.reference)
    height, width = reference.shape[:2]
    checks: dict = {"reference_channel_means": reference.astype(np.float64).mean(axis=(0, 1)).round(5).tolist()}
    pfm = args.reference.with_suffix(".pfm")
    if args.reference.suffix.lower() == ".exr" and pfm.exists():
        checks["reference_exr_vs_pfm_relmse"] = M.rel_mse(read_image(pfm), reference)

    images = args.out / "cycles-images"
    images.mkdir(parents=True, exist_ok=True)
    variant = f"{VARIANT} {args.threads} threads"
    renderers = [("Cycles", variant)]
    if not args.skip_magg:
        renderers.append(("magg", args.magg_mode + (" " + args.magg_args if args.magg_args else "")))

    # Untimed warm-ups: the page cache for bpy's 380 MB and for every program.
    log(f"warm-up runs at {args.spp_list[0]} spp (untimed)")
    warm = run_cycles(args, args.spp_list[0], images / "warmup-cycles.exr", width, height)
    (images / "warmup-cycles.exr").unlink()
    checks["import"] = {k: warm["detail"][k] for k in
                        ("materials", "meshes", "camera", "glTF_camera", "warnings", "front_only_emission")}
    if not args.skip_magg:
        M.run_magg(args, args.spp_list[0], images / "warmup-magg.exr", width, height)
        for p in images.glob("warmup-magg*"):
            p.unlink()

    load_before = load_average()
    rows = []
    for spp in args.spp_list:
        for renderer, var in renderers:
            tag = "magg" if renderer == "magg" else "cycles"
            out_image = images / f"{tag}-{spp}spp.exr"
            runs = []
            for _ in range(args.repeat):
                if renderer == "magg":
                    runs.append(M.run_magg(args, spp, out_image, width, height))
                else:
                    runs.append(run_cycles(args, spp, out_image, width, height))
            image = read_image(out_image)
            err = M.rel_mse(image, reference)
            detail = runs[-1]["detail"]
            if renderer == "Cycles":
                # The import findings are the same every run; the table keeps them once.
                detail = {k: v for k, v in detail.items() if k not in checks["import"]}
            row = {
                "renderer": renderer, "variant": var, "spp": spp,
                "wall_s": statistics.median(r["wall_s"] for r in runs),
                "render_s": statistics.median(r["render_s"] for r in runs),
                "cpu_s": statistics.median(r["cpu_s"] for r in runs),
                "rel_mse": err, "image": str(out_image),
                "channel_means": image.astype(np.float64).mean(axis=(0, 1)).round(5).tolist(),
                "wall_s_runs": [r["wall_s"] for r in runs],
                "render_s_runs": [r["render_s"] for r in runs],
                "cpu_s_runs": [r["cpu_s"] for r in runs],
                "detail": detail,
            }
            if "command" in runs[-1]:
                row["command"] = runs[-1]["command"]
            rows.append(row)
            log(f"{renderer:7s} {var:16s} {spp:5d} spp: wall {row['wall_s']:7.2f} s, "
                f"render {row['render_s']:7.2f} s, CPU {row['cpu_s']:7.2f} s, relMSE {err:.3e}")
    load_after = load_average()

    # Cross-check the NumPy relMSE (and Blender's EXR reader) against magg's own `compare`.
    if not args.skip_magg:
        for r in rows[: len(renderers)]:
            theirs = M.magg_compare(args, Path(r["image"]), args.reference)
            checks.setdefault("magg_compare", []).append(
                {"image": r["image"], "numpy_relmse": r["rel_mse"], "magg_compare_relmse": theirs})

    s = warm["detail"]["settings"]
    depth = {"Cycles": f"CPU, {s['threads']} threads, box filter {s['pixel_filter'].split()[1]} px, "
                       f"no denoising, no adaptive sampling, no clamping, blur_glossy 0, "
                       f"all bounce limits {CYCLES_MAX_BOUNCES} (Cycles' maximum) with its Russian "
                       f"roulette, sampling pattern {s['sampling_pattern']}, light tree "
                       f"{'on' if s['light_tree'] else 'off'}, light threshold {s['light_threshold']}"}
    if not args.skip_magg:
        depth["magg"] = "path tracer (NEE + MIS), " + M.magg_depth_note(args) + " (its defaults)"
    magg_version = None
    if not args.skip_magg:
        v = subprocess.run([str(args.magg), "--version"], capture_output=True, text=True)
        magg_version = v.stdout.strip() or None
    meta = {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "scene": str(args.scene), "reference": str(args.reference),
        "width": width, "height": height, "spp": args.spp_list, "repeat": args.repeat,
        "seed": args.seed, "machine": M.machine_note(), "platform": platform.platform(),
        "load_average_before": load_before, "load_average_after": load_after,
        "versions": {"blender": bpy.app.version_string, "blender_build": bpy.app.build_hash.decode(),
                     "bpy": PINS[0].split("==")[1], "numpy": np.__version__,
                     "python": platform.python_version(), "magg": magg_version},
        "cycles_settings": s,
        "depth": depth, "magg_mode": None if args.skip_magg else args.magg_mode,
        "magg_args": args.magg_args,
    }
    write_report(args.out, meta, rows, renderers, checks)


def write_report(out: Path, meta: dict, rows: list[dict], renderers: list[tuple[str, str]],
                 checks: dict) -> None:
    """Prints the tables and writes OUT/cycles-table.md and OUT/cycles-results.json."""
    table, summary = build_tables(rows, renderers, meta)
    lines = ["", "Checks:", ""]
    imp = checks["import"]
    lines.append(f"- Blender's glTF import matches the file's numbers: {len(imp['materials'])} "
                 f"materials (base colour, metallic, specular level, emission colour x strength), "
                 f"{len(imp['meshes'])} meshes' world-space vertices, the camera "
                 f"(yfov {imp['camera'].get('yfov_deg', float('nan')):.4f} degrees)")
    lines.append(f"- single-sided emission made front-only: {', '.join(imp['front_only_emission']) or 'none'}")
    lines.append(f"- reference channel means {checks['reference_channel_means']}; "
                 + "; ".join(f"{r['renderer']} {r['spp']} spp {r['channel_means']}"
                             for r in rows if r["spp"] == meta["spp"][-1]))
    if "reference_exr_vs_pfm_relmse" in checks:
        lines.append(f"- reference EXR vs PFM relMSE: {checks['reference_exr_vs_pfm_relmse']:.3g}")
    for c in checks.get("magg_compare", []):
        lines.append(f"- relMSE of {Path(c['image']).name}: NumPy {c['numpy_relmse']:.6e}, "
                     f"`magg-host compare` {M.fmt(c['magg_compare_relmse'], 7)}")
    for w in imp.get("warnings", []):
        lines.append(f"- import warning: {w}")
    table += "\n".join(lines) + "\n"
    print(table)

    out.mkdir(parents=True, exist_ok=True)
    (out / "cycles-table.md").write_text(table)
    (out / "cycles-results.json").write_text(json.dumps(
        {"meta": meta, "runs": rows, "summary": summary, "checks": checks}, indent=2) + "\n")
    log(f"wrote {out / 'cycles-table.md'} and {out / 'cycles-results.json'}")


def table_only(out: Path) -> None:
    """The tables again from OUT/cycles-results.json, without rendering."""
    path = out / "cycles-results.json"
    if not path.is_file():
        sys.exit(f"error: no {path} (run the sweep first)")
    doc = json.loads(path.read_text())
    renderers = list(dict.fromkeys((r["renderer"], r["variant"]) for r in doc["runs"]))
    write_report(out, doc["meta"], doc["runs"], renderers, doc["checks"])


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        worker_main(sys.argv[2:])
    else:
        bootstrap()
        main()
