"""How heavy-tailed path's pilot samples are, per part of path space, on each scene.

    .venv/bin/python tools/pilot_tails.py scenes_xml/*.xml ../shared/scenes/*/*.xml --res 256

twopass's pilot (1024 pixels x 144 samples, ``mi_twopass.compose.pilot``) traced by the
component path tracer, as ``twopass`` runs it. Per part (all, direct, caustic, indirect, and
caustic + indirect) it prints the relative variance v (``pilot.relative_variance`` against the
pilot's own pixel means), the share of the sum of squared relative deviations that the largest
0.1 % of the (sample, channel) terms carry, and the relative standard error of that sum
(sqrt(sum of (d^2 - mean d^2)^2) / sum of d^2). A share near 1 means a few samples carry the
variance: fireflies the pilot has seen a handful of times, so its v is far from settled.
"""
import argparse

import mitsuba as mi
import numpy as np

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.compose import cost
from mi_twopass.compose.choose import path_pilot
from mi_twopass.compose.pilot import PilotSettings, choose_pixels, pixel_means, relative_variance
from mi_twopass.evaluation.metrics import RELMSE_EPS
from mi_twopass.scenefile import load_scene, scene_label

#: the share of the terms whose part of the sum is printed
TOP = 0.001


def tail_figures(values, reference):
    """(v, share of the largest TOP of the terms, relative standard error of their sum)."""
    d2 = (values - values.mean(axis=1, keepdims=True)) ** 2 / (reference[:, None, :] ** 2
                                                              + RELMSE_EPS)
    flat = np.sort(d2.ravel())[::-1]
    total = max(float(flat.sum()), 1e-30)
    top = flat[:max(1, int(len(flat) * TOP))].sum() / total
    rse = float(np.sqrt(((d2 - d2.mean()) ** 2).sum()) / total)
    return relative_variance(values, reference), top, rse


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    names = ("all", "direct", "caustic", "indirect", "caustic + indirect")
    print("| scene | " + " | ".join(f"{n}: v / top 0.1 % / rse" for n in names) + " |")
    print("| --- " * (1 + len(names)) + "|")
    settings = PilotSettings()
    for path in a.scenes:
        scene = load_scene(path, film_res=a.res)
        sensor = scene.sensors()[0]
        path_integ = mi.load_dict({"type": "twopass"}).candidate(cost.COMPOSITIONS[0])
        pixels = choose_pixels(sensor, settings.pixels, a.seed)
        run, parts = path_pilot(scene, sensor, pixels, settings, path_integ, a.seed)
        ref = pixel_means(run.values)
        cells = [tail_figures(v, ref) for v in
                 (run.values, parts[0], parts[1], parts[2], parts[1] + parts[2])]
        print(f"| {scene_label(path)} | "
              + " | ".join(f"{v:.3g} / {top:.2f} / {rse:.3f}" for v, top, rse in cells) + " |",
              flush=True)


if __name__ == "__main__":
    main()
