"""``python -m mi_twopass bench``: the speed-vs-error harness over scenes × integrators, as one
report a person reads.

For every scene and integrator :func:`mi_twopass.evaluation.harness.run_compare` renders at
doubling spp until the time budget is spent (each point with a fresh integrator, its prepass
timed; ``path`` is always measured, it is the baseline). Written into the output folder:

* ``bench.json``: machine, date, command, variant, versions, and per scene its curves and table
  rows; ``<scene>.json`` beside it holds the same curves in ``compare``'s format;
* ``<scene>.png``: relMSE against time, log-log, every integrator on one plot;
* ``<scene>_images.png``: the reference, and per integrator its image at its largest spp with
  its FLIP error map beneath;
* ``results.md``: one Markdown table over all scenes (columns: :data:`COLUMNS`), then each
  scene's reference noise (:func:`reference_relmse`: the reference is ``path`` too, so its own
  relMSE is read off path's curve), marked where it takes more than a quarter of the target;
* ``bench.log``: every point as the harness logged it.

Run time. An integrator costs at most its budget (the harness stops before a point that, at
about twice the last, would overrun it; it usually spends 60-90 % of it) plus an untimed 1-spp
warm-up and the error metrics, :data:`OVERHEAD_SECONDS` (4 s) together. A point faster than
:data:`~mi_twopass.evaluation.harness.REPEAT_BELOW_SECONDS` (1 s) is rendered
:data:`~mi_twopass.evaluation.harness.DEFAULT_REPEATS` (3) times and the run of median time kept
(``--repeats``; the budget counts the kept run). Where a curve's time doubles with its samples
its points under 1 s sum to under 2 s, and their repeats add under 4 s; where a prepass
dominates, several points sit just under a second (spike_gather on many_lights at 256²: four,
0.85-1.02 s). The corpus bench at 256² took 26.4 min with repeats against 21.5-22.0 min
without, about 4.5 s more per integrator. References are rendered
once and cached (``$MI_TWOPASS_CACHE``, else ``.cache/references``): ``path`` at 4096 spp and
128² takes 8-41 s per corpus scene on a 2-core AMD EPYC, 188 s for the seven,
:data:`REFERENCE_SECONDS_PER_SCENE` (30 s) a scene in the estimate. Default run, 7 scenes ×
6 integrators, budget 25 s, references not cached:
42 × (25 + 4) s + 7 × 30 s = 1218 + 210 = 1428 s ≈ 24 min (< 30 min; :func:`estimate_seconds`;
the six scenes of before: 36 × 29 + 180 = 1224 s ≈ 20 min). The budget is wall time, so a busier
machine lengthens only the references and warm-ups.

Two other reports share the command: ``bench --sweep 64,128,...``, the speed-up over ``path``
against the image's size (:mod:`mi_twopass.evaluation.sweep`), and ``bench --cold``, the first
render's cost with and without Dr.Jit's kernel cache (:mod:`mi_twopass.evaluation.cold_start`).
"""
from __future__ import annotations

import datetime
import glob
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import textwrap
import time
import xml.etree.ElementTree as ET
from dataclasses import asdict

import numpy as np

from . import harness
from .images import srgb_tonemap
from .runs import markdown_report, num, run_integrators, table_line

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
#: the corpus: every scene of this folder, by default
CORPUS_DIR = os.path.join(ROOT, "scenes_xml")
#: seconds per integrator per scene (see the module docstring for the arithmetic)
DEFAULT_BUDGET = 25.0
#: the film's size in pixels (``-D res=PX``, or the longer side for scenes without ``$res``)
DEFAULT_RES = 128
DEFAULT_OUTPUT_DIR = "benchmarks"
#: per (scene, integrator), beyond its budget: the untimed 1-spp warm-up (prepass included:
#: ≤ 2 s measured at 128², plus compiling kernels not yet cached) and relMSE + FLIP per point
#: (0.06 s at 128² × at most 17 points)
OVERHEAD_SECONDS = 4.0
#: a reference, path at 4096 spp at 128² on a 2-core AMD EPYC, rounded up from the corpus's
#: (cornell_box 16, office 41, window_interior 29, many_lights 41, furnace 16, caustic 8,
#: mixed_room 37 s: 32² at 64 spp timed, × 1024)
REFERENCE_SECONDS_PER_SCENE = 30.0
#: results.md's columns, in order
COLUMNS = ("scene", "integrator", "t(relMSE 0.01) s", "speed-up vs path", "equal-time ratio",
           "equal-spp ratio", "relMSE @ max spp", "prepass share", "rays / viewing ray",
           "twopass chose")


