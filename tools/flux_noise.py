"""A guided radiosity solve's particle target (``radiosity.FLUX_NOISE``) against what it buys.

    .venv/bin/python tools/flux_noise.py scenes_xml/window_interior.xml radiosity_gather \
        --values 0.0025,0.005 [--res 256] [--seeds 4] [--spp 128] [--mean-seeds 10] [--mean-spp 32]

For each value of the module constant (set in this process), per ``--seeds`` prepass seeds a
render of ``--spp`` against the cached ``path`` reference (``MI_TWOPASS_CACHE``, 2048 spp):
the solve's particles, the median prepass seconds, the bias part (the mean over pairs of
renders of their error products over R² + ε, as ``tools/bias_map.py``: what the samples'
noise does not explain) and one render's relMSE; then the spread of the image mean between
``--mean-seeds`` prepass seeds at ``--mean-spp`` (relative standard deviation, the renders'
own noise included). A first render, discarded, compiles the kernels.
docs/results/flux-noise-2026-11-28 came from this command.
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import mitsuba as mi
import numpy as np

from mi_twopass.evaluation.metrics import RELMSE_EPS
from mi_twopass.evaluation.reference import reference_image
from mi_twopass.prepass import radiosity
from mi_twopass.scenefile import load_scene


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("integrator")
    ap.add_argument("--values", default="0.0025,0.005")
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--mean-seeds", type=int, default=10)
    ap.add_argument("--mean-spp", type=int, default=32)
    a = ap.parse_args()
    ref = reference_image(a.scene, {}, 2048, film_res=a.res)[..., :3]
    den = ref ** 2 + RELMSE_EPS
    scene = load_scene(a.scene, film_res=a.res)
    # compile the kernels first, so that no value's prepass time holds them
    mi.render(scene, integrator=mi.load_dict({"type": a.integrator}), spp=1, seed=99)
    for value in (float(v) for v in a.values.split(",")):
        radiosity.FLUX_NOISE = value
        imgs, prepass, particles = [], [], []
        for s in range(a.seeds):
            integ = mi.load_dict({"type": a.integrator})
            imgs.append(np.asarray(mi.render(scene, integrator=integ, spp=a.spp,
                                             seed=s))[..., :3])
            prepass.append(integ.stats["prepass_seconds"])
            particles.append(integ.structure.solution.particles)
        err = [im - ref for im in imgs]
        bias = np.mean([(err[i] * err[j] / den).mean()
                        for i in range(len(err)) for j in range(i + 1, len(err))])
        relmse = np.mean([(e ** 2 / den).mean() for e in err])
        means = np.array([np.asarray(mi.render(scene, integrator=mi.load_dict(
            {"type": a.integrator}), spp=a.mean_spp, seed=s))[..., :3].mean()
            for s in range(a.mean_seeds)])
        print(f"FLUX_NOISE {value}: particles {np.mean(particles):.0f}, prepass "
              f"{np.median(prepass):.3f} s, bias part {bias:.3e}, one render's relMSE "
              f"{relmse:.3e}; image mean {means.mean():.5f}, spread between prepass seeds "
              f"{means.std(ddof=1) / means.mean() * 100:.2f} %")


if __name__ == "__main__":
    main()
