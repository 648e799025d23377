"""Seconds of repeated whole renders (prepass included, as the harness times a point), per
integrator spec, interleaved so that the machine's drift hits every spec alike: min and median.

    .venv/bin/python tools/repeat_timing.py scenes_xml/cornell_box.xml --res 256 --spp 32 \\
        path twopass --repeat 7

The harness times one render per point; on a 2-core machine two renders of 0.4 s differ by
several per cent, so a speed-up of 0.93 at one point is read against this.
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import numpy as np

from mi_twopass.evaluation.harness import timed_render
from mi_twopass.scenefile import load_scene


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("specs", nargs="+", help="integrator specs NAME[:key=value...]")
    ap.add_argument("--res", type=int, default=128, help="film's longer side in pixels")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    scene = load_scene(args.scene, film_res=args.res)
    for spec in args.specs:  # compile, untimed
        timed_render(scene, spec, args.spp, 1)
    seconds = {spec: [] for spec in args.specs}
    for r in range(args.repeat):
        for spec in args.specs:
            seconds[spec].append(timed_render(scene, spec, args.spp, 10 + r)[1])
    for spec in args.specs:
        print(f"{spec:<32} min {min(seconds[spec]):.4f} s  median {np.median(seconds[spec]):.4f} s")


if __name__ == "__main__":
    main()
