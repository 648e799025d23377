"""Bias of the radiosity prepass in the far gather: mean image ratio and relMSE vs ``path``.

    .venv/bin/python tools/radiosity_bias.py scenes_xml/office.xml --res 64 --spp 256 \
        radiosity_gather radiosity_gather:r_thresh=0

For each integrator spec: the image's mean over the reference's (``ratio``; 1 is unbiased), the
relMSE against the cached ``path`` reference, and the prepass seconds. A reference cached at a
multiple of ``--res`` (box filter) is averaged down instead of rendering a new one.
``--patches`` also prints, per patch budget, the area fraction of patches that lies inside other
geometry (:func:`mi_twopass.scene.patches.exposed_fraction`) and the prepass time.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import time

import mi_twopass  # noqa: F401  (variant, libLLVM)
import drjit as dr
import mitsuba as mi
import numpy as np

from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.evaluation.metrics import relmse
from mi_twopass.evaluation.reference import default_cache_dir, reference_image
from mi_twopass.scenefile import load_scene


def cached_reference(scene_path, res):
    """A cached reference at res or at a multiple of it (box-averaged down), else render one."""
    path = os.path.abspath(scene_path)
    best = None
    for meta in glob.glob(os.path.join(default_cache_dir(), "*.json")):
        with open(meta) as f:
            info = json.load(f)
        r = int(info.get("params", {}).get("res", 0))
        if info.get("scene") == path and r and r % res == 0 and set(info["params"]) == {"res"}:
            if best is None or r < best[0]:
                best = (r, info["spp"])
    if best is None:
        return reference_image(scene_path, {"res": res}, verbose=True)
    r, spp = best
    img = reference_image(scene_path, {"res": r}, spp=spp).astype(np.float64)
    k = r // res
    return img.reshape(res, k, res, k, 3).mean(axis=(1, 3))


def render(scene, spec, spp, seed):
    integrator = make_integrator(spec)
    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    per_pass = max(1, min(spp, (1 << 22) // (w * h)))
    acc, done, k, prepass = np.zeros((h, w, 3)), 0, 0, 0.0
    while done < spp:
        n = min(per_pass, spp - done)
        img = mi.render(scene, integrator=integrator, spp=n, seed=seed + 7919 * k)
        acc += np.asarray(img, dtype=np.float64)[..., :3] * n
        prepass += float(getattr(integrator, "stats", {}).get("prepass_seconds", 0.0))
        done, k = done + n, k + 1
    return acc / spp, prepass


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("specs", nargs="*", default=["radiosity_gather"])
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--patches", type=int, nargs="*", default=None,
                    help="patch budgets for the exposed-area report")
    args = ap.parse_intermixed_args(argv)
    scene = load_scene(args.scene, res=args.res)
    if args.patches:
        from mi_twopass.prepass.radiosity import solve_radiosity
        from mi_twopass.scene.patches import build_patches
        for budget in args.patches:
            dr.sync_thread()
            t0 = time.perf_counter()
            p = build_patches(scene, max_patches=budget)
            dr.sync_thread()
            t1 = time.perf_counter()
            sol = solve_radiosity(scene, p, progress=False)
            geo = p.geometric_area if p.geometric_area is not None else p.area
            hidden = 1.0 - p.area.sum() / geo.sum()
            part = np.mean((p.area < 0.999 * geo) & (p.area > 0))
            print(f"max_patches={budget}: {p.count} patches, hidden area {hidden:.3%}, "
                  f"{part:.1%} patches partly hidden, {np.mean(p.area == 0):.1%} fully; "
                  f"build {t1 - t0:.3f} s, solve {sol.seconds:.3f} s")
    if not args.specs:
        return 0
    ref = cached_reference(args.scene, args.res)
    print(f"{args.scene} {args.res}² {args.spp} spp, seed {args.seed}")
    for spec in args.specs:
        img, prepass = render(scene, spec, args.spp, args.seed)
        ratio = img.mean() / ref.mean()
        print(f"  {spec:48s} ratio {ratio:.4f}  relMSE {relmse(img, ref):.4e}  "
              f"prepass {prepass:.3f} s")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
