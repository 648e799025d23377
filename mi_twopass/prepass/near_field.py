r"""Near-field correction :math:`B_C` of the radiance cache (Arikan, Forsyth & O'Brien 2005, §5, §7).

With the far field :math:`L_F` replaced by its mean :math:`\bar L_F = B_D/\pi` (§5, footnote 1),
eq. 6 in irradiance units reads

.. math::

    B_C(P, N) = \sum_{t_i \in T} (R_i - B_D)\, F(P, N \to t_i),

where :math:`F = \frac1\pi\int_{t_i} \cos\theta_1\cos\theta_2 / r^2\, dA` is the point-to-triangle
form factor (the paper's integral is :math:`\pi F`), :math:`R_i` the radiosity of triangle
:math:`t_i` (W/m²; the *reflected* radiosity: direct light is computed by emitter sampling, and
the far field holds indirect light only) and :math:`B_D` the far-field irradiance at P. T is the
set of triangles whose centroid is within ``alpha`` of P; they are assumed visible (§5).

Without the constant-L_F assumption (eq. 5, which footnote 1 says works as well), each triangle
is compared with the far field in its own direction D_t instead:
:math:`B_C = \sum (R_i - \pi L_F(D_t))\, F_i`, with L_F the interpolated SH at P
(``L_F=`` of :meth:`NearField.correction`). The integrator uses this form by default: where part
of the near geometry is already in the far-field fit (shading points farther than alpha from it
saw it), eq. 6 subtracts it twice and over-darkens corners.

§7: a bounding-volume hierarchy of all triangles stores, per node, the area-weighted sums of
radiosity and normal and the total area. A node is skipped when none of its triangles can count:
the sphere bounding its triangles' *centroids* lies farther than alpha from P (T holds
triangles by centroid), or its bounding sphere lies wholly below P's tangent plane (every form
factor is 0 there, cos θ_P ≤ 0). A node farther than ``open_factor`` (4) × its bounding radius is
counted as one disk (:func:`~mi_twopass.form_factor.point_to_disk_approx`); otherwise its
children are visited, and a leaf triangle gets the exact
:func:`~mi_twopass.form_factor.polygon_form_factor` (finite at corners and edges). Both form
factors sit in symbolic branches, so a packet of lanes skips the one none of its lanes needs.

The BVH is stored flat in pre-order with *skip links* (the index of the next node once a subtree
is done): a lane walks it with one counter and no stack (:meth:`NearField.correction`, a Dr.Jit
loop). Triangles are one-sided (patches are, see :mod:`mi_twopass.scene.patches`): a triangle
is counted only where P lies in front of it, which also drops the shading point's own and coplanar
triangles (P in their plane).

:func:`correction_numpy` is the obvious O(T) reference used by the tests.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import sh
from ..form_factor import point_to_disk_approx, polygon_form_factor

#: §7: a node farther than this many bounding radii is summed as a whole
OPEN_FACTOR = 4.0
#: P counts as in front of a triangle when n_t·(P − a) > FRONT_EPS × alpha
FRONT_EPS = 1e-4


@dataclass
class NearField:
    """Flat BVH over triangles with per-node radiosity / normal / area (§7).

    numpy arrays (``M`` nodes, ``T`` triangles, leaves hold one triangle each):
    ``center``/``radius`` the bounding sphere, ``area`` Σ A, ``B`` Σ A·R / Σ A (mean radiosity,
    (M, 3)), ``normal`` Σ A·n / Σ A (|·| ≤ 1), ``skip`` the next node after the subtree,
    ``tri`` the triangle of a leaf (−1 for inner nodes), ``ccenter``/``cradius`` the sphere
    bounding the node's triangle centroids; triangles ``verts`` (T, 3, 3), ``tri_normal`` (T, 3),
    ``tri_B`` (T, 3).
    """
    center: np.ndarray
    radius: np.ndarray
    area: np.ndarray
    B: np.ndarray
    normal: np.ndarray
    skip: np.ndarray
    tri: np.ndarray
    verts: np.ndarray
    tri_normal: np.ndarray
    tri_B: np.ndarray
    ccenter: np.ndarray
    cradius: np.ndarray

    @property
    def node_count(self) -> int:
        return int(self.skip.size)

    @property
    def nbytes(self) -> int:
        return int(sum(a.astype(np.float32).nbytes for a in (
            self.center, self.radius, self.area, self.B, self.normal, self.skip, self.tri,
            self.verts, self.tri_normal, self.tri_B, self.ccenter, self.cradius)))

    def _tables(self):
        if not hasattr(self, "_dr"):
            f = lambda a: mi.Float(np.ascontiguousarray(a, dtype=np.float32).ravel())  # noqa: E731
            self._dr = dict(
                center=f(self.center), radius=f(self.radius), area=f(self.area), B=f(self.B),
                normal=f(self.normal), skip=mi.UInt32(self.skip.astype(np.uint32)),
                tri=mi.UInt32(np.where(self.tri < 0, 0xFFFFFFFF, self.tri).astype(np.uint32)),
                verts=f(self.verts), tri_normal=f(self.tri_normal), tri_B=f(self.tri_B),
                ccenter=f(self.ccenter), cradius=f(self.cradius),
                M=dr.opaque(mi.UInt32, self.node_count))
            dr.eval(self._dr)
        return self._dr

    def correction(self, x, n, B_D, alpha, active=True, open_factor=OPEN_FACTOR, L_F=None):
        r""":math:`B_C = \sum (R_i - B_D) F_i` at points ``x`` (``mi.Point3f``) with unit normals
        ``n`` and far-field irradiance ``B_D`` (``mi.Color3f``) → ``(mi.Color3f, mi.UInt32 nodes
        visited)``. ``open_factor = inf`` always descends to the triangles (exact eq. 6).

        ``L_F``: optional per-lane SH coefficients of the far field (9 ``mi.Color3f``); then each
        triangle (node) subtracts :math:`\pi L_F(D_t)`, the far field in its own direction D_t
        (eq. 5 without the constant-L_F assumption, footnote 1), instead of B_D."""
        if self.node_count == 0:
            return mi.Color3f(0.0), mi.UInt32(0)
        if L_F is None:
            L_F = []
        return self._traverse(x, n, B_D, alpha, active, open_factor, list(L_F))

    @dr.syntax
    def _traverse(self, x, n, B_D, alpha, active, open_factor, L_F):
        """The stackless skip-link walk of :meth:`correction` (one lane per point)."""
        t = self._tables()
        x = mi.Point3f(x)
        n = mi.Vector3f(n)
        B_D = mi.Color3f(B_D)
        alpha = mi.Float(alpha)
        of = mi.Float(float(open_factor) if np.isfinite(open_factor) else 3e38)
        B_C = mi.Color3f(0.0)
        node = mi.UInt32(0)
        visits = mi.UInt32(0)
        active = mi.Bool(active)
        while dr.hint(active, label="near_field_bvh"):
            c = dr.gather(mi.Point3f, t["center"], node, active)
            r = dr.gather(mi.Float, t["radius"], node, active)
            cc = dr.gather(mi.Point3f, t["ccenter"], node, active)
            cr = dr.gather(mi.Float, t["cradius"], node, active)
            skip = dr.gather(mi.UInt32, t["skip"], node, active)
            tri = dr.gather(mi.UInt32, t["tri"], node, active)
            d = dr.norm(c - x)
            visits += 1
            # no centroid within alpha, or the whole node below the tangent plane: F = 0
            miss = (dr.norm(cc - x) > alpha + cr) | (dr.dot(n, c - x) < -r)
            is_leaf = tri != 0xFFFFFFFF
            as_disk = active & ~miss & ~is_leaf & (d > of * r)
            leaf = active & ~miss & is_leaf
            # Symbolic branches: a packet of lanes skips a form factor none of its lanes needs.
            if as_disk:  # a node far enough away: one disk of its area, mean radiosity, normal
                A = dr.gather(mi.Float, t["area"], node)
                m = dr.gather(mi.Vector3f, t["normal"], node)
                Bn = dr.gather(mi.Color3f, t["B"], node)
                B_C += (Bn - _far(B_D, L_F, c - x)) * point_to_disk_approx(x, n, c, m, A)
            if leaf:  # the exact form factor of its triangle, if its centroid is near, P in front
                a = dr.gather(mi.Point3f, t["verts"], 3 * tri)
                b = dr.gather(mi.Point3f, t["verts"], 3 * tri + 1)
                c3 = dr.gather(mi.Point3f, t["verts"], 3 * tri + 2)
                nt = dr.gather(mi.Vector3f, t["tri_normal"], tri)
                centroid = (a + b + c3) * (1.0 / 3.0)
                use = (dr.norm(centroid - x) <= alpha) & (dr.dot(nt, x - a) > FRONT_EPS * alpha)
                Bt = dr.gather(mi.Color3f, t["tri_B"], tri, use)
                F_tri = polygon_form_factor(x, n, [a, b, c3])
                B_C += dr.select(use, (Bt - _far(B_D, L_F, centroid - x)) * F_tri, 0.0)
            descend = active & ~miss & ~is_leaf & ~as_disk
            node = dr.select(descend, node + 1, skip)
            active &= node < t["M"]
        return B_C, visits


def _far(B_D, L_F, d):
    """The far-field irradiance a near triangle replaces: B_D (eq. 6) or π·L_F(d/|d|) (eq. 5)."""
    if not L_F:
        return B_D
    return dr.pi * sh.evaluate(L_F, dr.normalize(d))


def build_near_field(verts, tri_normal, tri_B) -> NearField:
    """Median-split BVH (longest centroid axis) over triangles ``verts`` (T, 3, 3) with one-sided
    unit normals (T, 3) and radiosities ``tri_B`` (T, 3). Bookkeeping in numpy, vectorised over
    all nodes of one tree level (about log2 T passes); zero-area triangles are dropped."""
    verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3, 3)
    tri_normal = np.asarray(tri_normal, dtype=np.float64).reshape(-1, 3)
    tri_B = np.asarray(tri_B, dtype=np.float64).reshape(-1, 3)
    tri_area = 0.5 * np.linalg.norm(np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0]),
                                    axis=1)
    keep = np.nonzero(np.isfinite(tri_area) & (tri_area > 0))[0]
    verts, tri_normal, tri_B, tri_area = verts[keep], tri_normal[keep], tri_B[keep], tri_area[keep]
    T = len(verts)
    centroid = verts.mean(axis=1)
    M = max(0, 2 * T - 1)
    center = np.zeros((M, 3)); radius = np.zeros(M); area = np.zeros(M)
    B = np.zeros((M, 3)); normal = np.zeros((M, 3))
    skip = np.zeros(M, dtype=np.int64); tri = np.full(M, -1, dtype=np.int64)
    ccenter = np.zeros((M, 3)); cradius = np.zeros(M)
    if T == 0:
        near = NearField(center, radius, area, B, normal, skip, tri, verts, tri_normal, tri_B,
                         ccenter, cradius)
        near._tables()
        return near
    # Level by level: ``perm`` orders the triangles so that every node is a contiguous segment
    # [start, end) of it; a node of n triangles has 2n − 1 nodes in its subtree, so in pre-order
    # its left child is node + 1, its right child node + 2·n_left and its skip link node + 2n − 1.
    perm = np.arange(T)
    start, end, node = np.array([0]), np.array([T]), np.array([0])
    while len(node):
        n_seg = end - start
        seg = np.repeat(np.arange(len(node)), n_seg)  # segment of each position of perm
        ids = perm[_ranges(start, end)]
        # node aggregates (reduceat over the contiguous segments)
        first = n_seg.cumsum() - n_seg
        vp = verts[ids]  # (Σn, 3, 3)
        lo = np.minimum.reduceat(vp.min(axis=1), first, axis=0)
        hi = np.maximum.reduceat(vp.max(axis=1), first, axis=0)
        c_n = 0.5 * (lo + hi)
        d2 = ((vp - c_n[seg][:, None, :]) ** 2).sum(-1).max(axis=1)
        center[node] = c_n
        radius[node] = np.sqrt(np.maximum.reduceat(d2, first))
        cts = centroid[ids]
        clo = np.minimum.reduceat(cts, first, axis=0)
        chi = np.maximum.reduceat(cts, first, axis=0)
        ccenter[node] = 0.5 * (clo + chi)
        cradius[node] = np.sqrt(np.maximum.reduceat(((cts - ccenter[node][seg]) ** 2).sum(-1),
                                                    first))
        w = tri_area[ids]
        area[node] = np.add.reduceat(w, first)
        B[node] = np.add.reduceat(w[:, None] * tri_B[ids], first, axis=0) / area[node][:, None]
        normal[node] = (np.add.reduceat(w[:, None] * tri_normal[ids], first, axis=0)
                        / area[node][:, None])
        skip[node] = node + 2 * n_seg - 1
        leaf = n_seg == 1
        tri[node[leaf]] = ids[first[leaf]]
        # split the inner nodes at the median along their longest centroid axis (stable sort)
        axis = np.argmax(chi - clo, axis=1)
        key = cts[np.arange(len(ids)), axis[seg]]
        order = np.lexsort((key, seg))
        perm[_ranges(start, end)] = ids[order]
        inner = ~leaf
        half = n_seg[inner] // 2
        s_i, e_i, nd = start[inner], end[inner], node[inner]
        start = np.concatenate([s_i, s_i + half])
        end = np.concatenate([s_i + half, e_i])
        node = np.concatenate([nd + 1, nd + 2 * half])
    near = NearField(center, radius, area, B, normal, skip, tri, verts, tri_normal, tri_B,
                     ccenter, cradius)
    near._tables()  # Dr.Jit copies now, never first inside a symbolic loop
    return near


def _ranges(start, end):
    """Concatenated aranges [start_i, end_i) (numpy, vectorised)."""
    n = end - start
    offs = np.repeat(start - np.concatenate([[0], np.cumsum(n)[:-1]]), n)
    return np.arange(int(n.sum())) + offs


def correction_numpy(x, n, B_D, alpha, verts, tri_normal, tri_B, L_F=None):
    """Brute-force eq. 6 (exact form factors, every triangle tested): ``x``, ``n`` (P, 3), ``B_D``
    (P, 3), optional ``L_F`` (P, 9, 3) (eq. 5: subtract π L_F(D_t)) → (P, 3). The reference for
    :meth:`NearField.correction` with ``open_factor=inf``."""
    x = np.asarray(x, dtype=np.float64).reshape(-1, 1, 3)
    n = np.asarray(n, dtype=np.float64).reshape(-1, 1, 3)
    verts = np.asarray(verts, dtype=np.float64)[None]
    tri_normal = np.asarray(tri_normal, dtype=np.float64)[None]
    area = 0.5 * np.linalg.norm(np.cross(verts[..., 1, :] - verts[..., 0, :],
                                         verts[..., 2, :] - verts[..., 0, :]), axis=-1)
    F = polygon_form_factor(x, n, verts)
    near = np.linalg.norm(verts.mean(axis=2) - x, axis=-1) <= alpha
    front = ((x - verts[..., 0, :]) * tri_normal).sum(-1) > FRONT_EPS * alpha
    F = np.where(near & front & (area > 0), F, 0.0)
    if L_F is None:
        far = np.asarray(B_D, dtype=np.float64)[:, None]
    else:
        d = verts.mean(axis=2) - x
        d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300)
        far = np.pi * sh.evaluate(np.asarray(L_F, dtype=np.float64)[:, None], d)
    diff = np.asarray(tri_B, dtype=np.float64)[None] - far
    return (F[..., None] * diff).sum(axis=1)
