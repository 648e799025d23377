"""The refined elements' cells against the light ``path`` finds where gather rays land on them.

    .venv/bin/python tools/refined_hits.py scenes_xml/window_interior.xml [--res 64]
        [--lanes 1048576] [--paths 64] [--seed 3]

Builds radiance_cache's prepass, then from the camera's first Lambertian hits casts one
cosine-sampled ray each; of the rays that land on an element refined into cells
(:mod:`mi_twopass.prepass.element_grid`), prints the mean of the element's mean B_r/π, of its
cell's, and of ``--paths`` path-traced estimates of the reflected light there (emission at the
hit subtracted), the per-element ratios, and the RMS per-hit error of each read.
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import drjit as dr
import mitsuba as mi
import numpy as np

from far_gather_hits import gather_rays, reflected_by_path  # (tools/, the script's folder)
from mi_twopass.scenefile import load_scene


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--lanes", type=int, default=1 << 20)
    ap.add_argument("--paths", type=int, default=64)
    ap.add_argument("--seed", type=int, default=3, help="the prepass's seed")
    a = ap.parse_args()
    scene = load_scene(a.scene, film_res=a.res)
    integ = mi.load_dict({"type": "radiance_cache"})
    mi.render(scene, integrator=integ, spp=1, seed=a.seed)  # builds the prepass
    sol = integ.structure.solution
    grid = sol.grid
    if grid is None or not grid.count:
        print("no refined elements")
        return
    ray, si1, ok0 = gather_rays(scene, a.lanes)
    on = grid.refined(sol.elements.lookup(si1, ok0 & si1.is_valid()), ok0 & si1.is_valid())
    idx = dr.compress(on)
    m = dr.width(idx)
    print(f"{grid.count} refined elements; {m} of {a.lanes} gather rays land on them")
    if m == 0:
        return
    ray = dr.gather(mi.Ray3f, ray, idx)
    si1 = scene.ray_intersect(ray)
    rid = sol.elements.lookup(si1, si1.is_valid())
    mean = sol.receiver_reflected_radiance(rid, True)
    cell = sol.receiver_reflected_radiance(rid, True, si1.p)
    traced = reflected_by_path(scene, ray, si1, True, a.paths)
    grey = lambda c: np.asarray(c).T.mean(axis=1)  # noqa: E731
    M, C, P = grey(mean), grey(cell), grey(traced)
    r = np.asarray(rid)
    print(f"element mean / path {M.mean() / P.mean():.4f}   cell / path {C.mean() / P.mean():.4f}"
          f"   (path's standard error {P.std() / np.sqrt(m) / P.mean():.4f})")
    per_m, per_c = [], []
    for e in np.unique(r):
        k = r == e
        if k.sum() >= 50:
            per_m.append(M[k].mean() / P[k].mean())
            per_c.append(C[k].mean() / P[k].mean())
    np.set_printoptions(precision=2, linewidth=100)
    print("per element (≥ 50 hits), mean / path:", np.array(per_m))
    print("per element (≥ 50 hits), cell / path:", np.array(per_c))
    print(f"RMS per-hit error over the mean light (path's own noise included): element mean "
          f"{np.sqrt(np.mean((M - P) ** 2)) / P.mean():.3f}, cell "
          f"{np.sqrt(np.mean((C - P) ** 2)) / P.mean():.3f}")


if __name__ == "__main__":
    main()
