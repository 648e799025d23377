"""The emission guide's noise as the pilot predicts it and as it is, over prepass seeds.

    .venv/bin/python tools/guide_noise.py scenes_xml/mixed_room.xml --res 128 --seeds 100-137 \
        [--max-patches 1010] [--per-cell 4 16] [--truth 22]

For each seed: the patches, the receiving elements and the pilot exactly as the radiosity
prepass builds them (``radiosity.guide_pilot``, ``emission_guide.fitted``), then
:func:`~mi_twopass.prepass.emission_guide.image_noise` of the fitted guide twice, per particle:

* ``pred``: from the pilot's own particles (what sets the solve's particle count);
* ``true``: from 2^``truth`` particles drawn uniformly over the cells, the same camera pass.

A pilot that missed lit cells leaves them only the guide's defensive share, and particles drawn
there carry up to 1/``DEFENSIVE`` times Mitsuba's own weight: ``true`` then rises above its
median while ``pred`` cannot see it (docs/results/guide-pilot-2026-11-28). ``--per-cell``
compares values of ``emission_guide.PILOT_PER_CELL``.
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import numpy as np

from mi_twopass.prepass import emission_guide as EG
from mi_twopass.prepass import radiosity as R
from mi_twopass.scene.patches import build_patches, scene_shapes
from mi_twopass.scenefile import load_scene


def seeds_arg(text):
    if "-" in text:
        lo, hi = text.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(s) for s in text.split(",")]


def truth(scene, patches, elements, camera, cells, n, seed):
    """(cell, read, first) of ``n`` particles drawn uniformly over ``cells``."""
    parts = []
    batch = 1 << 18
    for k, first in enumerate(range(0, n, batch)):
        m = min(batch, n - first)
        c, _, read, first_ = R.pilot_trace(scene, patches, elements, camera, EG.uniform(cells),
                                           m, seed + 7919 * k)
        parts.append((c, read * (m / n), first_ * (m / n)))  # the common scale of all n
    return [np.concatenate(p) for p in zip(*parts)]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=128, help="film's longer side in pixels")
    ap.add_argument("--seeds", type=seeds_arg, default=list(range(8)),
                    help="prepass seeds: 'A-B' or 'a,b,c'")
    ap.add_argument("--max-patches", type=int, default=1024)
    ap.add_argument("--per-cell", type=int, nargs="+", default=[EG.PILOT_PER_CELL])
    ap.add_argument("--truth", type=int, default=22, help="log2 of the uniform particles")
    a = ap.parse_args()
    scene = load_scene(a.scene, film_res=a.res)
    sensor = scene.sensors()[0]
    shapes = scene_shapes(scene)
    rows = {pc: [] for pc in a.per_cell}
    for seed in a.seeds:
        patches = build_patches(scene, max_patches=a.max_patches, seed=seed, shapes=shapes)
        elements = R.receiving_elements(scene, a.max_patches, 16, seed, shapes=shapes)
        line = [f"seed {seed}"]
        T = None
        for pc in a.per_cell:
            EG.PILOT_PER_CELL = pc
            P = R.guide_pilot(scene, sensor, patches, elements, seed)
            if P is None:
                raise SystemExit("no guide: every emitter is an area light, or the camera "
                                 "reads nothing")
            g = EG.fitted(P.cells, P.cell_of, P.score)
            if T is None:
                T = truth(scene, patches, elements, P.camera, P.cells, 1 << a.truth, 977 + seed)
            pred = EG.image_noise(P.cells, g.pmf, P.cell_of, P.read, P.first, 1)
            true = EG.image_noise(P.cells, g.pmf, *T, 1)
            rows[pc].append(true)
            line.append(f"per_cell {pc}: pilot {P.traced} pred {pred:.2f} true {true:.2f}")
        print(" | ".join(line), flush=True)
    for pc, v in rows.items():
        v = np.sort(v)
        print(f"per_cell {pc}: true noise per particle median {np.median(v):.2f}, rms "
              f"{np.sqrt(np.mean(v ** 2)):.2f}, largest {', '.join(f'{x:.2f}' for x in v[-3:])}")


if __name__ == "__main__":
    main()
