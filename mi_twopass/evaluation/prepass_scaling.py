"""``python -m mi_twopass bench --prepass``: what each prepass costs, in seconds and memory, as
the image, the geometry and the lights grow.

A prepass should cost what the image needs. This measures, for every integrator of the suite
(and ``path``, the reference line), in one run:

1. **image size**: the prepass at film sizes :data:`DEFAULT_SIZES` (the film's longer side:
   64² … 1024²) on one scene (default ``scenes_xml/cornell_box.xml``), beside ``path``'s time
   for :data:`PATH_SPP` (32) spp of the same image;
2. **triangles**: the Cornell box with a floating sphere mesh of about :data:`DEFAULT_TRIANGLES`
   (1k, 10k, 100k) triangles (a UV sphere written as OBJ into a temporary folder;
   :func:`triangle_scene`), at :data:`STUDY_RES` (128²);
3. **emitters**: the Cornell box whose light is replaced by :data:`DEFAULT_EMITTERS` (1, 10,
   100, 1000) small rectangular area lights on a grid under the ceiling, their total power the
   original light's (:func:`emitter_scene`), at 128²;
4. **full HD**: the scene at 1920×1080 (:data:`FULL_HD`; the issue's target is at most
   :data:`TARGET_BYTES`, 2 GB, per integrator), ``path`` at :data:`FULL_HD_PATH_SPP` (1) spp.

Each measurement is a fresh Python process (``sys.executable -c`` :data:`SNIPPET`, its result a
JSON line on stdout): it loads the scene, builds a fresh integrator and runs its prepass alone
(``integrator.ensure_prepass(scene, seed, sensor)``: the seconds it returns), then reads its own
peak resident memory (``resource.getrusage(RUSAGE_SELF).ru_maxrss``, KiB on Linux). ``twopass``
runs its pilot and the prepasses it builds for a render of :data:`TWOPASS_SPP` (64) spp (its
seconds are both; the pilot's share is reported apart). ``path`` instead renders its spp (in
passes of at most :data:`mi_twopass.cli.LANES_PER_PASS` lanes, as ``render`` does). Per scene
and size a *baseline* process only loads the scene: each row gives the peak and the peak less
that baseline (what the prepass added to Python, Mitsuba and the scene). A process that runs
past ``--timeout`` (default :data:`DEFAULT_TIMEOUT` s) is stopped and recorded as
``"timeout"``; the larger points of the same study and integrator are then skipped. Dr.Jit's
on-disk kernel cache is left as it is: kernels are compiled once (by the first process that
needs them) and read from disk by the others, so the seconds are a user's second run.

Written into the output folder: ``prepass_scaling.json`` (machine, versions, command, settings,
and every measurement), ``prepass_scaling.md`` (per study a table of seconds and one of peak
memory, and the full-HD table) and ``prepass_scaling.png`` (log-log seconds against pixels,
triangles and emitters, one line per integrator, ``path`` dashed; and the peak memory at full
HD as bars with the 2 GB target).

Run time: :func:`estimate_seconds`, from :data:`CHILD_OVERHEAD_SECONDS` per process and
per-integrator costs measured on 2 cores (:data:`COST_MODEL`); the arithmetic is in
:func:`estimate_text` and the ``bench --help`` text. Default run: 13 points × 7 processes = 91
processes × 1 s = 91 s, plus the work: sizes 107 s, triangles 52 s, emitters 247 s (rex alone
131 s with 1000 lights), 1920×1080 30 s; about 527 s ≈ 9 min (measured on 2 cores, in two
parts: about 8 min). ``--quick`` (sizes 64…256, 1k and 10k triangles, 1…100 emitters, and
1920×1080): 63 processes, about 4 min (its points without full HD took 2.8 min).
"""
from __future__ import annotations

import datetime
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET

from .runs import table_line

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CORNELL_BOX = os.path.join(ROOT, "scenes_xml", "cornell_box.xml")
DEFAULT_SCENE = CORNELL_BOX
#: film sizes (longer side, pixels) of the image-size study; --quick: :data:`QUICK_SIZES`
DEFAULT_SIZES = (64, 128, 256, 512, 1024)
QUICK_SIZES = (64, 128, 256)
#: triangles of the sphere mesh (about: a UV sphere has 4 s (s - 1)) and emitter counts
DEFAULT_TRIANGLES = (1000, 10000, 100000)
QUICK_TRIANGLES = (1000, 10000)
DEFAULT_EMITTERS = (1, 10, 100, 1000)
QUICK_EMITTERS = (1, 10, 100)
#: film size (longer side) of the triangle and emitter studies
STUDY_RES = 128
FULL_HD = (1920, 1080)
#: path's spp: the reference line of the studies, and at full HD (the issue's number)
PATH_SPP = 32
FULL_HD_PATH_SPP = 1
#: the render spp twopass chooses for (its pilot weighs prepasses against path at this spp)
TWOPASS_SPP = 64
DEFAULT_TIMEOUT = 300.0
#: the issue's target for an integrator's peak memory at full HD (bytes, 10^9 per GB)
TARGET_BYTES = 2e9
#: the line of a child's stdout that carries its result
RESULT_MARK = "MI_TWOPASS_PREPASS "
#: what a child runs: ``sys.executable -c SNIPPET CONFIG_JSON``
SNIPPET = """\
import time
_t0 = time.perf_counter()
import json, sys
import mi_twopass
from mi_twopass.evaluation.prepass_scaling import RESULT_MARK, child_main
result = child_main(json.loads(sys.argv[1]), import_seconds=time.perf_counter() - _t0)
print(RESULT_MARK + json.dumps(result), flush=True)
"""
STUDIES = ("size", "triangles", "emitters", "full_hd")
#: path and the suite (:data:`mi_twopass.integrators.PLUGINS`), for the estimate
DEFAULT_SPECS = ("path", "radiosity_gather", "radiance_cache", "rex", "spike_gather", "twopass")
STUDY_TITLES = {"size": "image size", "triangles": "triangles", "emitters": "emitters",
                "full_hd": "1920×1080"}

