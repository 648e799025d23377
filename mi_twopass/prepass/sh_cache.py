r"""Far field of the radiance cache: a sparse field of order-2 SH incident radiance
(Arikan, Forsyth & O'Brien 2005, §4.1).

Steps (:func:`build_radiance_cache`):

1. **Shading points** (§4.1 "we know in advance all the shading points"): camera rays through a
   regular grid of film positions, followed through delta (specular) bounces to the first
   non-delta hit, kept where that surface is purely diffuse (:func:`collect_shading_points`):
   the render reads the cache only there.
2. **Clusters**: starting from one cluster of all points, a cluster whose bounding sphere
   (about its centroid) has a radius larger than ``alpha`` is split in two by 2-means, until every
   cluster fits or ``max_clusters`` is reached (:func:`cluster_labels`: numpy, all clusters of a
   level at once); where the budget is reached first, alpha grows until every cluster fits
   (:func:`fit_clusters`), and the cache's ``alpha`` (the near-field radius) is that one. The
   paper's lazier criterion (split only where gather rays hit geometry inside the sphere) is not
   implemented: flat regions get clusters of size alpha too. Points are clustered by position
   *and* normal (``(p, NORMAL_SPLIT · alpha · n)``, since session 22): a cluster spanning a
   crease of more than about 60° fits one field from rays of different hemispheres, and a
   point reads directions only its own side's rays sampled where the far environment differs
   across the crease (a window's reveal beside the wall; below). With ``parallax`` κ > 0 a
   cluster is held smaller still where its points see geometry just beyond alpha
   (:func:`parallax_limits`: κ over the mean inverse distance of the far hits, after Ward et
   al.'s irradiance-cache validity radius), where a cluster of size alpha blurs that
   geometry's occlusion across its points.
3. **Gather** (eq. 4): per cluster, ``rays_per_cluster`` rays from shading points of the
   cluster drawn at random, uniform over each point's hemisphere, read the coarse solution at the
   hit: the *reflected* radiance B_r/π of the radiosity patch (indirect light only; direct light is
   Mitsuba's emitter sampling at render time), and only where the surface hit is *cached*
   (:class:`CachedReceivers`: purely diffuse, its element not cut by geometry). A ray that meets
   glass, metal, a glossy or mixed surface reads 0: the render traces that light (L S+ D
   included) and must not find it in the fit as well. Every ray is fitted, those that hit
   geometry closer than ``alpha`` too, as in the paper (whose clusters are the points within
   alpha and whose rays read the photon map wherever they hit): B_C subtracts π L_F(D_t)
   where a *reading* point has its near triangles, so the fit's value there cancels whatever
   it is, while the cluster's other points, farther from that geometry, read the same
   directions as far field. Until session 21 those hits were dropped; the fit then had holes
   exactly there, which the order-2 SH filled by extrapolation: the bias part of
   ``tools/bias_map.py SCENE radiance_cache --res 256 --spp 256 --ref-spp 2048`` went
   2.31e-3 → 1.71e-3 on window_interior and 2.08e-3 → 1.82e-3 on the office when they were
   fitted. A miss reads 0 (an environment emitter is direct light).
4. **Fit**: :func:`~mi_twopass.sh.project_least_squares` (Tikhonov-regularised, so one sample or
   a few directions give a smooth, finite fit) → 9 coefficients × RGB per cluster.

At render time :meth:`RadianceCache.coefficients` interpolates the clusters' SH coefficients of
L_F with normalised Gaussian RBF weights (σ = max(cluster radius, alpha/4), weights below
:data:`RBF_MIN_WEIGHT` dropped, i.e. a support of radius :data:`RBF_SUPPORT` σ), falling back to
the nearest cluster where all weights underflow, and :meth:`RadianceCache.far_field` dots them
with the clamped cosine: :math:`B_D = \overline{\max(N\cdot\omega,0)}\cdot\overline{L_F}` (eq. 3).
A lane visits only the clusters listed in its cell of a uniform grid (:class:`ClusterGrid`, built
in numpy: each cluster is listed in every cell its support sphere overlaps), so the weights it
sums are exactly those of the brute-force sum over all clusters.

Each weight is scaled by :func:`normal_weight` of the cosine between the query's normal and the
cluster's mean normal (0 beyond 60°), and a query whose scaled weights sum to less than
:data:`COVER_MIN` is *not covered*: no cluster of its orientation is near, so the render traces
its path on as at a surface the cache does not hold. On ``scenes_xml/window_interior.xml`` the
top reveal of the window (a strip a few pixels high, hardly any shading points on it) read the
far field of the wall's clusters beside it, fitted from rays into the room, where it sees the
sunlit ground outside: 0.3× the light of ``path`` along the strip. With both rules the strip
reads 1.0 ± noise, the bias part of ``tools/bias_map.py ... --res 256 --spp 256`` went 1.89e-3 →
1.39e-3, paired renders (same seeds, 64 px, 128 spp) moved the image mean by +0.60 ± 0.18 %
(office +0.24 ± 0.06 %, mixed_room +0.69 ± 0.13 %), and against ``path`` the means read
1.0000 ± 0.0025 (window_interior) and 1.0029 ± 0.0015 (mixed_room; ``tools/image_means.py
--res 64 --spp 512 -k 6``). 0.9 % of the cache reads at 256² are not covered there
(``uncovered_reads``); NFGS 567 → 614.

The default ``alpha`` (:func:`default_alpha`) is a fraction of the bounding-box diagonal of the
shading points, the part of the scene the camera sees (§6: alpha is the scale of the detail one
cares about in the view), not of the whole scene's bounding box.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import sh
from ..host_arrays import columns, jit, vectors
from ..scene.bounds import scene_diagonal
from ..scene.patches import build_patches
from ..scene.view import collect_shading_points, view_diagonal
from ..seeds import hash31
from ..tables import Tables
from .near_field import build_near_field, buried_triangles, split_near_triangles
from .near_merge import merge_small_triangles
from .radiosity import VL_CONTRAST, RadiositySettings, reclassified_patches
from .radiosity import build as build_radiosity
from .spike_grid import SpikeSettings, build_spike_prepass
from ..scene.lambertian import LambertianShapes, lambertian_flags

#: RBF weights exp(−|x−c|²/2σ²) below this are dropped (and the fallback is the nearest cluster).
#: 1e-2 (a support of 3.0 σ), not 1e-4 (4.3 σ): a read on window_interior visited 26 clusters, 16
#: inside their support, and the interpolation took a quarter of the render; at 1e-2 the render
#: took 0.135 s, not 0.146 s (``tools/variance_parts.py scenes_xml/window_interior.xml
#: radiance_cache --res 128 --spp 16``, the same variance) and ``check --renders 2`` read the
#: same bias parts on window_interior, office, mixed_room, veach-bidir and the Cornell box
RBF_MIN_WEIGHT = 1e-2
#: support radius of a cluster's RBF in units of its σ: exp(−s²/2) = RBF_MIN_WEIGHT
RBF_SUPPORT = float(np.sqrt(2.0 * np.log(1.0 / RBF_MIN_WEIGHT)))
#: most cells along one axis of the cluster grid
GRID_MAX_RES = 64
#: cluster-grid cell size over the median RBF support radius: a lane's cell lists the clusters
#: whose support touches the cell, about (1 + 0.87 × this)² × those that hold the point.
#: 0.5 until session 20: a read looped over 13.6 listed clusters for 8.4 used (window_interior
#: at 256²). With 0.25 the render at 64 spp took 1.047/1.051 -> 1.014/0.999 s (two alternating
#: runs of ``tools/render_cost.py scenes_xml/window_interior.xml radiance_cache --res 256 --spp
#: 64 --repeats 4``); its memory 0.25 -> 1.5 MB. The grid's build, which tested every cell
#: of each support's bounding box, went 11 -> 44 ms (545 clusters, a synthetic layout); by
#: columns (:meth:`ClusterGrid._pairs`) it takes 7.6 ms
GRID_CELL_REL = 0.25


class CachedReceivers:
    """The surfaces the cache holds: one flag per *receiver* of the coarse solution (its
    receiving elements, else its patches: the mesh whose radiosity a gather ray reads), and
    the near field's triangles with their R_t. A receiver is cached where its shape is
    Lambertian (:mod:`mi_twopass.scene.lambertian`), it is diffuse on the side hit, not cut by
    geometry and not unevenly lit (``is_diffuse``: :mod:`mi_twopass.scene.patches`,
    :func:`~mi_twopass.prepass.radiosity.receiver_spread`) unless refined into cells that
    each hold their own light (:mod:`~mi_twopass.prepass.element_grid`, read at the point
    hit; since session 22), and not a bright reflector
    (:func:`bright_receivers`). The SH gather reads B_r/π only there (:func:`gather_far_field`),
    only cached surfaces send R_t into the near field, and the render's path ends only there;
    everywhere else (glossy, glass, a cut or bright receiver, a shape without patches, the
    black back of a one-sided surface) the path is traced on.

    With elements the element decides, as for radiosity_gather's far gather
    (:meth:`~mi_twopass.prepass.radiosity.RadiositySolution.cached_at`), unless its patch is a
    bright reflector. Until session 18 its patch had to be uncut too: on window_interior
    37–41 % of the camera's Lambertian hits and 36 % of the cache vertices' BSDF rays then
    met an uncached surface and were path traced (28 % of the hits lay on the 499 of 2028
    patches cut by geometry); with the element's rule 20 % and 16 %.

    ``near`` is ``(vertices (T, 3, 3), normals (T, 3), R_t (T, 3))``: the triangles of the
    cached patches with the patch's reflected radiosity (as before session 18: a patch's mean
    holds four elements' particles, and its larger triangles are the near field the corner
    tests were measured with), and those of the cached elements that lie on a cut or unevenly
    lit patch, with the element's own (a cut patch's mean mixes its lit and shadowed parts)."""

    def __init__(self, receivers, cached, near, bright=None):
        #: the receiving mesh (:class:`~mi_twopass.scene.patches.Patches`)
        self.receivers = receivers
        #: (M,) bool: cached
        self.cached = np.asarray(cached, dtype=bool)
        self.near = near
        #: ids of the receivers left out as bright reflectors (or lying on one)
        self.bright = np.zeros(0, np.uint32) if bright is None else np.asarray(bright, np.uint32)
        # Dr.Jit copies now, never first inside a symbolic loop; the invalid id reads False
        self._table = jit(mi.Bool, np.append(self.cached, False))
        bright_mask = np.zeros(len(self.cached) + 1, dtype=bool)
        bright_mask[self.bright] = True
        self._bright_table = jit(mi.Bool, bright_mask)

    @property
    def nbytes(self) -> int:
        return int(2 * self.cached.nbytes + sum(a.nbytes for a in self.near))

    def at(self, si, active=True):
        """``mi.Bool``: the cache holds the light reflected at ``si`` toward its ray."""
        return self.receiver_at(si, active)[0]

    def receiver_at(self, si, active=True):
        """``(cached, receiver id)`` at ``si``: :meth:`at` and the receiver it read (the
        count, an invalid id, where there is none), looked up once."""
        ok = mi.Bool(active) & si.is_valid()
        ok &= lambertian_flags(si.bsdf().flags())
        rid = self.receivers.lookup(si, ok)
        return ok & dr.gather(mi.Bool, self._table, rid, ok), rid

    def bright_at(self, rid, active=True):
        """``mi.Bool``: receiver ``rid`` (:meth:`receiver_at`'s) is a bright reflector the
        cache leaves out (:func:`bright_receivers`); False for the invalid id."""
        active = mi.Bool(active)
        return active & dr.gather(mi.Bool, self._bright_table, rid, active)


def bright_receivers(B_reflected, area, is_diffuse, contrast: float) -> np.ndarray:
    """Ids of the bright reflectors the cache leaves out: receivers whose reflected radiosity
    is at least ``contrast`` × the area-weighted mean of the cached ones, where together they
    carry at least 2 % of the reflected power
    (:func:`~mi_twopass.prepass.radiosity.reclassified_patches` with GSII's fraction of the
    maximum at 0: the contrast alone decides).

    An order-2 SH field cannot hold light from a reflector that much brighter than the rest:
    fitted from the few gather rays of a cluster that hit it and spread by the RBF
    interpolation to points that do not see it, it left blotches of ±20–50 % in 8×8-pixel
    blocks around veach-bidir's lamps, in another place for each prepass seed (``check
    --renders 2`` at 128 px, 64 spp: bias part 9.4e-3, 3.4e-2, 1.1e-2, 1.9e-2 over four
    seeds, the bound 3e-3; neither 8192 gather rays per cluster nor 8× the particles brought
    seed 1 under 1.1e-2). Left out, they send no B_r into the far field or the near field, and
    the cache vertex's BSDF ray that meets them traced on, as for every surface the cache does
    not hold: seeds 0 and 1 read −4.2e-4 and −2.5e-4 (± 2.2e-3), measured on patches (session
    11). Since session 25 a ray past the cache vertex that meets one at least alpha away reads
    its B_r/π from the coarse solution instead (:meth:`CachedReceivers.bright_at`): traced on,
    the emitter sample toward the light beside it carried 1/r² (many_lights: rare samples of
    900 where the pixel's mean is 0.46). Leaving out only those also above half the brightest
    (GSII's rule, the virtual luminaires') left 4.4–7.2e-3. A mask of the cache's own: the solution, which other
    prepasses may share through a memo, is not changed (until session 18 it was)."""
    Br = np.asarray(B_reflected, dtype=np.float64).mean(axis=1)
    return reclassified_patches(Br, area, is_diffuse, 0.0, contrast)


def patch_of_triangles(scene, patches, vertices, normals) -> np.ndarray:
    """The patch of ``patches`` each triangle (``vertices`` (T, 3, 3), side ``normals``) lies
    on: a short ray cast at its centroid against its normal; ``patches.count`` where none."""
    if not len(vertices):
        return np.zeros(0, np.int64)
    c = np.asarray(vertices, dtype=np.float64).mean(axis=1)
    n = np.asarray(normals, dtype=np.float64)
    eps = 1e-4 * scene_diagonal(scene) + 1e-5 * np.abs(c).max()
    ray = mi.Ray3f(vectors(c + eps * n, mi.Point3f), vectors(-n, mi.Vector3f))
    ray.maxt = mi.Float(2.0 * eps)
    si = scene.ray_intersect(ray)
    return np.asarray(patches.lookup(si, si.is_valid()), dtype=np.int64)


def _triangles(mesh, ids, R):
    """(vertices, normals, R_t) of the triangles of ``mesh`` whose receiver is in ``ids``
    (a bool mask over the receivers), R_t from the per-receiver ``R``."""
    tri = np.asarray(mesh.tri_patch, dtype=np.int64)
    keep = ids[tri]
    return (np.asarray(mesh.tri_vertices)[keep], np.asarray(mesh.tri_normal)[keep],
            np.asarray(R, dtype=np.float64)[tri[keep]])


def refined_mask(solution) -> np.ndarray:
    """(M,) bool over the elements of ``solution``: refined into cells
    (:attr:`~mi_twopass.prepass.radiosity.RadiositySolution.grid`, its unevenly lit flat
    elements), so read at the point hit rather than as their mean."""
    mask = np.zeros(solution.elements.count, dtype=bool)
    if solution.grid is not None:
        mask[solution.grid.ids] = True
    return mask


def refined_count(solution) -> int:
    """Number of elements of ``solution`` refined into cells (0 without a solution)."""
    if solution is None or getattr(solution, "grid", None) is None:
        return 0
    return solution.grid.count


def cached_receivers(scene, solution, lambertian, contrast: float = 0.0) -> CachedReceivers:
    """:class:`CachedReceivers` of ``solution`` (a
    :class:`~mi_twopass.prepass.radiosity.RadiositySolution`): its elements where it has
    them, else its patches; bright reflectors (:func:`bright_receivers`, among the patches
    and among the elements) left out where ``contrast`` > 0."""
    P = solution.patches
    lam = lambda mesh: lambertian.per_shape[np.asarray(mesh.shape_index, dtype=np.int64)]  # noqa
    p_ok = np.asarray(P.is_diffuse, dtype=bool) & lam(P)
    p_bright = bright_receivers(solution.B_reflected, P.area, p_ok, contrast) \
        if contrast > 0 else np.zeros(0, np.uint32)
    p_cached = p_ok.copy()
    p_cached[p_bright] = False
    near_p = _triangles(P, p_cached, solution.B_reflected)
    if solution.elements is None:
        return CachedReceivers(P, p_cached, near_p, p_bright)
    E = solution.elements
    # an unevenly lit element refined into cells (:mod:`.element_grid`) is read by its cell
    e_ok = (np.asarray(E.is_diffuse, dtype=bool) | refined_mask(solution)) & lam(E)
    e_bright = bright_receivers(solution.B_reflected_elements, E.area, e_ok, contrast) \
        if contrast > 0 else np.zeros(0, np.uint32)
    # each element's patch, from its first triangle
    tri = np.asarray(E.tri_patch, dtype=np.int64)
    first = np.full(E.count, -1, np.int64)
    first[tri[::-1]] = np.arange(len(tri))[::-1]
    has = first >= 0
    on = np.full(E.count, P.count, np.int64)
    on[has] = patch_of_triangles(scene, P, np.asarray(E.tri_vertices)[first[has]],
                                 np.asarray(E.tri_normal)[first[has]])
    inside = on < P.count
    on_bright = np.zeros(E.count, dtype=bool)
    on_bright[inside] = np.isin(on[inside], p_bright)
    on_whole = np.zeros(E.count, dtype=bool)  # on a patch the near field holds whole
    on_whole[inside] = p_ok[on[inside]]
    e_cached = e_ok & ~on_bright
    e_cached[e_bright] = False
    bright = np.nonzero(e_ok & ~e_cached)[0]
    near_e = _triangles(E, e_cached & ~on_whole, solution.B_reflected_elements)
    near = tuple(np.concatenate([a, b]) for a, b in zip(near_p, near_e))
    return CachedReceivers(E, e_cached, near, bright)


def default_alpha(points, alpha_rel: float, fallback_diagonal: float) -> float:
    """§6: ``alpha_rel`` × the bounding-box diagonal of the camera's shading points ``points``
    (n, 3): the extent of what the camera sees, so a big unseen ground plane or sky dome does
    not inflate the near-field radius. ``fallback_diagonal`` (the scene's bounding-box diagonal)
    where there are fewer than two distinct points (:func:`~mi_twopass.scene.view.view_diagonal`).
    Scales with the scene."""
    return float(alpha_rel) * max(view_diagonal(points, fallback_diagonal), 1e-30)


@dataclass
class Clusters:
    """A partition of shading points into clusters: ``labels`` (n,) the cluster of each point,
    ``center`` (K, 3) the centroids, ``radius`` (K,) the largest distance of a member from its
    centroid, ``count`` (K,) the members."""
    labels: np.ndarray
    center: np.ndarray
    radius: np.ndarray
    count: np.ndarray
    #: (K, 3) unit mean normal of the members, where the points came with normals, else None
    normal: np.ndarray | None = None

    def __len__(self) -> int:
        return int(len(self.count))

    def members(self):
        """The point ids of each cluster (a list of K arrays, for tests and inspection)."""
        order = np.argsort(self.labels, kind="stable")
        return np.split(order, np.cumsum(self.count)[:-1]) if len(self) else []


def _group_stats(p, labels, K):
    """Per cluster of ``labels`` (K groups): counts, centroids, each point's distance from its
    centroid and the groups' largest such distance."""
    count = np.bincount(labels, minlength=K)
    center = np.stack([np.bincount(labels, weights=p[:, k], minlength=K)
                       for k in range(p.shape[1])], 1)
    center /= np.maximum(count, 1)[:, None]
    d = np.linalg.norm(p - center[labels], axis=1)
    radius = np.zeros(K)
    np.maximum.at(radius, labels, d)
    return count, center, d, radius


def _group_argmax(values, labels, K):
    """Per group 0..K−1 of ``labels``, the index of its largest value (groups must be
    non-empty; ties: the first index, as ``np.argmax``)."""
    order = np.lexsort((-np.arange(len(values)), values, labels))
    return order[np.cumsum(np.bincount(labels, minlength=K)) - 1]


def cluster_labels(p, alpha: float, max_clusters: int = 256, normals=None) -> Clusters:
    """§4.1 clustering, all clusters of a level at once (numpy, no loop over clusters): every
    cluster whose bounding radius about its centroid exceeds ``alpha`` is split in two by
    2-means (seeds: its point farthest from the centroid and the point farthest from that one;
    at most 8 Lloyd iterations), level after level, until every cluster fits or
    ``max_clusters`` is reached. Where the budget does not allow every split of a level, the
    widest clusters split first. Coincident points cannot be split.

    ``normals`` (n, 3), unit: the points are clustered by position and normal together, as
    (p, NORMAL_SPLIT · alpha · n), so a cluster never spans a crease of more than about 60°
    (its members' hemispheres would differ, and the far field one side sees is a direction
    the other side's rays never sampled: a window's reveal read the room's floor where it
    sees the sunlit ground outside, 0.3× the light). The returned centres and radii are
    positions only; ``normal`` the members' mean normals."""
    pos = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    p = pos
    limit = np.broadcast_to(np.asarray(alpha, dtype=np.float64), (len(pos),))
    scale = float(alpha) if np.ndim(alpha) == 0 else float(limit.max(initial=0.0))
    if normals is not None:
        p = np.hstack([pos, NORMAL_SPLIT * scale
                       * np.asarray(normals, dtype=np.float64).reshape(-1, 3)])
    n = len(p)
    labels = np.zeros(n, dtype=np.int64)
    K = 1 if n else 0
    splittable = np.ones(K, dtype=bool)
    while True:
        count, center, d, radius = _group_stats(p, labels, K)
        bound = np.full(K, np.inf)
        np.minimum.at(bound, labels, limit)
        want = np.flatnonzero(splittable & (radius > bound) & (count >= 2))
        room = int(max_clusters) - K
        if room <= 0 or len(want) == 0:
            break
        if len(want) > room:  # the widest (against its bound) first
            want = want[np.argsort(-radius[want] / bound[want], kind="stable")[:room]]
        split = np.zeros(K, dtype=bool)
        split[want] = True
        sel = np.flatnonzero(split[labels])
        q, ql = p[sel], labels[sel]
        # seeds of 2-means: the member farthest from the centroid, then the one farthest from it
        seg = np.full(K, 0, dtype=np.int64)
        seg[want] = np.arange(len(want))
        g = seg[ql]  # each selected point's group among the splitting clusters
        a = q[_group_argmax(d[sel], g, len(want))]
        b = q[_group_argmax(np.linalg.norm(q - a[g], axis=1), g, len(want))]
        cA, cB = a.copy(), b.copy()
        side = None
        for _ in range(8):  # Lloyd iterations, until no label changes
            new = ((q - cB[g]) ** 2).sum(-1) < ((q - cA[g]) ** 2).sum(-1)
            if side is not None and np.array_equal(new, side):
                break
            side = new
            nB = np.bincount(g, weights=side, minlength=len(want))
            nA = np.bincount(g, minlength=len(want)) - nB
            both = (nA > 0) & (nB > 0)  # a one-sided group keeps its centres (cannot split)
            for c, w, m in ((cA, ~side, nA), (cB, side, nB)):
                s = np.stack([np.bincount(g, weights=q[:, k] * w, minlength=len(want))
                              for k in range(q.shape[1])], 1)
                c[both] = s[both] / m[both][:, None]
        nB = np.bincount(g, weights=side, minlength=len(want))
        nA = np.bincount(g, minlength=len(want)) - nB
        ok = (nA > 0) & (nB > 0)
        splittable[want[~ok]] = False  # all its points coincide
        new_id = np.full(len(want), -1, dtype=np.int64)
        new_id[ok] = K + np.arange(int(ok.sum()))
        move = side & ok[g]
        labels[sel[move]] = new_id[g[move]]
        K += int(ok.sum())
        splittable = np.concatenate([splittable, np.ones(int(ok.sum()), dtype=bool)])
    if n == 0:
        return Clusters(labels, np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64),
                        None if normals is None else np.zeros((0, 3)))
    count, center, _, radius = _group_stats(pos, labels, K)
    normal = None
    if normals is not None:
        _, normal, _, _ = _group_stats(np.asarray(normals, dtype=np.float64).reshape(-1, 3),
                                       labels, K)
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        normal = np.where(length > 0, normal / np.where(length > 0, length, 1.0), 0.0)
    return Clusters(labels, center, radius, count, normal)


def cluster_points(p, alpha: float, max_clusters: int = 256, seed: int = 0):
    """:func:`cluster_labels` as a list of index arrays (one cluster per array)."""
    return cluster_labels(p, alpha, max_clusters).members()


def fit_clusters(p, alpha: float, max_clusters: int = 256, seed: int = 0, normals=None,
                 limits=None):
    """:func:`cluster_labels` with every cluster within ``alpha`` (and within the smallest of
    its points' ``limits``, where given: :func:`parallax_limits`), growing alpha (and the
    limits with it) where ``max_clusters`` cannot cover the points with clusters that small →
    ``(alpha', Clusters)`` with alpha' ≥ alpha the smallest size found (doubling, then 6
    bisection steps) at which the budget suffices.

    Why alpha grows rather than the clusters alone: the far field of a cluster, fitted from
    rays of its points that travel farther than alpha, stands for every point of the cluster
    only if the cluster is no larger than alpha (parallax of the geometry between alpha and
    the cluster's size is in no term). Clusters left larger by the budget made the cache 40 %
    dark on the indirect light of a box lit by a 5 mm sphere (64 clusters for 138 needed);
    with alpha grown to fit them, 0 ± 3 %. alpha is also the near-field radius (§5), so the
    caller must use alpha' there."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    alpha = float(alpha)
    base = alpha if limits is None else \
        np.minimum(np.asarray(limits, dtype=np.float64).reshape(-1), alpha)

    def attempt(f):
        c = cluster_labels(p, base * f, max_clusters, normals)
        bound = np.full(len(c), alpha * f)
        np.minimum.at(bound, c.labels, np.broadcast_to(base * f, c.labels.shape))
        return c, bool(np.all(c.radius <= bound * (1 + 1e-9)))

    clusters, ok = attempt(1.0)
    if ok:
        return alpha, clusters
    lo, hi = 1.0, 2.0
    extent = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    best = None
    for _ in range(64):
        c, ok = attempt(hi)
        if ok:
            best = c
            break
        lo, hi = hi, 2.0 * hi
        if float(np.min(base)) * hi > 4.0 * extent + alpha:
            best, _ = attempt(hi)  # one cluster always fits its own extent
            break
    for _ in range(6):
        mid = float(np.sqrt(lo * hi))
        c, ok = attempt(mid)
        if ok:
            hi, best = mid, c
        else:
            lo = mid
    return alpha * hi, best


class ClusterGrid:
    """Uniform grid over the RBF supports of the clusters (numpy build, Dr.Jit query).

    Cluster k (centre ``center[k]``, support radius ``support[k]``) is listed in every cell its
    support sphere overlaps (exact sphere–box test), in CSR form: ``cell_start`` (C + 1,) and
    ``cell_ids``. A point's own cell then lists every cluster whose support contains the point,
    so summing RBF weights over the cell equals the sum over all clusters (weights outside the
    support are dropped there too). Points outside the grid are outside every support. The cell
    size is :data:`GRID_CELL_REL` × the median support radius, at most :data:`GRID_MAX_RES`
    cells per axis.
    """

    def __init__(self, center, support):
        center = np.asarray(center, dtype=np.float64).reshape(-1, 3)
        support = np.asarray(support, dtype=np.float64).reshape(-1)
        K = len(center)
        self.lo = (center - support[:, None]).min(axis=0) if K else np.zeros(3)
        hi = (center + support[:, None]).max(axis=0) if K else np.ones(3)
        extent = np.maximum(hi - self.lo, 1e-30)
        h = max(GRID_CELL_REL * float(np.median(support)) if K else 1.0,
                float(extent.max()) / GRID_MAX_RES, 1e-30)
        self.res = np.clip(np.ceil(extent / h), 1, GRID_MAX_RES).astype(np.int64)
        self.cell = extent / self.res
        k, cid = self._pairs(center, support)
        order = np.lexsort((k, cid))  # per cell, clusters in index order
        counts = np.bincount(cid, minlength=int(np.prod(self.res)))
        self.cell_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.cell_ids = k[order].astype(np.int64)

    def _pairs(self, center, support):
        """Every (cluster, cell id) pair whose cell's box the cluster's support sphere touches,
        among the cells of the sphere's bounding box (numpy, vectorised): per (cluster, x, y)
        column of that box, the run of z cells the sphere meets, d_xy² + d_z² ≤ r² (the
        pairs a test of every cell of the box keeps, at an eighth of its work for a box 8
        cells wide: 44 -> 7.6 ms for 545 clusters; where a sphere touches a cell's face
        exactly, rounding may add that cell)."""
        K = len(center)
        if K == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        a = np.clip(np.floor((center - support[:, None] - self.lo) / self.cell), 0,
                    self.res - 1).astype(np.int64)
        b = np.clip(np.floor((center + support[:, None] - self.lo) / self.cell), 0,
                    self.res - 1).astype(np.int64)
        span = b - a + 1
        n = span[:, 0] * span[:, 1]
        k = np.repeat(np.arange(K), n)
        r = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)  # rank in the xy box
        ij = a[k, :2] + np.stack([r // span[k, 1], r % span[k, 1]], axis=1)
        box_lo = self.lo[:2] + ij * self.cell[:2]
        c = center[k]
        d_xy = np.maximum(np.maximum(box_lo - c[:, :2], c[:, :2] - box_lo - self.cell[:2]), 0.0)
        r2 = support[k] ** 2 - (d_xy ** 2).sum(axis=1)
        hz = np.sqrt(np.maximum(r2, 0.0))
        # cell z touches [c_z − hz, c_z + hz]: lo + z h ≤ c_z + hz and lo + (z + 1) h ≥ c_z − hz
        z0 = np.maximum(np.ceil((c[:, 2] - hz - self.lo[2]) / self.cell[2]) - 1, a[k, 2])
        z1 = np.minimum(np.floor((c[:, 2] + hz - self.lo[2]) / self.cell[2]), b[k, 2])
        nz = np.where(r2 >= 0, np.maximum(z1 - z0 + 1, 0), 0).astype(np.int64)
        kk = np.repeat(k, nz)
        rz = np.arange(int(nz.sum())) - np.repeat(np.cumsum(nz) - nz, nz)
        z = np.repeat(z0.astype(np.int64), nz) + rz
        i, j = np.repeat(ij[:, 0], nz), np.repeat(ij[:, 1], nz)
        return kk, (i * self.res[1] + j) * self.res[2] + z

    @property
    def nbytes(self) -> int:
        return int(4 * (len(self.cell_start) + len(self.cell_ids)))

    def candidates(self, x):
        """numpy: the cluster ids listed in the cell of each point ``x`` (n, 3) (for tests)."""
        c = self.cell_index_numpy(x)
        return [self.cell_ids[self.cell_start[i]:self.cell_start[i + 1]] for i in c]

    def cell_index_numpy(self, x):
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        ijk = np.clip(np.floor((x - self.lo) / self.cell), 0, self.res - 1).astype(np.int64)
        return (ijk[:, 0] * self.res[1] + ijk[:, 1]) * self.res[2] + ijk[:, 2]

    def tables(self):
        """Dr.Jit copies: ``lo``, ``inv_cell``, ``res`` (Python tuples, constant per prepass)
        and ``start``/``ids`` (``mi.UInt32``)."""
        return dict(start=jit(mi.UInt32, self.cell_start.astype(np.uint32)),
                    ids=jit(mi.UInt32, self.cell_ids.astype(np.uint32)))

    def cell_index(self, x, t):
        """Dr.Jit: the cell of ``x`` (clamped to the grid); ``t`` the tables of :meth:`tables`
        plus ``lo``/``inv_cell`` (``mi.Point3f``/``mi.Vector3f``) and ``res`` (``mi.Vector3i``)."""
        q = mi.Vector3i(dr.floor((x - t["lo"]) * t["inv_cell"]))
        q = dr.clip(q, 0, t["res"] - 1)
        return mi.UInt32((q.x * t["res"].y + q.y) * t["res"].z + q.z)


#: weight of the normals in :func:`cluster_labels`' features (p, NORMAL_SPLIT · alpha · n):
#: a cluster whose members' normals differ by more than about 60° (|Δn| = 1, half of it from
#: the mean) is wider than alpha and splits
NORMAL_SPLIT = 2.0
#: a cluster whose mean normal is at more than acos(NORMAL_COS) = 60° from a query's normal
#: lends it nothing (:func:`normal_weight`)
NORMAL_COS = 0.5


#: a query whose normal-weighted RBF weights (:func:`normal_weight`) sum to less than this is
#: not held by the far field (:meth:`RadianceCache.coefficients` with ``coverage``): no
#: cluster of its orientation lies near it, so the SH it would read was fitted from rays of
#: other hemispheres (a window's reveal between the wall's clusters). The render path-traces
#: there. 0.1: the weight 2.1 σ from the centre of one matching cluster
COVER_MIN = 0.1


def normal_weight(cos):
    """The RBF weight's factor for a cluster whose mean normal makes cosine ``cos`` with the
    query's: 1 for the same orientation, falling linearly to 0 at :data:`NORMAL_COS`."""
    return dr.clip((cos - NORMAL_COS) * (1.0 / (1.0 - NORMAL_COS)), 0.0, 1.0)


def _accumulate(acc, S_table, k, w, active):
    """acc_j + w · S_kj for the 9 SH coefficients of cluster ``k``."""
    return [a + w * dr.gather(mi.Color3f, S_table, k * sh.SH_COUNT + j, active)
            for j, a in enumerate(acc)]


@dataclass
class RadianceCache:
    """The SH far field: ``center`` (K, 3) centroids of the clusters, ``radius`` (K,),
    ``coeffs`` (K, 9, 3) incident radiance L_F, ``ambient`` (3,) a constant radiance added to
    every cluster (fake GI, §8.1), ``alpha``; ``sample_dirs``/``sample_origins`` the gather rays
    (for inspection), ``points`` the shading points, ``rays`` gather rays traced."""
    center: np.ndarray
    radius: np.ndarray
    coeffs: np.ndarray
    alpha: float
    ambient: np.ndarray
    points: np.ndarray
    rays: int
    shading_rays: int = 0
    #: (K, 3) the clusters' unit mean normals (:func:`cluster_labels`), or None: the RBF
    #: weights then ignore the query's normal
    normal: np.ndarray | None = None

    @property
    def count(self) -> int:
        return int(len(self.center))

    @property
    def sigma(self) -> np.ndarray:
        """RBF widths σ_k = max(cluster radius, alpha/4)."""
        return np.maximum(self.radius, 0.25 * self.alpha)

    @cached_property
    def grid(self) -> ClusterGrid:
        """The cluster grid over the RBF supports, built on first use and kept."""
        return ClusterGrid(self.center, RBF_SUPPORT * self.sigma)

    @property
    def nbytes(self) -> int:
        return int(self.count * (3 + 1 + 27) * 4 + (self.grid.nbytes if self.count else 0))

    @cached_property
    def _tables(self) -> Tables:
        """Dr.Jit copies of the field and its grid, built on first use and kept (first use
        outside symbolic loops: the prepass builds them, through :func:`build_radiance_cache`).
        Grid constants are opaque, so a new prepass does not recompile the render kernels."""
        normal = self.normal if self.normal is not None else np.zeros((self.count, 3))
        t = dict(center=jit(mi.Float, self.center.astype(np.float32).ravel()),
                 normal=jit(mi.Float, np.asarray(normal, np.float32).ravel()),
                 sigma=jit(mi.Float, self.sigma.astype(np.float32)),
                 S=jit(mi.Float, self.coeffs.astype(np.float32).ravel()))
        if self.count:
            g = self.grid
            t.update(g.tables())
            t["lo"] = dr.opaque(mi.Point3f, [float(v) for v in g.lo])
            t["inv_cell"] = dr.opaque(mi.Vector3f, [float(1.0 / v) for v in g.cell])
            t["res"] = dr.opaque(mi.Vector3i, [int(v) for v in g.res])
            t["K"] = dr.opaque(mi.UInt32, self.count)
        tables = Tables(**t)
        dr.eval(*tables.values())
        return tables

    def coefficients(self, x, active=True, n=None, coverage=False):
        """Interpolated L_F at points ``x``: 9 ``mi.Color3f`` SH coefficients (incident radiance),
        normalised Gaussian RBF weights over the clusters whose support holds ``x`` (the lane's
        grid cell; nearest-cluster fallback), plus the constant ``ambient`` radiance in band 0.
        With the query's unit normal ``n`` (and clusters with normals) each weight is scaled
        by :func:`normal_weight` of the normals' cosine. ``coverage``: also return where the
        field holds the query (:meth:`covers`)."""
        amb = [float(a) / sh._C00 for a in self.ambient]  # constant L: c_00 = L / Y_00
        covered = mi.Bool(active)
        if self.count == 0:
            coeffs = [mi.Color3f(0.0) for _ in range(sh.SH_COUNT)]
        else:
            acc, sum_w = self._interpolate(x, active, n)
            fallback = mi.Bool(active) & (sum_w <= 1e-3)
            nearest = self._nearest(x, fallback)
            near_acc = _accumulate([mi.Color3f(0.0) for _ in range(sh.SH_COUNT)],
                                   self._tables["S"], nearest, mi.Float(1.0), fallback)
            inv = dr.rcp(dr.maximum(sum_w, 1e-30))
            coeffs = [dr.select(fallback, b, a * inv) for a, b in zip(acc, near_acc)]
            if n is not None and self.normal is not None:
                covered &= sum_w >= COVER_MIN
        coeffs[0] = coeffs[0] + mi.Color3f(*amb)
        coeffs = [dr.select(mi.Bool(active), c, 0.0) for c in coeffs]
        return (coeffs, covered) if coverage else coeffs

    def far_field(self, x, n, active=True, coeffs=None):
        """B_D (``mi.Color3f``, irradiance W/m², clamped ≥ 0) at points ``x`` with unit normals
        ``n``: the interpolated SH (``coeffs``, else :meth:`coefficients`) dotted with the clamped
        cosine (eq. 3)."""
        if coeffs is None:
            coeffs = self.coefficients(x, active)
        E = sh.irradiance(coeffs, mi.Vector3f(n))
        return dr.select(mi.Bool(active), dr.maximum(E, 0.0), 0.0)

    @dr.syntax
    def _interpolate(self, x, active, n=None):
        """(Σ_k w_k S_k, Σ_k w_k) over the clusters listed in the grid cell of ``x`` with
        w_k = exp(−|x − c_k|²/2σ_k²) ≥ :data:`RBF_MIN_WEIGHT` (Gaussian RBF), times
        :func:`normal_weight` (n · n_k) where ``n`` is given and the clusters have normals."""
        t = self._tables
        x = mi.Point3f(x)
        by_normal = n is not None and self.normal is not None
        nq = mi.Vector3f(n) if by_normal else mi.Vector3f(0.0)
        active = mi.Bool(active)
        cell = self.grid.cell_index(x, t)
        j = dr.gather(mi.UInt32, t["start"], cell, active)
        end = dr.gather(mi.UInt32, t["start"], cell + 1, active)
        sum_w = mi.Float(0.0)
        acc = [mi.Color3f(0.0) for _ in range(sh.SH_COUNT)]
        while dr.hint(active & (j < end), label="radiance_cache_rbf"):
            k = dr.gather(mi.UInt32, t["ids"], j)
            c = dr.gather(mi.Point3f, t["center"], k)
            s = dr.gather(mi.Float, t["sigma"], k)
            w = dr.exp(-0.5 * dr.squared_norm(x - c) / dr.square(s))
            use = w >= RBF_MIN_WEIGHT
            if by_normal:
                w *= normal_weight(dr.dot(nq, dr.gather(mi.Vector3f, t["normal"], k)))
            acc = _accumulate(acc, t["S"], k, dr.select(use, w, 0.0), use)
            sum_w += dr.select(use, w, 0.0)
            j += 1
        return acc, sum_w

    @dr.syntax
    def _nearest(self, x, active):
        """The cluster with the smallest |x − c_k|/σ_k, by a loop over all clusters; only lanes
        in ``active`` (those outside every support) run it."""
        t = self._tables
        x = mi.Point3f(x)
        active = mi.Bool(active)
        best_d = mi.Float(3e38)
        best = mi.UInt32(0)
        k = mi.UInt32(0)
        while dr.hint(active & (k < t["K"]), label="radiance_cache_nearest"):
            c = dr.gather(mi.Point3f, t["center"], k)
            s = dr.gather(mi.Float, t["sigma"], k)
            rel = dr.squared_norm(x - c) / dr.square(s)
            closer = rel < best_d
            best_d = dr.select(closer, rel, best_d)
            best = dr.select(closer, k, best)
            k += 1
        return best

    def coefficients_numpy(self, x, n=None):
        """Brute-force reference of :meth:`coefficients` (every cluster, float64) for tests:
        ``x`` (n, 3) → (n, 9, 3)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        out = np.zeros((len(x), sh.SH_COUNT, 3))
        if self.count:
            rel = ((x[:, None] - self.center[None]) ** 2).sum(-1) / self.sigma[None] ** 2
            w = np.exp(-0.5 * rel)
            w = np.where(w >= RBF_MIN_WEIGHT, w, 0.0)
            if n is not None and self.normal is not None:
                cos = np.asarray(n, dtype=np.float64).reshape(-1, 3) @ self.normal.T
                w = w * np.clip((cos - NORMAL_COS) / (1.0 - NORMAL_COS), 0.0, 1.0)
            sw = w.sum(1)
            interp = np.einsum("nk,kjc->njc", w, self.coeffs) / np.maximum(sw, 1e-30)[:, None, None]
            nearest = self.coeffs[np.argmin(rel, axis=1)]
            out = np.where((sw > 1e-3)[:, None, None], interp, nearest)
        out[:, 0] += np.asarray(self.ambient) / sh._C00
        return out

    @dr.syntax
    def near_centre(self, x, radius, active=True):
        """``mi.Bool``: a cluster centre lies within ``radius`` of ``x`` (debug "samples")."""
        K = self.count
        t = self._tables
        x = mi.Point3f(x)
        active = mi.Bool(active) & (K > 0)
        hit = mi.Bool(False)
        k = mi.UInt32(0)
        while dr.hint(active & (k < K), label="radiance_cache_near_centre"):
            c = dr.gather(mi.Point3f, t["center"], k)
            hit |= dr.squared_norm(x - c) < radius * radius
            k += 1
        return hit


def _hemisphere_rays(scene, o, n, z, phi):
    """Rays from the points ``o`` about their unit normals ``n`` (numpy, (m, 3)) in the
    directions of hemisphere coordinates ``z`` = cos θ and ``phi`` (uniform over the
    hemisphere where both are uniform), the origins offset along ``n`` relative to the scene's
    size: ``(mi.Ray3f, directions (m, 3))``."""
    r = np.sqrt(np.maximum(0.0, 1 - z * z))
    tmp = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    s = np.cross(n, tmp)
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    t = np.cross(n, s)
    d = (r * np.cos(phi))[:, None] * s + (r * np.sin(phi))[:, None] * t + z[:, None] * n
    eps = 1e-4 * scene_diagonal(scene) + 1e-5 * np.abs(o).max()
    return mi.Ray3f(vectors(o + eps * n, mi.Point3f), vectors(d, mi.Vector3f)), d


def parallax_limits(scene, p, n, alpha: float, kappa: float, rays: int = 16, seed: int = 0):
    """Per shading point (``p``, ``n``: (m, 3)), the widest cluster whose far field it may
    share: min(``alpha``, ``kappa`` / g) with g = mean over ``rays`` uniform hemisphere rays of
    [t > alpha] / t, t the distance to the first hit (a miss or a hit nearer than alpha adds 0:
    the near field holds what lies within alpha). A cluster of radius r fitted from rays that
    meet geometry at t sees it shifted by an angle of about r / t across its points (the
    translational gradient of Ward et al.'s irradiance cache, whose records are valid out to a
    multiple of the harmonic mean distance); kappa bounds the mean of that shift over the far
    field. Where the far field lies well beyond alpha, the limit is alpha itself."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    m = len(p)
    if m == 0 or kappa <= 0 or rays < 1:
        return np.full(m, float(alpha))
    nn = np.asarray(n, dtype=np.float64).reshape(-1, 3)
    rng = np.random.default_rng(hash31(seed, 5))
    k = int(rays)
    src = np.repeat(np.arange(m), k)
    o, nr = p[src], nn[src]
    # stratified uniform hemisphere: one ray per cell of a k-cell grid in (z, phi)
    cell = np.tile(np.arange(k), m)
    side = max(int(np.sqrt(k)), 1)
    z = (cell // side % side + rng.random(len(src))) / side
    phi = 2 * np.pi * ((cell % side) + rng.random(len(src))) / side
    ray, _ = _hemisphere_rays(scene, o, nr, z, phi)
    t = np.asarray(scene.ray_intersect_preliminary(ray).t, dtype=np.float64).reshape(-1)
    far = np.isfinite(t) & (t > alpha)
    g = np.bincount(src, weights=np.where(far, 1.0 / np.where(far, t, 1.0), 0.0),
                    minlength=m) / k
    return np.minimum(float(alpha), kappa / np.maximum(g, 1e-30))


def gather_far_field(scene, solution, p, n, clusters, rays_per_cluster=128, seed=0,
                     reg=sh.DEFAULT_REG, cached=None):
    """Eq. 4: per cluster of ``clusters`` (:class:`Clusters`), ``rays_per_cluster`` gather
    rays from random shading points of the cluster (uniform hemisphere) read B_r/π of the
    receiver hit where it is cached (``cached``, a :class:`CachedReceivers`; default: the
    solution's receivers, no bright reflector left out), 0 elsewhere, near hits included
    (module docstring, step 3). Ray origins are offset relative to the scene's size.
    → ``(coeffs (K, 9, 3), rays traced)``."""
    K = len(clusters)
    coeffs = np.zeros((K, sh.SH_COUNT, 3))
    if K == 0 or rays_per_cluster < 1:
        return coeffs, 0
    rng = np.random.default_rng(hash31(seed, 3))
    m = int(rays_per_cluster)
    owner = np.repeat(np.arange(K), m)
    # m members of each cluster drawn at random (with replacement), all clusters at once
    by_cluster = np.argsort(clusters.labels, kind="stable")
    first = np.cumsum(clusters.count) - clusters.count
    pick = np.minimum((rng.random(K * m) * clusters.count[owner]).astype(np.int64),
                      clusters.count[owner] - 1)
    src = by_cluster[first[owner] + pick]
    o, nn = p[src], n[src]
    # uniform hemisphere about nn: local (x, y, z) then the frame of nn
    u1, u2 = rng.random(len(src)), rng.random(len(src))
    ray, d = _hemisphere_rays(scene, o, nn, u1, 2 * np.pi * u2)
    si = scene.ray_intersect(ray)
    # only a cached surface sends B_r/π: on any other the render traces the path on
    if cached is None:
        cached = cached_receivers(scene, solution, LambertianShapes(scene))
    valid = cached.at(si, si.is_valid())
    L = solution.reflected_radiance(si, valid)
    L = dr.select(valid, L, 0.0)
    # columns: np.asarray of a Color3f interleaves it in a kernel with its width as a literal,
    # and the width (clusters x rays) follows the seed: a kernel compiled for every render
    L = columns(L)
    L = np.where(np.isfinite(L), L, 0.0)
    # one regularised least-squares fit per cluster, solved as a batch (eq. 4)
    coeffs = sh.project_least_squares_groups(d, L, owner, K, reg=reg)
    return coeffs, len(src)


def build_radiance_cache(scene, solution, alpha, sensor=None, max_points=4096,
                         max_clusters=256, rays_per_cluster=128, seed=0, ambient=0.0,
                         fake_gi=False, shading_points=None, cached=None,
                         parallax: float = 0.0):
    """Steps 1–4 of the module docstring → :class:`RadianceCache`. ``fake_gi``: no shading
    points and no gather, only the constant ``ambient`` radiance (§8.1). ``shading_points``:
    the ``(p, n, rays)`` of :func:`collect_shading_points` when the caller already has them
    (the integrator does: its default alpha depends on them). ``cached``: the receivers the
    gather reads (:class:`CachedReceivers`; default :func:`cached_receivers`)."""
    amb = np.broadcast_to(np.asarray(ambient, dtype=np.float64), (3,)).copy()
    if fake_gi or solution is None:
        return RadianceCache(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 9, 3)), float(alpha),
                             amb, np.zeros((0, 3)), 0,
                             int(shading_points[2]) if shading_points is not None else 0)
    if shading_points is None:
        shading_points = collect_shading_points(scene, sensor, max_points, seed)
    p, n, shading_rays = shading_points
    # clusters smaller than alpha where the far field lies near alpha (parallax_limits)
    limits = parallax_limits(scene, p, n, alpha, parallax, seed=seed) if parallax > 0 else None
    alpha, clusters = fit_clusters(p, alpha, max_clusters, seed, normals=n, limits=limits)
    center, radius = clusters.center.reshape(-1, 3), clusters.radius.reshape(-1)
    coeffs, rays = gather_far_field(scene, solution, p, n, clusters, rays_per_cluster, seed,
                                    cached=cached)
    cache = RadianceCache(center, radius, coeffs, float(alpha), amb, p, rays, shading_rays,
                          normal=clusters.normal)
    cache._tables  # Dr.Jit copies now, never first inside a symbolic loop
    return cache


