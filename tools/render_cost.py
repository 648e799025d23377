"""Render cost per sample against Mitsuba's ``path``, the prepass built once and reused.

    .venv/bin/python tools/render_cost.py scenes_xml/office.xml --res 128 --spp 32 \\
        path radiosity_gather

Issue 13 asks for each integrator's cost per sample next to ``path``'s (spike_gather ≤ 1.3×,
radiance_cache's render ≤ 3×). Every spec renders once at 4 spp with seed 0 (its prepass and
kernel compilation), then ``--repeats`` times at ``--spp`` with the same seed, so the prepass
(whose seed is the render's) is reused and only the render is timed, after ``dr.sync_thread()``
via the numpy conversion; the fastest repeat counts (a 2-core machine is noisy). Prints seconds
and the ratio to the first spec's.
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)

from mi_twopass.evaluation.harness import make_integrator, render_only_seconds
from mi_twopass.scenefile import load_scene


def render_seconds(scene, spec: str, spp: int, repeats: int) -> float:
    """Fastest of ``repeats`` renders of ``spp`` samples per pixel, the prepass reused."""
    integ = make_integrator(spec)
    return min(render_only_seconds(scene, integ, spp, 0)[1] for _ in range(repeats))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("specs", nargs="+", help="integrator specs NAME[:key=value...]; the first "
                                             "is the baseline (usually path)")
    ap.add_argument("--res", type=int, default=128, help="film's longer side in pixels")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    scene = load_scene(a.scene, film_res=a.res)
    base = None
    for spec in a.specs:
        s = render_seconds(scene, spec, a.spp, a.repeats)
        base = s if base is None else base
        print(f"{spec:45s} {s:8.3f} s   {s / base:5.2f}x {a.specs[0]}", flush=True)


if __name__ == "__main__":
    main()