#: per process: Python's start, the imports and the scene's load (0.5-1 s measured on 2 cores)
CHILD_OVERHEAD_SECONDS = 1.0
#: seconds of a measurement, for :func:`estimate_seconds`: (fixed, per megapixel, per 1k
#: triangles, per emitter), fitted to a run on the Cornell box on a 2-core AMD EPYC
#: (2026-11-25; ``path``: its render at PATH_SPP spp, 13.3 s at 1024², 4.8 s with 1000
#: emitters; rex: 12.2 s at 128², 17.5 s at 1024², 16.3 s at 1920×1080, 131 s with 1000
#: emitters; twopass: pilot and prepasses for 64 spp, 3.4 s at 1024², 0.01 s at 128² where it
#: renders path without a pilot; the others 0.5-1 s at every size, 3-28 s with 1000 emitters)
COST_MODEL = {
    "path": (0.2, 13.0, 0.0, 0.0045),
    "radiosity_gather": (0.5, 0.0, 0.004, 0.011),
    "radiance_cache": (0.8, 0.0, 0.015, 0.0022),
    "rex": (13.0, 4.0, 0.01, 0.12),
    "spike_gather": (0.7, 0.0, 0.006, 0.027),
    "twopass": (0.5, 2.5, 0.0, 0.0),
}


# -- generated scenes -------------------------------------------------------------------------

def sphere_mesh(triangles: int, centre=(0.3, 0.1, 0.35), radius=0.25):
    """(vertices (V, 3), faces (F, 3) 0-based, outward) of a UV sphere with about ``triangles``
    faces: ``s`` stacks and ``2 s`` slices give 4 s (s − 1)."""
    import numpy as np

    s = max(2, int(round((1 + math.sqrt(1 + max(int(triangles), 8))) / 2)))
    n = 2 * s
    theta = np.pi * np.arange(1, s) / s                      # rings between the poles
    phi = 2 * np.pi * np.arange(n) / n
    ring = np.stack([np.outer(np.sin(theta), np.cos(phi)), np.repeat(np.cos(theta), n)
                     .reshape(s - 1, n), np.outer(np.sin(theta), np.sin(phi))], axis=-1)
    verts = np.concatenate([[[0, 1, 0]], ring.reshape(-1, 3), [[0, -1, 0]]])
    north, south = 0, len(verts) - 1

    def idx(i, j):  # ring i (0-based), slice j
        return 1 + i * n + (j % n)

    j = np.arange(n)
    faces = [np.stack([np.full(n, north), idx(0, j), idx(0, j + 1)], axis=1),
             np.stack([np.full(n, south), idx(s - 2, j + 1), idx(s - 2, j)], axis=1)]
    for i in range(s - 2):
        a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)
        faces += [np.stack([a, c, b], axis=1), np.stack([b, c, d], axis=1)]
    faces = np.concatenate(faces)
    # outward: flip every face whose normal points to the centre
    p = verts[faces]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    inward = (normal * p.mean(axis=1)).sum(axis=1) < 0
    faces[inward] = faces[inward][:, ::-1]
    return verts * radius + np.asarray(centre, dtype=float), faces


def write_obj(path, verts, faces) -> None:
    """An OBJ file of positions and triangles."""
    import numpy as np

    with open(path, "w") as f:
        np.savetxt(f, verts, fmt="v %.6f %.6f %.6f")
        np.savetxt(f, faces + 1, fmt="f %d %d %d")


def _scene_root(path):
    from ..scenefile import SceneFileError

    try:
        return ET.parse(path).getroot()
    except ET.ParseError as e:
        raise SceneFileError(f"{path}: malformed XML: {e}") from e


def _write(root, folder, name) -> str:
    path = os.path.join(folder, name)
    ET.ElementTree(root).write(path, encoding="unicode")
    return path


def triangle_scene(folder, triangles: int, base=CORNELL_BOX) -> tuple:
    """(XML path, mesh triangles): ``base`` plus a white sphere mesh of about ``triangles``
    faces floating above the small box, written into ``folder``."""
    verts, faces = sphere_mesh(triangles)
    obj = f"sphere_{len(faces)}.obj"
    write_obj(os.path.join(folder, obj), verts, faces)
    root = _scene_root(base)
    shape = ET.SubElement(root, "shape", {"type": "obj", "id": "sphere-mesh"})
    ET.SubElement(shape, "string", {"name": "filename", "value": obj})
    ET.SubElement(shape, "boolean", {"name": "face_normals", "value": "true"})
    ET.SubElement(shape, "ref", {"id": "white"})
    return _write(root, folder, f"triangles_{len(faces)}.xml"), int(len(faces))


#: the Cornell box's light: a 0.46 × 0.38 m rectangle and its radiance
_LIGHT_AREA = 0.46 * 0.38
_LIGHT_RADIANCE = (18.387, 13.9873, 6.75357)


