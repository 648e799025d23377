"""Seconds of one ``build_patches`` (patches or receiving elements) per scene and budget.

    .venv/bin/python tools/patch_build_seconds.py scenes_xml/*.xml ../shared/scenes/*/*.xml \\
        [--budgets 1024,16384] [--repeats 5] [--res 256]

Per scene and patch budget: the median of ``--repeats`` builds (seeds 1…), after one build
that compiles or loads the kernels, each timed to its last kernel's end. The radiosity
prepass builds two: ``max_patches`` patches and 16 × that many receiving elements
(``radiosity_gather``'s defaults: 1024 and 16384). Run two checkouts alternately
(``PYTHONPATH``) to compare a change; session 32 did so for the property points made in
Dr.Jit (docs/results/prepass-points-2026-11-29).
"""
import argparse
import statistics
import time

import drjit as dr

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.scene.patches import build_patches, scene_shapes
from mi_twopass.scenefile import load_scene, scene_label


def build_seconds(scene, shapes, budget: int, seed: int) -> float:
    """Seconds of one build of ``budget`` patches (to the last kernel's end)."""
    dr.sync_thread()
    t0 = time.perf_counter()
    build_patches(scene, max_patches=budget, seed=seed, shapes=shapes)
    dr.sync_thread()
    return time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--budgets", default="1024,16384", help="comma-separated max_patches")
    ap.add_argument("--repeats", type=int, default=5, help="timed builds per budget")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    a = ap.parse_args()
    budgets = [int(b) for b in a.budgets.split(",")]
    print("| scene | " + " | ".join(f"{b} patches s" for b in budgets) + " |")
    print("| --- |" + " --- |" * len(budgets))
    for path in a.scenes:
        scene = load_scene(path, film_res=a.res)
        shapes = scene_shapes(scene)
        cells = []
        for budget in budgets:
            build_seconds(scene, shapes, budget, 0)  # kernels compiled or loaded
            cells.append(statistics.median(build_seconds(scene, shapes, budget, seed)
                                           for seed in range(1, a.repeats + 1)))
        print(f"| {scene_label(path)} | " + " | ".join(f"{c:.3f}" for c in cells) + " |",
              flush=True)


if __name__ == "__main__":
    main()
