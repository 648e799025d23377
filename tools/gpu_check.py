"""Run every registered integrator on cuda_ad_rgb and time it beside path (device check).

    MI_TWOPASS_VARIANT=cuda_ad_rgb python tools/gpu_check.py [SCENE ...] [--res R] [--spp N]

Prints, per scene and integrator, the first render's seconds (kernels compiled), then a second
render's total and prepass seconds (after dr.sync_thread), whether the image is finite, its mean
over that of a path render of 16× the spp made in the same run, and relMSE against it. An
integrator that raises is reported with its traceback and the check goes on; the exit status is
1 when any failed.
"""
import argparse
import os
import time
import traceback

import mitsuba as mi

mi.set_variant(os.environ.get("MI_TWOPASS_VARIANT", "cuda_ad_rgb"))

import drjit as dr
import numpy as np

import mi_twopass
from mi_twopass.evaluation.metrics import relmse


def render_once(scene, name, spp, seed):
    """(image, seconds after dr.sync_thread, integrator) of one render with a fresh integrator."""
    integ = mi.load_dict({"type": name} if name != "path" else {"type": "path", "max_depth": -1})
    dr.sync_thread()
    t0 = time.perf_counter()
    img = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=seed))
    dr.sync_thread()
    return img, time.perf_counter() - t0, integ


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="*", default=["scenes_xml/cornell_box.xml"])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    args = ap.parse_args()
    print("variant", mi.variant(), "plugins", mi_twopass.registered_names(), flush=True)
    failed = []
    for path in args.scenes:
        scene = mi.load_file(path, res=args.res)
        ref = np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": -1}),
                                   spp=args.spp * 16, seed=99))
        for name in ["path"] + mi_twopass.registered_names():
            try:
                # the first run compiles the kernels; the second is the one timed
                _, t_first, _ = render_once(scene, name, args.spp, 0)
                img, t, integ = render_once(scene, name, args.spp, 1)
            except Exception:  # noqa: BLE001 (report every integrator's failure, go on)
                failed.append((os.path.basename(path), name))
                print(f"{os.path.basename(path):22s} {name:18s} FAILED", flush=True)
                traceback.print_exc()
                continue
            st = getattr(integ, "stats", {}) or {}
            ratio = float(np.mean(img)) / max(float(np.mean(ref)), 1e-12)
            print(f"{os.path.basename(path):22s} {name:18s} first {t_first:7.3f} s  total {t:7.3f} s  "
                  f"prepass {st.get('prepass_seconds', 0):6.3f} s  finite "
                  f"{bool(np.all(np.isfinite(img)))}  mean/path {ratio:.4f}  "
                  f"relMSE {relmse(img, ref):.3e}", flush=True)
    print("failed:", failed or "none", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
