"""Rays leaving a scene's emitters, as Mitsuba's ``sample_ray`` samples them, built where
Mitsuba's would be wrong. Shared by every light-tracing prepass: rex's photons
(:mod:`mi_twopass.prepass.rex_textures`) and the radiosity particles
(:mod:`mi_twopass.prepass.radiosity`), so a sky lights a room of merged rectangles the same in
both."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..rays import spawn_ray


def emitter_rays(scene, bounds, em, s2, s3, active=True):
    """Photon rays ``(ray, weight)`` leaving the emitters ``em`` (indices into
    ``scene.emitters()``) from the primary samples ``s2``, ``s3``, as Mitsuba's ``sample_ray``
    samples them, built here where Mitsuba's would be wrong:

    * surface (area) emitters: a point by ``sample_position`` (``s2``), a cosine-weighted
      direction (``s3``), weight Le·π/pdf, the origin offset by :func:`mi_twopass.rays.spawn_ray` (Mitsuba's
      absolute offset starts photons in the middle of a sub-millimetre scene);
    * infinite emitters (constant, envmap, sunsky, directional, ...): a direction by
      ``sample_direction`` (``s2``, weight L/pdf) and a point of the disk of radius R facing it
      (``s3``), R the bounding sphere of :func:`scene_bounds`: weight L/pdf · πR². Mitsuba's own
      infinite ``sample_ray`` starts on the sphere around ``scene.bbox()``, which misses the
      rectangles Mitsuba merges into one mesh (its bbox is that of the other parts, or empty):
      those photons started inside the scene, past its walls;
    * others (point, spot, projector, ...): Mitsuba's ``sample_ray``."""
    active = mi.Bool(active)
    n = dr.width(em)
    ep = dr.gather(mi.EmitterPtr, scene.emitters_dr(), em, active)
    flags = ep.flags()
    infinite = active & mi.has_flag(flags, mi.EmitterFlags.Infinite)
    surface = active & ~infinite & mi.has_flag(flags, mi.EmitterFlags.Surface)
    other = active & ~infinite & ~surface
    ray, weight = ep.sample_ray(0.0, 0.5, s2, s3, other)
    weight = dr.select(other, weight, 0.0)

    # surface emitters
    ps, pos_weight = ep.sample_position(0.0, s2, surface)
    si = mi.SurfaceInteraction3f(ps, dr.zeros(mi.Color0f, n))
    local = mi.warp.square_to_cosine_hemisphere(s3)
    si.wi = local
    Le = ep.eval(si, surface)
    d = si.to_world(local)
    ok = surface & (ps.pdf > 0) & (local.z > 0)
    ray = dr.select(surface, spawn_ray(si, d, float(bounds.radius)), ray)
    weight = dr.select(surface, dr.select(ok, Le * pos_weight * math.pi, 0.0), weight)

    # infinite emitters
    center = mi.Point3f(*(float(c) for c in bounds.center))
    radius = float(bounds.radius)
    it = dr.zeros(mi.Interaction3f, n)
    it.p = center
    ds, w_dir = ep.sample_direction(it, s2, infinite)
    frame = mi.Frame3f(ds.d)  # ds.d points from the scene towards the emitter
    disk = mi.warp.square_to_uniform_disk_concentric(s3)
    origin = center + radius * (ds.d + frame.to_world(mi.Vector3f(disk.x, disk.y, 0.0)))
    ok = infinite & (ds.pdf > 0)
    ray = dr.select(infinite, mi.Ray3f(origin, -ds.d), ray)
    weight = dr.select(infinite, dr.select(ok, w_dir * (math.pi * radius * radius), 0.0), weight)
    return ray, weight


def emitter_kinds(scene):
    """Per emitter of ``scene.emitters()``: "surface", "infinite" or "other", the three cases of
    :func:`emitter_rays`."""
    kinds = []
    for e in scene.emitters():
        flags = e.flags()
        if mi.has_flag(flags, mi.EmitterFlags.Infinite):
            kinds.append("infinite")
        elif mi.has_flag(flags, mi.EmitterFlags.Surface):
            kinds.append("surface")
        else:
            kinds.append("other")
    return kinds


def has_infinite_emitters(scene) -> bool:
    """``scene`` has a sky, sun or environment map (:func:`mi_twopass.rays.shadow_ray` asks
    their rays' emitter only then)."""
    return any(mi.has_flag(e.flags(), mi.EmitterFlags.Infinite) for e in scene.emitters())


__all__ = ["emitter_kinds", "emitter_rays", "has_infinite_emitters"]