def check_no_media(scene):
    """ValueError naming the first participating medium of ``scene`` (on a sensor, an emitter or
    a shape's inside or outside): radiance_cache transports light between surfaces only."""
    found = []
    for sensor in scene.sensors():
        found.append(("sensor", sensor, sensor.get_medium()))
    for emitter in scene.emitters():
        found.append(("emitter", emitter, emitter.get_medium()))
    for shape in scene.shapes():
        found.append(("interior of shape", shape, shape.interior_medium()))
        found.append(("exterior of shape", shape, shape.exterior_medium()))
    for where, obj, medium in found:
        if medium is not None:
            raise ValueError(
                f"radiance_cache: the scene has a participating medium ({medium.class_name()} "
                f"'{medium.id()}', {where} '{obj.id()}'); radiance_cache transports light "
                "between surfaces only and would render it as if it were not there: render the "
                "scene with 'volpath', or set ignore_media=true to ignore it as 'path' does")


#: default alpha as a fraction of the bounding-box diagonal of the camera's shading points.
#: window_interior 64² (diagonal 7.7 m), relMSE at 256 spp against path: 0.0037 at 0.02 and
#: 0.03, 0.0052 at 0.05, 0.0075 at 0.1 (darker as alpha grows: the visibility assumption of
#: B_C, §6); 0.03 needs about half the SH samples of 0.02.
ALPHA_REL = 0.03
#: a patch whose reflected radiosity is this many times the cached patches' area-weighted mean
#: is not cached (:func:`bright_receivers`): the contrast of GSII's virtual luminaires
BRIGHT_CONTRAST = VL_CONTRAST
#: near-field triangles whose longest edge is below this × alpha are merged by vertex
#: clustering at cells of that side (:mod:`~mi_twopass.prepass.near_merge`): the merged ones
#: are at most about alpha/2 across, the size the lazy split (§5) leaves
NEAR_MERGE_REL = 0.25


