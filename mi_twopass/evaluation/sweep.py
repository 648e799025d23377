"""``python -m mi_twopass bench --sweep 64,128,256,512,1024``: does a prepass amortise as the
image grows?

The papers' argument for a two-pass method is that its prepass costs about the same at every
image size while the render's cost grows with the pixels, so its speed-up over ``path`` should
grow with the image. This runs the harness (:func:`mi_twopass.evaluation.harness.run_compare`:
doubling spp, a fresh integrator and its prepass per point, ``path`` measured in the same run)
on each scene at each film size and plots the speed-up against the image's pixels.

Defaults: the scenes of :data:`HOME_INTEGRATORS` (many_lights, caustic, window_interior), each
with ``path``, its home integrator (the suite's method made for it) and ``twopass``.

Speed-up. ``path``'s time to relMSE 0.01 over the method's (prepass included), as the bench.
Where either did not reach 0.01 within its budget, the point is drawn hollow at the equal-time
relMSE ratio instead (path's relMSE at the method's time, interpolated log-log, over the
method's): for unbiased methods whose relMSE falls as 1/time that is the same number, and it is
measured at every size. Where the method's first point already lies beyond path's whole curve
(a prepass longer than path's budget, at small sizes), path's relMSE there is extrapolated from
its last point as falling as 1/time above the reference floor (``≈`` in the table, hollow in
the figure). A point with none of these is left out (its table cell says ``—``).

Budget, scaled with the film's side (pixels^0.5): ``--budget`` is the seconds per (scene,
integrator) at 128², and a size of ``res`` gets ``budget × res / 128``. Why: a flat budget
leaves 1024² a handful of spp (``path`` on many_lights costs about 0.3 s per spp there), so the
large sizes would compare prepasses with 1-4 spp renders; a budget ∝ pixels keeps the spp
reached but costs 64× at 1024² (10 s becomes 11 min per run). ∝ pixels^0.5 is between: the
spp reached halves per doubling of the side, and a sweep 64…1024 costs 15.5 runs at 128².

Reference, scaled the same way: ``--ref-spp`` is the reference's spp at 128² and a size of
``res`` gets ``ref_spp × 128 / res`` (at least :data:`MIN_REF_SPP`), so its cost also grows as
the side (``path`` at 4096 spp and 1024² would take ~40 min per scene). Its noise sets a floor
under every relMSE measured against it; with both rules the floor grows with the side as the
errors reached at the end of the budgets do, so its share of them is the same at every size.
The floor is estimated from ``path``'s own curve (:func:`reference_floor`: path is the
reference's estimator, its relMSE falls as 1/spp) and printed per size; rows where it exceeds
:data:`FLOOR_WARNING` of the target are flagged, and the table gives the equal-time ratio with
the floor taken off both errors beside the raw one.

Written into the output folder: ``sweep.json`` (machine, versions, command, rules, and per
(scene, size) the curves and rows), ``sweep.png`` (speed-up against pixels, log-log, one line
per (scene, integrator)), ``sweep.md`` (:data:`COLUMNS`) and ``sweep.log`` (every point).

Run time of the default (3 scenes × 3 integrators × 64…1024, budget 10 s, reference 2048 spp at
128², references not cached; :func:`estimate_seconds`): the budgets 9 × 10 s × (0.5 + 1 + 2 +
4 + 8) = 1395 s; the warm-ups and metrics, :func:`overhead_seconds` per run, 9 × (4 + 4 + 6.1 +
14.5 + 48.1) s = 690 s; the references 3 × 15 s × (0.5 + 1 + 2 + 4 + 8) = 698 s (15 s: a 128²
reference at 2048 spp, half the bench's 30 s at 4096; the three took 19, 12 and 24 s at 4096
spp). Together 2783 s ≈ 46 min on an idle 2-core machine. The metrics are most of the
overhead at the large sizes: the harness computes HDR-FLIP for every point, about 0.07 s per
128² of image (4.5 s per point at 1024², 8-17 s measured on a machine loaded twice over).
"""
from __future__ import annotations

