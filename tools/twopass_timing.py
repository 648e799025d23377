"""Whole twopass renders, timed, with what twopass built and chose: its overhead before/after.

    .venv/bin/python tools/twopass_timing.py scenes_xml/mixed_room.xml --res 256 --spp 256 \
        [--seeds 1 2]

One render at seed 0 compiles the kernels; then one fresh twopass per seed renders ``--spp``
samples per pixel, timed after the numpy conversion (``dr.sync_thread``). Prints per seed the
seconds, ``prepass_seconds`` (the pilot and every prepass built), how many candidates were
built and the composition chosen. Run two checkouts alternately (``PYTHONPATH``) to compare
(docs/results/twopass-shared-solve-2026-11-28).
"""
import argparse
import time

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import mitsuba as mi
import numpy as np

from mi_twopass.scenefile import load_scene


def timed_renders(scene, spp: int, seeds, before_each=None):
    """One twopass render at seed 0 (it compiles the kernels), then one fresh twopass per seed
    of ``seeds``: yields ``(seed, seconds to the numpy copy, the integrator)``.
    ``before_each()``, where given, is called just before each timed render."""
    np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "twopass"}), spp=spp, seed=0))
    for seed in seeds:
        if before_each is not None:
            before_each()
        integ = mi.load_dict({"type": "twopass"})
        t = time.perf_counter()
        np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=seed))
        yield seed, time.perf_counter() - t, integ


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    a = ap.parse_args()
    scene = load_scene(a.scene, film_res=a.res)
    for seed, t, integ in timed_renders(scene, a.spp, a.seeds):
        st = integ.stats
        print(f"seed {seed}: {t:.2f} s, pilot+prepasses {st['prepass_seconds']:.2f} s, "
              f"built {len(st['twopass_candidates'])}, chose {st['twopass_choice']}", flush=True)


if __name__ == "__main__":
    main()
