"""The README "Results" table, from the harness's JSON files.

    python tools/results_table.py out/results/cornell_box.json out/results/128/many_lights.json ...

One Markdown row per integrator other than the baseline: time to relMSE 0.01 (prepass
included) beside path's in the same run, the speed-up, the equal-time and equal-spp ratios
(path's relMSE over the method's; > 1: the method is better), and the relMSE at the largest spp
reached (an upper bound of the bias floor, reference noise included).
"""
import json
import os
import sys


def fmt(v, spec, none="—"):
    return none if v is None else format(v, spec)


def rows(path):
    with open(path) as f:
        data = json.load(f)
    meta, curves = data.get("meta", {}), data["curves"]
    scene = os.path.splitext(os.path.basename(meta.get("scene", path)))[0]
    res = (meta.get("params") or {}).get("res")
    where = f"{scene} ({res}²)" if res else scene
    base = next((c for k, c in curves.items() if k.split(":")[0] == "path"), None)
    base_t = base["summary"]["time_to_target"] if base else None
    out = []
    for label, c in curves.items():
        if c is base:
            continue
        s = c["summary"]
        out.append(
            f"| {where} | {label} | {fmt(s['time_to_target'], '.2f', 'not reached')} | "
            f"{fmt(base_t, '.2f')} | {fmt(s['speedup_to_target'], '.2f')} | "
            f"{fmt(s['equal_time_ratio'], '.2f')} | {fmt(s.get('equal_spp_ratio'), '.1f')} | "
            f"{fmt(s['final_relmse'], '.1e')} ({s['final_spp']} spp) |")
    return out


def main(paths):
    print("| scene (res) | integrator | t(0.01) s | path t(0.01) s | speed-up | equal-time "
          "ratio | equal-spp ratio | relMSE @ max spp |")
    print("|" + " --- |" * 8)
    for p in paths:
        for r in rows(p):
            print(r)


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
