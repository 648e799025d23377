"""Speed-vs-error harness (docs/design.md "Measuring speed against error").

For each integrator: render at doubling spp (1, 2, 4, ...), each point with a *fresh* integrator so
its prepass is paid again and counted; the point's cost is the wall time of ``mi.render`` with the
prepass, stopped after ``dr.sync_thread()``. Before the timed points, each integrator renders one
untimed 1-spp warm-up so Dr.Jit's kernel compilation is not charged to the first point (it is the
same for every integrator; ``twopass`` plans it as a long render, :func:`warm_up`). Error is
relMSE (ε = 0.01) and FLIP against Mitsuba's ``path`` at high spp (cached). Points stop when the next one (about twice the last) would not fit in the budget.

Short points can be timed more than once (``repeats``, :func:`timed_point`): a point faster
than ``repeat_below`` seconds is rendered ``repeats`` times, each with a fresh integrator and
the same seed, and the point is the run of the median time, its image and its time together
(``twopass`` decides from its own timings, so its repeats may render different images; the
point is one run as a user would get it, not the fastest time beside another run's error).

Reported per integrator: the (time, relMSE, FLIP) curve; the equal-time relMSE ratio against
``path`` measured in the same run (path's error at the method's time, interpolated log-log, over
the method's); the time to reach relMSE 0.01 (log-log interpolation between bracketing points);
the error at the largest spp (an upper bound of the bias floor).
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..scenefile import load_scene, parse_value
from . import metrics
from .reference import DEFAULT_REFERENCE_SPP, reference_image

TARGET_RELMSE = 0.01


@dataclass
class Point:
    spp: int
    seconds: float
    relmse: float
    flip: float
    mse: float
    stats: dict = field(default_factory=dict)


@dataclass
class Curve:
    label: str
    points: list
    summary: dict = field(default_factory=dict)


def parse_integrator_spec(spec: str) -> tuple[str, dict]:
    """``"spike_gather:r_thresh=0.1:max_depth=8"`` → ``("spike_gather", {...})``."""
    name, *rest = spec.split(":")
    props = {}
    for item in rest:
        if "=" not in item:
            raise ValueError(f"integrator spec {spec!r}: {item!r} is not key=value")
        k, v = item.split("=", 1)
        props[k] = parse_value(v)
    return name, props


def make_integrator(spec: str):
    """A fresh integrator from a spec; ``path`` defaults to unbounded depth as the reference."""
    name, props = parse_integrator_spec(spec)
    d = {"type": name, **props}
    if name == "path":
        d.setdefault("max_depth", -1)
    return mi.load_dict(d)


def timed_render(scene, spec: str, spp: int, seed: int):
    """(image, seconds, stats) of one render with a fresh integrator, prepass included.

    Mitsuba splits a render into passes by itself when spp × pixels is too large."""
    dr.sync_thread()
    t0 = time.perf_counter()
    integrator = make_integrator(spec)
    image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    image = np.asarray(image, dtype=np.float32)[..., :3]  # numpy conversion waits for the kernel
    dr.sync_thread()
    seconds = time.perf_counter() - t0
    stats = dict(getattr(integrator, "stats", {}) or {})
    return image, seconds, stats


#: the samples per pixel ``twopass``'s warm-up plans for (:func:`warm_up`)
WARM_UP_PLANNED_SPP = 4096


#: the default repeats of a short point for ``bench`` and ``compare`` (:func:`timed_point`;
#: :func:`run_compare` itself renders each point once unless asked)
DEFAULT_REPEATS = 3
#: a point is repeated only where its first render took less than this many seconds: where a
#: curve crosses relMSE 0.01 in under a second, single timings moved cells by 10–40 % between
#: runs of one commit on the 2-core machine (session 35: twopass's 16-spp point on tut-cbox,
#: the same image, took 0.565, 0.577, 0.592 and 0.637 s); longer points vary less and cost more
REPEAT_BELOW_SECONDS = 1.0


def timed_point(scene, spec: str, spp: int, seed: int, reference, repeats: int = 1,
                repeat_below: float = REPEAT_BELOW_SECONDS) -> tuple[Point, np.ndarray]:
    """``(point, image)``: one point of a curve. :func:`timed_render` once, and where that
    took less than ``repeat_below`` seconds, ``repeats`` − 1 times more (fresh integrators,
    the same seed). The point is the run of the median time (the lower of the middle two for
    an even count): its image, and that image's metrics with its own seconds. With repeats
    its ``stats`` also hold ``repeat_seconds`` and ``repeat_relmse`` (every run's, in order)
    and ``repeat_kept`` (the index of the run kept)."""
    runs = [timed_render(scene, spec, spp, seed)]
    if repeats > 1 and runs[0][1] < repeat_below:
        runs += [timed_render(scene, spec, spp, seed) for _ in range(repeats - 1)]
    by_time = sorted(range(len(runs)), key=lambda i: runs[i][1])
    kept = by_time[(len(runs) - 1) // 2]
    image, seconds, stats = runs[kept]
    m = metrics.all_metrics(image, reference)
    if len(runs) > 1:
        stats = dict(stats, repeat_seconds=[r[1] for r in runs],
                     repeat_relmse=[metrics.relmse(r[0], reference) for r in runs],
                     repeat_kept=kept)
    return Point(spp, seconds, m["relmse"], m["flip"], m["mse"], stats), image


def warm_up(scene, spec: str, seed: int):
    """The untimed render before an integrator's points: 1 spp, so that Dr.Jit compiles the
    kernels of its prepass and render outside the timed curve. An integrator that chooses
    what to build from the render's samples per pixel (``twopass``: ``planned_spp``) plans
    for :data:`WARM_UP_PLANNED_SPP`, so that its pilot and the structures a long render
    builds are compiled too; at 1 spp it would build nothing and its first point that pilots
    would pay every candidate's compilation (spike lists with the radiance cache on
    veach-bidir at 256²: 5.7 s on a cold kernel cache, 1.0 s on a warm one). Returns the
    integrator."""
    integrator = make_integrator(spec)
    if hasattr(integrator, "planned_spp"):
        integrator.planned_spp = WARM_UP_PLANNED_SPP
    np.asarray(mi.render(scene, integrator=integrator, spp=1, seed=seed))
    dr.sync_thread()
    return integrator


def render_only_seconds(scene, integrator, spp: int, seed: int) -> tuple[np.ndarray, float]:
    """(image, seconds) of a render whose prepass and kernels are already built: an untimed
    4-spp render with the same ``seed`` first (the prepass's seed is the render's, so the timed
    render reuses it), then ``spp`` timed after ``dr.sync_thread()`` to the numpy copy."""
    np.asarray(mi.render(scene, integrator=integrator, spp=4, seed=seed))
    dr.sync_thread()
    t0 = time.perf_counter()
    image = np.asarray(mi.render(scene, integrator=integrator, spp=spp, seed=seed))
    return image, time.perf_counter() - t0


def _loglog_interp(xs, ys, x):
    """Interpolate y(x) linearly in log-log between the bracketing points; None outside."""
    for (x0, y0), (x1, y1) in zip(zip(xs, ys), zip(xs[1:], ys[1:])):
        lo, hi = min(x0, x1), max(x0, x1)
        if lo <= x <= hi and x0 > 0 and x1 > 0 and y0 > 0 and y1 > 0:
            if x0 == x1:
                return min(y0, y1)
            t = (math.log(x) - math.log(x0)) / (math.log(x1) - math.log(x0))
            return math.exp(math.log(y0) + t * (math.log(y1) - math.log(y0)))
    return None


def time_to_error(points, target=TARGET_RELMSE):
    """First time the curve reaches ``target`` relMSE (log-log interpolation), or None."""
    prev = None
    for p in points:
        if p.relmse <= target:
            if prev is None:
                return p.seconds
            return _loglog_interp([prev.relmse, p.relmse], [prev.seconds, p.seconds], target)
        prev = p
    return None


def envelope_seconds(points) -> list:
    """Each point's seconds, or a later (more spp) point's where that is less: a render of
    more samples cannot take less time, so a point slower than a later one was held up (a
    kernel compiled, the machine busy). On an H200 path's 4-spp point of staircase2 took
    0.54 s between 0.011 s at 2 spp and 0.017 s at 8 spp; interpolated as measured, path's
    own equal-time ratio read 92."""
    out, least = [], math.inf
    for p in reversed(points):
        least = min(least, p.seconds)
        out.append(least)
    return out[::-1]


def summarise(curves: dict, baseline: str = "path", target=TARGET_RELMSE) -> None:
    """Fill each curve's summary: equal-time ratio, equal-spp ratio, time to target, bias
    floor. The baseline's relMSE at a time is read off its curve with
    :func:`envelope_seconds`."""
    base = curves.get(baseline)
    base_t = envelope_seconds(base.points) if base else []
    base_e = [p.relmse for p in base.points] if base else []
    base_tte = time_to_error(base.points, target) if base else None
    for curve in curves.values():
        s = curve.summary
        pts = curve.points
        s["time_to_target"] = time_to_error(pts, target)
        s["final_relmse"] = pts[-1].relmse if pts else None
        s["final_flip"] = pts[-1].flip if pts else None
        s["final_spp"] = pts[-1].spp if pts else None
        ratios = []
        for p in pts:
            e = _loglog_interp(base_t, base_e, p.seconds) if base else None
            if e is not None and p.relmse > 0:
                ratios.append((p.seconds, e / p.relmse))
        s["equal_time_ratio"] = ratios[-1][1] if ratios else None
        s["equal_time_at"] = ratios[-1][0] if ratios else None
        # per-sample quality, free of how fast either implementation is: baseline relMSE over
        # this one's at the largest spp both curves reached
        base_by_spp = {p.spp: p.relmse for p in base.points} if base else {}
        common = [p for p in pts if p.spp in base_by_spp and p.relmse > 0]
        s["equal_spp_ratio"] = base_by_spp[common[-1].spp] / common[-1].relmse if common else None
        s["equal_spp_at"] = common[-1].spp if common else None
        tte = s["time_to_target"]
        s["speedup_to_target"] = (base_tte / tte) if (base_tte and tte) else None


def run_compare(scene_path, integrators, budget: float, params: dict | None = None,
                ref_spp: int = DEFAULT_REFERENCE_SPP, seed: int = 0, max_spp: int = 1 << 16,
                log=print, film_res: int | None = None, on_curve=None, repeats: int = 1,
                repeat_below: float = REPEAT_BELOW_SECONDS) -> dict:
    """Run the harness; returns {label: Curve} with summaries filled.

    ``film_res``: the film's longer side in pixels for scene and reference (see
    :func:`~mi_twopass.scenefile.load_scene`; for scenes without a ``$res`` parameter).
    ``on_curve(spec, curve, image)``: called once per integrator when its points are done,
    ``image`` being its render at the largest spp (before the summaries are filled).
    ``repeats``, ``repeat_below``: short points timed more than once (:func:`timed_point`)."""
    params = dict(params or {})
    reference = reference_image(scene_path, params, spp=ref_spp, verbose=True, film_res=film_res)
    scene = load_scene(scene_path, film_res=film_res, **params)
    curves = {}
    for spec in integrators:
        warm_up(scene, spec, seed + 999_983)  # compile kernels, untimed
        points, spent, spp = [], 0.0, 1
        while spp <= max_spp:
            point, image = timed_point(scene, spec, spp, seed + spp, reference, repeats,
                                       repeat_below)
            points.append(point)
            seconds = point.seconds
            spent += seconds
            times = point.stats.get("repeat_seconds")
            median = "" if times is None else \
                "  (median of " + ", ".join(f"{t:.3f}" for t in times) + " s)"
            log(f"  {spec:<28} spp {spp:>6}  {seconds:8.3f} s  relMSE {point.relmse:.3e}  "
                f"FLIP {point.flip:.4f}{median}")
            if spent + 2.2 * seconds > budget:
                break
            spp *= 2
        curves[spec] = Curve(spec, points)
        if on_curve is not None:
            on_curve(spec, curves[spec], image)
    summarise(curves, baseline=next((s for s in integrators if s.split(":")[0] == "path"), "path"))
    return curves


def format_table(curves: dict, target=TARGET_RELMSE) -> str:
    def f(v, fmt):
        return "—" if v is None else format(v, fmt)

    lines = [f"{'integrator':<28} {'spp':>6} {'time s':>9} {'relMSE':>10} {'FLIP':>7}"]
    for c in curves.values():
        for p in c.points:
            lines.append(f"{c.label:<28} {p.spp:>6} {p.seconds:>9.3f} {p.relmse:>10.3e} {p.flip:>7.4f}")
    lines.append("")
    lines.append(f"{'integrator':<28} {'t(relMSE≤' + str(target) + ') s':>18} {'speed-up':>9} "
                 f"{'equal-time ratio':>17} {'at s':>7} {'equal-spp ratio':>16} {'at spp':>7} "
                 f"{'relMSE@max spp':>15} {'max spp':>8}")
    for c in curves.values():
        s = c.summary
        lines.append(f"{c.label:<28} {f(s['time_to_target'], '.3f'):>18} "
                     f"{f(s['speedup_to_target'], '.2f'):>9} {f(s['equal_time_ratio'], '.2f'):>17} "
                     f"{f(s['equal_time_at'], '.2f'):>7} {f(s['equal_spp_ratio'], '.2f'):>16} "
                     f"{f(s['equal_spp_at'], 'd'):>7} {f(s['final_relmse'], '.3e'):>15} "
                     f"{f(s['final_spp'], 'd'):>8}")
    return "\n".join(lines)


def write_plot(curves: dict, path: str, title: str = "") -> None:
    """Log-log plot of relMSE against time, one line per integrator."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.2), dpi=120)
    for c in curves.values():
        t = [p.seconds for p in c.points]
        e = [max(p.relmse, 1e-12) for p in c.points]
        ax.loglog(t, e, "o-", label=c.label)
    ax.axhline(TARGET_RELMSE, color="gray", ls=":", lw=1, label=f"relMSE {TARGET_RELMSE}")
    ax.set_xlabel("time (s, prepass included)")
    ax.set_ylabel("relMSE")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def write_json(curves: dict, path: str, meta: dict | None = None) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    data = {"meta": meta or {}, "curves": {k: asdict(c) for k, c in curves.items()}}
    with open(path, "w") as f:
        json.dump(data, f, indent=1, default=float)