import datetime
import json
import math
import os
import sys
import time
from dataclasses import asdict

from . import harness
from .runs import markdown_report, num, run_integrators, table_line
from .bench import (CORPUS_DIR, OVERHEAD_SECONDS, REFERENCE_SECONDS_PER_SCENE, _duration,
                    _json_default, command_line, machine_info, machine_label, run_label,
                    scene_names,
                    scene_settings, software_info, table_row as bench_row)

#: the sweep's scenes and, per scene (file stem), the suite's integrator made for it
HOME_INTEGRATORS = {"many_lights": "spike_gather", "caustic": "rex",
                    "window_interior": "radiance_cache"}
DEFAULT_SCENES = tuple(os.path.join(CORPUS_DIR, f"{stem}.xml") for stem in HOME_INTEGRATORS)
DEFAULT_SIZES = (64, 128, 256, 512, 1024)
#: the size the budget and the reference's spp are given at
BASE_RES = 128
#: seconds per (scene, integrator) at 128² (module docstring for the arithmetic)
DEFAULT_BUDGET = 10.0
#: the reference's spp at 128²
DEFAULT_REF_SPP = 2048
MIN_REF_SPP = 16
#: the harness's spp stop at most this many lanes (pixels × spp) per render: a mi_twopass
#: render holds a few numbers per lane (spike_gather's radiance and ray counts: 24 bytes, 3 GB)
MAX_LANES = 1 << 27
#: a reference floor above this share of the target is flagged in the table
FLOOR_WARNING = 0.25
TARGET = harness.TARGET_RELMSE
#: sweep.md's columns, in order
COLUMNS = ("scene", "size", "pixels", "integrator", "budget s", "ref spp", "ref floor",
           "t(relMSE 0.01) s", "path t(0.01) s", "speed-up", "from", "equal-time ratio",
           "floor-removed ratio", "relMSE @ max spp", "prepass share")


# -- the rules ---------------------------------------------------------------------------------

def parse_sizes(text: str) -> list:
    """``"64,128,256"`` → [64, 128, 256]: film sizes in pixels, sorted, each once; ValueError
    for anything that is not a whole number ≥ 1."""
    sizes = set()
    for item in str(text).split(","):
        item = item.strip()
        if not item:
            continue
        if not item.isdigit() or int(item) < 1:
            raise ValueError(f"{item!r} is not a film size in pixels (a whole number >= 1)")
        sizes.add(int(item))
    if not sizes:
        raise ValueError("no film sizes")
    return sorted(sizes)


def home_integrator(scene_path):
    """The suite's integrator made for the scene (:data:`HOME_INTEGRATORS`, by file stem), or
    None."""
    return HOME_INTEGRATORS.get(os.path.splitext(os.path.basename(scene_path))[0])


def default_specs(scene_path) -> list:
    """``path``, the scene's home integrator (if it has one) and ``twopass``."""
    specs = ["path"]
    for spec in (home_integrator(scene_path), "twopass"):
        if spec and spec not in specs:
            specs.append(spec)
    return specs


def size_factor(res: int) -> float:
    """The film's side over :data:`BASE_RES` (pixels^0.5, relative): what the budget and the
    reference's cost are scaled by."""
    return res / BASE_RES


def point_budget(budget: float, res: int) -> float:
    """Seconds per (scene, integrator) at size ``res``: ``budget`` (given at 128²) × res / 128."""
    return budget * size_factor(res)


def reference_spp(ref_spp: int, res: int) -> int:
    """The reference's spp at size ``res``: ``ref_spp`` (given at 128²) × 128 / res, rounded,
    at least :data:`MIN_REF_SPP` (or ``ref_spp`` itself where that is smaller)."""
    return max(min(MIN_REF_SPP, ref_spp), int(round(ref_spp / size_factor(res))))


