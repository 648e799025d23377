r"""The radiance cache's irradiance at the camera's pixel centres, read by interpolation.

Arikan et al. evaluate :math:`B_D + \lambda B_C` (eqs. 3 and 5) once per shading point, and
their shading points are the image's: one per pixel. A Monte Carlo render of ``spp`` samples
per pixel meets a camera ray's first diffuse hit ``spp`` times per pixel, at ``spp`` points
within one pixel's footprint, and each read interpolated the SH field and summed the near
field's form factors again: at 256², 16 spp on window_interior the cache term was 0.17–0.25 s
of a 0.40–0.46 s render (``tools/render_cost.py ... radiance_cache
radiance_cache:pixel_table=false radiance_cache:lambda=0``).

:class:`PixelTable` evaluates the cache's irradiance :math:`E = \max(B_D + \lambda B_C, 0)`
once at the first hit of every pixel centre's camera ray (the pinhole ray: aperture sample
0.5), and a camera ray's first hit at ``x`` reads it by bilinear interpolation between the four
pixel centres around ``x``'s film position (``Sensor.sample_direction``, the projection the
particle tracer splats with), over those that lie on ``x``'s surface: their geometric normal
within :data:`NORMAL_COS` of ``x``'s, their offset from ``x``'s tangent plane at most
:data:`PLANE_SLOPE` × their distance, and that distance at most :data:`REACH_ALPHA` × the
cache's alpha (their weights renormalised, where they hold at least
:data:`MIN_WEIGHT` of it). Everywhere else the lane evaluates :math:`E` at ``x`` as before: no
centre of its surface near enough, a centre within reach on geometry above its tangent plane (a
crease or a contact, where E changes within a pixel), a hit behind a specular vertex. The values interpolated are
the cache's own; what is added is the interpolation error of a smooth function across at most
one pixel spacing, on one surface.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: the four pixel centres' geometric normals must be within acos(0.995) ≈ 5.7° of the point's
NORMAL_COS = 0.995
#: and their offset from the point's tangent plane at most this times their distance to it
#: (tan 5.7°: a curved surface's neighbours pass, a parallel surface behind a step does not)
PLANE_SLOPE = 0.1
#: and their distance to it at most this times the cache's alpha (the scale on which B_C and the
#: RBF-interpolated far field change): a film too coarse for that evaluates E per sample
REACH_ALPHA = 0.25
#: a point is served where the centres on its surface hold at least this share of its bilinear
#: weight (their values renormalised): at a silhouette or a crease, the centres on the point's
#: own side, at most one pixel spacing away. Requiring all four served 79 % of the camera's
#: cache reads on window_interior at 256², this 96.6 %; the render at 16 spp, 0.396–0.402 s
#: without the table, took 0.337 and 0.288 s (``tools/render_cost.py``, one sitting);
#: the lanes left evaluate E (a packet of lanes runs that evaluation if any one needs it)
MIN_WEIGHT = 0.25


class PixelTable:
    """``E`` (Color3f), ``p`` (Point3f), ``n`` (Vector3f) and ``ok`` (Bool) of every pixel
    centre of ``sensor``'s crop window, row by row (``width`` × ``height``), as Dr.Jit arrays
    evaluated at construction (the render loop only gathers from them). Build with
    :meth:`build`."""

    def __init__(self, sensor, width: int, height: int, E, p, n, ok, hit, reach: float):
        self.sensor = sensor
        #: farthest pixel centre a point reads (:data:`REACH_ALPHA` × alpha)
        self.reach = float(reach)
        self.width, self.height = int(width), int(height)
        self.E, self.p, self.n, self.ok, self.hit = E, p, n, ok, hit
        dr.eval(self.E, self.p, self.n, self.ok, self.hit)

    @property
    def nbytes(self) -> int:
        return self.width * self.height * (9 * 4 + 2)

    @property
    def count(self) -> int:
        """Pixel centres with a value."""
        return int(dr.count(self.ok)[0])

    @staticmethod
    def pixel_centres(sensor):
        """The pinhole camera rays through every pixel centre of ``sensor``'s crop window,
        row by row → ``(ray, width, height)``."""
        width, height = (int(v) for v in sensor.film().crop_size())
        # opaque: a literal film size would compile this kernel per size
        w, h = dr.opaque(mi.UInt32, width), dr.opaque(mi.UInt32, height)
        idx = dr.arange(mi.UInt32, width * height)
        row = idx // w
        col = idx - row * w
        pos = mi.Point2f((mi.Float(col) + 0.5) / mi.Float(w), (mi.Float(row) + 0.5) / mi.Float(h))
        ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
        return ray, width, height

    @staticmethod
    def projects(sensor) -> bool:
        """Whether ``sensor`` maps a world point to its film (``sample_direction``: Mitsuba's
        perspective and thin-lens cameras do; its orthographic camera and others do not)."""
        it = dr.zeros(mi.Interaction3f)
        try:
            sensor.sample_direction(it, mi.Point2f(0.5), mi.Bool(True))
        except RuntimeError:
            return False
        return True

    @classmethod
    def build(cls, scene, sensor, irradiance, diffuse_at, alpha: float) -> "PixelTable | None":
        """Evaluate ``irradiance(si, n, active) -> (Color3f, Bool)`` (the cache's
        max(B_D + λB_C, 0) at ``si`` with viewer-facing geometric normal ``n``, and where the
        cache holds the point) at the first hit of every pixel centre's ray where
        ``diffuse_at(si, active)`` (the surfaces that read the cache); a centre the cache does
        not hold has no value.
        None for a sensor that does not project points onto its film (:meth:`projects`)."""
        if not cls.projects(sensor):
            return None
        ray, width, height = cls.pixel_centres(sensor)
        si = scene.ray_intersect(ray)
        ok = si.is_valid() & diffuse_at(si, si.is_valid())
        n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
        E, held = irradiance(si, n, ok)
        ok &= held
        E = dr.select(ok, E, 0.0)
        return cls(sensor, width, height, E, mi.Point3f(si.p), mi.Vector3f(n), ok,
                   si.is_valid(), REACH_ALPHA * alpha)

    def lookup(self, x, n, active):
        """Bilinear interpolation of ``E`` at world point ``x`` (normal ``n``, facing the
        camera) between the four pixel centres around its film position → ``(E, served)``;
        ``served`` is False (and E 0) where the centres on ``x``'s surface hold less than
        :data:`MIN_WEIGHT` of the bilinear weight."""
        it = dr.zeros(mi.Interaction3f)
        it.p = x
        ds, _ = self.sensor.sample_direction(it, mi.Point2f(0.5), active)
        served = active & (ds.pdf > 0)
        w = dr.opaque(mi.Int32, self.width)
        h = dr.opaque(mi.Int32, self.height)
        reach2 = dr.opaque(mi.Float, self.reach * self.reach)
        # pixel centres sit at integer + 0.5; the four around uv, clamped to the window (half
        # a pixel at its border reads the nearest centres' values)
        u = ds.uv.x - 0.5
        v = ds.uv.y - 0.5
        i0 = dr.clip(mi.Int32(dr.floor(u)), 0, dr.maximum(w - 2, 0))
        j0 = dr.clip(mi.Int32(dr.floor(v)), 0, dr.maximum(h - 2, 0))
        i1 = dr.minimum(i0 + 1, w - 1)
        j1 = dr.minimum(j0 + 1, h - 1)
        tu = dr.clip(u - mi.Float(i0), 0.0, 1.0)
        tv = dr.clip(v - mi.Float(j0), 0.0, 1.0)
        E = mi.Color3f(0.0)
        total = mi.Float(0.0)
        for jj, ii, wt in ((j0, i0, (1 - tu) * (1 - tv)), (j0, i1, tu * (1 - tv)),
                           (j1, i0, (1 - tu) * tv), (j1, i1, tu * tv)):
            k = mi.UInt32(jj * w + ii)
            hit = dr.gather(mi.Bool, self.hit, k, served)
            ok = dr.gather(mi.Bool, self.ok, k, hit)
            p = dr.gather(mi.Point3f, self.p, k, hit)
            nc = dr.gather(mi.Vector3f, self.n, k, ok)
            d = p - x
            d2 = dr.squared_norm(d)
            height = dr.dot(d, n)
            flat = dr.abs(height) <= PLANE_SLOPE * dr.sqrt(d2)
            same = ok & (dr.dot(nc, n) >= NORMAL_COS) & (d2 <= reach2) & flat
            # a centre on geometry above x's tangent plane and within reach: a crease or a
            # contact, where E changes within a pixel; x evaluates E itself (at 128² in the
            # test room the 99.9th percentile of the read's error went 18 % -> 9 %; on
            # window_interior at 256², 98.6 % -> 96.6 % of the reads served)
            served &= ~(hit & ~flat & (height > 0) & (d2 <= reach2))
            wt = dr.select(same, wt, 0.0)
            total += wt
            E += wt * dr.gather(mi.Color3f, self.E, k, same)
        served &= total > MIN_WEIGHT
        return dr.select(served, E / total, 0.0), served
