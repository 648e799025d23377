"""Bias under the noise: image means of K independent renders per integrator against the first.

    .venv/bin/python tools/image_means.py ../shared/scenes/veach-bidir/scene.xml \
        --res 32 --spp 256 -k 40 path radiosity_gather spike_gather

Every render uses a fresh integrator and its own seed (1000 + 17·k), so a prepass's randomness
is part of the spread; the same seeds for every spec (``ptracer`` as the first spec: the
reference where ``path`` cannot sample some light, docs/results/sun-behind-glass-2026-11-27).
Prints each spec's mean ± standard error,
its ratio to the first spec's and z = Δ / sqrt(se₁² + se²). Where ``check`` is noise-limited
(fireflies), this is how a bias of a percent is told from noise (README "Right on real scenes").
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import mitsuba as mi
import numpy as np

from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.scenefile import load_scene


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("specs", nargs="+", help="integrator specs NAME[:key=value...]; the first "
                                             "is the reference (usually path)")
    ap.add_argument("--res", type=int, default=32, help="film's longer side in pixels")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("-k", type=int, default=40, help="independent renders per spec")
    ap.add_argument("-D", action="append", default=[], metavar="KEY=VALUE",
                    help="scene parameter ($KEY in the XML)")
    a = ap.parse_args()
    params = dict(d.split("=", 1) for d in a.D)
    scene = load_scene(a.scene, film_res=a.res, **params)
    ref = None
    for spec in a.specs:
        means = np.array([np.mean(np.asarray(mi.render(scene, integrator=make_integrator(spec),
                                                        spp=a.spp, seed=1000 + 17 * k))[..., :3])
                          for k in range(a.k)])
        m, se = float(means.mean()), float(means.std(ddof=1) / np.sqrt(a.k))
        if ref is None:
            ref = (m, se)
        z = (m - ref[0]) / np.hypot(se, ref[1]) if spec != a.specs[0] else 0.0
        print(f"{spec:45s} mean {m:.5f} ± {se:.5f}  ratio {m / ref[0]:.4f}  z {z:.2f}",
              flush=True)


if __name__ == "__main__":
    main()
