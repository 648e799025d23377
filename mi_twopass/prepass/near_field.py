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
triangles by centroid), or its bounding box lies on or below P's tangent plane (every form
factor is 0 there, cos θ_P ≤ 0; a box test, so a child of a skipped node is skipped too). A node farther than ``open_factor`` (4) × its bounding radius is
counted as one disk (:func:`~mi_twopass.form_factor.point_to_disk_approx`); otherwise its
children are visited, and a leaf triangle gets the exact
:func:`~mi_twopass.form_factor.polygon_form_factor` (finite at corners and edges). Both form
factors sit in symbolic branches, so a packet of lanes skips the one none of its lanes needs.

The BVH is stored flat in pre-order with *skip links* (the index of the next node once a subtree
is done): a lane walks it with one counter and no stack (:meth:`NearField.correction`, a Dr.Jit
loop). Around the camera's shading points, where the cache is read, a lane does not walk the
tree: its cell lists the leaves a point of the cell may count (:class:`LeafCells`, built in the
prepass), and it sums those with the same leaf tests.

§5 lazy splitting (:func:`split_near_triangles`): triangles that a shading point may lie within
alpha of are bisected until their longest edge is ≤ alpha, each half keeping its patch's
radiosity, so the centroid rule of T matches the far field's "hit within alpha" rule to within
half a triangle. :func:`buried_triangles` finds the faces inside closed solids (overlapping
boxes), which the visibility assumption must not count. Triangles are one-sided (patches are, see :mod:`mi_twopass.scene.patches`): a triangle
is counted only where P lies in front of it, which also drops the shading point's own and coplanar
triangles (P in their plane).