@dataclass(frozen=True)
class CacheSettings:
    """What the radiance_cache prepass reads (the integrator's XML properties, checked at load;
    its class docstring is the manual)."""

    alpha_rel: float = ALPHA_REL
    #: an absolute near-field radius, else alpha_rel × the diagonal of the shading points
    alpha: float | None = None
    fake_gi: bool = False
    ambient: float = 0.1
    radiosity: RadiositySettings = RadiositySettings(max_patches=2048, elements_per_patch=4)
    max_points: int = 4096
    max_clusters: int = 1024
    #: clusters split further to at most this / (mean 1/t of far hits) (:func:`parallax_limits`)
    parallax: float = 0.0
    rays_per_cluster: int = 128
    #: patches whose reflected radiosity is this many times the cached patches' mean are not
    #: cached (:func:`bright_receivers`)
    bright_contrast: float = BRIGHT_CONTRAST
    max_near_triangles: int = 1 << 17
    near_cell_rel: float = 0.5
    #: near-field triangles smaller than this × alpha are merged by vertex clustering
    #: (:mod:`~mi_twopass.prepass.near_merge`); 0: never
    near_merge_rel: float = NEAR_MERGE_REL
    ignore_media: bool = False
    #: no vertex reads the cache and no debug view needs it: build nothing (path tracing)
    path_only: bool = False
    #: a debug view will show the structure: build it even where the render would not read it
    debug_view: bool = False
    #: spike lists for the direct light (emitters only: the cache holds the indirect light),
    #: None: Mitsuba's emitter sampling
    spike: SpikeSettings | None = None


