"""How many patches the radiosity prepass reclassifies as virtual luminaires, over solve seeds.

    .venv/bin/python tools/virtual_luminaires.py scenes_xml/office.xml --seeds 4

GSII's rule (B_r ≥ vl_threshold × max B_r) follows the noise of the brightest patch; the
contrast bound (B_r ≥ vl_contrast × the area-weighted mean, ``prepass.radiosity.VL_CONTRAST``)
keeps only patches that stand out of the field. Prints, per seed, max B_r over that mean and
the count (and its share of the cached area and of their reflected power) each rule picks, with spike_gather's default radiosity budget.
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import mitsuba as mi
import numpy as np

from mi_twopass.prepass import radiosity as R
from mi_twopass.scenefile import load_scene


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--vl-threshold", type=float, default=0.5)
    ap.add_argument("--contrasts", default="0,4,8", help="comma-separated vl_contrast values")
    a = ap.parse_args()
    scene = load_scene(a.scene, film_res=a.res)
    budget = mi.load_dict({"type": "spike_gather"}).radiosity
    contrasts = [float(c) for c in a.contrasts.split(",")]
    for seed in range(a.seeds):
        sol = R.build(scene, budget, seed, progress=False).solution
        Br = np.asarray(sol.B_reflected).mean(axis=1)
        area = np.asarray(sol.patches.area)
        ok = sol.patches.is_diffuse & (Br > 0) & (area > 0)
        mean = np.sum(Br[ok] * area[ok]) / np.sum(area[ok])
        cells = []
        for c in contrasts:
            ids = R.reclassified_patches(Br, area, sol.patches.is_diffuse, a.vl_threshold, c)
            power = Br * area
            cells.append(f"contrast {c:g}: {ids.size} (area {area[ids].sum() / area[ok].sum():.1%},"
                         f" power {power[ids].sum() / power[ok].sum():.1%})")
        print(f"seed {seed}: max/mean {Br.max() / mean:5.1f}   " + "   ".join(cells), flush=True)


if __name__ == "__main__":
    main()