def max_spp(pixels: int) -> int:
    """The largest power of two with pixels × spp ≤ :data:`MAX_LANES` (at least 1)."""
    return 1 << max(0, int(math.floor(math.log2(max(1, MAX_LANES // max(1, pixels))))))


def overhead_seconds(res: int) -> float:
    """Per (scene, size, integrator), beyond its budget: the untimed 1-spp warm-up (prepass
    included) and relMSE + FLIP per point; :data:`~mi_twopass.evaluation.bench.OVERHEAD_SECONDS`
    up to 128², then 0.7 s more per further 128² of image (FLIP ≈ 0.07 s per point per 128²,
    about 10 points, and a 1-spp render and prepasses that look through the camera)."""
    pixels = (res / BASE_RES) ** 2
    return OVERHEAD_SECONDS + 0.7 * max(0.0, pixels - 1.0)


def estimate_seconds(n_runs_per_size: int, sizes, budget: float, ref_spp: int,
                     n_scenes: int, references: bool = True) -> float:
    """Upper estimate of a sweep's wall time: per size, ``n_runs_per_size`` (scene, integrator)
    runs of :func:`point_budget` + :func:`overhead_seconds`, plus (``references``: not cached)
    per scene the reference, :data:`~mi_twopass.evaluation.bench.REFERENCE_SECONDS_PER_SCENE`
    at 128² and 4096 spp scaled by its spp and pixels."""
    total = 0.0
    for res in sizes:
        total += n_runs_per_size * (point_budget(budget, res) + overhead_seconds(res))
        if references:
            total += (n_scenes * REFERENCE_SECONDS_PER_SCENE * reference_spp(ref_spp, res)
                      / 4096 * size_factor(res) ** 2)
    return total


# -- the numbers -------------------------------------------------------------------------------

def reference_floor(path_points, ref_spp: int):
    """Estimated relMSE of the reference itself, which every measured relMSE includes.

    The reference is ``path`` at ``ref_spp``: with path's true relMSE c / spp, a path point
    measures about c / spp + c / ref_spp, so c = relMSE × spp × ref_spp / (spp + ref_spp) and
    the floor c / ref_spp = relMSE × spp / (spp + ref_spp); the median over path's points.
    None without points."""
    values = sorted(p.relmse * p.spp / (p.spp + ref_spp) for p in path_points
                    if p.relmse > 0 and p.spp > 0)
    if not values:
        return None
    mid = len(values) // 2
    return values[mid] if len(values) % 2 else 0.5 * (values[mid - 1] + values[mid])


def extrapolated_path_relmse(path_points, seconds: float, floor=None):
    """path's relMSE at ``seconds`` outside its measured time range: from its nearest point,
    the part above the reference floor falling as 1 / time (path is unbiased), the floor
    kept; None without points."""
    pts = [p for p in path_points if p.relmse > 0 and p.seconds > 0]
    if not pts:
        return None
    end = max(pts, key=lambda p: p.seconds) if seconds > pts[-1].seconds else \
        min(pts, key=lambda p: p.seconds)
    f = min(floor or 0.0, end.relmse)
    return f + (end.relmse - f) * end.seconds / seconds


def equal_time_errors(points, path_points, floor=None):
    """(time, path's relMSE there, the method's, extrapolated?) at the method's last point
    inside path's time range (as :func:`mi_twopass.evaluation.harness.summarise`'s equal-time
    ratio); where no point is inside it (a prepass longer than path's whole curve, at small
    sizes), at the method's last point with path's relMSE extrapolated
    (:func:`extrapolated_path_relmse`). None without points."""
    base_t = [p.seconds for p in path_points]
    base_e = [p.relmse for p in path_points]
    found = None
    for p in points:
        e = harness._loglog_interp(base_t, base_e, p.seconds)
        if e is not None and p.relmse > 0:
            found = (p.seconds, e, p.relmse, False)
    if found is None and points and points[-1].relmse > 0:
        last = points[-1]
        e = extrapolated_path_relmse(path_points, last.seconds, floor)
        if e is not None:
            found = (last.seconds, e, last.relmse, True)
    return found


def floor_removed_ratio(points, path_points, floor):
    """The equal-time ratio with the reference floor taken off both errors:
    (path's − floor) / (method's − floor); None where either is not above the floor."""
    got = equal_time_errors(points, path_points, floor)
    if got is None or floor is None:
        return None
    _, base, own, _ = got
    if base <= floor or own <= floor:
        return None
    return (base - floor) / (own - floor)


def plotted_speedup(row: dict):
    """(value, ``"t(0.01)"`` | ``"equal-time"`` | ``"equal-time≈"``) of a row (module
    docstring), or (None, None)."""
    if row.get("speedup") is not None:
        return row["speedup"], "t(0.01)"
    if row.get("equal_time_ratio") is not None:
        return row["equal_time_ratio"], ("equal-time≈" if row.get("equal_time_extrapolated")
                                         else "equal-time")
    return None, None


def sweep_row(scene: str, res: int, size, spec: str, curve, path_curve, budget: float,
              ref_spp: int, floor, failed: str | None = None) -> dict:
    """One row of sweep.md: the bench's row (:func:`mi_twopass.evaluation.bench.table_row`)
    plus the size, the budget, the reference, path's t(0.01), the plotted speed-up and the
    floor-removed ratio."""
    w, h = size
    if curve is None:
        row = {k: None for k in ("time_to_target", "speedup", "equal_time_ratio",
                                 "final_relmse", "final_spp", "prepass_share")}
        row.update(scene=scene, integrator=spec, failed=failed)
    else:
        row = bench_row(scene, curve, path_curve)
    path_points = path_curve.points if path_curve is not None else []
    row["equal_time_extrapolated"] = False
    if curve is not None and row["equal_time_ratio"] is None and path_points:
        got = equal_time_errors(curve.points, path_points, floor)
        if got is not None:
            row["equal_time_ratio"] = got[1] / got[2]
            row["equal_time_extrapolated"] = got[3]
    row.update(res=res, width=w, height=h, pixels=w * h, budget=budget, ref_spp=ref_spp,
               ref_floor=floor,
               path_time_to_target=(harness.time_to_error(path_points) if path_points
                                    else None),
               floor_removed_ratio=(floor_removed_ratio(curve.points, path_points, floor)
                                    if curve is not None else None))
    row["plotted"], row["plotted_from"] = plotted_speedup(row)
    return row


def _ratio(v) -> str:
    """A ratio to two decimals, or two significant digits below 0.1."""
    return num(v, ".2f" if v is None or abs(v) >= 0.1 else ".2g")


def format_row(row: dict) -> str:
    """One Markdown line of :func:`sweep_row`'s dict."""
    floor = row["ref_floor"]
    floor_cell = num(floor, ".1e")
    if floor is not None and floor > FLOOR_WARNING * TARGET:
        floor_cell += " ⚠"
    head = [row["scene"], f"{row['width']}×{row['height']}", str(row["pixels"]),
            f"`{row['integrator']}`", f"{row['budget']:.3g}", str(row["ref_spp"]), floor_cell]
    if row["failed"]:
        cells = head + [row["failed"]] + ["—"] * (len(COLUMNS) - len(head) - 1)
    else:
        tte = row["time_to_target"]
        share = row["prepass_share"]
        cells = head + [
            "not reached" if tte is None else f"{tte:.3g}",
            num(row["path_time_to_target"], ".3g"),
            _ratio(row["plotted"]),
            row["plotted_from"] or "—",
            ("≈" if row["equal_time_extrapolated"] and row["equal_time_ratio"] is not None
             else "") + _ratio(row["equal_time_ratio"]),
            _ratio(row["floor_removed_ratio"]),
            f"{row['final_relmse']:.2e} ({row['final_spp']} spp)",
            "—" if share is None else f"{100 * share:.0f} %",
        ]
    return table_line(cells)


def format_table(rows, header: str) -> str:
    """sweep.md: the header, one table over every (scene, size, integrator) and what each
    column means."""
    return markdown_report(header, COLUMNS, [format_row(r) for r in rows], [
        f"- **budget s**: seconds per (scene, integrator) at this size: the 128² budget × "
        f"side / {BASE_RES} (module docstring of mi_twopass/evaluation/sweep.py: why).",
        f"- **ref spp**: the reference's spp (path): the 128² value × {BASE_RES} / side.",
        "- **ref floor**: the reference's own relMSE, estimated from path's curve (path's "
        "relMSE × spp / (spp + ref spp), median over its points). Every relMSE here includes "
        f"about this much, so t(0.01) is overstated, and unreachable where the floor nears "
        f"0.01; ⚠: above {FLOOR_WARNING:.0%} of the target.",
        "- **t(relMSE 0.01) s**: seconds (prepass included) to relMSE 0.01, log-log "
        "interpolated; *not reached* within the budget. **path t(0.01) s**: the same for path.",
        "- **speed-up** (what sweep.png plots): path's t(0.01) over the integrator's where both "
        "were reached (*from* t(0.01), a filled marker), else the equal-time ratio (*from* "
        "equal-time, a hollow marker); — where neither was measured (left out of the plot).",
        "- **equal-time ratio**: path's relMSE at the integrator's time (log-log interpolated, "
        "at its last point inside path's time range) over the integrator's; > 1: better. "
        "≈ (*from* equal-time≈): no point inside path's range (the prepass alone outlasts "
        "path's curve), path's relMSE extrapolated from its last point as 1/time above the "
        "floor.",
        "- **floor-removed ratio**: the same with the reference floor taken off both errors "
        "(— where either is not above it): the ratio a noiseless reference would show.",
        "- **relMSE @ max spp**: error at the largest spp reached (an upper bound of the bias "
        "floor, the reference's included). **prepass share**: prepass seconds over the point's "
        "at that spp.",
    ])


# -- the figure --------------------------------------------------------------------------------

def write_figure(rows, path: str, title: str = "") -> None:
    """sweep.png: speed-up over path against the image's pixels (log-log), one line per
    (scene, integrator): filled markers where it is path's t(0.01) over the integrator's,
    hollow at the equal-time relMSE ratio where a t(0.01) is missing; points with neither are
    left out. Colour: the scene; marker and line style: the integrator; path is the line at 1."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    specs = list(dict.fromkeys(r["integrator"] for r in rows
                               if r["integrator"].split(":")[0] != "path"))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    markers, styles = "os^Dvp*h", ["-", "--", "-.", ":"]
    fig, ax = plt.subplots(figsize=(7.5, 4.8), dpi=120)
    ax.axhline(1.0, color="gray", lw=1.2, label="path (the baseline)")
    for i, scene in enumerate(scenes):
        for j, spec in enumerate(specs):
            pts = sorted((r["pixels"], r["plotted"], r["plotted_from"]) for r in rows
                         if r["scene"] == scene and r["integrator"] == spec
                         and r["plotted"] is not None and r["plotted"] > 0)
            if not pts:
                continue
            colour, marker = colours[i % len(colours)], markers[j % len(markers)]
            ax.plot([p[0] for p in pts], [p[1] for p in pts], ls=styles[j % len(styles)],
                    color=colour, lw=1.3, marker=marker, ms=7, mew=1.4,
                    label=f"{scene} · {spec}")
            hollow = [p for p in pts if p[2] != "t(0.01)"]
            ax.plot([p[0] for p in hollow], [p[1] for p in hollow], marker=marker, ms=7,
                    color=colour, mew=1.4, mfc="white", ls="none")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    sizes = sorted({(r["pixels"], r["width"], r["height"]) for r in rows})
    ax.set_xlim(sizes[0][0] / 1.5, sizes[-1][0] * 1.5)
    ax.set_xticks([s[0] for s in sizes])
    ax.set_xticklabels([f"{w}×{h}" for _, w, h in sizes], fontsize=8)
    ax.minorticks_off()
    ax.set_xlabel("image size (pixels, log scale)")
    ax.set_ylabel("speed-up over path (log)")
    ax.set_title(title, fontsize=8)
    ax.grid(True, which="major", alpha=0.3)
    filled = plt.Line2D([], [], marker="o", color="k", ls="none",
                        label="filled: path's t(relMSE 0.01) / the method's")
    hollow = plt.Line2D([], [], marker="o", color="k", mfc="white", ls="none",
                        label="hollow: equal-time relMSE ratio (a t(0.01) not reached;\n"
                              "path extrapolated as 1/time where the method's first point\n"
                              "comes after path's last)")
    missing = plt.Line2D([], [], ls="none",
                         label="no marker: neither measured (— in sweep.md), left out")
    handles, _ = ax.get_legend_handles_labels()
    ax.legend(handles=handles + [filled, hollow, missing], fontsize=7, loc="center left",
              bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


# -- the run -----------------------------------------------------------------------------------

def reference_seconds(scene_path, params: dict, spp: int, film_res):
    """Seconds the cached reference took to render (its cache entry's JSON), or None."""
    from .reference import default_cache_dir, reference_key

    meta = os.path.join(default_cache_dir(),
                        reference_key(scene_path, params, spp, 0, film_res) + ".json")
    try:
        with open(meta) as f:
            return json.load(f).get("seconds")
    except (OSError, ValueError):
        return None


def sweep_point(scene_path, name: str, res: int, specs, budget: float, ref_spp: int,
                params: dict, seed: int, counter, log=print, detail=None) -> dict:
    """Every integrator of ``specs`` on one scene at one size (budget and reference spp
    already scaled): the curves, the reference floor and the rows. An integrator that
    refuses the scene or fails gets a row saying so and the run goes on."""
    from .reference import reference_image

    detail = detail or (lambda *_: None)
    params, film_res = scene_settings(scene_path, res, params)
    # rendered (or read from the cache) before the integrators, outside their budgets
    ref = reference_image(scene_path, params, spp=ref_spp, verbose=True, film_res=film_res)
    h, w = ref.shape[:2]
    spp_cap = max_spp(w * h)
    curves, failures, walls, baseline = run_integrators(
        scene_path, specs, f"{name} {res}", budget, params, ref_spp, seed, counter, log, detail,
        film_res=film_res, max_spp=spp_cap)
    path_curve = curves.get(baseline)
    floor = reference_floor(path_curve.points, ref_spp) if path_curve is not None else None
    rows = [sweep_row(name, res, (w, h), spec, curves.get(spec), path_curve, budget, ref_spp,
                      floor, failures.get(spec)) for spec in specs]
    return {"scene": os.fspath(scene_path), "name": name, "res": res, "size": [w, h],
            "params": params, "film_res": film_res, "budget": budget, "ref_spp": ref_spp,
            "ref_floor": floor, "max_spp": spp_cap,
            "reference_seconds": reference_seconds(scene_path, params, ref_spp, film_res),
            "wall_seconds": walls, "failed": failures, "rows": rows,
            "curves": {k: asdict(c) for k, c in curves.items()}}


def write_report(out_dir: str, info: dict, points, names, wall_seconds: float,
                 done: bool = True) -> None:
    """Write ``sweep.json``, ``sweep.md`` and ``sweep.png`` for the points so far (``info``
    gains ``wall_seconds``, ``points``, ``rows`` and ``complete``); a run not ``done`` says
    in the table's first line that it is partial."""
    info["wall_seconds"] = wall_seconds
    info["points"] = points
    info["complete"] = done
    rows = sorted((r for p in points for r in p["rows"]),
                  key=lambda r: (names.index(r["scene"]), r["pixels"]))
    info["rows"] = rows
    with open(os.path.join(out_dir, "sweep.json"), "w") as f:
        json.dump(info, f, indent=1, default=_json_default)
    budget, ref_spp = info["budget_at_128"], info["ref_spp_at_128"]
    sizes_done = sorted({p["res"] for p in points})
    state = (f"took {_duration(wall_seconds)}" if done else
             f"partial: sizes {','.join(map(str, sizes_done))} of "
             f"{','.join(map(str, info['sizes']))} in {_duration(wall_seconds)}")
    header = (f"Resolution sweep of {run_label(info)}; "
              f"budget {budget:g} s and reference {ref_spp} spp at {BASE_RES}², scaled by "
              f"side / {BASE_RES}; {state}. Command: `{info['command']}`")
    with open(os.path.join(out_dir, "sweep.md"), "w") as f:
        f.write(format_table(rows, header))
    write_figure(rows, os.path.join(out_dir, "sweep.png"),
                 title=f"speed-up to relMSE {TARGET} over path; budget {budget:g} s × side / "
                       f"{BASE_RES}, reference {ref_spp} spp × {BASE_RES} / side")


def run_sweep(scenes, sizes, specs=None, budget: float = DEFAULT_BUDGET,
              ref_spp: int = DEFAULT_REF_SPP, params: dict | None = None, seed: int = 0,
              out_dir: str = "benchmarks", argv=(), log=print) -> dict:
    """Run the sweep (module docstring) and write its files into ``out_dir``; returns
    sweep.json's content. ``specs``: the integrators for every scene (``path`` first, the
    baseline), or None for :func:`default_specs` per scene. ``budget`` and ``ref_spp`` are
    given at 128² and scaled per size (:func:`point_budget`, :func:`reference_spp`)."""
    params = dict(params or {})
    sizes = sorted(set(int(s) for s in sizes))
    os.makedirs(out_dir, exist_ok=True)
    names = scene_names(scenes)
    per_scene = {name: list(specs) if specs else default_specs(path)
                 for path, name in zip(scenes, names)}
    runs_per_size = sum(len(v) for v in per_scene.values())
    started = datetime.datetime.now().astimezone()
    info = {"machine": machine_info(), "date": started.isoformat(timespec="seconds"),
            "command": command_line(argv), "cwd": os.getcwd(), "python": sys.executable,
            **software_info(), "sizes": sizes, "budget_at_128": budget,
            "ref_spp_at_128": ref_spp, "defines": params, "seed": seed,
            "integrators": per_scene, "target_relmse": TARGET, "max_lanes": MAX_LANES,
            "rules": {"budget": f"budget × side / {BASE_RES}",
                      "ref_spp": f"ref_spp × {BASE_RES} / side, at least {MIN_REF_SPP}",
                      "floor": "median over path's points of relMSE × spp / (spp + ref spp)"},
            "cache": os.environ.get("MI_TWOPASS_CACHE") or "(default: .cache/references)"}
    m = info["machine"]
    estimate = estimate_seconds(runs_per_size, sizes, budget, ref_spp, len(scenes))
    log(f"sweep: {len(scenes)} scenes × sizes {','.join(map(str, sizes))} × "
        f"{runs_per_size // max(1, len(scenes))} integrators; budget {budget:g} s and "
        f"reference {ref_spp} spp at {BASE_RES}² (scaled by side / {BASE_RES}); at most about "
        f"{_duration(estimate)} with uncached references, on {machine_label(m)}")
    counter = [0, runs_per_size * len(sizes)]
    t0 = time.perf_counter()
    points = []
    with open(os.path.join(out_dir, "sweep.log"), "w") as logfile:
        def detail(line):
            logfile.write(line + "\n")
            logfile.flush()

        detail(info["command"])
        for res in sizes:  # small sizes first: a reader sees the trend build up
            for path, name in zip(scenes, names):
                b, r = point_budget(budget, res), reference_spp(ref_spp, res)
                detail(f"{name} at {res}: {path}, budget {b:g} s, reference {r} spp")
                point = sweep_point(path, name, res, per_scene[name], b, r, params, seed,
                                    counter, log=log, detail=detail)
                if point["ref_floor"] is not None:
                    log(f"    reference {r} spp at {point['size'][0]}×{point['size'][1]}: "
                        f"floor relMSE ≈ {point['ref_floor']:.1e}")
                points.append(point)
            # rewritten after every size: a run stopped early leaves the sizes it did
            write_report(out_dir, info, points, names, time.perf_counter() - t0,
                         done=res == sizes[-1])
    log(f"wrote {out_dir}/sweep.md, sweep.png, sweep.json, sweep.log "
        f"({_duration(info['wall_seconds'])})")
    return info