:func:`correction_numpy` is the obvious O(T) reference used by the tests.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import sh
from ..form_factor import point_to_disk_approx, polygon_form_factor
from ..host_arrays import jit
from ..scene.bounds import scene_diagonal
from ..tables import Tables

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
    half: np.ndarray = None
    cells: "LeafCells" = None

    @property
    def node_count(self) -> int:
        return int(self.skip.size)

    @property
    def nbytes(self) -> int:
        own = sum(a.astype(np.float32).nbytes for a in (
            self.center, self.radius, self.area, self.B, self.normal, self.skip, self.tri,
            self.verts, self.tri_normal, self.tri_B, self.ccenter, self.cradius, self.half))
        return int(own + (self.cells.nbytes if self.cells is not None else 0))

    @cached_property
    def _tables(self) -> Tables:
        """Dr.Jit copies of the tree, the triangles and the cell lists (:meth:`LeafCells.tables`),
        built on first use and kept (:func:`build_near_field` builds them, outside any symbolic
        loop; set ``cells`` before)."""
        f = lambda a: jit(mi.Float, np.ascontiguousarray(a, dtype=np.float32).ravel())  # noqa: E731
        cells = self.cells if self.cells is not None else LeafCells.empty()
        t = Tables(
            center=f(self.center), radius=f(self.radius), area=f(self.area), B=f(self.B),
            normal=f(self.normal), skip=jit(mi.UInt32, self.skip.astype(np.uint32)),
            tri=jit(mi.UInt32, np.where(self.tri < 0, 0xFFFFFFFF, self.tri).astype(np.uint32)),
            verts=f(self.verts), tri_normal=f(self.tri_normal), tri_B=f(self.tri_B),
            ccenter=f(self.ccenter), cradius=f(self.cradius), half=f(self.half),
            M=dr.opaque(mi.UInt32, self.node_count), **cells.tables())
        dr.eval(*t.values())
        return t

    def correction(self, x, n, B_D, alpha, active=True, open_factor=OPEN_FACTOR, L_F=None):
        r""":math:`B_C = \sum (R_i - B_D) F_i` at points ``x`` (``mi.Point3f``) with unit normals
        ``n`` and far-field irradiance ``B_D`` (``mi.Color3f``) → ``(mi.Color3f, mi.UInt32 nodes
        visited)``. ``open_factor = inf`` always descends to the triangles (exact eq. 6).

        ``L_F``: optional per-lane SH coefficients of the far field (9 ``mi.Color3f``); then each
        triangle (node) subtracts :math:`\pi L_F(D_t)`, the far field in its own direction D_t
        (eq. 5 without the constant-L_F assumption, footnote 1), instead of B_D.

        Where the near field has cell lists (:class:`LeafCells`) built for this ``alpha``, a
        lane in a listed cell sums its cell's leaves (exactly: as ``open_factor = inf``) and the
        others walk the BVH from the root; else every lane walks from the root."""
        if self.node_count == 0:
            return mi.Color3f(0.0), mi.UInt32(0)
        L_F = [] if L_F is None else list(L_F)
        t = self._tables
        x = mi.Point3f(x)
        active = mi.Bool(active)
        cells = self.cells
        if cells is None or float(alpha) != cells.alpha or cells.entries == 0:
            return self._traverse(x, n, B_D, alpha, active, open_factor, L_F)
        first, count, listed = LeafCells.lookup(x, t, n)
        B_list, v_list = self._walk_leaves(x, n, B_D, alpha, active & listed, L_F, first, count)
        B_root, v_root = self._traverse(x, n, B_D, alpha, active & ~listed, open_factor, L_F)
        return B_list + B_root, v_list + v_root

    @dr.syntax
    def _traverse(self, x, n, B_D, alpha, active, open_factor, L_F):
        """The stackless skip-link walk of :meth:`correction` from the root, one lane per
        point."""
        t = self._tables
        n = mi.Vector3f(n)
        abs_n = dr.abs(n)
        B_D = mi.Color3f(B_D)
        alpha = dr.opaque(mi.Float, float(alpha))  # changes per prepass: not a literal
        of = mi.Float(float(open_factor) if np.isfinite(open_factor) else 3e38)
        B_C = mi.Color3f(0.0)
        visits = mi.UInt32(0)
        node = mi.UInt32(0)
        active = mi.Bool(active)
        while dr.hint(active, label="near_field_bvh"):
            c = dr.gather(mi.Point3f, t["center"], node, active)
            r = dr.gather(mi.Float, t["radius"], node, active)
            h = dr.gather(mi.Vector3f, t["half"], node, active)
            cc = dr.gather(mi.Point3f, t["ccenter"], node, active)
            cr = dr.gather(mi.Float, t["cradius"], node, active)
            skip = dr.gather(mi.UInt32, t["skip"], node, active)
            tri = dr.gather(mi.UInt32, t["tri"], node, active)
            d = dr.norm(c - x)
            visits += 1
            miss = _culled(x, n, abs_n, c, h, cc, alpha + cr)
            is_leaf = tri != 0xFFFFFFFF
            as_disk = active & ~miss & ~is_leaf & (d > of * r)
            leaf = active & ~miss & is_leaf
            # Symbolic branches: a packet of lanes skips a form factor none of its lanes needs.
            if as_disk:  # a node far enough away: one disk of its area, mean radiosity, normal
                A = dr.gather(mi.Float, t["area"], node)
                m = dr.gather(mi.Vector3f, t["normal"], node)
                Bn = dr.gather(mi.Color3f, t["B"], node)
                B_C += (Bn - _far(B_D, L_F, c - x)) * point_to_disk_approx(x, n, c, m, A)
            # a leaf counts if P is in front of its triangle (its centroid is the leaf's ccenter,
            # already within alpha): tested before the branch, so the form factor runs only there
            B_C += self._leaf_term(x, B_D, L_F, n, tri, cc, alpha, leaf)
            descend = active & ~miss & ~is_leaf & ~as_disk
            node = dr.select(descend, node + 1, skip)
            active &= node < t["M"]
        return B_C, visits

    @dr.syntax
    def _walk_leaves(self, x, n, B_D, alpha, active, L_F, first, count):
        """The lanes of listed cells: their cell's leaves ``cell_leaves[first : first +
        count]``, with the leaf tests of :meth:`_traverse` (centroid within alpha, box above the
        tangent plane, x in front of the triangle) and its exact form factor."""
        t = self._tables
        n = mi.Vector3f(n)
        abs_n = dr.abs(n)
        B_D = mi.Color3f(B_D)
        alpha = dr.opaque(mi.Float, float(alpha))
        B_C = mi.Color3f(0.0)
        visits = mi.UInt32(0)
        j = mi.UInt32(first)
        stop = j + mi.UInt32(count)
        active = mi.Bool(active) & (j < stop)
        while dr.hint(active, label="near_field_leaves"):
            node = dr.gather(mi.UInt32, t["cell_leaves"], j, active)
            c = dr.gather(mi.Point3f, t["center"], node, active)
            h = dr.gather(mi.Vector3f, t["half"], node, active)
            cc = dr.gather(mi.Point3f, t["ccenter"], node, active)
            tri = dr.gather(mi.UInt32, t["tri"], node, active)
            visits += 1
            miss = _culled(x, n, abs_n, c, h, cc, alpha)  # a leaf: its centroid sphere is 0
            B_C += self._leaf_term(x, B_D, L_F, n, tri, cc, alpha, active & ~miss)
            j += 1
            active &= j < stop
        return B_C, visits

    @dr.syntax
    def _leaf_term(self, x, B_D, L_F, n, tri, cc, alpha, leaf):
        """(R_t − far field) · F(x → t) of triangle ``tri`` (centroid ``cc``) where x is in front
        of it (0 elsewhere): the exact form factor, in a symbolic branch."""
        t = self._tables
        nt = dr.gather(mi.Vector3f, t["tri_normal"], tri, leaf)
        a = dr.gather(mi.Point3f, t["verts"], 3 * tri, leaf)
        use = leaf & (dr.dot(nt, x - a) > FRONT_EPS * alpha)
        term = mi.Color3f(0.0)
        if use:
            b = dr.gather(mi.Point3f, t["verts"], 3 * tri + 1)
            c3 = dr.gather(mi.Point3f, t["verts"], 3 * tri + 2)
            Bt = dr.gather(mi.Color3f, t["tri_B"], tri)
            term = (Bt - _far(B_D, L_F, cc - x)) * polygon_form_factor(x, n, [a, b, c3])
        return term


#: most cells along one axis of the list grid (:class:`LeafCells`)
CELLS_MAX_RES = 128
#: a plane of the shading points gets lists of its own (:class:`LeafCells`) when it holds at
#: least this many of them
PLANE_MIN_POINTS = 8
#: a lane reads a plane's lists when its normal is within this (per component) of the plane's
#: and its point within ``PLANE_OFFSET_EPS`` × alpha of the plane
PLANE_NORMAL_EPS = 1e-4
PLANE_OFFSET_EPS = 1e-5
#: a plane's list leaves out the triangles none of whose vertices lies more than this × alpha
#: above the plane (coplanar with it or below it: a form factor of 0 from every point of it)
PLANE_HEIGHT_EPS = 1e-5


