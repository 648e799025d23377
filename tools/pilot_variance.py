"""Path's relative variance as twopass's pilot measures it, against three pixel references:
its own pilot's means, the plain average of its and a candidate's pilot means (the reference
of every pilot until session 9), and the candidate's means alone
(``mi_twopass.compose.pilot.path_reference``, what twopass uses for path since).

    .venv/bin/python tools/pilot_variance.py scenes_xml/caustic.xml rex --res 256 --pairs 6

A heavy-tailed estimator (caustic paths) normalises its own fireflies away against its own
means: the first two columns underestimate what the harness's curve shows.
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import mitsuba as mi

from mi_twopass.compose.choose import candidate_estimator, path_sum_estimator
from mi_twopass.compose.pilot import (choose_pixels, path_reference, pixel_means,
                                      relative_variance, run_samples)
from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.integrators.component_path import ComponentPathIntegrator
from mi_twopass.scenefile import load_scene


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("candidate", help="integrator spec NAME[:key=value...], e.g. rex:photons=1000000")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--pairs", type=int, default=6, help="pilot pairs (path, candidate)")
    ap.add_argument("--pixels", type=int, default=1024)
    ap.add_argument("--samples", type=int, default=144, help="samples per pixel of each pilot")
    args = ap.parse_args()
    scene = load_scene(args.scene, film_res=args.res)
    sensor = scene.sensors()[0]
    props = mi.Properties()
    props["max_depth"] = -1
    path = ComponentPathIntegrator(props)
    cand = make_integrator(args.candidate)
    cand.ensure_prepass(scene, 0, sensor)
    pixels = choose_pixels(sensor, args.pixels, 0)
    print("pair  path: own means  plain pool  candidate's means | candidate: plain pool")
    for k in range(args.pairs):
        vp, _ = run_samples(scene, sensor, pixels, args.samples, path_sum_estimator(path), 10 + k)
        vc, _ = run_samples(scene, sensor, pixels, args.samples, candidate_estimator(cand),
                            50 + k)
        plain = 0.5 * (pixel_means(vp) + pixel_means(vc))
        others = path_reference(vp, [vc])
        print(f"{k:4d}  {relative_variance(vp, pixel_means(vp)):14.3g} "
              f"{relative_variance(vp, plain):11.3g} {relative_variance(vp, others):18.3g} | "
              f"{relative_variance(vc, plain):21.3g}")


if __name__ == "__main__":
    main()