def suite_integrators() -> list:
    """``path`` and every integrator of the suite (:data:`mi_twopass.integrators.PLUGINS`)."""
    from ..integrators import PLUGINS

    return ["path", *PLUGINS]


def corpus_scenes() -> list:
    """The scenes of :data:`CORPUS_DIR` (``scenes_xml/*.xml``), sorted."""
    return sorted(glob.glob(os.path.join(CORPUS_DIR, "*.xml")))


def estimate_seconds(n_scenes: int, n_integrators: int, budget: float,
                     references: bool = True) -> float:
    """Upper estimate of a bench's wall time at 128²: every (scene, integrator) its budget
    plus :data:`OVERHEAD_SECONDS`, plus (``references``: not cached)
    :data:`REFERENCE_SECONDS_PER_SCENE` per scene."""
    refs = n_scenes * REFERENCE_SECONDS_PER_SCENE if references else 0.0
    return n_scenes * n_integrators * (budget + OVERHEAD_SECONDS) + refs


def scene_names(paths) -> list:
    """A file-name-safe name per scene: the file's stem, or ``<folder>_<stem>`` where two
    scenes share a stem (``../shared/scenes/*/scene.xml``)."""
    stems = [os.path.splitext(os.path.basename(p))[0] for p in paths]
    names = []
    for p, stem in zip(paths, stems):
        if stems.count(stem) > 1:
            stem = f"{os.path.basename(os.path.dirname(os.path.abspath(p)))}_{stem}"
        names.append("".join(c if c.isalnum() or c in "-_." else "_" for c in stem))
    return names


def has_res_parameter(scene_path) -> bool:
    """Whether the scene declares ``<default name="res" .../>`` (then ``--res`` is passed as
    ``-D res=PX``; otherwise it sets the film's longer side)."""
    from ..scenefile import SceneFileError

    try:
        root = ET.parse(scene_path).getroot()
    except ET.ParseError as e:
        raise SceneFileError(f"{scene_path}: malformed XML: {e}") from e
    return any(el.get("name") == "res" for el in root.iter("default"))


def machine_info() -> dict:
    """CPU model (``/proc/cpuinfo``), logical cores, cores this process may use, Dr.Jit's
    thread count, OS and Python."""
    import drjit as dr

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    threads = dr.thread_count() if hasattr(dr, "thread_count") else None
    return {"cpu": cpu, "cores": os.cpu_count(), "usable_cores": usable,
            "drjit_threads": threads, "gpu": gpu_name(), "os": platform.platform(),
            "python": platform.python_version()}


def gpu_name() -> str | None:
    """The NVIDIA GPU the ``cuda_*`` variants render on (``nvidia-smi``), None when the variant
    is not a CUDA one or no GPU answers."""
    import mitsuba as mi

    if not mi.variant() or not mi.variant().startswith("cuda"):
        return None
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=20).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return out.splitlines()[0].strip() if out else None


def machine_label(m: dict) -> str:
    """``AMD EPYC (2 cores)``, or ``NVIDIA H200, host AMD EPYC (16 cores)`` on a GPU."""
    host = f"{m['cpu']} ({m['usable_cores']} cores)"
    return f"{m['gpu']}, host {host}" if m.get("gpu") else host


def run_label(info: dict) -> str:
    """When, where and with what a report was made, for the first line of its table:
    ``<date> on <machine_label>, <variant>, Mitsuba <version>, Dr.Jit <version>, commit <sha>``
    (``info``: :func:`machine_info` as ``machine``, the date, and :func:`software_info`)."""
    return (f"{info['date']} on {machine_label(info['machine'])}, {info['variant']}, "
            f"Mitsuba {info['mitsuba']}, Dr.Jit {info['drjit']}, commit {info['git_commit']}")


