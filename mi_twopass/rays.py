"""Rays leaving a surface with an offset relative to the scene's size, written once.

Mitsuba lifts a spawned ray's origin off the surface by (1 + max|p|)·RayEpsilon along the
geometric normal: at least 89 µm, which crosses a scene modelled in tenths of a millimetre
(the light of a 0.2 mm Cornell box leaks through its walls, shadows of thin occluders vanish).
Here the 1 (metre) is ``scale``, a length of the scene (its bounding radius or diagonal, at
most 1 where a caller wants Mitsuba's offset for scenes of a metre and more): the same relative
offset at every scale. ``scale = 1`` reproduces Mitsuba's ``spawn_ray`` / ``spawn_ray_to``.
Used by the prepasses (photons, particles) and by the render loops alike.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


def spawn_offset(si, d, scale):
    """Origin of a ray leaving ``si`` towards direction ``d``: ``si.p`` moved along the
    geometric normal, to the side of ``d``, by RayEpsilon·(scale + max|p|)."""
    mag = mi.math.RayEpsilon * (scale + dr.max(dr.abs(si.p)))
    mag = dr.detach(dr.mulsign(mag, dr.dot(si.n, d)))
    return dr.fma(mag, si.n, si.p)


def spawn_ray(si, d, scale):
    """``si.spawn_ray(d)`` with the offset of :func:`spawn_offset`."""
    return mi.Ray3f(spawn_offset(si, d, scale), d, si.time, si.wavelengths)


def spawn_ray_to(si, target, scale):
    """``si.spawn_ray_to(target)`` (a shadow ray ending ShadowEpsilon short of ``target``) with
    the offset of :func:`spawn_offset`."""
    o = spawn_offset(si, target - si.p, scale)
    d = target - o
    dist = dr.norm(d)
    return mi.Ray3f(o, d / dist, dist * (1.0 - mi.math.ShadowEpsilon), si.time, si.wavelengths)


def shadow_ray(si, ds, scale, infinite_emitters: bool = True):
    """The shadow ray of an emitter sample ``ds`` at ``si``: :func:`spawn_ray_to` its point,
    and on to infinity for an infinite emitter (sky, sun, envmap). Mitsuba places that point 2R
    away, R the radius of ``scene.bbox()``, and Mitsuba 3.9 leaves the rectangles it merges into
    one mesh out of that box: a shadow ray ending there passed a room's walls, and a sky lit
    the inside of a closed room (Mitsuba's ``path`` has that leak; tests/hard_scenes.py
    ``sky_room``). ``infinite_emitters``: whether the scene has any
    (:func:`mi_twopass.scene.emission.has_infinite_emitters`); without, the ray is
    :func:`spawn_ray_to`'s and no virtual call asks the emitter's flags."""
    ray = spawn_ray_to(si, ds.p, scale)
    if not infinite_emitters:
        return ray
    infinite = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
    ray.maxt = dr.select(infinite, dr.inf, ray.maxt)
    return ray

