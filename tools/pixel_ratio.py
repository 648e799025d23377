"""An integrator's image over ``path``'s reference, pixel by pixel, in a window of the film.

    .venv/bin/python tools/pixel_ratio.py scenes_xml/window_interior.xml radiance_cache \
        --rows 68 72 --cols 180 196 [--res 256] [--spp 256] [--ref-spp 2048]

The mean of two renders (seeds 0 and 1, so two prepasses) over the cached reference
(``MI_TWOPASS_CACHE``), channel-mean luminance, printed as a table: where a bias map
(``tools/bias_map.py``) shows a block, this shows its pixels (a strip a few pixels high reads
0.3 where its neighbours read 1).
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import mitsuba as mi
import numpy as np

from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.evaluation.reference import reference_image
from mi_twopass.scenefile import load_scene


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("spec", help="integrator spec, NAME[:key=value...]")
    ap.add_argument("--rows", type=int, nargs=2, required=True, metavar=("FIRST", "END"))
    ap.add_argument("--cols", type=int, nargs=2, required=True, metavar=("FIRST", "END"))
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--ref-spp", type=int, default=2048)
    a = ap.parse_args()
    ref = reference_image(a.scene, {}, a.ref_spp, film_res=a.res)[..., :3].mean(axis=-1)
    scene = load_scene(a.scene, film_res=a.res)
    imgs = [np.asarray(mi.render(scene, integrator=make_integrator(a.spec), spp=a.spp,
                                 seed=s))[..., :3].mean(axis=-1) for s in (0, 1)]
    mean = (imgs[0] + imgs[1]) / 2
    (r0, r1), (c0, c1) = a.rows, a.cols
    np.set_printoptions(precision=2, linewidth=250, suppress=True)
    print(f"{a.spec} over path ({a.ref_spp} spp), rows {r0}:{r1}, columns {c0}:{c1}")
    print(mean[r0:r1, c0:c1] / np.maximum(ref[r0:r1, c0:c1], 1e-3))


if __name__ == "__main__":
    main()
