"""Where twopass's own time goes when it renders ``path``: its renders beside ``path``'s, the
scene fingerprint (the prepass key) alone, and a profile of its render.

    python tools/twopass_overhead.py scenes_xml/many_lights.xml [--res 256] [--spp 4]

Set ``MI_TWOPASS_VARIANT=cuda_ad_rgb`` for the GPU. Each render is a fresh integrator (as the
harness renders every point), timed to the numpy copy, after one untimed render each that
compiles the kernels; ``--repeats`` renders of each, path's and twopass's interleaved, give the
fastest and the median. Then ``--repeats`` fingerprints of the
scene (with and without the camera) are timed, and one twopass render is profiled
(cProfile, the ``--top`` entries by cumulative time).
"""
import argparse
import cProfile
import io
import pstats
import time

import mitsuba as mi

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)

import numpy as np

from mi_twopass.integrators.base import parameter_fingerprint
from mi_twopass.scenefile import load_scene


def render_seconds(scene, spec: dict, spp: int) -> float:
    """One render with a fresh integrator, to the numpy copy."""
    integ = mi.load_dict(spec)
    t0 = time.perf_counter()
    np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=1))
    return time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--top", type=int, default=25)
    a = ap.parse_args()
    scene = load_scene(a.scene, film_res=a.res)
    print(f"variant {mi.variant()}, {a.scene} at {a.res} px, {a.spp} spp", flush=True)
    specs = ({"type": "path"}, {"type": "twopass"})
    for spec in specs:
        render_seconds(scene, spec, a.spp)  # compiles
    times = {spec["type"]: [] for spec in specs}
    for _ in range(a.repeats):  # interleaved: the machine's drift falls on both alike
        for spec in specs:
            times[spec["type"]].append(render_seconds(scene, spec, a.spp))
    for name, t in times.items():
        print(f"{name:8s} render {min(t) * 1000:.1f} ms fastest, {np.median(t) * 1000:.1f} ms "
              f"median of {a.repeats}", flush=True)
    for camera in (False, True):
        times = []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            parameter_fingerprint(scene, skip_camera=not camera)
            times.append(time.perf_counter() - t0)
        print(f"fingerprint (camera {camera}): {min(times) * 1000:.1f} ms, "
              f"{len(mi.traverse(scene).keys())} parameters", flush=True)
    profile = cProfile.Profile()
    profile.enable()
    render_seconds(scene, {"type": "twopass"}, a.spp)
    profile.disable()
    out = io.StringIO()
    pstats.Stats(profile, stream=out).sort_stats("cumtime").print_stats(a.top)
    print(out.getvalue())


if __name__ == "__main__":
    main()
