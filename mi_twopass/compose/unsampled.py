"""Light that ``path`` cannot sample: delta emitters seen through specular surfaces.

Mitsuba's ``path`` meets an emitter in two ways: a shadow ray (emitter sampling), which any
surface in between stops, glass and ``null`` interfaces included, and a BSDF-sampled ray that
hits the emitter, which never happens for a delta emitter (a point, spot or directional light:
one position or one direction). The light a delta emitter sends through specular (delta)
surfaces onto a diffuse surface (an L S+ D path: a sun behind a window pane, a bulb in a glass
shade, a spot seen in a mirror) is therefore missing from ``path``'s image at any sample count.
So is it from every composition of ``twopass`` but rexes, and from its path pilot, which is
why no variance share can reveal it.

Photons carry it. ``rex`` renders it. The radiosity prepass holds it only after a diffuse
bounce: radiosity_gather, spike_gather and radiance_cache render its reflections, but not the
patch it lights.

On docs/results/sun-behind-glass-2026-11-27/scene.xml (64², against Mitsuba's ``ptracer`` at
8192 spp, which samples these paths), the image means were:

=============================== =====
integrator                      mean
=============================== =====
``path``                        0.770
radiosity_gather, spike_gather  0.84
radiance_cache                  0.83
rex                             1.004
=============================== =====

With the pane removed, every integrator read 0.998–1.001.

:func:`unsampled_radiance` estimates that light as the image's mean by light tracing, as
Mitsuba's ``ptracer`` does, restricted to those paths:

1. Particles leave the delta emitters only, chosen uniformly.
2. They follow delta (specular) BSDF samples only.
3. At every hit after at least one delta bounce, a particle's flux is connected to the camera
   (``sensor.sample_direction``, a shadow ray, the BSDF toward the camera). The sum over the
   particles is the image's mean radiance of those paths, since the sensor's weight is
   normalised over the film: the light-traced sum of the sun's direct light on the floor of
   tests/compose/test_unsampled.py was 1.010 × ``path``'s image mean.

Light reaching the camera through a further specular bounce (a mirror seen by the camera) and
the diffuse reflections of the light counted are not included, so the estimate is a lower
bound of what ``path`` misses. On the scene above the estimate is 0.0116 (17 % of the image),
while ptracer and ``path`` differ by 0.0169: radiosity_gather's reflections make up the rest.
``twopass`` divides the estimate by itself plus its path pilot's image mean, says so in its
stats, and warns where the share is more than :data:`WARN_SHARE`.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..host_arrays import jit
from ..rays import spawn_ray, spawn_ray_to
from ..scene.bounds import scene_bounds
from ..scene.emission import emitter_rays
from ..seeds import splitmix64
from ..units import channel_mean

#: particles of the estimate
PARTICLES = 1 << 16
#: delta bounces a particle follows at most
MAX_DELTA_BOUNCES = 8
#: ``twopass`` warns where the light path cannot sample is at least this share of the image's
#: mean: ``check``'s bound on an image's mean
WARN_SHARE = 0.01

_DELTA_EMITTER = mi.EmitterFlags.DeltaPosition | mi.EmitterFlags.DeltaDirection
_DELTA_BSDF = mi.BSDFFlags.Delta | mi.BSDFFlags.Null


def delta_emitters(scene) -> list:
    """Indices (into ``scene.emitters()``) of the point, spot, directional and other delta
    emitters."""
    return [i for i, e in enumerate(scene.emitters())
            if mi.has_flag(e.flags(), _DELTA_EMITTER)]


def has_delta_surface(scene) -> bool:
    """Whether any shape's BSDF has a delta (specular) or null component."""
    return any(s.bsdf() is not None and mi.has_flag(s.bsdf().flags(), _DELTA_BSDF)
               for s in scene.shapes())


def unsampled_radiance(scene, sensor, seed: int = 0, particles: int = PARTICLES) -> float:
    """The image's mean radiance (channel mean) of the light delta emitters send through delta
    surfaces onto surfaces the camera sees (module docstring); 0.0 without delta emitters or
    delta surfaces, or without a camera."""
    emitters = delta_emitters(scene)
    if sensor is None or not emitters or not has_delta_surface(scene):
        return 0.0
    bounds = scene_bounds(scene)
    scale = min(1.0, 2.0 * float(bounds.radius))
    rng = mi.PCG32(size=particles, initstate=dr.opaque(mi.UInt64, splitmix64(seed)),
                   initseq=dr.arange(mi.UInt64, particles))
    table = jit(mi.UInt32, np.asarray(emitters, np.uint32))
    pick = mi.UInt32(dr.minimum(rng.next_float32() * len(emitters), len(emitters) - 1))
    em = dr.gather(mi.UInt32, table, pick)
    u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
    u3 = mi.Point2f(rng.next_float32(), rng.next_float32())
    ray, weight = emitter_rays(scene, bounds, em, u2, u3)
    flux = mi.Color3f(weight) * dr.opaque(mi.Float, len(emitters) / particles)
    flux = dr.select(dr.all(dr.isfinite(flux)), flux, 0.0)
    active = dr.max(flux) > 0
    through = mi.Bool(False)  # at least one delta bounce since the emitter
    seen = dr.zeros(mi.Float, particles)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    for _ in range(MAX_DELTA_BOUNCES + 1):
        si = scene.ray_intersect(ray, active)
        active &= si.is_valid()
        bsdf = si.bsdf(ray)
        # connect to the camera (ptracer's next event), after a delta bounce only
        at = active & through
        ds, importance = sensor.sample_direction(
            si, mi.Point2f(rng.next_float32(), rng.next_float32()), at)
        at &= (ds.pdf > 0) & ~scene.ray_test(spawn_ray_to(si, ds.p, scale), at)
        value = flux * bsdf.eval(ctx, si, si.to_local(ds.d), at) * mi.Color3f(importance)
        seen += dr.select(at & dr.all(dr.isfinite(value)), channel_mean(value), 0.0)
        bs, w = bsdf.sample(ctx, si, rng.next_float32(),
                            mi.Point2f(rng.next_float32(), rng.next_float32()), active)
        active &= mi.has_flag(bs.sampled_type, _DELTA_BSDF) & (bs.pdf > 0) & \
            dr.all(dr.isfinite(w)) & (dr.max(w) > 0)
        flux = dr.select(active, flux * w, 0.0)
        through |= active
        ray = spawn_ray(si, si.to_world(bs.wo), scale)
        dr.eval(seen, flux, ray, active, through, rng)
        if not dr.any(active)[0]:
            break
    total = float(dr.sum(seen)[0])
    return total if math.isfinite(total) else 0.0


__all__ = ["MAX_DELTA_BOUNCES", "PARTICLES", "WARN_SHARE", "delta_emitters", "has_delta_surface",
           "unsampled_radiance"]
