"""Which solve particles carry the image, and which guide cells hold the guide's variance.

    .venv/bin/python tools/guide_tail.py scenes_xml/mixed_room.xml --res 128 \
        --max-patches 1010 --seed 24301 [--truth 22]

For one prepass seed, the patches, elements, pilot and guide exactly as the radiosity prepass
builds them (``radiosity.guide_pilot``, ``emission_guide.fitted``), then:

1. the solve's own particles (its seed, batches and count, traced without deposits) scored by
   the camera's reads (:class:`~mi_twopass.prepass.emission_guide.CameraImportance` ``read``):
   the five largest shares of the total, with their cell, its probability and Mitsuba's own
   for it;
2. 2^``truth`` particles drawn uniformly over the cells: each cell's share of the fitted
   guide's variance (mean score² / P_c), the ten largest, with whether the pilot saw the
   cell lit, its pilot particles and, for a gridded emitter, its grid index and the Chebyshev
   distance to the nearest cell the pilot saw lit.

A heavy prepass shows as a few particles with percent shares from cells left at the guide's
defensive share, all near each other in the grid and far from every lit one
(docs/results/guide-pilot-2026-11-28: ``--per-cell 4``, the pilot before session 24, shows it).
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import numpy as np

from mi_twopass.prepass import emission_guide as EG
from mi_twopass.prepass import radiosity as R
from mi_twopass.scene.patches import build_patches, scene_shapes
from mi_twopass.scenefile import load_scene

from guide_noise import truth  # noqa: E402  (tools/ is the script's own directory)

BATCH = 1 << 18


def solve_scores(scene, patches, elements, camera, guide, n, seed):
    """(cell, read score) of the ``n`` particles :func:`~mi_twopass.prepass.radiosity.
    solve_radiosity` draws with ``guide`` and ``seed`` (the same batches, so the same
    particles), traced without deposits."""
    cells, reads = [], []
    for first in range(0, n, BATCH):
        m = min(BATCH, n - first)
        _, _, res, _ = R._trace_batch(scene, patches, m, first, seed, n, R.DEFAULT_MAX_BOUNCES,
                                      elements, guide=guide, importance=camera.hits,
                                      deposit_flux=False, reads=camera)
        cells.append(res["cell"])
        reads.append(res["read_score"])
    return np.concatenate(cells), np.concatenate(reads)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=128, help="film's longer side in pixels")
    ap.add_argument("--max-patches", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=0, help="the prepass's seed")
    ap.add_argument("--truth", type=int, default=22, help="log2 of the uniform particles")
    ap.add_argument("--per-cell", type=int, default=EG.PILOT_PER_CELL,
                    help="the pilot's first-stage particles per cell")
    a = ap.parse_args()
    EG.PILOT_PER_CELL = a.per_cell
    scene = load_scene(a.scene, film_res=a.res)
    shapes = scene_shapes(scene)
    patches = build_patches(scene, max_patches=a.max_patches, seed=a.seed, shapes=shapes)
    elements = R.receiving_elements(scene, a.max_patches, 16, a.seed, shapes=shapes)
    P = R.guide_pilot(scene, scene.sensors()[0], patches, elements, a.seed)
    if P is None:
        raise SystemExit("no guide: every emitter is an area light, or the camera reads nothing")
    C = P.cells
    guide = EG.fitted(C, P.cell_of, P.score)
    noise = EG.image_noise(C, guide.pmf, P.cell_of, P.read, P.first, 1)
    n = R.guided_particles(max(R.MIN_PARTICLES, R.PARTICLES_PER_PATCH * patches.count), noise)
    default = C.default / C.default.sum()
    cell, read = solve_scores(scene, patches, elements, P.camera, guide, n, a.seed)
    top = np.argsort(-read)[:5]
    print(f"{n} solve particles; largest shares of the camera-read flux: "
          + ", ".join(f"{read[i] / read.sum():.4f} (cell {cell[i]}, P {guide.pmf[cell[i]]:.2e},"
                      f" Mitsuba's {default[cell[i]]:.2e})" for i in top))
    tc, tr, _ = truth(scene, patches, elements, P.camera, C, 1 << a.truth, 977 + a.seed)
    count = np.bincount(tc, minlength=C.count)
    ms2 = np.bincount(tc, weights=(tr * (1 << a.truth) / C.count) ** 2,
                      minlength=C.count) / np.maximum(count, 1)
    share = ms2 / guide.pmf
    share /= share.sum()
    lit = EG.cell_rms(C, P.cell_of, P.score) > 0
    pilot_n = np.bincount(P.cell_of, minlength=C.count)
    print("cells holding most of the guide's variance:")
    for c in np.argsort(-share)[:10]:
        where = ""
        for start, shape in C.blocks:
            if shape and start <= c < start + int(np.prod(shape)):
                idx = np.array(np.unravel_index(c - start, shape))
                seen = np.flatnonzero(lit[start:start + int(np.prod(shape))])
                far = (np.abs(np.array(np.unravel_index(seen, shape)).T - idx).max(axis=1).min()
                       if len(seen) else -1)
                where = f" grid {idx.tolist()}, {far} cells from the nearest lit one"
        print(f"  cell {c}: share {share[c]:.3f}, P/Mitsuba's {guide.pmf[c] / default[c]:.2f}, "
              f"pilot saw it lit: {bool(lit[c])} ({pilot_n[c]} particles){where}")


if __name__ == "__main__":
    main()
