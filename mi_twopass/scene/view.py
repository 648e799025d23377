"""What the camera sees: the first non-delta hits of camera rays, and the extent they span.

Lengths that are "the scale of the view" are fractions of the bounding-box diagonal of these
points, not of the scene's: a big unseen ground plane, a sky dome or a street outside a window
would otherwise set them (Arikan et al. §6: alpha is the scale of the detail one cares about in
the view; the far gather's ``r_thresh`` of Zimmerman & Shirley §2.5 likewise).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..host_arrays import columns, jit
from ..seeds import hash31
from .bounds import scene_diagonal
from .lambertian import LambertianShapes

#: delta bounces followed when collecting shading points
MAX_DELTA_BOUNCES = 16


def collect_shading_points(scene, sensor=None, max_points: int = 4096, seed: int = 0,
                           lambertian_only: bool = True):
    """First non-delta hits of camera rays through a jittered grid of ≤ ``max_points`` film
    positions → ``(p (n, 3), normal (n, 3) facing the viewer, rays traced)`` numpy.

    ``lambertian_only``: keep only hits on Lambertian surfaces (the radiance cache's: the only
    vertices that read it; a camera ray that first meets a glossy, mixed or bump-mapped surface
    then gives no point); else every non-delta hit."""
    if sensor is None:
        sensor = scene.sensors()[0]
    size = np.asarray(sensor.film().crop_size(), dtype=np.int64)
    scale = min(1.0, float(np.sqrt(max_points / max(1, size[0] * size[1]))))
    w, h = max(1, int(size[0] * scale)), max(1, int(size[1] * scale))
    rng = np.random.default_rng(hash31(seed, 1))
    iy, ix = np.mgrid[0:h, 0:w]
    u = ((ix.ravel() + rng.random(w * h)) / w).astype(np.float32)
    v = ((iy.ravel() + rng.random(w * h)) / h).astype(np.float32)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, hash31(seed, 2)), w * h)  # literal: kernels per seed
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5),
                               mi.Point2f(jit(mi.Float, u), jit(mi.Float, v)), mi.Point2f(0.5, 0.5))
    ctx = mi.BSDFContext()
    active = dr.full(mi.Bool, True, w * h)
    found = dr.full(mi.Bool, False, w * h)
    p = dr.zeros(mi.Point3f, w * h)
    nrm = dr.zeros(mi.Vector3f, w * h)
    eps = 1e-5 * scene_diagonal(scene)
    rays = 0
    n_active = w * h
    lambertian = LambertianShapes(scene) if lambertian_only else None
    for _ in range(MAX_DELTA_BOUNCES):  # a few bounces over the whole batch, not per lane
        rays += n_active
        si = scene.ray_intersect(ray, active)
        active &= si.is_valid()
        bsdf = si.bsdf(ray)
        smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        stop = active & smooth
        keep = stop & lambertian.at(si, stop) if lambertian_only else stop
        n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
        p[keep] = si.p
        nrm[keep] = n
        found |= keep
        bs, _ = bsdf.sample(ctx, si, sampler.next_1d(active), sampler.next_2d(active), active & ~stop)
        active &= ~stop & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        d = si.to_world(bs.wo)
        side = dr.select(dr.dot(si.n, d) >= 0, 1.0, -1.0)
        ray = mi.Ray3f(si.p + si.n * (side * (eps + 1e-6 * dr.max(dr.abs(si.p)))), d)
        # one evaluation per bounce, of all the state: unevaluated, the next bounce's kernel
        # would trace this one's rays again (veach-bidir's 16 bounces: 0.21 s, now 0.04 s)
        dr.eval(p, nrm, found, ray, active)
        n_active = int(np.asarray(dr.count(active)).reshape(-1)[0])  # next bounce's rays
        if n_active == 0:
            break
    keep = np.asarray(found)
    P, N = columns(p)[keep], columns(nrm)[keep]
    return P.astype(np.float64), N.astype(np.float64), rays


def view_diagonal(points, fallback_diagonal: float) -> float:
    """The diagonal of the bounding box of ``points`` (n, 3; non-finite rows ignored), or
    ``fallback_diagonal`` (the scene's) where they span no extent (fewer than two distinct
    points)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    diag = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0))) if len(p) else 0.0
    return diag if diag > 0.0 else float(fallback_diagonal)