def software_info() -> dict:
    """Variant, Mitsuba and Dr.Jit versions, and the git commit of this checkout (``+dirty``
    when it has uncommitted changes; None outside git)."""
    import drjit as dr
    import mitsuba as mi

    commit = None
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True, timeout=10).stdout.strip() or None
        if commit and subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                                     cwd=ROOT, capture_output=True, text=True,
                                     timeout=10).stdout.strip():
            commit += "+dirty"
    except (OSError, subprocess.SubprocessError):
        pass
    # a copy of the working tree whose .git is not the code's (a GPU machine's) names it so
    commit = os.environ.get("MI_TWOPASS_GIT_COMMIT") or commit
    return {"variant": mi.variant(), "mitsuba": mi.__version__, "drjit": dr.__version__,
            "git_commit": commit}


def command_line(argv) -> str:
    """The command as typed: ``python -m mi_twopass`` and the arguments, shell-quoted."""
    return "python -m mi_twopass " + shlex.join(list(argv))


# -- the table's numbers -----------------------------------------------------------------------

def path_relmse_at_spp(path_points, spp: int):
    """(relMSE of ``path`` at ``spp``, extrapolated?): log-log interpolation between path's
    points; beyond them path's nearest point scaled by its spp / ``spp`` (an unbiased
    estimator's relMSE falls as 1/spp), marked extrapolated. (None, False) without points."""
    pts = [p for p in path_points if p.relmse > 0]
    if not pts:
        return None, False
    for p in pts:
        if p.spp == spp:
            return p.relmse, False
    value = harness._loglog_interp([p.spp for p in pts], [p.relmse for p in pts], spp)
    if value is not None:
        return value, False
    end = pts[-1] if spp > pts[-1].spp else pts[0]
    return end.relmse * end.spp / spp, True


#: a reference whose own relMSE is above this share of the target is marked in results.md:
#: every curve's error then carries a floor of that size, and times to the target stretch
REFERENCE_NOISE_SHARE = 0.25


def reference_relmse(path_points, ref_spp: int):
    """The reference's own relMSE, estimated from ``path``'s curve: the reference is ``path``
    at ``ref_spp``, independent of the curve's renders, so path's error at ``spp`` is about
    c·(1/spp + 1/ref_spp) (two unbiased estimates, each of variance c/spp against the truth),
    and the reference's share is c/ref_spp. c is the median over path's points of
    relMSE / (1/spp + 1/ref_spp) (the median: one firefly-struck point does not move it).
    Every integrator's relMSE carries that floor; where it is a large part of the target
    (many_lights at 256², ref 2048 spp: 6e-3 of 0.01) no curve reaches the target in time,
    and a larger ``--ref-spp`` is the fix. None without points."""
    pts = [p for p in path_points if p.relmse > 0 and p.spp > 0]
    if not pts or ref_spp <= 0:
        return None
    c = float(np.median([p.relmse / (1.0 / p.spp + 1.0 / ref_spp) for p in pts]))
    return c / ref_spp


def equal_spp_ratio(path_points, points):
    """(path's relMSE over the method's at the method's largest spp, path interpolated there;
    extrapolated?) — per-sample quality, free of either implementation's speed."""
    if not points or points[-1].relmse <= 0:
        return None, False
    base, extrapolated = path_relmse_at_spp(path_points, points[-1].spp)
    return (None if base is None else base / points[-1].relmse), extrapolated


def prepass_share(point):
    """The prepass's share of the point's time (``prepass_seconds`` / seconds); None when the
    integrator reports no prepass (Mitsuba's ``path``)."""
    pre = point.stats.get("prepass_seconds")
    if pre is None or point.seconds <= 0:
        return None
    return float(pre) / point.seconds


