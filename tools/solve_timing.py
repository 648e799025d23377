"""The radiosity solve alone (particle tracing and deposits), timed per scene.

    .venv/bin/python tools/solve_timing.py scenes_xml/*.xml [--res 256] [--repeats 5]
        [--mode Direct|Auto|Local|Expand]

Per scene: the patches and receiving elements of the default radiosity settings, then
``solve_radiosity`` with the default particle count (unguided), ``--repeats`` times with seeds
0, 1, …; prints the median seconds (the first solve compiles the kernel and is dropped when
there are at least three), the particles and the rays. ``--mode`` sets how the deposits'
scatter-additions are compiled (``radiosity._DEPOSIT_MODE``: ``dr.ReduceMode``), so one
command gives both sides of a before/after comparison.
"""
import argparse
import statistics
import time

import drjit as dr

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.prepass import radiosity
from mi_twopass.scene.patches import build_patches
from mi_twopass.scenefile import load_scene, scene_label


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--mode", default=None, help="dr.ReduceMode of the deposits")
    a = ap.parse_args()
    if a.mode:
        radiosity._DEPOSIT_MODE = getattr(dr.ReduceMode, a.mode)
    settings = radiosity.RadiositySettings()
    print(f"deposits: {radiosity._DEPOSIT_MODE}")
    print("| scene | patches | elements | particles | rays | solve s (median) |")
    print("| --- | --- | --- | --- | --- | --- |")
    for path in a.scenes:
        scene = load_scene(path, film_res=a.res)
        patches = build_patches(scene, max_patches=settings.max_patches, seed=0)
        elements = radiosity.receiving_elements(scene, settings.max_patches,
                                                settings.elements_per_patch, 0)
        n = max(settings.min_particles, settings.particles_per_patch * patches.count)
        times, solution = [], None
        for seed in range(a.repeats):
            t0 = time.perf_counter()
            solution = radiosity.solve_radiosity(scene, patches, n_particles=n, seed=seed,
                                                 elements=elements, progress=False)
            dr.sync_thread()
            times.append(time.perf_counter() - t0)
        kept = times[1:] if len(times) >= 3 else times
        print(f"| {scene_label(path)} | {patches.count} | {elements.count} | {n} | "
              f"{solution.rays} | {statistics.median(kept):.4f} |", flush=True)


if __name__ == "__main__":
    main()
