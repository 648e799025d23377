"""Far-gather reads against a path-traced estimate of the same light, hit by hit.

    .venv/bin/python tools/far_gather_hits.py ../shared/scenes/veach-bidir/scene.xml \
        [--props '{"elements_per_patch": 16}'] [--res 64] [--paths 64] [--seed 3]

From the camera's first Lambertian hits, one cosine-sampled gather ray each; where it lands
farther than ``r_thresh`` on a cached receiver, radiosity_gather reads B_r/π of the element
(``F``). The same ray is path-traced ``--paths`` times with Mitsuba's ``path`` and the emission
at the hit subtracted (``P``: the reflected light the read stands for). Prints mean F / mean P
over all far reads, per shape and for the patches holding most of the excess: where a far
read is biased, not only how much (README "Right on real scenes", prepass.radiosity.SPREAD_MAX).
"""
import argparse
import json

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import drjit as dr
import mitsuba as mi
import numpy as np

from mi_twopass.scene.lambertian import LambertianShapes
from mi_twopass.scenefile import load_scene


def gather_rays(scene, n):
    """``n`` camera rays' first Lambertian hits, one cosine-sampled ray each on the side seen:
    ``(ray, its hit, the Lambertian mask of the first hits)``."""
    smp = mi.load_dict({"type": "independent"})
    smp.seed(1, n)
    ray0, _ = scene.sensors()[0].sample_ray(0.0, 0.5, smp.next_2d(), smp.next_2d())
    si0 = scene.ray_intersect(ray0)
    ok0 = LambertianShapes(scene).at(si0)
    d_local = mi.warp.square_to_cosine_hemisphere(smp.next_2d())
    d_local = dr.select(mi.Frame3f.cos_theta(si0.wi) < 0, -d_local, d_local)  # the seen side
    ray = si0.spawn_ray(si0.to_world(d_local))
    return ray, scene.ray_intersect(ray, ok0), ok0


def reflected_by_path(scene, ray, hit, active, paths):
    """The light ``path`` finds along ``ray`` (mean of ``paths`` estimates) less the emission
    at its ``hit``: the reflected light a cache read there stands for."""
    path = mi.load_dict({"type": "path"})
    acc = dr.zeros(mi.Color3f, dr.width(ray.o))
    for m in range(paths):
        sp = mi.load_dict({"type": "independent"})
        sp.seed(100 + m, dr.width(ray.o))
        L, _, _ = path.sample(scene, sp, ray, None, active)
        acc += mi.Color3f(L)
        dr.eval(acc)
    return acc / paths - hit.emitter(scene).eval(hit, active)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--props", default="{}", help="radiosity_gather properties, JSON")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--lanes", type=int, default=1 << 18)
    ap.add_argument("--paths", type=int, default=64)
    ap.add_argument("--seed", type=int, default=3, help="the prepass's seed")
    a = ap.parse_args()
    scene = load_scene(a.scene, film_res=a.res)
    integ = mi.load_dict({"type": "radiosity_gather", **json.loads(a.props)})
    mi.render(scene, integrator=integ, spp=1, seed=a.seed)  # builds the prepass
    sol = integ.structure.solution
    n = a.lanes
    ray, si1, ok0 = gather_rays(scene, n)
    far = ok0 & si1.is_valid() & (si1.t >= integ.r_thresh(scene))
    far &= sol.cached_at(si1, far)
    F = sol.reflected_radiance(si1, far)
    P = reflected_by_path(scene, ray, si1, far, a.paths)
    mask = np.asarray(far)
    Fn = np.asarray(F).T.mean(1)[mask]
    Pn = np.asarray(P).T.mean(1)[mask]
    print(f"far reads {mask.sum()} of {n}: mean F {Fn.mean():.5f}  path {Pn.mean():.5f}  "
          f"ratio {Fn.mean() / Pn.mean():.4f}")
    excess = Fn - Pn
    sid = np.asarray(dr.reinterpret_array(mi.UInt32, si1.shape))[mask]
    ids = np.asarray(dr.reinterpret_array(mi.UInt32, scene.shapes_dr()))
    names = {int(i): (s.id() or s.class_name()) for i, s in zip(ids, scene.shapes())}
    for k in np.unique(sid):
        m = sid == k
        if m.sum() >= 200:
            se = Pn[m].std() / np.sqrt(m.sum())
            print(f"  shape {names.get(int(k), k):20s} n={m.sum():6d} F {Fn[m].mean():.5f} "
                  f"path {Pn[m].mean():.5f} ± {se:.5f} share of excess "
                  f"{excess[m].sum() / excess.sum():.2f}")
    pid = np.asarray(sol.patches.lookup(si1, far))[mask]
    p1 = np.stack([np.asarray(si1.p[i]) for i in range(3)], 1)[mask]
    for k in np.argsort(-np.bincount(pid, weights=excess))[:8]:
        m = pid == k
        print(f"  patch {k:6d} n={m.sum():5d} F {Fn[m].mean():.4f} path {Pn[m].mean():.4f} "
              f"share {excess[m].sum() / excess.sum():.2f} at {p1[m].mean(0).round(2)}")


if __name__ == "__main__":
    main()