def rays_per_viewing_ray(point):
    """(implicit + explicit + viewing rays) / viewing rays of the point's render; None when
    the integrator does not count them."""
    s = point.stats
    if not all(k in s for k in ("implicit_rays", "explicit_rays", "viewing_rays")):
        return None
    if not s["viewing_rays"]:
        return None
    return (s["implicit_rays"] + s["explicit_rays"] + s["viewing_rays"]) / s["viewing_rays"]


def table_row(scene_label: str, curve, path_curve) -> dict:
    """One row of results.md (raw numbers, None where not measured) from a summarised curve and
    path's curve of the same scene."""
    s = curve.summary
    last = curve.points[-1]
    ratio, extrapolated = equal_spp_ratio(path_curve.points if path_curve else [], curve.points)
    return {
        "scene": scene_label, "integrator": curve.label,
        "time_to_target": s.get("time_to_target"),
        "speedup": s.get("speedup_to_target"),
        "equal_time_ratio": s.get("equal_time_ratio"),
        "equal_spp_ratio": ratio, "equal_spp_extrapolated": extrapolated,
        "final_relmse": last.relmse, "final_spp": last.spp, "final_seconds": last.seconds,
        "prepass_share": prepass_share(last),
        "rays_per_viewing_ray": rays_per_viewing_ray(last),
        "twopass_choice": last.stats.get("twopass_choice"),
        "failed": None,
    }


def failed_row(scene_label: str, spec: str, why: str) -> dict:
    """A row for an integrator that refused the scene or failed: only ``failed`` is set."""
    row = {k: None for k in ("time_to_target", "speedup", "equal_time_ratio", "equal_spp_ratio",
                             "final_relmse", "final_spp", "final_seconds", "prepass_share",
                             "rays_per_viewing_ray", "twopass_choice")}
    row.update(scene=scene_label, integrator=spec, equal_spp_extrapolated=False, failed=why)
    return row


def format_row(row: dict) -> str:
    """One Markdown table line for :func:`table_row`'s dict."""
    if row["failed"]:
        cells = [row["scene"], f"`{row['integrator']}`", f"{row['failed']}"] + \
            ["—"] * (len(COLUMNS) - 3)
        return table_line(cells)
    tte = row["time_to_target"]
    spp_ratio = num(row["equal_spp_ratio"], ".2f")
    if row["equal_spp_extrapolated"] and row["equal_spp_ratio"] is not None:
        spp_ratio = "≈" + spp_ratio
    share = row["prepass_share"]
    cells = [
        row["scene"], f"`{row['integrator']}`",
        "not reached" if tte is None else f"{tte:.3g}",
        num(row["speedup"], ".2f"),
        num(row["equal_time_ratio"], ".2f"),
        spp_ratio,
        f"{row['final_relmse']:.2e} ({row['final_spp']} spp)",
        "—" if share is None else f"{100 * share:.0f} %",
        num(row["rays_per_viewing_ray"], ".2f"),
        row["twopass_choice"] or "",
    ]
    return table_line(cells)


def reference_notes(reference_noise: dict, target: float = harness.TARGET_RELMSE) -> list:
    """results.md lines on each scene's reference noise (:func:`reference_relmse`):
    ``{scene label: (relMSE or None, ref_spp)}``; a scene whose reference takes more than
    :data:`REFERENCE_NOISE_SHARE` of the target is marked."""
    lines = []
    for label, (value, ref_spp) in reference_noise.items():
        if value is None:
            continue
        share = value / target
        mark = " — **reference-limited**: raise `--ref-spp`" \
            if share > REFERENCE_NOISE_SHARE else ""
        lines.append(f"- {label}: the reference ({ref_spp} spp) has relMSE ≈ {value:.1e}, "
                     f"{100 * share:.0f} % of the target{mark}")
    if not lines:
        return []
    return ["", "Reference noise (estimated from `path`'s curve, `bench.reference_relmse`; "
                "every curve's relMSE carries it):", *lines]