class LeafCells:
    """Per-cell lists of the BVH leaves (triangles) a point of the cell may count, built in the
    prepass only where the image needs them: cells holding a camera shading point, and their 26
    neighbours, so that render-time points between the shading points are covered.

    A leaf is listed in a cell when its triangle's centroid lies within ``alpha`` of the cell's
    box (T holds triangles by centroid) and some point of the box is in front of the triangle
    (one-sided), the box grown by a small margin so that no float32 lane needs a leaf the
    build left out. A lane in a listed cell walks its cell's list with the leaf tests of the
    BVH walk (:meth:`NearField.correction`) and so sums exactly the triangles the walk from the
    root sums with ``open_factor = inf``, in the same (pre-)order: every triangle's exact form
    factor, no disks (§7's disks stand for nodes far from x, and a list holds none). Lanes
    outside the listed cells walk the BVH from the root. Valid for the ``alpha`` it was built
    for.

    Why leaves and not the top of the tree: a cache read visited ~98 nodes from per-cell lists
    of subtrees (window_interior and the office at 256²), 54 of them culled and 34 opened, for
    ~10 leaves tested and ~5 counted. The (leaf, cell) pairs come from one Dr.Jit kernel over
    every leaf and every cell of the cube around its centroid, compressed, then ordered per
    cell in numpy.

    **Plane lists.** Most shading points lie on a few planes (floors, walls, table tops), and
    most of a cell's leaves are coplanar with the point or below its tangent plane: on
    window_interior a read walked 45 leaves, 25 had their centroid within alpha and 5.5 were
    above the tangent plane (3.6 counted). Each plane that holds at least
    :data:`PLANE_MIN_POINTS` shading points (with ``normals``) gets, in the cells around its
    points, a list of its own: the cell's leaves that have a vertex more than
    :data:`PLANE_HEIGHT_EPS` × alpha above the plane. A lane whose normal and point match a
    plane of its cell (:data:`PLANE_NORMAL_EPS`, :data:`PLANE_OFFSET_EPS`) walks that list. The
    leaves it leaves out give a form factor of 0 from the lane's point, up to a sliver of at
    most ~1e-4 alpha above its tangent plane.
    """

    def __init__(self, lo, cell, res, first, count, leaves, alpha, planes=None):
        self.lo, self.cell, self.res = lo, cell, res
        self.first, self.count, self.leaves = first, count, leaves
        self.alpha = float(alpha)
        #: :class:`PlaneLists` (None: none)
        self.planes = planes

    @property
    def nbytes(self) -> int:
        own = 4 * (self.first.size + self.count.size + self.leaves.size)
        return int(own + (self.planes.nbytes if self.planes is not None else 0))

    @property
    def listed_cells(self) -> int:
        return int((self.count > 0).sum())

    @property
    def entries(self) -> int:
        return int(self.leaves.size)

    @classmethod
    def empty(cls):
        """No listed cell: every lane walks from the root."""
        return cls(np.full(3, np.inf), np.ones(3), np.ones(3, dtype=np.int64),
                   np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64),
                   np.zeros(1, dtype=np.int64), np.nan)

    @classmethod
    def build(cls, near, points, alpha, cell_size=None, normals=None):
        """The lists for the cells around ``points`` (n, 3); with their viewer-facing
        ``normals`` (n, 3), also the plane lists (class docstring)."""
        alpha = float(alpha)
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        finite = np.all(np.isfinite(p), axis=1)
        p = p[finite]
        if normals is not None:
            normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)[finite]
        if len(p) == 0 or near.node_count == 0 or not alpha > 0:
            return cls.empty()
        h = float(cell_size) if cell_size else 0.5 * alpha
        lo = p.min(axis=0) - h
        extent = p.max(axis=0) + h - lo
        res = np.clip(np.ceil(extent / h), 1, CELLS_MAX_RES).astype(np.int64)
        cell = extent / res
        ijk = np.minimum(np.floor((p - lo) / cell), res - 1).astype(np.int64)
        occ = np.zeros(tuple(res), dtype=bool)
        occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
        for ax in range(3):  # dilate by one cell along each axis: the 3×3×3 neighbourhood
            o = occ.copy()
            sl = [slice(None)] * 3
            sl[ax] = slice(1, None); dst = tuple(sl)
            sl[ax] = slice(None, -1); src = tuple(sl)
            o[dst] |= occ[src]
            o[src] |= occ[dst]
            occ = o
        margin = 1e-5 * (float(np.abs(p).max()) + alpha) + 1e-4 * alpha
        leaves = np.flatnonzero(near.tri >= 0)  # pre-order: the root walk's order
        rank, cid = _leaf_cell_pairs(near, leaves, occ.ravel(), lo, cell, res, alpha, margin)
        order = _stable_order(cid)  # per cell; leaves ascending within (lane order)
        cid, rank = cid[order], rank[order]
        C = int(np.prod(res))
        count = np.bincount(cid, minlength=C).astype(np.int64)
        first = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
        listed = leaves[rank].astype(np.int64)
        planes = None
        if normals is not None:
            planes = PlaneLists.build(near, p, normals, listed, first, count, lo, cell, res,
                                      alpha)
            if planes is not None:
                listed = np.concatenate([listed, planes.leaves])
        return cls(lo, cell, res, first, count, listed, alpha, planes)

    def tables(self):
        """Dr.Jit copies (grid constants opaque: a new prepass does not recompile)."""
        planes = self.planes if self.planes is not None else PlaneLists.empty(self.count.size)
        return dict(cell_first=jit(mi.UInt32, self.first.astype(np.uint32)),
                    cell_count=jit(mi.UInt32, self.count.astype(np.uint32)),
                    cell_leaves=jit(mi.UInt32, self.leaves.astype(np.uint32)),
                    cell_lo=dr.opaque(mi.Point3f, [float(v) for v in self.lo]),
                    cell_inv=dr.opaque(mi.Vector3f, [float(1.0 / v) for v in self.cell]),
                    cell_res=dr.opaque(mi.Vector3i, [int(v) for v in self.res]),
                    **planes.tables(self.alpha))

    @staticmethod
    def lookup(x, t, n=None):
        """Dr.Jit: the (first, count) of the list of the cell of ``x``, and whether it is
        listed (not outside the grid or in an unlisted cell: those lanes walk from the root).
        With the lane's normal ``n``, the list of the cell's plane that ``x`` and ``n`` lie on,
        where there is one (:class:`PlaneLists`; it may be empty: nothing above the plane)."""
        q = dr.floor((x - t["cell_lo"]) * t["cell_inv"])
        res = mi.Vector3f(t["cell_res"])
        inside = dr.all((q >= 0) & (q < res))
        qi = mi.Vector3i(dr.clip(q, 0, res - 1))
        cid = mi.UInt32((qi.x * t["cell_res"].y + qi.y) * t["cell_res"].z + qi.z)
        first = dr.gather(mi.UInt32, t["cell_first"], cid, inside)
        count = dr.select(inside, dr.gather(mi.UInt32, t["cell_count"], cid, inside), 0)
        listed = count > 0
        if n is None:
            return first, count, listed
        first, count = PlaneLists.lookup(x, mi.Vector3f(n), cid, listed, first, count, t)
        return first, count, listed


