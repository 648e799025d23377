"""How noisy is `path` on the sharp light of a scene? Predicted from photons, not from path.

    .venv/bin/python tools/sharp_variance.py SCENE.xml [SCENE.xml ...] [--res 256]

twopass tries rexes only where its path pilot finds caustics carry a share of path's variance.
Light that reaches a diffuse surface through a delta chain (a lamp behind glass) is sampled by
path only when a BSDF ray happens to find the light's image through the chain, so it comes as
rare bright samples, which a pilot of ~144 samples on a subset of pixels catches now and then
(veach-bidir: 14 % of the pilot's mean for one render seed, 0 % for two others).

Photons find that light every time. From rex's size pass (one eye sample per pixel: the rex it
reads, a = β·ρ/π, what it takes from elsewhere) and probe shoot (the sharp deposits per size
cell, :func:`~mi_twopass.prepass.rex_textures.probe_cell_sums`), per pixel:

* the sharp irradiance E_s at its rex hit;
* path's variance of one sample on that light, about (π·a)² · L · E_s / π: a BSDF ray (cosine
  sampling of a Lambertian surface, weight ρ) finds light of radiance L through the chain with
  probability E_s / (π·L) and then carries β·ρ·L. L is taken as the brightest area emitter's
  radiance (channel mean), an upper bound;
* over (the pixel's radiance² + ε), as relMSE reads it; averaged over the pixels.

Prints that prediction beside the sharp share of the image (rex's ``sharp_share``). Delta
emitters (a sun, a point light) through glass are not path-sampled at all: that light is
``compose.unsampled``'s, and L above ignores them. Session 30 (docs/results/
shape-order-sharp-light-2026-11-29) compares it with path's curves in the harness.
"""
import argparse

import numpy as np

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import mitsuba as mi

from mi_twopass import units
from mi_twopass.evaluation.metrics import RELMSE_EPS
from mi_twopass.prepass import rex_textures as R
from mi_twopass.scenefile import load_scene, scene_label


def brightest_area_radiance(scene) -> float:
    """The largest channel-mean ``radiance`` of the scene's area emitters (0 without any)."""
    params = mi.traverse(scene)
    best = 0.0
    for key in params.keys():
        if key.endswith("emitter.radiance.value"):
            value = np.asarray(params[key], np.float64).ravel()
            if 0 < value.size <= 3:  # a constant radiance (a texture is left out)
                best = max(best, float(value.mean()))
    return best


def sharp_variance(scene, seed: int = 0) -> tuple:
    """(predicted relative variance of one path sample on sharp light, sharp share)."""
    settings = R.RexSettings(direct="shadow")
    tables = R.RexTables(scene)
    _, seen, _, need = R.size_pass(scene, tables, settings, seed)
    power, adapt = R.probe_emitters(scene, seed, tables.bounds)
    *_, records = R.probe_shoot(scene, tables, seen, settings, seed, power, adapt, False)
    hits, known = need["hits"], need["known"]
    if not len(hits.get("rex", ())) or not len(records["rex"]):
        return 0.0, 0.0
    s1, _, s1_sharp = R.probe_cell_sums(tables, records)
    cell, area = R.hit_cells(tables, hits)
    a = hits["beta"] * hits["albedo"] * units.INV_PI
    width, height = need["film"]
    model = need.get("model_pixels")
    model = np.arange(width * height) if model is None else model
    radiance = np.zeros(width * height)
    radiance[model] += known
    np.add.at(radiance, hits["pixel"], a * s1[cell] / area)
    e_sharp = s1_sharp[cell] / area
    var = np.zeros(width * height)
    np.add.at(var, hits["pixel"], np.pi * a * a * brightest_area_radiance(scene) * e_sharp)
    relvar = float(np.mean(var[model] / (radiance[model] ** 2 + RELMSE_EPS)))
    share = float(np.sum(a * e_sharp) / max(radiance[model].sum(), 1e-30))
    return relvar, share


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    args = ap.parse_args()
    print("| scene | brightest area emitter L | sharp share | path's relative variance on "
          "sharp light (predicted) |")
    print("| --- | --- | --- | --- |")
    for path in args.scenes:
        scene = load_scene(path, film_res=args.res)
        relvar, share = sharp_variance(scene)
        print(f"| {scene_label(path)} | {brightest_area_radiance(scene):.4g} | {share:.4f} | "
              f"{relvar:.3g} |")


if __name__ == "__main__":
    main()
