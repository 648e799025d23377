"""Pieces every report of ``bench`` shares: one integrator's harness run that survives a
refusal, a scene's integrators run in turn with a progress line each, and Markdown table lines
and report files."""
from __future__ import annotations

import math
import time
import traceback

from . import harness


def run_integrator(scene_path, spec: str, budget: float, params: dict, ref_spp: int, seed: int,
                   detail, **compare_options):
    """:func:`mi_twopass.evaluation.harness.run_compare` for one integrator spec →
    ``(curve or None, failure or None, wall seconds)``. A scene-file error stops the run (the
    scene is wrong for every integrator); anything else becomes ``"refused: ..."`` (a
    ValueError / NotImplementedError naming what is not supported,
    :func:`~mi_twopass.evaluation.check.refusal_of`) or ``"failed: ..."``, with the traceback
    sent to ``detail``, so that one integrator's failure never ends a report."""
    from ..scenefile import SceneFileError
    from .check import refusal_of

    t0 = time.perf_counter()
    curve = failure = None
    try:
        curve = harness.run_compare(scene_path, [spec], budget, params, ref_spp=ref_spp,
                                    seed=seed, log=detail, **compare_options)[spec]
    except SceneFileError:
        raise
    except Exception as e:  # noqa: BLE001 (one integrator's failure must not end the run)
        cause = refusal_of(e)
        failure = (f"refused: {' '.join(str(cause).split())}" if cause is not None
                   else f"failed: {type(e).__name__}: {' '.join(str(e).split())[:300]}")
        detail(f"  {spec}: {failure}\n{traceback.format_exc()}")
    return curve, failure, time.perf_counter() - t0


def run_integrators(scene_path, specs, label: str, budget: float, params: dict, ref_spp: int,
                    seed: int, counter, log, detail, **compare_options):
    """:func:`run_integrator` for every spec of ``specs`` in turn, logging one
    :func:`progress_line` each (``counter``: [done, total] of (scene, integrator) runs, advanced
    here; ``label`` names the scene in the line) → ``(curves, failures, walls, baseline)``:
    dicts by spec of the curves (not for an integrator that refused or failed), the failures
    and the wall seconds; the curves summarised (:func:`mi_twopass.evaluation.harness.summarise`)
    against ``baseline``, the first ``path`` spec of ``specs`` (else ``"path"``)."""
    curves, failures, walls = {}, {}, {}
    for spec in specs:
        curve, failure, walls[spec] = run_integrator(
            scene_path, spec, budget, params, ref_spp, seed, detail, **compare_options)
        if curve is not None:
            curves[spec] = curve
        if failure is not None:
            failures[spec] = failure
        counter[0] += 1
        log(progress_line(counter, label, spec, curves.get(spec), failures.get(spec),
                          walls[spec]))
    baseline = next((s for s in specs if s.split(":")[0] == "path"), "path")
    harness.summarise(curves, baseline=baseline)
    return curves, failures, walls, baseline


def progress_line(counter, name, spec, curve, failure, wall) -> str:
    """``[3/36] office  rex  10 points to 512 spp, 24.1 s, relMSE 3.1e-03, t(0.01) 4.2 s``."""
    width = len(str(counter[1]))
    head = f"[{counter[0]:>{width}}/{counter[1]}] {name:<18} {spec:<28}"
    if curve is None:
        return f"{head} {failure}  ({wall:.1f} s)"
    last = curve.points[-1]
    tte = harness.time_to_error(curve.points)
    reached = "not reached" if tte is None else f"{tte:.2f} s"
    return (f"{head} {len(curve.points):>2} points to {last.spp:>5} spp, "
            f"relMSE {last.relmse:.2e}, t(relMSE 0.01) {reached}  ({wall:.1f} s)")


def num(v, fmt) -> str:
    """``v`` formatted, or — where it is missing or not finite."""
    return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def table_line(cells) -> str:
    """One Markdown table line (``|`` inside a cell escaped)."""
    return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"


def table_head(columns) -> list:
    """The header and rule lines of a Markdown table."""
    return [table_line(columns), table_line("---" for _ in columns)]


def markdown_report(header: str, columns, lines, notes) -> str:
    """A report file's text (results.md, sweep.md, cold.md): the ``header`` line, a Markdown
    table of ``columns`` over the formatted table ``lines``, then the ``notes`` (what each
    column means, one line each) after a blank line."""
    return "\n".join([header, "", *table_head(columns), *lines, "", *notes]) + "\n"
