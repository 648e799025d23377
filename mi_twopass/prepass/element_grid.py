"""Irradiance inside the unevenly lit elements: a K × K grid of cells in each element's plane.

The radiosity solve caches an element as its mean irradiance E = ΣΦ / A (Cohen, Greenberg,
Immel & Brock 1986's patch/element substructuring). Where the light across an element is
uneven (:func:`~mi_twopass.prepass.radiosity.receiver_spread`: the rim of a sun patch, a
shadow edge), the mean is no stand-in for the light where a gather ray lands, so the element
used to be left uncached and every ray that met it was traced on. On
``scenes_xml/window_interior.xml`` those were 67–71 of 8032 elements, at the sun patch's
edges, and the paths traced on from them were most of the radiance cache's indirect noise.

This module refines exactly those elements one level further, as Heckbert's adaptive radiosity
textures refine where the light changes: every particle deposit also lands in the cell of its
element that holds the hit (:meth:`ElementFrames.cell`: K × K cells over the square of the
element's radius, on the two world axes its normal is least along), and after the solve the
uneven flat elements read E_cell = ΣΦ_cell / A_cell (:func:`cell_areas`, exact), the others
their mean as before. The grid costs one scatter per particle hit (the solve on
window_interior 0.038 → 0.042–0.045 s, office 0.150 → 0.159–0.169 s, ``tools/solve_timing.py``)
and K² counters per element; only the refined elements keep a table (:class:`ElementGrid`).

Measured on window_interior (35 of its 67 uneven elements refined; the others are cut by
geometry or partly buried): the cells read 0.996–1.013 of the light ``path`` finds where
gather rays from the camera's first hits land on them, the element means 0.977–0.982; the
radiance cache's indirect noise at 128², 16 spp went 0.0093 → 0.0037 (relvar, total 0.0172 →
0.0116, ``tools/variance_parts.py``), and paired renders moved its image mean by −0.06 ±
0.04 % (mixed_room −0.19 ± 0.07 %).

A curved element (a sphere's cell: its uneven light comes from faces turned to or from a
light, which a grid in one plane does not separate) is not refined: ``bend``, the shortfall of
its area-weighted mean normal from unit length, must be below ``FLAT_BEND``.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import units
from ..host_arrays import id_table, jit
from ..tables import Tables

#: cells along each axis of an element's grid
GRID_RES = 4
#: an element is flat enough to refine in its plane where sqrt(1 − |n̄|²) (n̄ its area-weighted
#: mean normal) is below this: about 6° of turn across it
FLAT_BEND = 0.1
#: an element is refined only where at least this fraction of it is exposed (``area /
#: geometric_area``, the exposure probe's): which of its cells are buried is not known, and
#: spreading the exposure over all of them read 3–6× the light in the open ones (an element of
#: window_interior 12.5 % exposed)
MIN_EXPOSURE = 0.95
#: a cell with less than this fraction of its element's area reads the element's mean: the
#: few deposits such a sliver gets would make its value noise, and gather rays rarely land on it
MIN_CELL_FRACTION = 0.25 / GRID_RES ** 2


class ElementFrames:
    """Per element, the map from a point on it to its grid: the offset (p − c) / r from its
    centre c in units of its radius r (the largest distance of its vertices from c, so every
    point of it lies within [−1, 1]³), projected on the two world axes its normal is least
    along, (u, v), and the cell ⌊(u + 1) K / 2⌋ + K ⌊(v + 1) K / 2⌋.

    World axes, not a frame fitted to each element: the particle kernel already has the offset
    (:func:`~mi_twopass.prepass.radiosity.receiver_spread`'s moments), and the cell then costs
    one gather (the axis) where a fitted frame cost nine and took the solve on window_interior
    from 0.039 to 0.061–0.067 s (``tools/solve_timing.py``)."""

    def __init__(self, elements, res: int = GRID_RES):
        from .radiosity import receiver_radius  # (radiosity imports this module)

        self.res = int(res)
        M = elements.count
        normal = np.abs(np.asarray(elements.normal, dtype=np.float64).reshape(M, 3))
        #: (M,) the world axis each element's normal is most along, which its cells drop
        self.axis = np.argmax(normal, axis=1).astype(np.uint32) if M else np.zeros(0, np.uint32)
        self.center = np.asarray(elements.center, dtype=np.float64).reshape(M, 3)
        self.inv_radius = 1.0 / np.maximum(receiver_radius(elements), 1e-30)
        self._tables = Tables(axis=jit(mi.UInt32, np.append(self.axis, 0).astype(np.uint32)),
                              center=id_table(self.center, mi.Point3f),
                              inv_radius=jit(mi.Float, np.append(self.inv_radius, 0.0)
                                             .astype(np.float32)))

    @property
    def inv_radius_table(self):
        """``mi.Float``: 1/r per element (0 for the invalid id), the particle kernel's scale of
        the offset (p − c)/r it deposits and :meth:`cell_of_offset` reads."""
        return self._tables["inv_radius"]

    def cell_of_offset(self, rid, offset, active=True):
        """``mi.UInt32``: the cell of element ``rid`` at ``offset`` = (p − c) / r (0 for lanes
        that are not active)."""
        a = dr.gather(mi.UInt32, self._tables["axis"], rid, active)
        u = dr.select(a == 0, offset.y, offset.x)
        v = dr.select(a == 2, offset.y, offset.z)
        K = self.res
        iu = dr.clip(mi.Int32(dr.floor((u + 1.0) * (0.5 * K))), 0, K - 1)
        iv = dr.clip(mi.Int32(dr.floor((v + 1.0) * (0.5 * K))), 0, K - 1)
        return dr.select(active, mi.UInt32(iu + K * iv), 0)

    def cell(self, rid, p, active=True):
        """``mi.UInt32``: the cell of element ``rid`` holding the point ``p``."""
        t = self._tables
        offset = (p - dr.gather(mi.Point3f, t["center"], rid, active)) \
            * dr.gather(mi.Float, t["inv_radius"], rid, active)
        return self.cell_of_offset(rid, offset, active)

    def uv_np(self, ids, points):
        """(n, 2): the (u, v) of ``points`` (n, 3) on the elements ``ids`` (n,), numpy."""
        ids = np.asarray(ids, dtype=np.int64)
        off = (np.asarray(points, dtype=np.float64) - self.center[ids]) \
            * self.inv_radius[ids][:, None]
        a = self.axis[ids]
        return np.column_stack([np.where(a == 0, off[:, 1], off[:, 0]),
                                np.where(a == 2, off[:, 1], off[:, 2])])

    def cells_np(self, ids, points):
        """The cells of ``points`` (n, 3) on the elements ``ids`` (n,), numpy."""
        u, v = self.uv_np(ids, points).T
        K = self.res
        iu = np.clip(np.floor((u + 1.0) * (0.5 * K)), 0, K - 1)
        iv = np.clip(np.floor((v + 1.0) * (0.5 * K)), 0, K - 1)
        return (iu + K * iv).astype(np.int64)


def _clip(poly, count, axis: int, bound, sign: float):
    """Sutherland–Hodgman, vectorised: each polygon ``poly`` (P, V, 2) of ``count`` (P,)
    vertices clipped to sign · (x[axis] − bound) ≥ 0 (``bound`` (P,)). Returns the clipped
    polygons (P, V + 1, 2) and their counts; slots past a count repeat the first vertex, so
    :func:`_shoelace` may sum over all of them."""
    P, V = poly.shape[:2]
    i = np.arange(V)
    valid = i[None, :] < count[:, None]
    nxt = np.where(i[None, :] + 1 < count[:, None], i[None, :] + 1, 0)
    cur_p = poly
    nxt_p = np.take_along_axis(poly, nxt[..., None], axis=1)
    s_cur = sign * (cur_p[..., axis] - bound[:, None])
    s_nxt = sign * (nxt_p[..., axis] - bound[:, None])
    inside = s_cur >= 0
    cross = valid & (inside != (s_nxt >= 0))
    denom = np.where(cross, s_cur - s_nxt, 1.0)
    t = np.where(cross, s_cur / denom, 0.0)
    meet = cur_p + t[..., None] * (nxt_p - cur_p)
    out = np.stack([cur_p, meet], axis=2).reshape(P, 2 * V, 2)
    keep = np.stack([valid & inside, cross], axis=2).reshape(P, 2 * V)
    order = np.argsort(~keep, axis=1, kind="stable")
    out = np.take_along_axis(out, order[..., None], axis=1)
    n = keep.sum(axis=1)
    width = V + 1
    out = out[:, :width]
    pad = np.arange(width)[None, :] >= n[:, None]
    out = np.where(pad[..., None], out[:, :1], out)
    return out, n


def _shoelace(poly) -> np.ndarray:
    """Unsigned area of each polygon (P, V, 2) whose unused slots repeat its first vertex."""
    x, y = poly[..., 0], poly[..., 1]
    return 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))


def cell_areas(elements, frames: ElementFrames, ids) -> np.ndarray:
    """(len(ids), K²) geometric area of each cell of the elements ``ids``, exact: each of
    their triangles projected on the element's (u, v) plane (:class:`ElementFrames`) and
    clipped to each cell (:func:`_clip`), its area divided by the projection's cosine
    |n · e_axis| and scaled back from units of the radius."""
    ids = np.asarray(ids, dtype=np.int64)
    K = frames.res
    out = np.zeros((len(ids), K * K))
    if not len(ids):
        return out
    row = np.full(elements.count, -1, np.int64)
    row[ids] = np.arange(len(ids))
    tri = np.asarray(elements.tri_patch, dtype=np.int64)
    keep = np.nonzero(row[tri] >= 0)[0]
    if not len(keep):
        return out
    owner = tri[keep]
    tv = np.asarray(elements.tri_vertices, dtype=np.float64)[keep]  # (T, 3, 3)
    uv = np.stack([frames.uv_np(owner, tv[:, k]) for k in range(3)], axis=1)  # (T, 3, 2)
    cosine = np.abs(np.take_along_axis(np.asarray(elements.tri_normal, np.float64)[keep],
                                       frames.axis[owner][:, None].astype(np.int64), axis=1)
                    )[:, 0]
    r = 1.0 / frames.inv_radius[owner]
    scale = np.where(cosine > 1e-6, r * r / np.maximum(cosine, 1e-6), 0.0)
    T = len(keep)
    edges = -1.0 + 2.0 * np.arange(K + 1) / K
    cu, cv = np.meshgrid(np.arange(K), np.arange(K), indexing="xy")  # cell = iu + K iv
    cu, cv = cu.ravel(), cv.ravel()
    poly = np.repeat(uv, K * K, axis=0)  # (T·K², 3, 2), cell-fastest
    count = np.full(T * K * K, 3)
    iu, iv = np.tile(cu, T), np.tile(cv, T)
    for axis, lo, hi in ((0, edges[iu], edges[iu + 1]), (1, edges[iv], edges[iv + 1])):
        poly, count = _clip(poly, count, axis, lo, 1.0)
        poly, count = _clip(poly, count, axis, hi, -1.0)
    area = _shoelace(poly).reshape(T, K * K) * scale[:, None]
    np.add.at(out, row[owner], area)
    return out


def refinable(elements, uneven, bend) -> np.ndarray:
    """Ids of the elements to refine: unevenly lit (``uneven``, (M,) bool), cached but for
    that (diffuse, not cut by geometry: ``elements.is_diffuse`` before the solve uncached the
    uneven ones, so the caller passes it ANDed in), flat (``bend`` < ``FLAT_BEND``) and
    exposed (≥ ``MIN_EXPOSURE`` of the geometric area)."""
    return np.nonzero(np.asarray(uneven, dtype=bool) & (np.asarray(bend) < FLAT_BEND)
                      & (_exposure(elements) >= MIN_EXPOSURE))[0]


def _exposure(elements) -> np.ndarray:
    """(M,) the open fraction of each element, ``area / geometric_area`` (1 without the
    exposure probe's geometric areas, 0 for an element of no area)."""
    area = np.asarray(elements.area, dtype=np.float64)
    geometric = getattr(elements, "geometric_area", None)
    geometric = area if geometric is None else np.asarray(geometric, dtype=np.float64)
    return np.where(geometric > 0, area / np.where(geometric > 0, geometric, 1.0), 0.0)


class ElementGrid:
    """The refined elements of a solution and their cells' reflected radiance B_r,cell / π.

    ``ids`` (S,) the refined elements; ``flux`` (S, K²) the flux deposited in their cells
    (the channel mean, one counter per cell in the particle kernel: a cell takes its element's
    colour, scaled to its own brightness);
    ``areas`` (S, K²) the cells' geometric areas (:func:`cell_areas`), scaled by the element's
    exposure (``area / geometric_area``); ``albedo`` (S, 3); ``E_mean`` (S, 3) each element's
    mean irradiance, which a cell under ``MIN_CELL_FRACTION`` of the area reads instead."""

    def __init__(self, elements, frames: ElementFrames, ids, flux, areas, E_mean):
        self.frames = frames
        self.ids = np.asarray(ids, dtype=np.int64)
        M, S, K2 = elements.count, len(self.ids), frames.res ** 2
        areas = np.asarray(areas, dtype=np.float64).reshape(S, K2)
        total = areas.sum(axis=1, keepdims=True)
        exposed = areas * _exposure(elements)[self.ids][:, None]  # ≥ MIN_EXPOSURE (refinable)
        wide = areas >= MIN_CELL_FRACTION * total
        E_mean = np.asarray(E_mean, dtype=np.float64).reshape(S, 1, 3)
        grey = E_mean.mean(axis=2, keepdims=True)
        colour = np.where(grey > 0, E_mean / np.where(grey > 0, grey, 1.0), 1.0)
        E_grey = np.asarray(flux, dtype=np.float64).reshape(S, K2, 1) \
            / np.where(exposed > 0, exposed, 1.0)[..., None]
        E = np.where(wide[..., None], E_grey * colour, E_mean)
        #: (S, K², 3) irradiance of each cell
        self.E = E
        albedo = np.asarray(elements.albedo, dtype=np.float64)[self.ids]
        #: (S, K², 3) reflected radiosity ρ E of each cell
        self.B_reflected = albedo[:, None, :] * E
        base = np.full(M + 1, 0xFFFFFFFF, np.uint32)
        base[self.ids] = (np.arange(S) * K2).astype(np.uint32)
        self._tables = Tables(base=jit(mi.UInt32, base),
                              L=id_table(units.radiance_from_radiosity(self.B_reflected),
                                         mi.Color3f))

    @property
    def count(self) -> int:
        """Number of refined elements."""
        return int(len(self.ids))

    @property
    def nbytes(self) -> int:
        return int(self.E.nbytes + self.B_reflected.nbytes + 4 * len(self._tables["base"])
                   + 12 * (self.B_reflected.size // 3 + 1))

    def refined(self, rid, active=True):
        """``mi.Bool``: element ``rid`` has a grid."""
        base = dr.gather(mi.UInt32, self._tables["base"], rid, active)
        return mi.Bool(active) & (base != 0xFFFFFFFF)

    def reflected_radiance(self, rid, p, mean, active=True):
        """B_r/π at ``p`` on element ``rid``: its cell's where the element is refined, else
        ``mean`` (the caller's read of the element's mean)."""
        base = dr.gather(mi.UInt32, self._tables["base"], rid, active)
        on = mi.Bool(active) & (base != 0xFFFFFFFF)
        slot = base + self.frames.cell(rid, p, on)
        return dr.select(on, dr.gather(mi.Color3f, self._tables["L"], slot, on), mean)
