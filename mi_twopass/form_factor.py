r"""Point-to-polygon form factors for the near field of the radiance cache.

The correction term of Arikan, Forsyth & O'Brien 2005 (§5, eq. 6) weighs every nearby triangle
by the differential-area-to-polygon form factor

.. math::

    F(x, n \to T) = \frac1\pi \int_T \frac{\cos\theta_x \cos\theta_y}{r^2}\, dA_y ,

and §7 replaces far BVH nodes by one disk-like cluster (:func:`point_to_disk_approx`).
Note the 1/π: the paper's integral in eq. 6 is π·F.

:func:`polygon_form_factor` is exact (Lambert's contour integral); :func:`point_to_disk_approx`
is the cheap far-field estimate. Both accept Dr.Jit arrays (``mi.Point3f`` / ``mi.Vector3f``, one
configuration per lane, any JIT variant) or numpy float64 arrays, and return the same kind.

Conventions a caller must know
------------------------------
* ``n`` (the receiver normal) must be a unit vector; only the hemisphere ``n·ω > 0`` counts
  (cos θ_x is clamped at 0), so polygons partly or wholly behind the point are handled.
* The emitter is **two-sided**: the result uses |cos θ_y| and does not depend on the winding of
  the vertices. For one-sided surfaces, cull at the caller where the point is behind the polygon:
  ``dr.dot(x - a, dr.cross(b - a, c - a)) <= 0``.
* A point lying in the polygon's plane (relative tolerance :data:`PLANE_EPS` of the distance to
  the farthest vertex), and a zero-area polygon, get F = 0: the polygon is seen edge-on. This is
  what makes a shading point on a triangle get 0 from its own triangle and from coplanar
  neighbours. Float32 hit points far from the origin can be farther off the plane than this
  tolerance, so the near-field sum should still skip the shading point's own triangle by index.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

#: relative distance to the polygon's plane below which the point counts as in the plane
PLANE_EPS = 1e-5
#: guard against dividing by a zero length (representable in float32)
_TINY = 1e-30
_INV_2PI = 0.5 / math.pi


#: operations that numpy and Dr.Jit both spell the same and that act alike on ``(..., 3)`` arrays
_COMMON_OPS = ("cross", "maximum", "minimum", "abs", "sqrt")
#: operations each backend supplies itself (different name or different semantics in numpy)
_OWN_OPS = ("dot", "atan2", "select", "vec")


class _Ops:
    """The vector algebra of :func:`_form_factor` and :func:`point_to_disk_approx` for one array
    library, as attributes: ``lib``'s functions named in :data:`_COMMON_OPS`, and every one of
    :data:`_OWN_OPS` (no others) given as a keyword."""

    def __init__(self, lib, **own):
        if set(own) != set(_OWN_OPS):
            raise TypeError(f"_Ops needs exactly {_OWN_OPS}, got {tuple(own)}")
        for name in _COMMON_OPS:
            setattr(self, name, getattr(lib, name))
        for name, fn in own.items():
            setattr(self, name, fn)


def _np_dot(a, b):
    """Dot product over the last axis of numpy ``(..., 3)`` arrays."""
    return np.sum(a * b, axis=-1)


def _np_select(mask, a, b):
    """``np.where`` that lets a per-point mask ``(...)`` pick between ``(..., 3)`` vectors."""
    a, b = np.asarray(a), np.asarray(b)
    if max(a.ndim, b.ndim) > np.ndim(mask):
        mask = np.asarray(mask)[..., None]
    return np.where(mask, a, b)


def _np_vec(v):
    """A per-point scalar ``(...)`` as ``(..., 1)``, to scale ``(..., 3)`` vectors."""
    return v[..., None]


def _dr_vec(v):
    """The identity: Dr.Jit already broadcasts a ``mi.Float`` against a 3-vector."""
    return v


#: vector algebra on numpy ``(..., 3)`` arrays (float64)
_NumpyOps = _Ops(np, dot=_np_dot, atan2=np.arctan2, select=_np_select, vec=_np_vec)
#: the same operations on Dr.Jit arrays (``mi.Float``, ``mi.Vector3f``, ``mi.Point3f``)
_DrJitOps = _Ops(dr, dot=dr.dot, atan2=dr.atan2, select=dr.select, vec=_dr_vec)


def _normalize(ops, v):
    """v/|v|, and 0 for v = 0 (no division by zero)."""
    return v / ops.vec(ops.maximum(ops.sqrt(ops.dot(v, v)), _TINY))


def _edge_term(ops, x, n, p, q):
    r"""One term of Lambert's sum: γ · n·(r̂_p × r̂_q)/|r̂_p × r̂_q|, r = vertex − x.

    γ = atan2(|r̂_p × r̂_q|, r̂_p·r̂_q) is the angle between r_p and r_q. Since |n·c| ≤ |c| the term
    is bounded by γ ≤ π whatever the lengths; a zero-length edge or one seen end-on gives 0.
    """
    a = _normalize(ops, p - x)
    b = _normalize(ops, q - x)
    c = ops.cross(a, b)
    s = ops.sqrt(ops.dot(c, c))
    gamma = ops.atan2(s, ops.dot(a, b))
    return gamma * ops.dot(n, c) / ops.maximum(s, _TINY)


def _form_factor(ops, x, n, verts):
    """Shared body of :func:`polygon_form_factor` for both backends (verts: list of points)."""
    K = len(verts)
    r = [v - x for v in verts]
    h = [ops.dot(n, ri) for ri in r]  # heights above the tangent plane n·(p − x) = 0
    inside = [hi >= 0 for hi in h]

    # Sutherland-Hodgman clipping against n·(p − x) ≥ 0, edge by edge: each edge keeps its part
    # above the plane; for a convex polygon at most one edge exits and one re-enters, and the
    # clipped contour closes with the segment exit → entry along the plane.
    total = 0.0 * h[0]
    exit_pt = entry_pt = verts[0]
    clipped = inside[0] != inside[0]  # all-False mask of the right type
    for i in range(K):
        j = (i + 1) % K
        crosses = inside[i] != inside[j]
        t = h[i] / ops.select(crosses, h[i] - h[j], 1.0)  # h_i - h_j ≠ 0 where it crosses
        hit = verts[i] + (verts[j] - verts[i]) * ops.vec(t)
        start = ops.select(inside[i], verts[i], hit)
        end = ops.select(inside[j], verts[j], hit)
        term = _edge_term(ops, x, n, start, end)
        total = total + ops.select(inside[i] | inside[j], term, 0.0)
        exits = inside[i] & ~inside[j]
        exit_pt = ops.select(exits, hit, exit_pt)
        entry_pt = ops.select(~inside[i] & inside[j], hit, entry_pt)
        clipped = clipped | exits
    total = total + ops.select(clipped, _edge_term(ops, x, n, exit_pt, entry_pt), 0.0)

    # Edge-on: x in the polygon's plane, or zero area. N = Σ_k e_k × e_{k+1}, e_k = p_k − p_0, is
    # 2·area·n̂ for a planar polygon (0 for a degenerate one), so N·(x − p_0) = −N·r_0 is
    # 2·area·(signed distance of x to the plane).
    e = [v - verts[0] for v in verts[1:]]
    N = ops.cross(e[0], e[1])
    for k in range(1, K - 2):
        N = N + ops.cross(e[k], e[k + 1])
    R2 = ops.dot(r[0], r[0])
    for i in range(1, K):
        R2 = ops.maximum(R2, ops.dot(r[i], r[i]))
    in_plane = ops.abs(ops.dot(N, r[0])) <= PLANE_EPS * ops.sqrt(ops.dot(N, N)) * ops.sqrt(R2)

    return ops.select(in_plane, 0.0, ops.minimum(ops.abs(total) * _INV_2PI, 1.0))


def polygon_form_factor(x, n, verts):
    r"""Exact form factor from a differential area at ``x`` (unit normal ``n``) to a polygon.

    Lambert's (Baum et al. 1989) contour integral over the polygon clipped to the hemisphere
    above x (the plane n·(p − x) ≥ 0):

    .. math::

        F = \frac{1}{2\pi} \Bigl|\sum_i \gamma_i\,
            \frac{n\cdot(r_i \times r_{i+1})}{|r_i \times r_{i+1}|}\Bigr|,
        \qquad r_i = p_i - x,\quad \gamma_i = \angle(r_i, r_{i+1}),

    equal to :math:`\frac1\pi\int \max(0,\cos\theta_x)\,|\cos\theta_y|\,/\,r^2\,dA`
    (Arikan et al. eq. 6 divided by π). Each term is bounded by γ_i ≤ π, so F stays finite as x
    approaches an edge or a vertex; the result is clamped to [0, 1]. See the module docstring
    for the two-sided and in-plane conventions.

    * Dr.Jit: ``x`` ``mi.Point3f``, ``n`` ``mi.Vector3f``, ``verts`` a sequence of K ≥ 3
      ``mi.Point3f`` (a triangle ``(a, b, c)``: one triangle per lane) → ``mi.Float``.
    * numpy: ``x``, ``n`` ``(..., 3)``, ``verts`` ``(..., K, 3)``, broadcast → ``(...)``.

    The polygon must be planar and convex (triangles always are).
    """
    if isinstance(verts, (list, tuple)) and len(verts) > 0 and dr.is_array_v(verts[0]):
        if len(verts) < 3:
            raise ValueError(f"polygon_form_factor: need at least 3 vertices, got {len(verts)}")
        return _form_factor(_DrJitOps, x, n, list(verts))
    verts = np.asarray(verts, dtype=np.float64)
    if verts.ndim < 2 or verts.shape[-1] != 3 or verts.shape[-2] < 3:
        raise ValueError(f"polygon_form_factor: verts must have shape (..., K>=3, 3), got {verts.shape}")
    x = np.asarray(x, dtype=np.float64)
    n = np.asarray(n, dtype=np.float64)
    return _form_factor(_NumpyOps, x, n, [verts[..., k, :] for k in range(verts.shape[-2])])


def point_to_disk_approx(x, n, centre, normal, area):
    r"""Far-field form factor from a point to a small emitter (a triangle or a BVH cluster).

    .. math::

        F \approx \frac{A \max(0, n\cdot\omega)\, |m\cdot\omega|}{\pi r^2 + A},
        \qquad \omega = (c - x)/r,\ r = |c - x|,

    with c = ``centre``, m = ``normal``, A = ``area``. This is the form factor of a disk of
    area A facing the point, exact on the disk's axis (F = A / (πr² + A)); off axis it tends to
    the one-point quadrature A cosθ_x cosθ_y / (π r²) of Arikan et al. eq. 7 as r² ≫ A/π, and
    unlike that quadrature it stays ≤ 1 as r → 0. Arikan et al. §7 (citing Baum et al.) use it
    for a node farther than 4 times its bounding radius, where the error is below about 10 %;
    closer than that use :func:`polygon_form_factor` on the triangles.

    ``n`` must be unit; ``normal`` may be an area-weighted mean normal of a cluster
    (|m| ≤ 1), whose shorter length then discounts triangles whose normals disagree. The emitter
    is two-sided (|m·ω|). x = centre gives 0 (no direction).

    Dr.Jit (``mi.Point3f``, ``mi.Vector3f``, ``mi.Float`` area) or numpy ``(..., 3)`` arrays.
    """
    ops = _DrJitOps if dr.is_array_v(x) else _NumpyOps
    if ops is _NumpyOps:
        x, n, centre, normal, area = (np.asarray(v, dtype=np.float64) for v in (x, n, centre, normal, area))
    d = centre - x
    r2 = ops.dot(d, d)
    w = _normalize(ops, d)
    cos_x = ops.maximum(ops.dot(n, w), 0.0)
    cos_y = ops.abs(ops.dot(normal, w))
    return area * cos_x * cos_y / ops.maximum(math.pi * r2 + area, _TINY)