def format_results(rows, header: str, reference_noise: dict | None = None) -> str:
    """results.md: the header line, one table over all rows, what each column means, and
    each scene's reference noise (``{scene label: (relMSE, ref_spp)}``)."""
    return markdown_report(header, COLUMNS, [format_row(r) for r in rows], [
        "- **t(relMSE 0.01)**: seconds (prepass included) to reach relMSE 0.01, log-log "
        "interpolated between the bracketing points; *not reached* within the budget.",
        "- **speed-up vs path**: path's t(relMSE 0.01) over the integrator's (— where either "
        "was not reached).",
        "- **equal-time ratio**: path's relMSE at the integrator's time (interpolated, at its "
        "last point inside path's range) over the integrator's; > 1: better than path.",
        "- **equal-spp ratio**: path's relMSE at the integrator's largest spp (interpolated; ≈: "
        "extrapolated as 1/spp from path's nearest point) over the integrator's.",
        "- **relMSE @ max spp**: error at the largest spp reached, an upper bound of the bias "
        "floor.",
        "- **prepass share**: prepass seconds over the point's seconds at the largest spp.",
        "- **rays / viewing ray**: (implicit + explicit + viewing rays) / viewing rays at the "
        "largest spp; — where the integrator does not count them (Mitsuba's path).",
        "- **twopass chose**: the composition twopass rendered with at the largest spp.",
    ] + reference_notes(reference_noise or {}))


# -- images ------------------------------------------------------------------------------------

def flip_map(image, reference) -> np.ndarray:
    """FLIP error map (H, W) in [0, 1] of ``image`` against ``reference`` (HDR-FLIP, inputs
    prepared as :func:`mi_twopass.evaluation.metrics.flip` prepares them)."""
    import flip_evaluator

    def prep(x):
        x = np.asarray(x, dtype=np.float64)[..., :3]
        return np.nan_to_num(np.maximum(x, 0), nan=0.0, posinf=0.0).astype(np.float32)

    error, _, _ = flip_evaluator.evaluate(prep(reference), prep(image), "HDR", applyMagma=False)
    return np.asarray(error, dtype=np.float32).reshape(error.shape[0], error.shape[1])


def auto_exposure(reference) -> float:
    """Stops that put the reference's 95th-percentile channel value at 0.8, in half stops
    within ±6 (0 for a black reference): one exposure for every tile of a scene's strip."""
    ref = np.nan_to_num(np.asarray(reference, dtype=np.float64))
    p = float(np.percentile(ref, 95)) if ref.size else 0.0
    if p <= 0:
        return 0.0
    return float(np.clip(round(2 * math.log2(0.8 / p)) / 2, -6, 6))


def write_image_strip(path, reference, ref_label: str, tiles, title: str = "") -> None:
    """The reference, then per integrator its image with its FLIP map beneath.

    ``tiles``: list of (label, image or None, caption); a None image (refused, failed) leaves
    its column with the caption only."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    exposure = auto_exposure(reference)
    n = 1 + len(tiles)
    fig, axes = plt.subplots(2, n, figsize=(2.3 * n, 5.0), dpi=110, squeeze=False,
                             layout="constrained")
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    axes[0, 0].imshow(srgb_tonemap(reference, exposure), interpolation="nearest")
    axes[0, 0].set_title(ref_label, fontsize=7)
    axes[1, 0].axis("off")
    shown = None
    for k, (label, image, caption) in enumerate(tiles, start=1):
        axes[0, k].set_title(label, fontsize=7)
        if image is None:
            axes[0, k].text(0.5, 0.5, textwrap.fill(caption, 30), ha="center", va="center",
                            fontsize=6, transform=axes[0, k].transAxes)
            axes[1, k].axis("off")
            continue
        err = flip_map(image, reference)
        axes[0, k].imshow(srgb_tonemap(image, exposure), interpolation="nearest")
        axes[0, k].set_xlabel(caption, fontsize=6)
        shown = axes[1, k].imshow(err, cmap="magma", vmin=0.0, vmax=1.0, interpolation="nearest")
        axes[1, k].set_xlabel(f"FLIP mean {float(err.mean()):.4f}", fontsize=7)
    if shown is not None:
        fig.colorbar(shown, ax=axes[1, 0], location="left", fraction=0.5, label="FLIP error")
    fig.suptitle(f"{title}  (exposure {exposure:+.1f} stops)", fontsize=8)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


# -- the run -----------------------------------------------------------------------------------

def scene_settings(scene_path, res: int, params: dict):
    """(params, film_res) for one scene: ``res`` as ``-D res=PX`` where the scene declares
    ``$res`` (a ``-D res`` of the command line wins), else as the film's longer side."""
    params = dict(params)
    if has_res_parameter(scene_path):
        params.setdefault("res", res)
        return params, None
    return params, res


