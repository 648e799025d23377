"""How heavy-tailed an integrator's samples are at chosen pixels: the rare, huge samples a
pilot or a short render does not see.

    .venv/bin/python tools/sample_tails.py scenes_xml/many_lights.xml radiance_cache \\
        spike_gather [--res 256] --pixels 198,72 200,112 [--samples 65536] [--seed 7]

Per integrator spec (``NAME[:key=value...]``, as the bench takes them): the prepass at seed 0,
then ``--samples`` camera samples of each pixel ``X,Y``, traced by the integrator's own
estimator as twopass's pilot traces them (:func:`mi_twopass.compose.pilot.run_samples`).
Printed per pixel: the mean of the samples' channel mean, the five largest, and the share of
the sum the ten largest carry. Session 25 found radiance_cache's bright-reflector samples on
many_lights with it (docs/results/radiance-cache-spike-2026-11-28).
"""
import argparse

import numpy as np

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.compose.choose import candidate_estimator
from mi_twopass.compose.pilot import PilotPixels, run_samples
from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.scenefile import load_scene, scene_label


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("specs", nargs="+")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--pixels", nargs="+", required=True, help="X,Y film pixels")
    ap.add_argument("--samples", type=int, default=1 << 16)
    ap.add_argument("--seed", type=int, default=7, help="the samples' seed")
    a = ap.parse_args()
    scene = load_scene(a.scene, film_res=a.res)
    sensor = scene.sensors()[0]
    width, height = (int(v) for v in sensor.film().crop_size())
    xy = [tuple(int(v) for v in p.split(",")) for p in a.pixels]
    if any(not (0 <= x < width and 0 <= y < height) for x, y in xy):
        ap.error(f"--pixels must lie in the {width}x{height} film")
    pixels = PilotPixels(index=np.array([y * width + x for x, y in xy], np.uint32),
                         width=width, height=height)
    print(f"{scene_label(a.scene)} at {width}x{height}, {a.samples} samples a pixel")
    for spec in a.specs:
        integ = make_integrator(spec)
        if hasattr(integ, "ensure_prepass"):
            integ.ensure_prepass(scene, 0, sensor)
        values, _ = run_samples(scene, sensor, pixels, a.samples, candidate_estimator(integ),
                                a.seed)
        lum = values.mean(axis=2)
        for (x, y), row in zip(xy, lum):
            top = np.sort(row)[::-1]
            share = top[:10].sum() / row.sum() if row.sum() > 0 else 0.0
            print(f"{spec:32s} ({x}, {y}): mean {row.mean():.3f}, largest "
                  + " ".join(f"{v:.1f}" for v in top[:5]) + f", top 10 carry {share:.1%}",
                  flush=True)


if __name__ == "__main__":
    main()