class PlaneLists:
    """The plane lists of :class:`LeafCells` (its docstring): ``normal`` (G, 3) and ``offset``
    (G,) of each plane (n·p = offset); per cell, its entries ``cell_first``/``cell_count``
    (C,) into ``plane``/``first``/``count`` (E,), each entry a plane and its list;
    ``first``/``count`` index the :class:`LeafCells`' ``leaves``, after whose own lists these
    lists' ``leaves`` are appended."""

    def __init__(self, normal, offset, cell_first, cell_count, plane, first, count, leaves):
        self.normal, self.offset = normal, offset
        self.cell_first, self.cell_count = cell_first, cell_count
        self.plane, self.first, self.count = plane, first, count
        self.leaves = leaves

    @property
    def nbytes(self) -> int:
        return int(16 * len(self.offset) + 4 * (2 * self.cell_first.size + 3 * self.plane.size
                                                + self.leaves.size))

    @classmethod
    def empty(cls, cells: int):
        z = np.zeros(1, dtype=np.int64)
        return cls(np.zeros((1, 3)), np.zeros(1), np.zeros(cells, np.int64),
                   np.zeros(cells, np.int64), z, z, z, np.zeros(0, np.int64))

    @staticmethod
    def planes_of(points, normals, alpha):
        """The planes that at least :data:`PLANE_MIN_POINTS` of ``points`` lie on, with the
        points' plane ids (−1: on none): points grouped by their normal and offset, rounded
        to :data:`PLANE_NORMAL_EPS` and :data:`PLANE_OFFSET_EPS` × alpha → ``(normal (G, 3),
        offset (G,), ids (n,))``."""
        d = (points * normals).sum(axis=1)
        key = np.column_stack([np.round(normals / PLANE_NORMAL_EPS),
                               np.round(d / (PLANE_OFFSET_EPS * alpha))]).astype(np.int64)
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        inv = inv.reshape(-1)
        big = np.flatnonzero(cnt >= PLANE_MIN_POINTS)
        remap = np.full(len(cnt), -1, np.int64)
        remap[big] = np.arange(len(big))
        ids = remap[inv]
        G = len(big)
        normal = np.zeros((G, 3))
        offset = np.zeros(G)
        on = ids >= 0
        np.add.at(normal, ids[on], normals[on])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
        offset = np.bincount(ids[on], weights=d[on], minlength=G) / \
            np.maximum(np.bincount(ids[on], minlength=G), 1)
        return normal, offset, ids

    @classmethod
    def build(cls, near, points, normals, listed, first, count, lo, cell, res, alpha):
        """Each plane's lists in the cells around its points (the 3×3×3 cells about each, as
        the cells' own lists): the cell's leaves with a vertex more than
        :data:`PLANE_HEIGHT_EPS` × alpha above the plane. None where no plane has enough
        points."""
        normal, offset, ids = cls.planes_of(points, normals, alpha)
        if len(offset) == 0:
            return None
        on = ids >= 0
        ijk = np.minimum(np.floor((points[on] - lo) / cell), res - 1).astype(np.int64)
        off = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"),
                       -1).reshape(-1, 3)
        q = (ijk[:, None, :] + off[None]).reshape(-1, 3)
        g = np.repeat(ids[on], len(off))
        ok = np.all((q >= 0) & (q < res), axis=1)
        cid = (q[ok, 0] * res[1] + q[ok, 1]) * res[2] + q[ok, 2]
        G = len(offset)
        key = np.unique(cid * G + g[ok])  # (cell, plane), by cell
        pairs = np.column_stack([key // G, key % G])
        pairs = pairs[count[pairs[:, 0]] > 0]
        if len(pairs) == 0:
            return None
        n_c = count[pairs[:, 0]]
        entry = np.repeat(np.arange(len(pairs)), n_c)
        idx = _ranges(first[pairs[:, 0]], first[pairs[:, 0]] + n_c)
        # the planes share few normals (a floor and a table top): each triangle's highest
        # vertex along each distinct normal, once, then one lookup per entry
        normals_u, k_of = np.unique(np.round(normal / PLANE_NORMAL_EPS).astype(np.int64),
                                    axis=0, return_inverse=True)
        k_of = k_of.reshape(-1)
        unit = np.zeros((len(normals_u), 3))
        np.add.at(unit, k_of, normal)
        unit /= np.linalg.norm(unit, axis=1, keepdims=True)
        top = (near.verts @ unit.T).max(axis=1)  # (T, K)
        pl = pairs[entry, 1]
        h = top[near.tri[listed[idx]], k_of[pl]] - offset[pl]
        keep = h > PLANE_HEIGHT_EPS * alpha
        kept_count = np.bincount(entry[keep], minlength=len(pairs)).astype(np.int64)
        base = len(listed)
        kept_first = base + np.concatenate([[0], np.cumsum(kept_count)[:-1]]).astype(np.int64)
        C = count.size
        cell_count = np.bincount(pairs[:, 0], minlength=C).astype(np.int64)
        cell_first = np.concatenate([[0], np.cumsum(cell_count)[:-1]]).astype(np.int64)
        return cls(normal, offset, cell_first, cell_count, pairs[:, 1].astype(np.int64),
                   kept_first, kept_count, listed[idx[keep]])

    def tables(self, alpha: float):
        """Dr.Jit copies (the offset tolerance opaque: a new prepass does not recompile)."""
        cf, cc = self.cell_first, self.cell_count
        f32 = lambda a: jit(mi.Float, np.ascontiguousarray(a, dtype=np.float32).ravel())  # noqa
        u32 = lambda a: jit(mi.UInt32, np.asarray(a).astype(np.uint32))  # noqa: E731
        return dict(plane_cell_first=u32(cf), plane_cell_count=u32(cc),
                    plane_id=u32(self.plane), plane_first=u32(self.first),
                    plane_count=u32(self.count), plane_normal=f32(self.normal),
                    plane_offset=f32(self.offset),
                    plane_eps=dr.opaque(mi.Float, PLANE_OFFSET_EPS * float(alpha)))

    @staticmethod
    def lookup(x, n, cid, inside, first, count, t):
        """Dr.Jit: the (first, count) of the list of the plane of cell ``cid`` that ``x`` and
        ``n`` lie on, else the cell's own ``first``/``count``."""
        j = dr.gather(mi.UInt32, t["plane_cell_first"], cid, inside)
        end = j + dr.select(inside, dr.gather(mi.UInt32, t["plane_cell_count"], cid, inside), 0)

        def cond(j, end, first, count):
            return j < end

        def body(j, end, first, count):
            active = j < end
            g = dr.gather(mi.UInt32, t["plane_id"], j, active)
            pn = dr.gather(mi.Vector3f, t["plane_normal"], g, active)
            pd = dr.gather(mi.Float, t["plane_offset"], g, active)
            match = active & (dr.max(dr.abs(n - pn)) <= PLANE_NORMAL_EPS) \
                & (dr.abs(dr.dot(pn, x) - pd) <= t["plane_eps"])
            first = dr.select(match, dr.gather(mi.UInt32, t["plane_first"], j, match), first)
            count = dr.select(match, dr.gather(mi.UInt32, t["plane_count"], j, match), count)
            return dr.select(match, end, j + 1), end, first, count

        _, _, first, count = dr.while_loop((j, end, first, count), cond, body,
                                           label="near_field_plane")
        return first, count


def _leaf_cell_pairs(near, leaves, occupied, lo, cell, res, alpha, margin):
    """The (leaf rank, cell id) pairs of :meth:`LeafCells.build`, in leaf order: one Dr.Jit
    kernel over every leaf and every cell of the cube of cells that meets the box of half-side
    alpha + margin about its centroid, kept where the cell is ``occupied``, its box (grown by
    ``margin``) within ``alpha`` of the centroid and partly in front of the triangle. Sizes and
    constants are opaque: no kernel per scene."""
    L = len(leaves)
    reach = alpha + margin
    # the cells that meet [c - reach, c + reach] along an axis: from floor((c - reach - lo)/cell)
    # on, at most floor(2 reach / cell) + 2 of them (a cell that meets the box only at its edge,
    # a rounding away, lies reach > alpha from c: the test below drops it)
    span = (np.floor(2.0 * reach / cell) + 2).astype(np.int64)
    K = int(np.prod(span))
    if L == 0 or L * K >= 1 << 31:
        raise ValueError(f"near field: {L} leaves x {K} cells each is too many for the lists")
    f = lambda a: jit(mi.Float, np.ascontiguousarray(a, dtype=np.float32).ravel())  # noqa: E731
    tri = near.tri[leaves]
    cc_t, nt_t, a_t = f(near.ccenter[leaves]), f(near.tri_normal[tri]), f(near.verts[tri, 0])
    occ_t = jit(mi.UInt32, occupied.astype(np.uint32))
    K_o, sy, sz = (dr.opaque(mi.UInt32, int(v)) for v in (K, span[1], span[2]))
    res_o = dr.opaque(mi.Vector3i, [int(v) for v in res])
    lo_o = dr.opaque(mi.Point3f, [float(v) for v in lo])
    cell_o = dr.opaque(mi.Vector3f, [float(v) for v in cell])
    alpha_o, margin_o = dr.opaque(mi.Float, alpha), dr.opaque(mi.Float, margin)
    reach_o = dr.opaque(mi.Float, reach)

    def pair(idx):
        li = idx // K_o
        o = idx - li * K_o
        off = mi.Vector3i(mi.Int32(o // (sy * sz)), mi.Int32((o // sz) % sy), mi.Int32(o % sz))
        c = dr.gather(mi.Point3f, cc_t, li)
        q = mi.Vector3i(dr.floor((c - reach_o - lo_o) / cell_o)) + off
        inside = dr.all((q >= 0) & (q < res_o))
        cid = mi.UInt32((q.x * res_o.y + q.y) * res_o.z + q.z)
        return li, c, q, inside, cid

    idx = dr.arange(mi.UInt32, L * K)
    li, c, q, inside, cid = pair(idx)
    ok = inside & (dr.gather(mi.UInt32, occ_t, cid, inside) != 0)
    blo = lo_o + mi.Vector3f(q) * cell_o - margin_o
    bhi = blo + cell_o + 2.0 * margin_o
    dmin = dr.norm(dr.maximum(dr.maximum(blo - c, c - bhi), 0.0))
    nt = dr.gather(mi.Vector3f, nt_t, li, ok)
    a = dr.gather(mi.Point3f, a_t, li, ok)
    front = dr.dot(nt, dr.select(nt > 0, bhi, blo)) - dr.dot(nt, a)
    keep = ok & (dmin <= alpha_o) & (front > FRONT_EPS * alpha_o)
    sel = dr.compress(keep)
    if dr.width(sel) == 0:  # no leaf near any listed cell (a black scene, say)
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    li, _, _, _, cid = pair(sel)
    return np.asarray(li).astype(np.int64), np.asarray(cid).astype(np.int64)


def _stable_order(keys):
    """``np.argsort(keys, kind="stable")`` of non-negative integer ``keys`` below 2³², as two
    stable radix passes over 16-bit halves (numpy sorts 16-bit keys by radix; wider ones by
    timsort): window_interior's 0.69 M (leaf, cell) pairs at 256² in 11 ms instead of 17."""
    keys = np.asarray(keys, dtype=np.int64)
    if keys.size and int(keys.max()) >= 1 << 32:
        return np.argsort(keys, kind="stable")
    low = np.argsort((keys & 0xFFFF).astype(np.uint16), kind="stable")
    return low[np.argsort((keys[low] >> 16).astype(np.uint16), kind="stable")]


def _culled(x, n, abs_n, c, h, cc, reach):
    """The walk's cull test of a node (box centre ``c``, half-extent ``h``, centroid sphere
    centre ``cc``) at x with normal n (``abs_n`` = |n|): no triangle centroid within ``reach``
    (alpha plus the centroid sphere's radius), or the box on or below the tangent plane, where
    every form factor is 0. The root walk and the cell lists' leaves share it."""
    return (dr.norm(cc - x) > reach) | (dr.dot(n, c - x) + dr.dot(abs_n, h) <= 0)


def _far(B_D, L_F, d):
    """The far-field irradiance a near triangle replaces: B_D (eq. 6) or π·L_F(d/|d|) (eq. 5)."""
    if not L_F:
        return B_D
    return dr.pi * sh.evaluate(L_F, dr.normalize(d))


def build_near_field(verts, tri_normal, tri_B, points=None, alpha=None,
                     cell_size=None, normals=None) -> NearField:
    """Median-split BVH (longest centroid axis) over triangles ``verts`` (T, 3, 3) with one-sided
    unit normals (T, 3) and radiosities ``tri_B`` (T, 3); zero-area triangles are dropped.

    Numpy, vectorised over all nodes of one tree level, in two sweeps: top-down, the split (the
    order of the triangles, each node a contiguous segment of it; about log2 T passes of one
    stable sort each); bottom-up, the node aggregates from their two children (O(T) in all):
    boxes, areas and the area-weighted sums are exact; a node's bounding radius (about its box
    centre, over its vertices) and centroid radius (about its centroid box's centre) are the
    smaller of the children's spheres grown to the node's centre and the box's half-diagonal —
    upper bounds, exact at the leaves, so the walk's culling stays conservative.

    With shading ``points`` (n, 3) and ``alpha``, also the per-cell leaf lists of the cache reads
    (:class:`LeafCells`, cells of ``cell_size``, default ``alpha``/2); with the points'
    viewer-facing ``normals`` (n, 3), also the lists of their planes."""
    verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3, 3)
    tri_normal = np.asarray(tri_normal, dtype=np.float64).reshape(-1, 3)
    tri_B = np.asarray(tri_B, dtype=np.float64).reshape(-1, 3)
    tri_area = 0.5 * np.linalg.norm(np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0]),
                                    axis=1)
    keep = np.nonzero(np.isfinite(tri_area) & (tri_area > 0))[0]
    verts, tri_normal, tri_B, tri_area = verts[keep], tri_normal[keep], tri_B[keep], tri_area[keep]
    T = len(verts)
    centroid = verts.mean(axis=1)
    # each axis's centroid coordinates as dense ranks (ties equal): one stable integer sort per
    # level orders a segment as sorting (segment, coordinate) would, ties kept in place
    rank = np.stack([np.unique(centroid[:, a], return_inverse=True)[1].reshape(-1)
                     for a in range(3)]) if T else np.zeros((3, 0), np.int64)
    M = max(0, 2 * T - 1)
    center = np.zeros((M, 3)); radius = np.zeros(M); area = np.zeros(M)
    B = np.zeros((M, 3)); normal = np.zeros((M, 3))
    skip = np.zeros(M, dtype=np.int64); tri = np.full(M, -1, dtype=np.int64)
    ccenter = np.zeros((M, 3)); cradius = np.zeros(M); half = np.zeros((M, 3))
    if T == 0:
        near = NearField(center, radius, area, B, normal, skip, tri, verts, tri_normal, tri_B,
                         ccenter, cradius, half)
        near._tables  # the Dr.Jit copies, built now
        return near
    # Top-down: ``perm`` orders the triangles so that every node is a contiguous segment
    # [start, end) of it; a node of n triangles has 2n − 1 nodes in its subtree, so in pre-order
    # its left child is node + 1, its right child node + 2·n_left and its skip link node + 2n − 1.
    perm = np.arange(T)
    levels = []  # (node, n_left) of the inner nodes of each level
    start, end, node = np.array([0]), np.array([T]), np.array([0])
    while len(node):
        n_seg = end - start
        skip[node] = node + 2 * n_seg - 1
        leaf = n_seg == 1
        tri[node[leaf]] = perm[start[leaf]]
        inner = ~leaf
        start, end, node, n_seg = start[inner], end[inner], node[inner], n_seg[inner]
        if not len(node):
            break
        at = _ranges(start, end)
        seg = np.repeat(np.arange(len(node)), n_seg)
        ids = perm[at]
        cts = centroid[ids]
        first = n_seg.cumsum() - n_seg
        extent = np.maximum.reduceat(cts, first, axis=0) - np.minimum.reduceat(cts, first, axis=0)
        key = rank[np.argmax(extent, axis=1)[seg], ids]
        perm[at] = ids[np.argsort(seg * T + key, kind="stable")]  # median split, longest axis
        n_left = n_seg // 2
        levels.append((node, n_left))
        mid = start + n_left
        start, end = np.concatenate([start, mid]), np.concatenate([mid, end])
        node = np.concatenate([node + 1, node + 2 * n_left])
    # leaves: exact aggregates of their triangle
    lf = np.flatnonzero(tri >= 0)
    t = tri[lf]
    lo, hi = np.zeros((M, 3)), np.zeros((M, 3))
    clo, chi = np.zeros((M, 3)), np.zeros((M, 3))
    vt = verts[t]
    lo[lf] = np.minimum(np.minimum(vt[:, 0], vt[:, 1]), vt[:, 2])
    hi[lf] = np.maximum(np.maximum(vt[:, 0], vt[:, 1]), vt[:, 2])
    center[lf] = 0.5 * (lo[lf] + hi[lf])
    radius[lf] = np.sqrt(((vt - center[lf][:, None, :]) ** 2).sum(-1).max(axis=1))
    clo[lf] = chi[lf] = ccenter[lf] = centroid[t]
    area[lf], B[lf], normal[lf] = tri_area[t], tri_B[t], tri_normal[t]
    # bottom-up: each inner node from its two children (a deeper level, done first)
    for nd, n_left in reversed(levels):
        l, r = nd + 1, nd + 2 * n_left
        lo[nd], hi[nd] = np.minimum(lo[l], lo[r]), np.maximum(hi[l], hi[r])
        clo[nd], chi[nd] = np.minimum(clo[l], clo[r]), np.maximum(chi[l], chi[r])
        c = center[nd] = 0.5 * (lo[nd] + hi[nd])
        cc = ccenter[nd] = 0.5 * (clo[nd] + chi[nd])
        grown = np.maximum(np.linalg.norm(c - center[l], axis=1) + radius[l],
                           np.linalg.norm(c - center[r], axis=1) + radius[r])
        radius[nd] = np.minimum(grown, 0.5 * np.linalg.norm(hi[nd] - lo[nd], axis=1))
        cgrown = np.maximum(np.linalg.norm(cc - ccenter[l], axis=1) + cradius[l],
                            np.linalg.norm(cc - ccenter[r], axis=1) + cradius[r])
        cradius[nd] = np.minimum(cgrown, 0.5 * np.linalg.norm(chi[nd] - clo[nd], axis=1))
        al, ar = area[l], area[r]
        area[nd] = al + ar
        B[nd] = (al[:, None] * B[l] + ar[:, None] * B[r]) / area[nd][:, None]
        normal[nd] = (al[:, None] * normal[l] + ar[:, None] * normal[r]) / area[nd][:, None]
    half[:] = 0.5 * (hi - lo)
    near = NearField(center, radius, area, B, normal, skip, tri, verts, tri_normal, tri_B,
                     ccenter, cradius, half)
    if points is not None:
        near.cells = LeafCells.build(near, points, alpha, cell_size=cell_size,
                                     normals=normals)
    near._tables  # Dr.Jit copies now, never first inside a symbolic loop
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


#: most cells along one axis of the shading-point occupancy grid of :func:`split_near_triangles`
OCCUPANCY_MAX_RES = 128


class PointOccupancy:
    """Which axis-aligned boxes contain a shading point (numpy): the points binned in a uniform
    grid of cells of size ≥ ``h`` (at most :data:`OCCUPANCY_MAX_RES` per axis), with a 3-D
    summed-area table of the counts, so one box query is 8 lookups. A query counts the points
    in every cell the box overlaps: a superset of the points in the box, never fewer."""

    def __init__(self, points, h: float):
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        p = p[np.all(np.isfinite(p), axis=1)]
        self.empty = len(p) == 0
        if self.empty:
            return
        self.lo = p.min(axis=0)
        extent = np.maximum(p.max(axis=0) - self.lo, 1e-30)
        self.res = np.clip(np.ceil(extent / max(float(h), 1e-30)), 1,
                           OCCUPANCY_MAX_RES).astype(np.int64)
        self.cell = extent / self.res
        ijk = np.minimum(np.floor((p - self.lo) / self.cell), self.res - 1).astype(np.int64)
        counts = np.zeros(tuple(self.res), dtype=np.int64)
        np.add.at(counts, (ijk[:, 0], ijk[:, 1], ijk[:, 2]), 1)
        sat = np.zeros(tuple(self.res + 1), dtype=np.int64)
        sat[1:, 1:, 1:] = counts.cumsum(0).cumsum(1).cumsum(2)
        self.sat = sat

    def any_in_boxes(self, box_lo, box_hi):
        """(m,) bool: a point lies in a cell that the box [box_lo, box_hi] (m, 3) overlaps."""
        box_lo = np.asarray(box_lo, dtype=np.float64).reshape(-1, 3)
        box_hi = np.asarray(box_hi, dtype=np.float64).reshape(-1, 3)
        if self.empty:
            return np.zeros(len(box_lo), dtype=bool)
        a = np.clip(np.floor((box_lo - self.lo) / self.cell), 0, self.res).astype(np.int64)
        b = np.clip(np.floor((box_hi - self.lo) / self.cell) + 1, 0, self.res).astype(np.int64)
        b = np.maximum(a, b)
        S = self.sat
        n = (S[b[:, 0], b[:, 1], b[:, 2]] - S[a[:, 0], b[:, 1], b[:, 2]]
             - S[b[:, 0], a[:, 1], b[:, 2]] - S[b[:, 0], b[:, 1], a[:, 2]]
             + S[a[:, 0], a[:, 1], b[:, 2]] + S[a[:, 0], b[:, 1], a[:, 2]]
             + S[b[:, 0], a[:, 1], a[:, 2]] - S[a[:, 0], a[:, 1], a[:, 2]])
        return n > 0


def split_near_triangles(verts, tri_normal, tri_B, points, alpha: float,
                         max_triangles: int = 1 << 17):
    """§5 lazy splitting: "we split the scene triangles until they are smaller than alpha. Only
    those triangles that are near the shading points need to be split."

    A triangle is split while its longest edge exceeds ``alpha`` and a shading point of
    ``points`` (n, 3) may lie within ``alpha`` of it (a point in its bounding box grown by
    ``alpha``, tested conservatively on a :class:`PointOccupancy` grid of cell ``alpha``). The
    split is longest-edge bisection: (a, b, c) with longest edge ab → (a, m, c), (m, b, c),
    m = (a + b)/2, two halves of equal area and the parent's winding; each half keeps the
    parent's one-sided normal and radiosity (its patch's). Triangles far from every shading point
    stay as they are (the image does not need them fine). Vectorised over all triangles of one
    generation (about 2·log2(edge/alpha) passes).

    ``max_triangles`` bounds the output (alpha far below the scene's detail would otherwise
    create millions): when the next generation would exceed it, only the triangles with the
    longest edges are split, and splitting stops.

    → ``(verts (T', 3, 3), tri_normal (T', 3), tri_B (T', 3), complete)`` with ``complete``
    False where the budget stopped the splitting before every near triangle reached alpha.
    """
    verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3, 3)
    tri_normal = np.asarray(tri_normal, dtype=np.float64).reshape(-1, 3)
    tri_B = np.asarray(tri_B, dtype=np.float64).reshape(-1, 3)
    alpha = float(alpha)
    occ = PointOccupancy(points, alpha)
    if occ.empty or not alpha > 0.0 or len(verts) == 0:
        return verts, tri_normal, tri_B, True
    out_v, out_n, out_B = [], [], []
    V, N, B = verts, tri_normal, tri_B
    total = len(V)
    complete = True
    while len(V):
        edge = np.linalg.norm(V[:, [1, 2, 0]] - V, axis=2)  # edge k: v_k → v_{k+1}
        longest = edge.max(axis=1)
        split = longest > alpha
        if split.any():
            split[split] = occ.any_in_boxes(V[split].min(axis=1) - alpha,
                                            V[split].max(axis=1) + alpha)
        ids = np.nonzero(split)[0]
        if total + len(ids) > max_triangles:  # budget: the longest edges first, then stop
            room = max(0, int(max_triangles) - total)
            ids = ids[np.argsort(-longest[ids], kind="stable")[:room]]
            complete = False
        keep = np.ones(len(V), dtype=bool)
        keep[ids] = False
        out_v.append(V[keep]); out_n.append(N[keep]); out_B.append(B[keep])
        if len(ids) == 0:
            break
        k = np.argmax(edge[ids], axis=1)  # rotate so that the longest edge is v0 → v1
        V = _bisect(V[ids[:, None], (k[:, None] + np.arange(3)[None]) % 3])
        N, B = np.repeat(N[ids], 2, axis=0), np.repeat(B[ids], 2, axis=0)
        total += len(ids)
        if not complete:
            out_v.append(V); out_n.append(N); out_B.append(B)
            break
    return (np.concatenate(out_v), np.concatenate(out_n), np.concatenate(out_B), complete)