class CachePrepass:
    """The prepass output: ``alpha`` (the near-field radius), ``patches``, ``elements`` (or
    None), ``solution`` (None with fake_gi), ``cache`` (:class:`RadianceCache`), ``near``
    (:class:`~mi_twopass.prepass.near_field.NearField`), ``scale`` (the scene's diagonal) and
    ``lambertian`` (:class:`~mi_twopass.scene.lambertian.LambertianShapes`: where a vertex may
    read the cache). ``cache`` is None where no vertex reads it (a finite max_depth, component
    "direct", a scene whose bounding box misses shapes beside an infinite emitter). ``spike``:
    the spike lists of the direct light (:class:`~mi_twopass.prepass.spike_grid.SpikePrepass`,
    emitters only) or None. A plain
    class, not a dataclass: Dr.Jit would traverse a dataclass as a PyTree, and the render loop
    that reads it would take its arrays for loop state."""

    def __init__(self, scale, lambertian, alpha=0.0, patches=None, elements=None, solution=None,
                 cache=None, near=None, split_complete=True, spike=None, cached=None,
                 near_merged=0):
        self.scale, self.lambertian, self.alpha = scale, lambertian, alpha
        self.patches, self.elements, self.solution = patches, elements, solution
        self.cache, self.near, self.split_complete = cache, near, split_complete
        self.spike = spike
        #: near-field triangles merged away as far smaller than alpha (near_merge)
        self.near_merged = near_merged
        #: the surfaces the cache holds (:class:`CachedReceivers`), None where nothing is built
        self.cached = cached
        #: the cache's irradiance at the camera's pixel centres
        #: (:class:`~mi_twopass.prepass.pixel_table.PixelTable`), None where there is none
        self.pixels = None

    @property
    def grid(self):
        """The spike-list grid of the direct light (None: emitter sampling)."""
        return None if self.spike is None else self.spike.grid

    @property
    def nbytes(self) -> int:
        lists = int(self.spike.grid.nbytes) if self.spike is not None else 0
        if self.cache is None:
            return lists
        sol = int(self.solution.nbytes) if self.solution is not None else 0
        table = int(self.pixels.nbytes) if self.pixels is not None else 0
        return int(self.cache.nbytes + self.near.nbytes) + sol + lists + table


