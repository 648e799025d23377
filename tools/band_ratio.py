"""Image means over ``path``'s reference in horizontal bands of the film, per integrator.

    .venv/bin/python tools/band_ratio.py SCENE.xml SPEC [SPEC ...] --bands 228:236 236:244 \\
        [--res 256] [--spp 128] [--ref-spp 2048] [--seed 1]

A regional bias too dark to move ``check``'s block relMSE (whose 0.01 in the denominator
discounts dark blocks) shows here as a band reading 1.2 where ``path`` reads 1.00: each row is
one render (seed ``--seed``, so one prepass) against the cached reference (``MI_TWOPASS_CACHE``),
the mean of each band's pixels (all channels) over the reference's.
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import mitsuba as mi
import numpy as np

from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.evaluation.reference import reference_image
from mi_twopass.scenefile import load_scene


def band(text: str) -> tuple[int, int]:
    first, end = (int(v) for v in text.split(":"))
    if end <= first:
        raise argparse.ArgumentTypeError(f"band {text!r}: END must exceed FIRST")
    return first, end


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("specs", nargs="+", help="integrator specs, NAME[:key=value...]")
    ap.add_argument("--bands", type=band, nargs="+", required=True, metavar="FIRST:END",
                    help="film rows FIRST (inclusive) to END (exclusive)")
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    ref = reference_image(a.scene, {}, a.ref_spp, film_res=a.res)[..., :3]
    scene = load_scene(a.scene, film_res=a.res)
    print("| spec | " + " | ".join(f"rows {r0}:{r1}" for r0, r1 in a.bands) + " |")
    print("| --- |" + " --- |" * len(a.bands))
    for spec in a.specs:
        img = np.asarray(mi.render(scene, integrator=make_integrator(spec), spp=a.spp,
                                   seed=a.seed))[..., :3]
        cells = [f"{img[r0:r1].mean() / max(ref[r0:r1].mean(), 1e-12):.3f}"
                 for r0, r1 in a.bands]
        print(f"| {spec} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
