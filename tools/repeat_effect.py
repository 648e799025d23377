"""What timing short points three times changed in one bench run: each scene's cells as the
run reported them (every point the run of median time of its repeats) beside the cells that
the same run's first renders alone give (what a bench that timed each point once would have
read), and how far the repeats of one point spread.

    python tools/repeat_effect.py OUT/bench.json

A point of a run made with ``--repeats`` > 1 holds every repeat's seconds and relMSE
(``repeat_seconds``, ``repeat_relmse``: :func:`mi_twopass.evaluation.harness.timed_point`).
Here the curves are summarised twice (:func:`mi_twopass.evaluation.harness.summarise`): as
kept, and with each repeated point replaced by its first run. Prints a Markdown table per
scene: twopass's t(0.01), its speed-up over path and its figure against the best single
integrator (``tools/twopass_summary.py``'s :func:`versus_best`), both ways; then the spread
of the repeats: the median over points of (slowest − fastest) / kept, the largest, and the
share of points whose first run was more than 10 % from the kept one.
"""
import argparse
import importlib.util
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mi_twopass.evaluation import harness  # noqa: E402
from mi_twopass.evaluation.bench import table_row  # noqa: E402

def _summary_tool():
    """tools/twopass_summary.py as a module (its :func:`versus_best`)."""
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "twopass_summary.py")
    spec = importlib.util.spec_from_file_location("twopass_summary", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def first_run(point: dict) -> dict:
    """``point`` as its first repeat measured it (itself where it was not repeated)."""
    stats = point.get("stats") or {}
    if not stats.get("repeat_seconds"):
        return point
    return {**point, "seconds": stats["repeat_seconds"][0],
            "relmse": stats["repeat_relmse"][0]}


def rows(entry: dict, pick) -> dict:
    """{integrator: bench table row} of a scene entry, each point through ``pick``."""
    curves = {spec: harness.Curve(c["label"], [harness.Point(**pick(p)) for p in c["points"]])
              for spec, c in entry["curves"].items()}
    baseline = next((k for k in curves if k.split(":")[0] == "path"), "path")
    harness.summarise(curves, baseline=baseline)
    return {spec: table_row(entry["label"], curve, curves.get(baseline))
            for spec, curve in curves.items()}


def cells(entry: dict, pick, summary) -> tuple:
    """(twopass t(0.01), twopass speed-up, twopass against the best single) of one scene
    (``summary``: tools/twopass_summary.py, its suite and :func:`versus_best`)."""
    r = rows(entry, pick)
    tp = r.get("twopass")
    if tp is None:
        return None, None, "—"
    cands = [r[i] for i in summary.SUITE if i in r]
    return tp["time_to_target"], tp["speedup"], summary.versus_best(cands, tp)


def spread(run: dict) -> tuple:
    """(median and largest (slowest − fastest) / kept, share of points whose first run is
    more than 10 % from the kept one, points repeated) over every repeated point."""
    widths, off = [], []
    for entry in run["scenes"].values():
        for c in entry["curves"].values():
            for p in c["points"]:
                times = (p.get("stats") or {}).get("repeat_seconds")
                if times:
                    widths.append((max(times) - min(times)) / p["seconds"])
                    off.append(abs(times[0] - p["seconds"]) / p["seconds"] > 0.1)
    if not widths:
        return None, None, None, 0
    return float(np.median(widths)), float(max(widths)), float(np.mean(off)), len(widths)


def num(v, f="{:.3g}"):
    return "—" if v is None else f.format(v)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bench", metavar="bench.json")
    args = ap.parse_args(argv)
    with open(args.bench) as f:
        run = json.load(f)
    summary = _summary_tool()
    print("| scene | twopass t(0.01) s, kept / first runs | speed-up over path, kept / first "
          "runs | twopass / best single, kept / first runs |")
    print("| --- | --- | --- | --- |")
    for entry in run["scenes"].values():
        kept = cells(entry, lambda p: p, summary)
        first = cells(entry, first_run, summary)
        print(f"| {entry['label']} | {num(kept[0])} / {num(first[0])} | "
              f"{num(kept[1], '{:.2f}')} / {num(first[1], '{:.2f}')} | {kept[2]} / {first[2]} |")
    median, largest, off, n = spread(run)
    if n:
        print(f"\nRepeated points: {n}. Spread of one point's repeats, (slowest − fastest) / "
              f"kept: median {median:.1%}, largest {largest:.1%}. First run more than 10 % "
              f"from the kept one: {off:.0%} of points.")
    else:
        print("\nNo point of this run was repeated (--repeats 1, or every point over "
              "--repeat-below).")


if __name__ == "__main__":
    main()
