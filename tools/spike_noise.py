"""Pixel variance of ``spike_gather`` (or any integrator) settings on a scene, fresh prepass per
render: what the camera pass, gather cells, visibility rays... do to the noise.

    python tools/spike_noise.py SPEC [SPEC...] [--scene S.xml] [-D res=64] [--spp 128] [--renders 5]

Prints, per spec, the mean over pixels of var/(ref² + 0.01) across the renders (the noise part
of relMSE at that spp), the median and largest relMSE of one render, and the median prepass
seconds. The reference is the cached path reference (``--ref-spp``).
"""
import argparse

import mi_twopass  # noqa: F401
import mitsuba as mi
import numpy as np

from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.evaluation.metrics import RELMSE_EPS
from mi_twopass.evaluation.reference import reference_image
from mi_twopass.scenefile import load_scene, parse_defines


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("specs", nargs="+")
    ap.add_argument("--scene", default="scenes_xml/many_lights.xml")
    ap.add_argument("-D", dest="defines", action="append", default=[])
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--renders", type=int, default=5)
    ap.add_argument("--ref-spp", type=int, default=16384)
    a = ap.parse_args()
    if a.renders < 2:
        ap.error("--renders must be >= 2 (a variance needs two)")
    params = parse_defines(a.defines or ["res=64"])
    ref = np.asarray(reference_image(a.scene, params, spp=a.ref_spp, verbose=True))[..., :3]
    scene = load_scene(a.scene, **params)
    for spec in a.specs:
        imgs, pre = [], []
        for s in range(a.renders):
            integ = make_integrator(spec)
            imgs.append(np.asarray(mi.render(scene, integrator=integ, spp=a.spp, seed=100 + s))[..., :3])
            pre.append((getattr(integ, "stats", {}) or {}).get("prepass_seconds", 0.0))
        imgs = np.array(imgs)
        noise = float((imgs.var(axis=0, ddof=1) / (ref ** 2 + RELMSE_EPS)).mean())
        per = [float(((i - ref) ** 2 / (ref ** 2 + RELMSE_EPS)).mean()) for i in imgs]
        print(f"{spec:45s} noise {noise:.4f}  relMSE of one render: median {np.median(per):.4f} "
              f"max {np.max(per):.4f}  prepass {np.median(pre):.2f} s", flush=True)


if __name__ == "__main__":
    main()