def _bisect(V):
    """(m, 3, 3) triangles (a, b, c) → (2m, 3, 3): (a, m, c), (m, b, c) with m = (a + b)/2,
    children of triangle i at rows 2i and 2i + 1 (vertices used as given: rotate first)."""
    a, b, c = V[:, 0], V[:, 1], V[:, 2]
    m = 0.5 * (a + b)
    return np.stack([np.stack([a, m, c], axis=1), np.stack([m, b, c], axis=1)],
                    axis=1).reshape(-1, 3, 3)


#: directions of the buried-triangle test: the normal and three at this angle from it (degrees)
BURIED_RAY_ANGLE = 60.0


def buried_triangles(scene, verts, tri_normal):
    """(T,) bool: triangles whose centroid lies inside a closed solid of ``scene`` (a face of
    one box inside another, as where overlapping boxes model a thick wall): no point of the
    scene sees them, which the visibility assumption of B_C (§5, "all nearby triangles are
    visible") would break; the near field leaves them out.

    Four rays leave the centroid (offset along the one-sided normal): along the normal and three
    at :data:`BURIED_RAY_ANGLE` from it, 120° apart. The triangle is buried when all four hit the
    back of a surface (``dot(n_hit, d) > 0``): from inside a closed solid every ray does, while
    from open space at most the rays toward a one-sided surface seen from behind do. One batch
    of 4·T rays."""
    verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3, 3)
    n = np.asarray(tri_normal, dtype=np.float64).reshape(-1, 3)
    T = len(verts)
    if T == 0:
        return np.zeros(0, dtype=bool)
    c = verts.mean(axis=1)
    tmp = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    s = np.cross(n, tmp)
    s /= np.maximum(np.linalg.norm(s, axis=1, keepdims=True), 1e-30)
    t = np.cross(n, s)
    th = np.radians(BURIED_RAY_ANGLE)
    dirs = [n] + [np.cos(th) * n + np.sin(th) * (np.cos(p) * s + np.sin(p) * t)
                  for p in (0.0, 2 * np.pi / 3, 4 * np.pi / 3)]
    d = np.concatenate(dirs)
    scale = scene_diagonal(scene)  # offsets relative to the scene's size
    o = np.tile(c, (4, 1)) + 1e-5 * scale * np.tile(n, (4, 1))
    f = lambda a: mi.Vector3f(*(jit(mi.Float, np.ascontiguousarray(a[:, k], dtype=np.float32))  # noqa
                                for k in range(3)))
    ray = mi.Ray3f(mi.Point3f(f(o)), f(d))
    si = scene.ray_intersect(ray)
    back = np.asarray(si.is_valid() & (dr.dot(si.n, ray.d) > 0))
    return back.reshape(4, T).all(axis=0)