def bench_scene(scene_path, name: str, specs, budget: float, res: int, params: dict,
                ref_spp: int, seed: int, out_dir: str, counter, log=print, detail=None,
                repeats: int = 1, repeat_below: float = harness.REPEAT_BELOW_SECONDS) -> dict:
    """Run every integrator on one scene; write ``<name>.json``, ``<name>.png`` and
    ``<name>_images.png``; return the scene's entry of bench.json (curves, rows, files).
    ``repeats``, ``repeat_below``: short points timed more than once
    (:func:`mi_twopass.evaluation.harness.timed_point`).

    An integrator that refuses the scene (or fails) gets a row saying so and the run goes on;
    ``counter``: [done, total] of (scene, integrator) pairs, for the progress lines."""
    from .reference import reference_image

    detail = detail or (lambda *_: None)
    params, film_res = scene_settings(scene_path, res, params)
    images = {}

    def keep_image(spec, curve, image):  # the render at the largest spp, for the strip
        images[spec] = image

    curves, failures, walls, baseline = run_integrators(
        scene_path, specs, name, budget, params, ref_spp, seed, counter, log, detail,
        film_res=film_res, on_curve=keep_image, repeats=repeats, repeat_below=repeat_below)
    reference = reference_image(scene_path, params, spp=ref_spp, film_res=film_res)
    h, w = reference.shape[:2]
    label = f"{name} ({w}×{h})"
    rows = []
    for spec in specs:
        if spec in curves:
            rows.append(table_row(label, curves[spec], curves.get(baseline)))
        else:
            rows.append(failed_row(label, spec, failures[spec]))
    ref_noise = reference_relmse(curves[baseline].points, ref_spp) if baseline in curves \
        else None
    if ref_noise is not None:
        log(f"  reference's own relMSE ≈ {ref_noise:.1e} ({ref_spp} spp, from path's curve)")
    meta = {"scene": os.fspath(scene_path), "params": params, "film_res": film_res,
            "budget": budget, "ref_spp": ref_spp, "seed": seed,
            "reference_relmse": ref_noise, "label": label}
    files = {"json": f"{name}.json", "plot": f"{name}.png", "images": f"{name}_images.png"}
    harness.write_json(curves, os.path.join(out_dir, files["json"]), meta=meta)
    harness.write_plot(curves, os.path.join(out_dir, files["plot"]),
                       title=f"{name} {w}×{h}, budget {budget:g} s per integrator")
    tiles = []
    for spec in specs:
        if spec in curves:
            p = curves[spec].points[-1]
            tiles.append((spec, images[spec], f"{p.spp} spp, {p.seconds:.2f} s, "
                                              f"relMSE {p.relmse:.2e}"))
        else:
            tiles.append((spec, None, failures[spec]))
    write_image_strip(os.path.join(out_dir, files["images"]), reference,
                      f"reference: path, {ref_spp} spp", tiles, title=f"{name} {w}×{h}")
    return {**meta, "name": name, "size": [w, h], "files": files, "rows": rows,
            "wall_seconds": walls, "failed": failures,
            "curves": {k: asdict(c) for k, c in curves.items()}}