def emitter_scene(folder, count: int, base=CORNELL_BOX) -> str:
    """``base`` (the Cornell box) with its emitters removed and ``count`` small rectangular
    area lights facing down, 1 cm under the ceiling, on a ⌈√count⌉² grid over [−0.8, 0.8]²
    (row by row); each a square of side min(0.4, cell / 2) whose radiance makes the total
    power the original light's. Written into ``folder``; returns its path."""
    count = int(count)
    if count < 1:
        raise ValueError(f"emitters: {count}: must be >= 1")
    root = _scene_root(base)
    for parent in list(root.iter()):
        for child in list(parent):
            if child.tag == "shape" and child.find("emitter") is not None:
                parent.remove(child)
    grid = math.ceil(math.sqrt(count))
    cell = 1.6 / grid
    half = min(0.2, cell / 4)
    scale = _LIGHT_AREA / (count * (2 * half) ** 2)
    radiance = ", ".join(f"{v * scale:.6g}" for v in _LIGHT_RADIANCE)
    for k in range(count):
        cx = -0.8 + cell * (k % grid + 0.5)
        cz = -0.8 + cell * (k // grid + 0.5)
        shape = ET.SubElement(root, "shape", {"type": "rectangle", "id": f"light-{k}"})
        tr = ET.SubElement(shape, "transform", {"name": "to_world"})
        ET.SubElement(tr, "scale", {"x": f"{half:.6g}", "y": f"{half:.6g}", "z": "1"})
        ET.SubElement(tr, "rotate", {"x": "1", "angle": "90"})
        ET.SubElement(tr, "translate", {"x": f"{cx:.6g}", "y": "0.99", "z": f"{cz:.6g}"})
        ET.SubElement(shape, "ref", {"id": "white"})
        emitter = ET.SubElement(shape, "emitter", {"type": "area"})
        ET.SubElement(emitter, "rgb", {"name": "radiance", "value": radiance})
    return _write(root, folder, f"emitters_{count}.xml")


def sized_scene(scene_path, folder, size, params: dict) -> tuple:
    """(XML path, params): a copy of ``scene_path`` in ``folder`` whose every film is
    ``size`` = (width, height) pixels (crop windows dropped), and the ``params`` it still uses
    (a ``-D`` only the film size used, ``res``, is dropped). Load it with the scene's own
    folder on the file resolver (:func:`child_main`'s ``resolver``)."""
    import re

    with open(scene_path, "rb") as f:
        original = f.read()
    root = _scene_root(scene_path)
    for sensor in root.iter("sensor"):
        film = sensor.find("film")
        if film is None:
            film = ET.SubElement(sensor, "film", {"type": "hdrfilm"})
        for child in list(film):
            if child.get("name") in ("width", "height") or \
                    (child.get("name") or "").startswith("crop_"):
                film.remove(child)
        ET.SubElement(film, "integer", {"name": "width", "value": str(int(size[0]))})
        ET.SubElement(film, "integer", {"name": "height", "value": str(int(size[1]))})
    name = f"{os.path.splitext(os.path.basename(scene_path))[0]}_{size[0]}x{size[1]}.xml"
    path = _write(root, folder, name)
    with open(path) as f:
        text = f.read()
    kept = {}
    for key, value in params.items():
        pattern = r"\$" + re.escape(key) + r"(?![A-Za-z0-9_])"
        if re.search(pattern.encode(), original) and not re.search(pattern, text):
            continue
        kept[key] = value
    return path, kept


# -- one measurement, in a fresh process ----------------------------------------------------------

def peak_kib() -> int:
    """This process's peak resident memory so far (``ru_maxrss``: KiB on Linux)."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def _jsonable(value):
    """``value`` as JSON can hold it (numpy and Dr.Jit numbers as numbers, else strings)."""
    from .bench import _json_default

    return json.loads(json.dumps(value, default=_json_default))


def child_main(config: dict, import_seconds: float = 0.0) -> dict:
    """In the child: load the scene, then (``mode``) nothing (``"baseline"``), the
    integrator's prepass (``"prepass"``) or a render of ``spp`` spp (``"render"``); returns
    the seconds, the film size, the scene's triangles and emitters, and the peak memory."""
    import drjit as dr
    import mitsuba as mi

    from ..scenefile import load_scene
    from .harness import make_integrator

    if config.get("variant") and mi.variant() != config["variant"]:
        mi.set_variant(config["variant"])
    resolver = mi.file_resolver()
    for folder in config.get("resolver", ()):
        resolver.prepend(folder)
    t0 = time.perf_counter()
    scene = load_scene(config["scene"], film_res=config.get("film_res"), **config["params"])
    dr.sync_thread()
    sensor = scene.sensors()[0]
    size = [int(v) for v in sensor.film().crop_size()]
    meshes = [s for s in scene.shapes() if s.is_mesh()]
    result = {"import_seconds": import_seconds, "load_seconds": time.perf_counter() - t0,
              "size": size, "pixels": size[0] * size[1],
              "triangles": int(sum(m.face_count() for m in meshes)),
              "shapes": len(scene.shapes()), "emitters": len(scene.emitters()),
              "load_peak_kib": peak_kib(), "variant": mi.variant()}
    mode = config["mode"]
    if mode == "baseline":
        result["peak_kib"] = result["load_peak_kib"]
        return result
    integrator = make_integrator(config["spec"])
    seed = int(config.get("seed", 0))
    if mode == "prepass":
        if not hasattr(integrator, "ensure_prepass"):
            raise ValueError(f"{config['spec']}: not a mi_twopass integrator (no prepass)")
        if hasattr(integrator, "planned_spp"):  # twopass: choose for a render of this spp
            integrator.planned_spp = integrator._render_spp = int(config["spp"])
        dr.sync_thread()
        t1 = time.perf_counter()
        structure, seconds = integrator.ensure_prepass(scene, seed, sensor)
        dr.sync_thread()
        result["wall_seconds"] = time.perf_counter() - t1
        result["seconds"] = float(seconds)
        stats = dict(getattr(integrator, "_prepass_stats", {}) or {})
        split = getattr(structure, "seconds", None)  # twopass: {"pilot": s, "prepasses": s}
        if isinstance(split, dict):
            result["pilot_seconds"] = float(split.get("pilot", 0.0))
            result["prepasses_seconds"] = float(split.get("prepasses", 0.0))
        result["stats"] = _jsonable(stats)
    elif mode == "render":
        from ..cli import PASS_SEED_STRIDE, pass_sizes

        spp = int(config["spp"])
        passes = pass_sizes(spp, size[0] * size[1])
        dr.sync_thread()
        t1 = time.perf_counter()
        for k, n in enumerate(passes):
            image = mi.render(scene, sensor=sensor, integrator=integrator, spp=n,
                              seed=seed + PASS_SEED_STRIDE * k)
            dr.eval(image)
            dr.sync_thread()
            del image
        result["seconds"] = result["wall_seconds"] = time.perf_counter() - t1
        result["passes"] = len(passes)
    else:
        raise ValueError(f"mode {mode!r}: expected baseline, prepass or render")
    result["peak_kib"] = peak_kib()
    return result


def run_child(config: dict, timeout: float = DEFAULT_TIMEOUT) -> dict:
    """Run :data:`SNIPPET` on ``config`` in a fresh process; returns its result with
    ``status`` "ok" and ``process_seconds``, or ``{"status": "timeout"}`` after ``timeout``
    seconds (the process is killed), or ``{"status": "failed", "error": ...}``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    t0 = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, "-c", SNIPPET, json.dumps(config)], env=env,
                              capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"status": "timeout", "timeout": float(timeout),
                "process_seconds": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(RESULT_MARK)]
    if proc.returncode != 0 or not lines:
        tail = " ".join((proc.stderr or proc.stdout).strip().splitlines()[-3:])[-400:]
        why = f"exit status {proc.returncode}" + (" (killed: out of memory?)"
                                                 if proc.returncode in (-9, 137) else "")
        return {"status": "failed", "error": f"{why}: {tail}", "process_seconds": wall}
    result = json.loads(lines[-1][len(RESULT_MARK):])
    result.update(status="ok", process_seconds=wall)
    return result


# -- the studies ----------------------------------------------------------------------------------

def suite_specs() -> list:
    """``path`` and every integrator of the suite."""
    from .bench import suite_integrators

    return suite_integrators()


def is_path(spec: str) -> bool:
    return spec.split(":")[0] == "path"


def plan_points(scene_path, folder, sizes=DEFAULT_SIZES, triangles=DEFAULT_TRIANGLES,
                emitters=DEFAULT_EMITTERS, full_hd=True, params=None,
                study_res=STUDY_RES) -> list:
    """The measured points, in order: dicts of ``study``, ``x`` (film side / triangles /
    emitters / 0), ``label``, the scene to load and how (``scene``, ``film_res``, ``params``,
    ``resolver``) and ``path_spp``. Generated scenes are written into ``folder``."""
    from .bench import scene_settings

    params = dict(params or {})
    scene_path = os.path.abspath(scene_path)
    home = os.path.dirname(scene_path)
    points = []
    for res in sorted(set(int(s) for s in sizes)):
        p, film_res = scene_settings(scene_path, res, params)
        points.append({"study": "size", "x": res, "label": f"{res} px", "scene": scene_path,
                       "film_res": film_res, "params": p, "resolver": [],
                       "path_spp": PATH_SPP})
    for n in sorted(set(int(t) for t in triangles)):
        path, got = triangle_scene(folder, n)
        points.append({"study": "triangles", "x": got, "label": f"{got} triangles",
                       "scene": path, "film_res": study_res, "params": {},
                       "resolver": [os.path.dirname(CORNELL_BOX)], "path_spp": PATH_SPP})
    for n in sorted(set(int(e) for e in emitters)):
        path = emitter_scene(folder, n)
        points.append({"study": "emitters", "x": n, "label": f"{n} emitters", "scene": path,
                       "film_res": study_res, "params": {},
                       "resolver": [os.path.dirname(CORNELL_BOX)], "path_spp": PATH_SPP})
    if full_hd:
        path, p = sized_scene(scene_path, folder, FULL_HD, params)
        points.append({"study": "full_hd", "x": FULL_HD[0] * FULL_HD[1],
                       "label": f"{FULL_HD[0]}×{FULL_HD[1]}", "scene": path, "film_res": None,
                       "params": p, "resolver": [home], "path_spp": FULL_HD_PATH_SPP})
    return points


def child_config(point: dict, spec: str | None, mode: str, seed: int = 0,
                 variant: str | None = None) -> dict:
    """What one child does at ``point`` (see :func:`child_main`)."""
    spp = point["path_spp"] if mode == "render" else TWOPASS_SPP
    return {"scene": point["scene"], "film_res": point["film_res"], "params": point["params"],
            "resolver": point["resolver"], "spec": spec, "mode": mode, "spp": spp,
            "seed": int(seed), "variant": variant}


def entry_of(point: dict, spec: str | None, result: dict, baseline: dict | None) -> dict:
    """One measurement as prepass_scaling.json holds it: the point, the integrator, and the
    child's result with ``peak_bytes`` and ``extra_bytes`` (peak − the baseline's peak)."""
    entry = {"study": point["study"], "x": point["x"], "label": point["label"],
             "integrator": spec or "baseline (load only)", "kind": (
                 "baseline" if spec is None else "render" if is_path(spec) else "prepass"),
             **result}
    if spec is not None and is_path(spec):
        entry["spp"] = point["path_spp"]
    elif spec is not None and spec.split(":")[0] == "twopass":
        entry["spp"] = TWOPASS_SPP
    if result.get("status") == "ok":
        entry["peak_bytes"] = int(result["peak_kib"]) * 1024
        base = (baseline or {}).get("peak_kib") if (baseline or {}).get("status") == "ok" \
            else None
        entry["baseline_bytes"] = None if base is None else int(base) * 1024
        entry["extra_bytes"] = None if base is None else entry["peak_bytes"] - int(base) * 1024
    return entry


def measure(points, specs, timeout: float = DEFAULT_TIMEOUT, seed: int = 0,
            variant: str | None = None, log=print, runner=run_child) -> list:
    """Every point's baseline and every integrator at it, each in a fresh process; returns
    the entries (:func:`entry_of`). After a timeout, that integrator's later points of the
    same study are skipped (``status`` "skipped")."""
    entries = []
    timed_out = set()  # (study, spec)
    total = len(points) * (1 + len(specs))
    k = 0
    for point in points:
        k += 1
        base = runner(child_config(point, None, "baseline", seed, variant), timeout)
        entries.append(entry_of(point, None, base, None))
        log(_progress(k, total, point, "baseline (load only)", entries[-1]))
        for spec in specs:
            k += 1
            if (point["study"], spec) in timed_out:
                result = {"status": "skipped",
                          "error": "timed out at a smaller point of this study"}
            else:
                mode = "render" if is_path(spec) else "prepass"
                result = runner(child_config(point, spec, mode, seed, variant), timeout)
                if result["status"] == "timeout":
                    timed_out.add((point["study"], spec))
            entries.append(entry_of(point, spec, result, base))
            log(_progress(k, total, point, spec, entries[-1]))
    return entries


def _bytes(n) -> str:
    """``123456789`` → ``"123 MB"`` (— for None)."""
    if not isinstance(n, (int, float)):
        return "—"
    for unit in ("bytes", "kB", "MB", "GB"):
        if abs(n) < 1000 or unit == "GB":
            return f"{n:.3g} {unit}"
        n /= 1000.0


def _gb(n) -> str:
    return "—" if n is None else f"{n / 1e9:.3g}"


def _progress(k, total, point, spec, e) -> str:
    width = len(str(total))
    head = f"[{k:>{width}}/{total}] {point['study']:<9} {point['label']:<16} {spec:<34}"
    if e["status"] == "timeout":
        return f"{head} timeout after {e['timeout']:.0f} s"
    if e["status"] != "ok":
        return f"{head} {e['status']}: {e.get('error', '')[:200]}"
    what = {"baseline": "load", "render": f"render {e.get('spp')} spp",
            "prepass": "prepass"}[e["kind"]]
    secs = e["load_seconds"] if e["kind"] == "baseline" else e["seconds"]
    extra = "" if e.get("extra_bytes") is None else f" (+{_gb(e['extra_bytes'])})"
    return (f"{head} {what} {secs:7.2f} s, peak {_gb(e['peak_bytes'])} GB{extra}  "
            f"({e['process_seconds']:.0f} s)")


# -- the report ------------------------------------------------------------------------------------

def _cell_seconds(e) -> str:
    if e is None:
        return ""
    if e["status"] == "timeout":
        return f"timeout (> {e['timeout']:.0f} s)"
    if e["status"] == "skipped":
        return "skipped"
    if e["status"] != "ok":
        return "failed"
    text = f"{e['seconds']:.3g}"
    if e.get("pilot_seconds") is not None:
        text += f" (pilot {e['pilot_seconds']:.2g})"
    return text


def _cell_memory(e) -> str:
    if e is None:
        return ""
    if e["status"] != "ok":
        return _cell_seconds(e)
    extra = e.get("extra_bytes")
    return _gb(e["peak_bytes"]) + ("" if extra is None or e["kind"] == "baseline"
                                   else f" (+{_gb(extra)})")


def _row_name(spec: str, entries) -> str:
    if spec == "baseline (load only)":
        return "baseline (load only)"
    if is_path(spec):
        spp = sorted({e.get("spp") for e in entries if e.get("spp")})
        return f"`{spec}` ({'/'.join(map(str, spp))} spp render)"
    if spec.split(":")[0] == "twopass":
        return f"`{spec}` (pilot + prepasses, {TWOPASS_SPP} spp)"
    return f"`{spec}`"


def _column_label(study, e) -> str:
    if study == "size":
        w, h = (e.get("size") or [e["x"], e["x"]])
        return f"{w}×{h}"
    return str(e["x"])


def _table(lines, title, study, entries, cell, specs) -> None:
    xs = sorted({e["x"] for e in entries})
    heads = {}
    for e in entries:
        if e["status"] == "ok" or e["x"] not in heads:
            heads[e["x"]] = _column_label(study, e)
    first = {"size": "film", "triangles": "triangles", "emitters": "emitters"}[study]
    lines += [title, "", f"| integrator \\ {first} | " + " | ".join(heads[x] for x in xs) + " |",
              "| --- | " + " | ".join("---" for _ in xs) + " |"]
    for spec in specs:
        mine = {e["x"]: e for e in entries if e["integrator"] == spec}
        if not mine:
            continue
        cells = [cell(mine.get(x)) for x in xs]
        lines.append(f"| {_row_name(spec, mine.values())} | "
                     + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    lines.append("")


def _point_name(e) -> str:
    if e["study"] == "size" and e.get("size"):
        return f"{e['size'][0]}×{e['size'][1]}"
    return e["label"]


def format_report(data: dict) -> str:
    """prepass_scaling.md: the header, per study its seconds and memory tables, the full-HD
    table, and what the numbers are."""
    entries = data["entries"]
    specs = ["baseline (load only)"] + list(data["integrators"])
    lines = [data["header"], ""]
    for study in ("size", "triangles", "emitters"):
        mine = [e for e in entries if e["study"] == study]
        if not mine:
            continue
        where = {"size": os.path.basename(data["scene"]),
                 "triangles": f"Cornell box + sphere mesh, {data['study_res']} px",
                 "emitters": f"Cornell box, N small area lights, {data['study_res']} px"}[study]
        _table(lines, f"## Prepass seconds vs {STUDY_TITLES[study]} ({where})", study,
               [e for e in mine if e["kind"] != "baseline"], _cell_seconds, specs)
        _table(lines, f"## Peak memory, GB (+ over the baseline), vs {STUDY_TITLES[study]} "
               f"({where})", study, mine, _cell_memory, specs)
    hd = [e for e in entries if e["study"] == "full_hd"]
    if hd:
        lines += [f"## {FULL_HD[0]}×{FULL_HD[1]} ({os.path.basename(data['scene'])}): peak "
                  f"memory against the {TARGET_BYTES / 1e9:g} GB target", "",
                  "| integrator | seconds | peak GB | peak − baseline GB | ≤ "
                  f"{TARGET_BYTES / 1e9:g} GB | cache bytes | note |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for spec in specs:
            e = next((e for e in hd if e["integrator"] == spec), None)
            if e is None:
                continue
            ok = e["status"] == "ok"
            fits = "—" if not ok or e["kind"] == "baseline" else (
                "yes" if e["peak_bytes"] <= TARGET_BYTES else "**no**")
            stats = e.get("stats") or {}
            note = ""
            if stats.get("twopass_choice"):
                note = f"chose {stats['twopass_choice']}"
            if not ok:
                note = (e.get("error") or "")[:120]
            cells = [_row_name(spec, [e]),
                     _cell_seconds(e) if e["kind"] != "baseline" else (
                         f"{e['load_seconds']:.3g} (load)" if ok else _cell_seconds(e)),
                     _gb(e.get("peak_bytes")) if ok else "—",
                     _gb(e.get("extra_bytes")) if ok and e["kind"] != "baseline" else "—",
                     fits, _bytes(stats.get("cache_bytes")), note]
            lines.append(table_line(cells))
        lines.append("")
    chose = [e for e in entries if e["status"] == "ok" and (e.get("stats") or {}).get(
        "twopass_choice")]
    if chose:
        lines += [f"twopass chose, for a render of {TWOPASS_SPP} spp:", ""]
        lines += [f"- {_point_name(e)}: {e['stats']['twopass_choice']}" for e in chose]
        lines.append("")
    lines += [
        "- **seconds**: the prepass alone (`ensure_prepass` in a fresh process, after the "
        "scene's load); `twopass`: its pilot and the prepasses it built for a "
        f"{TWOPASS_SPP}-spp render (pilot's share in brackets); `path`: its render at the spp "
        "named, the reference line (no prepass).",
        "- **peak memory**: the process's peak resident set (`ru_maxrss`) after the prepass "
        "(path: after the render); in brackets, less the peak of a process that only loaded "
        "the same scene (the baseline row: Python, Mitsuba, Dr.Jit and the scene). GB = "
        "10^9 bytes.",
        "- **timeout**: stopped after `--timeout` seconds; **skipped**: not run, the same "
        "integrator timed out at a smaller point of the study.",
        "- Dr.Jit's kernel cache on disk is used as found: a kernel is compiled by the first "
        "process that needs it, so an early point may include some compilation.",
    ]
    return "\n".join(lines) + "\n"


def write_plot(data: dict, path: str) -> None:
    """prepass_scaling.png: seconds vs pixels / triangles / emitters (log-log, one line per
    integrator, path dashed, timeouts as × at the timeout) and the peak memory at full HD
    (bars: baseline + extra, the 2 GB target dashed; without full HD: peak vs pixels)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    entries = data["entries"]
    specs = list(data["integrators"])
    colours = {s: f"C{k}" for k, s in enumerate(s for s in specs if not is_path(s))}
    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    xlabels = {"size": "pixels", "triangles": "triangles (sphere mesh)",
               "emitters": "emitters"}
    for ax, study in zip(axes.flat, ("size", "triangles", "emitters")):
        mine = [e for e in entries if e["study"] == study and e["kind"] != "baseline"]
        ax.set_title(f"prepass seconds vs {STUDY_TITLES[study]}", fontsize=10)
        ax.set_xlabel(xlabels[study])
        ax.set_ylabel("seconds")
        if not mine:
            ax.text(0.5, 0.5, "not measured", ha="center", va="center", transform=ax.transAxes)
            continue
        marked = False
        for spec in specs:
            pts = [e for e in mine if e["integrator"] == spec]
            x = [_plot_x(study, e) for e in pts if e["status"] == "ok" and e["seconds"] > 0]
            y = [e["seconds"] for e in pts if e["status"] == "ok" and e["seconds"] > 0]
            style = dict(color="k", ls="--", marker=".") if is_path(spec) else \
                dict(color=colours[spec], marker="o", ms=4)
            label = f"{spec} ({pts[0].get('spp', PATH_SPP)} spp render)" if is_path(spec) \
                else spec
            if x:
                ax.plot(x, y, label=label, **style)
            late = [e for e in pts if e["status"] == "timeout"]
            if late:
                ax.plot([_plot_x(study, e) for e in late], [e["timeout"] for e in late],
                        ls="none", marker="x", ms=8, color=style["color"],
                        label=None if marked else f"timeout (> {late[0]['timeout']:g} s)")
                marked = True
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    ax = axes[1, 1]
    hd = [e for e in entries if e["study"] == "full_hd" and e["kind"] != "baseline"]
    if hd:
        names = [e["integrator"] for e in hd]
        base = [(e.get("baseline_bytes") or 0) / 1e9 if e["status"] == "ok" else 0 for e in hd]
        extra = [max(0.0, (e["peak_bytes"] / 1e9) - b) if e["status"] == "ok" else 0
                 for e, b in zip(hd, base)]
        pos = range(len(hd))
        ax.bar(pos, base, color="0.75", label="baseline (load only)")
        ax.bar(pos, extra, bottom=base, color=[("k" if is_path(n) else colours.get(n, "C0"))
                                               for n in names], label="prepass (path: render)")
        for p, e, b, x in zip(pos, hd, base, extra):
            text = f"{b + x:.2g} GB" if e["status"] == "ok" else e["status"]
            if e["status"] == "ok":
                text += f"\n{e['seconds']:.3g} s"
            ax.text(p, b + x, text, ha="center", va="bottom", fontsize=7)
        ax.axhline(TARGET_BYTES / 1e9, color="r", ls="--",
                   label=f"target {TARGET_BYTES / 1e9:g} GB")
        ax.set_xticks(list(pos))
        ax.set_xticklabels([n.split(":")[0] for n in names], rotation=30, ha="right",
                           fontsize=8)
        ax.set_ylabel("peak resident memory, GB")
        ax.set_title(f"peak memory at {FULL_HD[0]}×{FULL_HD[1]}", fontsize=10)
        ax.legend(fontsize=7)
    else:
        mine = [e for e in entries if e["study"] == "size" and e["kind"] != "baseline"]
        for spec in specs:
            pts = [e for e in mine if e["integrator"] == spec and e["status"] == "ok"]
            if pts:
                ax.plot([_plot_x("size", e) for e in pts], [e["peak_bytes"] / 1e9 for e in pts],
                        label=spec, **(dict(color="k", ls="--", marker=".") if is_path(spec)
                                       else dict(color=colours[spec], marker="o", ms=4)))
        ax.axhline(TARGET_BYTES / 1e9, color="r", ls="--",
                   label=f"target {TARGET_BYTES / 1e9:g} GB")
        ax.set_xscale("log")
        ax.set_xlabel("pixels")
        ax.set_ylabel("peak resident memory, GB")
        ax.set_title("peak memory vs image size (no full-HD run)", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(data.get("title", "prepass scaling"), fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_x(study, e):
    if study == "size":
        return e.get("pixels") or e["x"] ** 2
    return e["x"]


# -- run time -------------------------------------------------------------------------------------

def _model_seconds(spec: str, pixels: float, triangles: float, emitters: float) -> float:
    fixed, per_mpx, per_ktri, per_emitter = COST_MODEL.get(spec.split(":")[0],
                                                           COST_MODEL["twopass"])
    return fixed + per_mpx * pixels / 1e6 + per_ktri * triangles / 1e3 + per_emitter * emitters


def estimate_parts(specs=None, sizes=DEFAULT_SIZES, triangles=DEFAULT_TRIANGLES,
                   emitters=DEFAULT_EMITTERS, full_hd=True, timeout=DEFAULT_TIMEOUT,
                   study_res=STUDY_RES) -> dict:
    """Estimated seconds per study (``processes`` counts the processes, ``start`` their
    :data:`CHILD_OVERHEAD_SECONDS`): per point a baseline process and one per integrator, each
    its :data:`COST_MODEL` seconds (a process at most ``timeout``). ``path`` renders
    :data:`PATH_SPP` spp (its per-megapixel cost is for that), :data:`FULL_HD_PATH_SPP` at full
    HD."""
    specs = list(specs or DEFAULT_SPECS)
    px = study_res ** 2
    studies = {"size": [(s * s, 0, 1, 1.0) for s in sizes],
               "triangles": [(px, t, 1, 1.0) for t in triangles],
               "emitters": [(px, 0, n, 1.0) for n in emitters],
               "full_hd": [(FULL_HD[0] * FULL_HD[1], 0, 1, FULL_HD_PATH_SPP / PATH_SPP)]
               if full_hd else []}
    parts = {"processes": 0, "start": 0.0}
    for study, points in studies.items():
        total = 0.0
        for pixels, tris, lights, path_scale in points:
            parts["processes"] += 1 + len(specs)
            for spec in specs:
                work = _model_seconds(spec, pixels, tris, lights)
                if is_path(spec):
                    work *= path_scale
                total += min(work, max(0.0, timeout - CHILD_OVERHEAD_SECONDS))
        parts[study] = total
    parts["start"] = parts["processes"] * CHILD_OVERHEAD_SECONDS
    parts["total"] = parts["start"] + sum(parts[s] for s in STUDIES)
    return parts


def estimate_seconds(*args, **kwargs) -> float:
    """:func:`estimate_parts`' total."""
    return estimate_parts(*args, **kwargs)["total"]


def estimate_text(quick: bool = False) -> str:
    """The arithmetic of the default run's (``quick``: ``--quick``'s) estimated wall time,
    for the help text."""
    if quick:
        kw = dict(sizes=QUICK_SIZES, triangles=QUICK_TRIANGLES, emitters=QUICK_EMITTERS,
                  full_hd=True)
    else:
        kw = dict(sizes=DEFAULT_SIZES, triangles=DEFAULT_TRIANGLES, emitters=DEFAULT_EMITTERS,
                  full_hd=True)
    p = estimate_parts(**kw)
    n = len(DEFAULT_SPECS)
    points = len(kw["sizes"]) + len(kw["triangles"]) + len(kw["emitters"]) + kw["full_hd"]
    text = (f"{points} points x ({n} integrators + a baseline) = {p['processes']} processes x "
            f"{CHILD_OVERHEAD_SECONDS:g} s start = {p['start']:.0f} s; work (fitted to a run on 2 "
            f"cores, the 6 integrators together): sizes {_csv(kw['sizes'])} {p['size']:.0f} s, "
            f"triangles {_csv(kw['triangles'])} {p['triangles']:.0f} s, emitters "
            f"{_csv(kw['emitters'])} {p['emitters']:.0f} s")
    if kw["full_hd"]:
        text += f", 1920x1080 {p['full_hd']:.0f} s"
    else:
        text += ", no 1920x1080"
    return f"{text}: about {p['total']:.0f} s = {p['total'] / 60:.0f} min"


def _csv(values) -> str:
    return ",".join(map(str, values))


# -- the run ---------------------------------------------------------------------------------------

def run_prepass_scaling(scene_path=DEFAULT_SCENE, specs=None, sizes=DEFAULT_SIZES,
                        triangles=DEFAULT_TRIANGLES, emitters=DEFAULT_EMITTERS,
                        full_hd: bool = True, timeout: float = DEFAULT_TIMEOUT,
                        params: dict | None = None, seed: int = 0,
                        out_dir: str = "benchmarks", variant: str | None = None, argv=(),
                        log=print, study_res: int = STUDY_RES, runner=run_child) -> dict:
    """Measure (module docstring), write prepass_scaling.json / .md / .png into ``out_dir``
    and return the JSON's content. ``specs``: integrator specs (default :func:`suite_specs`;
    ``path`` is added first when missing: the reference line)."""
    from .bench import (_duration, command_line, machine_info, machine_label, run_label,
                        software_info)

    specs = list(specs or suite_specs())
    if not any(is_path(s) for s in specs):
        specs.insert(0, "path")
    os.makedirs(out_dir, exist_ok=True)
    started = datetime.datetime.now().astimezone()
    info = {"machine": machine_info(), "date": started.isoformat(timespec="seconds"),
            "command": command_line(argv), "python": sys.executable, **software_info(),
            "scene": os.path.abspath(scene_path), "sizes": sorted(set(map(int, sizes))),
            "triangles_requested": sorted(set(map(int, triangles))),
            "emitters": sorted(set(map(int, emitters))), "full_hd": bool(full_hd),
            "full_hd_size": list(FULL_HD), "study_res": study_res, "path_spp": PATH_SPP,
            "full_hd_path_spp": FULL_HD_PATH_SPP, "twopass_spp": TWOPASS_SPP,
            "timeout": float(timeout), "target_bytes": TARGET_BYTES, "defines": dict(params or {}),
            "seed": seed, "integrators": specs}
    m = info["machine"]
    estimate = estimate_seconds(specs, sizes, triangles, emitters, full_hd, timeout, study_res)
    folder = tempfile.mkdtemp(prefix="mi_twopass_prepass_scaling_")
    try:
        points = plan_points(scene_path, folder, sizes, triangles, emitters, full_hd, params,
                             study_res)
        log(f"prepass scaling: {len(points)} points × ({len(specs)} integrators + a baseline) "
            f"= {len(points) * (len(specs) + 1)} processes, timeout {timeout:g} s each; about "
            f"{_duration(estimate)} on {machine_label(m)}")
        t0 = time.perf_counter()
        entries = measure(points, specs, timeout, seed, variant, log=log, runner=runner)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    info["wall_seconds"] = time.perf_counter() - t0
    info["estimated_seconds"] = estimate
    info["entries"] = entries
    info["title"] = (f"prepass scaling, {info['date']}, {machine_label(m)}, "
                     f"commit {info['git_commit']}")
    info["header"] = (
        f"Prepass scaling of {run_label(info)}; took {_duration(info['wall_seconds'])} "
        f"(estimated {_duration(estimate)}). Command: `{info['command']}`")
    with open(os.path.join(out_dir, "prepass_scaling.json"), "w") as f:
        json.dump(info, f, indent=1, default=str)
    with open(os.path.join(out_dir, "prepass_scaling.md"), "w") as f:
        f.write(format_report(info))
    write_plot(info, os.path.join(out_dir, "prepass_scaling.png"))
    log(f"wrote {out_dir}/prepass_scaling.md, prepass_scaling.json and prepass_scaling.png "
        f"({_duration(info['wall_seconds'])})")
    return info


def parse_counts(text: str, what: str) -> list:
    """``"64,128"`` → [64, 128] (each ≥ 1, at least one)."""
    values = []
    for item in str(text).split(","):
        item = item.strip()
        if not item:
            continue
        try:
            value = int(item)
        except ValueError:
            raise ValueError(f"{item!r}: expected an integer") from None
        if value < 1:
            raise ValueError(f"{value}: each {what} must be >= 1")
        values.append(value)
    if not values:
        raise ValueError(f"no {what} given")
    return sorted(set(values))
