"""Where one integrator's prepass spends its time: cProfile of a build, kernels already compiled.

    .venv/bin/python tools/prepass_profile.py SCENE.xml INTEGRATOR [--res 256] [--top 30]

Builds the prepass twice with fresh integrators (seeds 0 and 1): the first compiles (or loads)
its kernels, the second is profiled. Prints both builds' seconds, then the second's functions
by cumulative time. Dr.Jit evaluates lazily, so a kernel's execution shows under the call
that first reads its result (often ``numpy.array`` or ``numpy.asarray``). Session 31
(docs/results/sharp-light-gate-2026-11-29) used it on many_lights for radiance_cache and
spike_gather.
"""
import argparse
import cProfile
import pstats
import time

import drjit as dr
import mitsuba as mi

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.scenefile import load_scene


def build(scene, integrator: str, seed: int) -> float:
    """Seconds of one prepass build of a fresh ``integrator`` (to the last kernel's end)."""
    integ = mi.load_dict({"type": integrator})
    t0 = time.perf_counter()
    integ.ensure_prepass(scene, seed, scene.sensors()[0])
    dr.sync_thread()
    return time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("integrator")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--top", type=int, default=30, help="functions to list")
    args = ap.parse_args()
    scene = load_scene(args.scene, film_res=args.res)
    print(f"first build (kernels compiled or loaded): {build(scene, args.integrator, 0):.3f} s")
    profile = cProfile.Profile()
    profile.enable()
    seconds = build(scene, args.integrator, 1)
    profile.disable()
    print(f"second build, profiled: {seconds:.3f} s")
    pstats.Stats(profile).sort_stats("cumulative").print_stats(args.top)


if __name__ == "__main__":
    main()
