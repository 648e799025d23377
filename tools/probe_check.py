"""How well twopass's render probe predicts ``path``'s render, and what twopass does with it.

    python tools/probe_check.py SCENE.xml ... [--res 256] [--spp 4,32,256] [--repeats 3]

Per scene: path's probe (:func:`mi_twopass.compose.pilot.probe_render`: one 1-spp render, its
kernels' compilation taken off; fixed part and seconds per spp), then per ``--spp`` the
probe's prediction beside path's render time measured (fastest of ``--repeats``, kernels
compiled), and twopass's render with ``path_probe`` "off" and "auto" (the default: on the CUDA
backend only; ``--settings off,on`` forces it on the CPU): its seconds, and the choice and the skip
reason (or the predicted figures) that decided it with the probe. Set
``MI_TWOPASS_VARIANT=cuda_ad_rgb`` for the GPU. Timings stop after the numpy copy.
"""
import argparse
import os
import time

import mitsuba as mi

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)

import numpy as np

from mi_twopass.compose.pilot import probe_render
from mi_twopass.scenefile import load_scene


def timed(scene, integ, spp, seed):
    """Seconds of one render to the numpy copy."""
    t0 = time.perf_counter()
    np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=seed))
    return time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", default="4,32,256")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--settings", default="off,auto",
                    help="twopass's path_probe settings, one column each (auto, on, off)")
    a = ap.parse_args()
    print(f"variant {mi.variant()}", flush=True)
    settings = a.settings.split(",")
    print("| scene | fixed s | s per spp | spp | path predicted s | path measured s | "
          + "".join(f"twopass {s} s | " for s in settings)
          + f"choice ({settings[-1]}) | why |")
    print("|" + " --- |" * (8 + len(settings)))
    for path in a.scenes:
        scene = load_scene(path, film_res=a.res)
        name = os.path.basename(os.path.dirname(path)) if path.endswith("scene.xml") else \
            os.path.splitext(os.path.basename(path))[0]
        path_integ = mi.load_dict({"type": "path"})
        timed(scene, path_integ, 4, 0)  # compiles path's kernels
        probe = min((probe_render(scene, scene.sensors()[0], path_integ, 1 + k)
                     for k in range(a.repeats)), key=lambda p: p.seconds(32))
        for spp in (int(s) for s in a.spp.split(",")):
            measured = min(timed(scene, path_integ, spp, 7 + k) for k in range(a.repeats))
            row = []
            for setting in settings:
                tp = mi.load_dict({"type": "twopass", "path_probe": setting})
                timed(scene, tp, spp, 0)  # compiles the kernels twopass's choice reads
                tp = mi.load_dict({"type": "twopass", "path_probe": setting})
                row.append((timed(scene, tp, spp, 3), tp.stats))
            st = row[-1][1]
            why = next(iter(st["twopass_skipped"].values()), "") if not st.get(
                "twopass_candidates") else st["twopass_reason"]
            print(f"| {name} | {probe.fixed:.4f} | {probe.per_spp:.5f} | {spp} | "
                  f"{probe.seconds(spp):.4f} | {measured:.4f} | "
                  + "".join(f"{t:.4f} | " for t, _ in row)
                  + f"{st['twopass_choice']} | {why[:110]} |", flush=True)


if __name__ == "__main__":
    main()
