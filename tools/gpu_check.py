"""Run every registered integrator on cuda_ad_rgb and time it beside path (device check).

    MI_TWOPASS_VARIANT=cuda_ad_rgb python tools/gpu_check.py [SCENE ...] [--res R] [--spp N]

Prints, per scene and integrator, the prepass and render seconds (after dr.sync_thread), whether
the image is finite, and relMSE against a path render of 16× the spp made in the same run.
"""
import argparse
import os
import time

import mitsuba as mi

mi.set_variant(os.environ.get("MI_TWOPASS_VARIANT", "cuda_ad_rgb"))

import drjit as dr
import numpy as np

import mi_twopass
from mi_twopass.evaluation.metrics import relmse


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="*", default=["scenes_xml/cornell_box.xml"])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    args = ap.parse_args()
    print("variant", mi.variant(), "plugins", mi_twopass.registered_names())
    for path in args.scenes:
        scene = mi.load_file(path, res=args.res)
        ref = np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": -1}),
                                   spp=args.spp * 16, seed=99))
        for name in ["path"] + mi_twopass.registered_names():
            for rep in range(2):  # the first run includes kernel compilation
                integ = mi.load_dict({"type": name} if name != "path" else
                                     {"type": "path", "max_depth": -1})
                dr.sync_thread()
                t0 = time.perf_counter()
                img = np.asarray(mi.render(scene, integrator=integ, spp=args.spp, seed=rep))
                dr.sync_thread()
                t = time.perf_counter() - t0
            st = getattr(integ, "stats", {}) or {}
            print(f"{os.path.basename(path):22s} {name:18s} total {t:7.3f} s  prepass "
                  f"{st.get('prepass_seconds', 0):6.3f} s  finite {bool(np.all(np.isfinite(img)))}  "
                  f"relMSE {relmse(img, ref):.3e}", flush=True)


if __name__ == "__main__":
    main()
