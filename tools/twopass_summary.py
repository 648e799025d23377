"""twopass against path and the best single integrator, per scene, from ``bench`` runs.

    python tools/twopass_summary.py out/bench128/bench.json [out/bench128_tp/bench.json]

The first run supplies the four integrators (and path); a later run, if given, supplies twopass
(and its own path: speed-ups are taken within a run, as timings drift between runs). Per scene:
path's time to relMSE 0.01, the best single integrator by speed-up (else by equal-time ratio),
twopass's speed-up, equal-time ratio and choice, and issue 14's figure, twopass against the best
single integrator (:func:`versus_best`). Prints a Markdown table.
"""
import json
import sys

SUITE = ("radiosity_gather", "spike_gather", "rex", "radiance_cache")


def rows_by_scene(path):
    bench = json.load(open(path))
    return {name: {r["integrator"]: r for r in s["rows"]} for name, s in bench["scenes"].items()}


def fmt(v, f="{:.2f}"):
    return "—" if v is None else f.format(v)


def versus_best(cands, tp) -> str:
    """twopass against the best single integrator of ``cands`` (bench rows): where twopass and
    some of them reach relMSE 0.01, twopass's t(0.01) over the least of theirs; else the
    largest of their equal-time ratios over twopass's (both read against path at the method's
    own time). "best" where twopass is ahead; the integrator and the basis named."""
    if tp is None or tp.get("failed"):
        return "—"
    reached = [r for r in cands if r.get("time_to_target")]
    if tp.get("time_to_target") and reached:
        best = min(reached, key=lambda r: r["time_to_target"])
        ratio, basis = tp["time_to_target"] / best["time_to_target"], "t(0.01)"
    else:
        timed = [r for r in cands if r.get("equal_time_ratio")]
        if not timed or not tp.get("equal_time_ratio"):
            return "—"
        best = max(timed, key=lambda r: r["equal_time_ratio"])
        ratio, basis = best["equal_time_ratio"] / tp["equal_time_ratio"], "equal-time"
    return ("best" if ratio <= 1.0 else f"{ratio:.2f}") + f" ({best['integrator']}, {basis})"


def main(argv):
    singles = rows_by_scene(argv[0])
    twopass = rows_by_scene(argv[-1])
    print("| scene | path t(0.01) s | best single (speed-up / equal-time) | twopass t(0.01) s | "
          "twopass speed-up | twopass equal-time | twopass / best single | twopass chose |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, rows in singles.items():
        cands = [rows[i] for i in SUITE if i in rows and not rows[i].get("failed")]
        best = max(cands, key=lambda r: (r["speedup"] or 0, r["equal_time_ratio"] or 0),
                   default=None)
        tp = twopass.get(name, {}).get("twopass")
        path = twopass.get(name, {}).get("path") or rows.get("path")
        best_txt = "—" if best is None else (
            f"{best['integrator']} {fmt(best['speedup'])} / {fmt(best['equal_time_ratio'])}")
        print(f"| {rows['path']['scene']} | {fmt(path and path['time_to_target'], '{:.3g}')} | "
              f"{best_txt} | {fmt(tp and tp['time_to_target'], '{:.3g}')} | "
              f"{fmt(tp and tp['speedup'])} | {fmt(tp and tp['equal_time_ratio'])} | "
              f"{versus_best(cands, tp)} | {(tp or {}).get('twopass_choice') or '—'} |")


if __name__ == "__main__":
    main(sys.argv[1:])
