"""Pieces every report of ``bench`` shares: one integrator's harness run that survives a
refusal, and Markdown table lines."""
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


def num(v, fmt) -> str:
    """``v`` formatted, or — where it is missing or not finite."""
    return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def table_line(cells) -> str:
    """One Markdown table line (``|`` inside a cell escaped)."""
    return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"


def table_head(columns) -> list:
    """The header and rule lines of a Markdown table."""
    return [table_line(columns), table_line("---" for _ in columns)]
