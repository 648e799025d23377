"""Where an integrator's bias is, per pixel: two renders against the cached `path` reference.

    .venv/bin/python tools/bias_map.py scenes_xml/window_interior.xml radiance_cache \
        --res 256 --spp 256 --ref-spp 2048 -o out/bias_map.png

Two renders of ``--spp`` each, with seeds 0 and 1 (so two prepasses), against the reference
of ``reference.reference_image`` (``MI_TWOPASS_CACHE`` holds it, rendered on a miss). Per pixel
and channel, with relMSE's denominator R² + ε (``metrics.RELMSE_EPS``):

* relMSE of the two renders' mean;
* its noise part, (a − b)² / 4 over R² + ε;
* its bias part, (a − R)(b − R) over R² + ε: the mean of the products of the two renders'
  errors. The renders' noise cancels in it; what no number of samples removes stays, that is
  the bias, the prepasses' shared error and the reference's own noise.

Prints the three, and the bias part as a table of 16×16-pixel blocks (×1e3). Writes a PNG of
the reference, the two renders' mean and their relative difference: red brighter, blue darker,
full scale ±``--scale``. docs/results/radiance-cache-far-reads-2026-11-28/remaining-bias.png
came from this command.
"""
import argparse

import numpy as np
from PIL import Image

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import mitsuba as mi

from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.evaluation.metrics import RELMSE_EPS
from mi_twopass.evaluation.reference import reference_image
from mi_twopass.scenefile import load_scene

#: side of the blocks of the printed table
BLOCK = 16


def tonemap(x):
    """x / (1 + x), gamma 2.2, 8 bits."""
    return (np.clip(x / (1.0 + x), 0.0, 1.0) ** (1.0 / 2.2) * 255).astype(np.uint8)


def difference_image(mean, ref, scale):
    """Relative difference (mean − ref) / (ref + 0.1), averaged over the channels: red where
    brighter, blue where darker, full at ±``scale``."""
    e = np.clip(((mean - ref) / (ref + 0.1)).mean(axis=-1) / scale, -1.0, 1.0)
    rgb = np.zeros(e.shape + (3,), np.uint8)
    rgb[..., 0] = (np.maximum(e, 0.0) * 255).astype(np.uint8)
    rgb[..., 2] = (np.maximum(-e, 0.0) * 255).astype(np.uint8)
    return rgb


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("spec", help="integrator spec NAME[:key=value...]")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--spp", type=int, default=256, help="samples per pixel of each render")
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--scale", type=float, default=0.2, help="full scale of the picture")
    ap.add_argument("-o", "--output", default="out/bias_map.png")
    a = ap.parse_args()
    ref = reference_image(a.scene, {}, a.ref_spp, film_res=a.res)
    scene = load_scene(a.scene, film_res=a.res)
    integrator = make_integrator(a.spec)
    r1, r2 = (np.asarray(mi.render(scene, integrator=integrator, spp=a.spp, seed=s))
              for s in (0, 1))
    den = ref ** 2 + RELMSE_EPS
    mean = 0.5 * (r1 + r2)
    bias = (r1 - ref) * (r2 - ref) / den
    print(f"{a.spec} on {a.scene} at {a.res} px, 2 x {a.spp} spp against {a.ref_spp} spp")
    print(f"relMSE of the mean {np.mean((mean - ref) ** 2 / den):.3e}   "
          f"noise part {np.mean((r1 - r2) ** 2 / 4 / den):.3e}   bias part {bias.mean():.3e}")
    h, w = (s - s % BLOCK for s in bias.shape[:2])
    blocks = bias[:h, :w].mean(axis=-1).reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK)
    print(f"bias part x 1e3 in {BLOCK}x{BLOCK} blocks:")
    with np.printoptions(precision=1, suppress=True, linewidth=200):
        print(blocks.mean(axis=(1, 3)) * 1e3)
    picture = np.concatenate([tonemap(ref), tonemap(mean),
                              difference_image(mean, ref, a.scale)], axis=1)
    Image.fromarray(picture).resize((picture.shape[1] * 2, picture.shape[0] * 2),
                                    Image.NEAREST).save(a.output)
    print(f"wrote {a.output}")


if __name__ == "__main__":
    main()