def cache_alpha(scene, settings: CacheSettings, points=None) -> float:
    """``alpha``, else ``alpha_rel`` × the bounding-box diagonal of the camera's shading
    ``points`` (:func:`default_alpha`; the scene's diagonal without points)."""
    if settings.alpha is not None:
        return settings.alpha
    return default_alpha(np.zeros((0, 3)) if points is None else points, settings.alpha_rel,
                         scene_diagonal(scene))


def build(scene, settings: CacheSettings, seed: int, progress: bool = True,
          sensor=None, memo=None) -> CachePrepass:
    """Shading points, coarse solution (radiosity), SH far field (§4.1), near-field BVH
    (§7). Only Lambertian surfaces carry radiosity into the cache: the shading points are the
    camera's first Lambertian hits, and the SH gather rays and the near-field triangles read 0
    on every other surface (the render traces paths there). ``sensor``: the camera whose
    shading points the cache is built for (default: the scene's first); ``progress``: bars on
    the radiosity solve and the spike lists' visibility rounds (on a terminal); ``memo``:
    radiosity solves shared with other prepasses (:func:`mi_twopass.prepass.radiosity.build`).

    With ``settings.spike``, spike lists of the emitters for the direct light (Zimmerman &
    Shirley §4, :func:`~mi_twopass.prepass.spike_grid.build_spike_prepass` on the coarse
    solution, no virtual luminaires: reflected light is the cache's)."""
    pre = _build_cache(scene, settings, seed, sensor, progress, memo)
    if settings.spike is not None and len(scene.emitters()) > 1:
        sp = settings.spike
        pre.spike = build_spike_prepass(scene, sp, solution=pre.solution,
                                        vl_threshold=float("inf"), e_high_rel=sp.e_high_rel,
                                        e_low_rel=sp.e_low_rel, E_high=sp.E_high,
                                        E_low=sp.E_low, seed=seed, sensor=sensor,
                                        progress=progress)
    return pre


