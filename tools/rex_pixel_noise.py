"""rex's photon noise per pixel, as the budget's noise model would predict it.

    .venv/bin/python tools/rex_pixel_noise.py SCENE.xml [SCENE.xml ...] [--res 256]

The automatic photon budget (:func:`mi_twopass.prepass.rex_textures.photon_need`) holds the
8×8-block relMSE the photons' noise leaves in the image
(:func:`~mi_twopass.prepass.rex_textures.predicted_noise`). This reads the same model per
pixel: each pixel's a²·Var(E_b) (a = β·ρ/π, Var(E_b) of the bucket at the size pass's cap, from
the probe shoot's deposits) over (its radiance² + ε), averaged over the modelled pixels, at
the photons the budget picks for ``rex`` with its defaults. Prints it beside the block figure
the budget holds. Compare it with rex's floor in the harness (``bench``, relMSE at the largest
spp): the model takes every bucket split down to the cap, so it overestimates where buckets
stay coarser (docs/results/sharp-light-gate-2026-11-29).
"""
import argparse

import mitsuba as mi
import numpy as np

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass import units
from mi_twopass.evaluation.metrics import RELMSE_EPS
from mi_twopass.prepass import rex_textures as R
from mi_twopass.prepass.sharp_light import pixel_radiance
from mi_twopass.scenefile import load_scene, scene_label


def pixel_noise(scene, seed: int = 0):
    """``(photons, block relMSE predicted, pixel relMSE predicted)`` at rex's default budget."""
    settings = mi.load_dict({"type": "rex"}).rex_settings(scene)
    m = R.measure_probe(scene, settings, seed)
    photons, stats = R.photon_need(m.need, settings, m.power, *m.probe, tables=m.tables)
    need, tables, records = m.need, m.tables, m.probe[3]
    hits = need.get("hits", {})
    if not len(hits.get("rex", ())) or not len(records["rex"]):
        return photons, 0.0, 0.0
    s1, s2, _ = R.probe_cell_sums(tables, records)
    cell, area_c = R.hit_cells(tables, hits)
    area_b = hits["jac"] * np.ldexp(1.0, -2 * hits["level"])
    var = np.where(area_b > 0, s2[cell] * records["photons"]
                   / (area_c * np.maximum(area_b, 1e-300)), 0.0)
    a = hits["beta"] * hits["albedo"] * units.INV_PI
    model, radiance = pixel_radiance(need, a * s1[cell] / area_c)
    noise = np.zeros(len(radiance))
    np.add.at(noise, hits["pixel"], a * a * var)
    pixel = float(np.mean(noise[model] / (radiance[model] ** 2 + RELMSE_EPS))) / photons
    return photons, float(stats.get("predicted_relmse", 0.0)), pixel


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    args = ap.parse_args()
    print("| scene | photons | block relMSE predicted | pixel relMSE predicted |")
    print("| --- | --- | --- | --- |")
    for path in args.scenes:
        photons, block, pixel = pixel_noise(load_scene(path, film_res=args.res))
        print(f"| {scene_label(path)} | {photons / 1e6:.2f} M | {block:.2g} | {pixel:.2g} |",
              flush=True)


if __name__ == "__main__":
    main()