def run_bench(scenes, specs, budget: float = DEFAULT_BUDGET, res: int = DEFAULT_RES,
              params: dict | None = None, ref_spp: int | None = None, seed: int = 0,
              out_dir: str = DEFAULT_OUTPUT_DIR, argv=(), log=print, repeats: int = 1,
              repeat_below: float = harness.REPEAT_BELOW_SECONDS) -> dict:
    """Run the bench (module docstring) and write its files into ``out_dir``; returns the
    content of bench.json. ``specs`` should start with ``path`` (the baseline); ``repeats``,
    ``repeat_below``: short points timed more than once
    (:func:`mi_twopass.evaluation.harness.timed_point`; the command's default is
    :data:`~mi_twopass.evaluation.harness.DEFAULT_REPEATS`)."""
    from .reference import DEFAULT_REFERENCE_SPP

    ref_spp = ref_spp or DEFAULT_REFERENCE_SPP
    params = dict(params or {})
    os.makedirs(out_dir, exist_ok=True)
    names = scene_names(scenes)
    started = datetime.datetime.now().astimezone()
    info = {"machine": machine_info(), "date": started.isoformat(timespec="seconds"),
            "command": command_line(argv), "cwd": os.getcwd(), "python": sys.executable,
            **software_info(), "budget": budget, "res": res, "defines": params,
            "ref_spp": ref_spp, "seed": seed, "integrators": list(specs),
            "repeats": repeats, "repeat_below": repeat_below,
            "cache": os.environ.get("MI_TWOPASS_CACHE") or "(default: .cache/references)"}
    m = info["machine"]
    log(f"bench: {len(scenes)} scenes × {len(specs)} integrators, budget {budget:g} s each, "
        f"res {res}, references {ref_spp} spp; at most about "
        f"{_duration(estimate_seconds(len(scenes), len(specs), budget, references=False))} "
        f"+ uncached references, on {machine_label(m)}")
    counter = [0, len(scenes) * len(specs)]
    t0 = time.perf_counter()
    entries = {}
    with open(os.path.join(out_dir, "bench.log"), "w") as logfile:
        def detail(line):
            logfile.write(line + "\n")
            logfile.flush()

        detail(info["command"])
        for path, name in zip(scenes, names):
            detail(f"{name}: {path}")
            entries[name] = bench_scene(path, name, specs, budget, res, params, ref_spp, seed,
                                        out_dir, counter, log=log, detail=detail,
                                        repeats=repeats, repeat_below=repeat_below)
            # rewritten after every scene: a run stopped early leaves the table of what it did
            write_report(out_dir, info, entries, time.perf_counter() - t0, len(scenes))
    log(f"wrote {out_dir}/results.md, bench.json, bench.log and per scene <scene>.json, "
        f"<scene>.png, <scene>_images.png ({_duration(info['wall_seconds'])})")
    return info


def write_report(out_dir: str, info: dict, entries: dict, wall_seconds: float,
                 n_scenes: int):
    """Write ``bench.json`` and ``results.md`` for the scenes in ``entries`` (``info`` gains
    ``wall_seconds``, ``scenes`` and ``complete``); while fewer than ``n_scenes`` are done the
    table's first line says it is partial."""
    done = len(entries) >= n_scenes
    info["wall_seconds"] = wall_seconds
    info["scenes"] = entries
    info["complete"] = done
    with open(os.path.join(out_dir, "bench.json"), "w") as f:
        json.dump(info, f, indent=1, default=_json_default)
    state = "took" if done else f"partial: {len(entries)} of {n_scenes} scenes in"
    repeats = info.get("repeats", 1)
    timing = (f" Points under {info.get('repeat_below', harness.REPEAT_BELOW_SECONDS):g} s: "
              f"median of {repeats} runs, each run's image with its time." if repeats > 1 else "")
    header = (f"Bench of {run_label(info)}; {state} {_duration(wall_seconds)}.{timing} "
              f"Command: `{info['command']}`")
    rows = [r for e in entries.values() for r in e["rows"]]
    with open(os.path.join(out_dir, "results.md"), "w") as f:
        f.write(format_results(rows, header, {
            e["label"]: (e["reference_relmse"], e["ref_spp"]) for e in entries.values()}))


def _duration(seconds: float) -> str:
    """``42 s`` under two minutes, else ``22.5 min``."""
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def _json_default(v):
    """numpy numbers and arrays, and anything else as its string."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    try:
        return float(v)
    except (TypeError, ValueError):
        return str(v)