def _build_cache(scene, settings: CacheSettings, seed: int, sensor=None,
                 progress: bool = True, memo=None) -> CachePrepass:
    """:func:`build` without the spike lists."""
    if not settings.ignore_media:
        check_no_media(scene)
    scale = scene_diagonal(scene)
    lambertian = LambertianShapes(scene)
    if settings.path_only:
        return CachePrepass(scale=scale, lambertian=lambertian)
    if sensor is None and len(scene.sensors()):
        sensor = scene.sensors()[0]
    points = collect_shading_points(scene, sensor, settings.max_points, seed) \
        if sensor is not None else None
    alpha = cache_alpha(scene, settings, None if points is None else points[0])
    rad = None if settings.fake_gi else build_radiosity(scene, settings.radiosity, seed, progress,
                                                        sensor=sensor, memo=memo)
    solution = rad.solution if rad is not None else None
    elements = rad.elements if rad is not None else None
    if solution is not None:
        cached = cached_receivers(scene, solution, lambertian, settings.bright_contrast)
    else:  # fake GI (§8.1): no radiosity, every triangle's R_t is 0; paths end as they would
        patches = build_patches(scene, max_patches=settings.radiosity.max_patches, seed=seed)
        ok = np.asarray(patches.is_diffuse, dtype=bool) & \
            lambertian.per_shape[np.asarray(patches.shape_index, dtype=np.int64)]
        cached = CachedReceivers(patches, ok, _triangles(patches, ok,
                                                         np.zeros((patches.count, 3))))
    patches = rad.patches if rad is not None else cached.receivers
    tri_vertices, tri_normal, tri_B = cached.near
    cache = build_radiance_cache(scene, solution, alpha, sensor=sensor, shading_points=points,
                                 max_points=settings.max_points,
                                 max_clusters=settings.max_clusters,
                                 parallax=settings.parallax,
                                 rays_per_cluster=settings.rays_per_cluster, seed=seed,
                                 ambient=settings.ambient if settings.fake_gi else 0.0,
                                 fake_gi=settings.fake_gi or sensor is None, cached=cached)
    # alpha grows where max_clusters cannot cover the points with clusters that small
    # (fit_clusters): a cluster's far field stands for its points only where the near field
    # reaches across the cluster
    alpha = cache.alpha
    # triangles far below alpha merged: the near field needs no finer detail (near_merge)
    tri_vertices, tri_normal, tri_B, merged = merge_small_triangles(
        tri_vertices, tri_normal, tri_B, settings.near_merge_rel * alpha)
    # §5: triangles near the camera's shading points split lazily until smaller than alpha
    shading = np.zeros((0, 3)) if points is None else points[0]
    verts, tri_n, tri_B, split_complete = split_near_triangles(
        tri_vertices, tri_normal, tri_B, shading, alpha,
        max_triangles=settings.max_near_triangles)
    seen = ~buried_triangles(scene, verts, tri_n)  # inside a solid: never visible (§5)
    near = build_near_field(verts[seen], tri_n[seen], tri_B[seen],
                            points=None if points is None else points[0], alpha=alpha,
                            cell_size=settings.near_cell_rel * alpha,
                            normals=None if points is None else points[1])
    return CachePrepass(scale=scale, lambertian=lambertian, alpha=alpha, patches=patches,
                        elements=elements, solution=solution, cache=cache, near=near,
                        split_complete=split_complete, cached=cached, near_merged=merged)
