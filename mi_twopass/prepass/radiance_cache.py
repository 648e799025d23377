r"""Far field of the radiance cache: a sparse field of order-2 SH incident radiance
(Arikan, Forsyth & O'Brien 2005, §4.1).

Steps (:func:`build_radiance_cache`):

1. **Shading points** (§4.1 "we know in advance all the shading points"): camera rays through a
   regular grid of film positions, followed through delta (specular) bounces to the first
   non-delta hit (:func:`collect_shading_points`).
2. **Clusters**: starting from one cluster of all points, a cluster whose bounding sphere
   (about its centroid) has a radius larger than ``alpha`` is split in two by 2-means, until every
   cluster fits or ``max_clusters`` is reached (:func:`cluster_points`; numpy bookkeeping). The
   paper's lazier criterion (split only where gather rays hit geometry inside the sphere) is not
   implemented: flat regions get clusters of size alpha too.
3. **Gather** (eq. 4): per cluster, ``rays_per_cluster`` rays from shading points of the
   cluster drawn at random, uniform over each point's hemisphere, read the coarse solution at the
   hit: the *reflected* radiance B_r/π of the radiosity patch (indirect light only; direct light is
   Mitsuba's emitter sampling at render time). Rays that hit geometry closer than ``alpha`` are
   dropped from the fit: that light is the near field, counted by B_C. A miss reads 0 (an
   environment emitter is direct light).
4. **Fit**: :func:`~mi_twopass.sh.project_least_squares` (Tikhonov-regularised, so one sample or
   a few directions give a smooth, finite fit) → 9 coefficients × RGB per cluster.

At render time :meth:`RadianceCache.coefficients` interpolates the clusters' SH coefficients of
L_F with normalised Gaussian RBF weights (σ = max(cluster radius, alpha/4)), falling back to the
nearest cluster where all weights underflow, and :meth:`RadianceCache.far_field` dots them with
the clamped cosine: :math:`B_D = \overline{\max(N\cdot\omega,0)}\cdot\overline{L_F}` (eq. 3).
The RBF loop visits every cluster per lane (O(K), K ≤ ``max_clusters``): a spatial index over
the clusters is the obvious next step for large K.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import sh

#: delta bounces followed when collecting shading points
MAX_DELTA_BOUNCES = 16


def _mix(seed: int, salt: int) -> int:
    return (int(seed) * 0x9E3779B1 + salt * 0x85EBCA77) & 0x7FFFFFFF


def _count(mask) -> int:
    return int(np.asarray(dr.count(mask)).reshape(-1)[0])


def collect_shading_points(scene, sensor=None, max_points: int = 4096, seed: int = 0):
    """First non-delta hits of camera rays through a jittered grid of ≤ ``max_points`` film
    positions → ``(p (n, 3), normal (n, 3) facing the viewer, rays traced)`` numpy."""
    if sensor is None:
        sensor = scene.sensors()[0]
    size = np.asarray(sensor.film().crop_size(), dtype=np.int64)
    scale = min(1.0, float(np.sqrt(max_points / max(1, size[0] * size[1]))))
    w, h = max(1, int(size[0] * scale)), max(1, int(size[1] * scale))
    rng = np.random.default_rng(_mix(seed, 1))
    iy, ix = np.mgrid[0:h, 0:w]
    u = ((ix.ravel() + rng.random(w * h)) / w).astype(np.float32)
    v = ((iy.ravel() + rng.random(w * h)) / h).astype(np.float32)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(_mix(seed, 2), w * h)
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), mi.Point2f(mi.Float(u), mi.Float(v)),
                               mi.Point2f(0.5, 0.5))
    ctx = mi.BSDFContext()
    active = dr.full(mi.Bool, True, w * h)
    found = dr.full(mi.Bool, False, w * h)
    p = dr.zeros(mi.Point3f, w * h)
    nrm = dr.zeros(mi.Vector3f, w * h)
    rays = 0
    for _ in range(MAX_DELTA_BOUNCES):  # a few bounces over the whole batch, not per lane
        rays += _count(active)
        si = scene.ray_intersect(ray, active)
        active &= si.is_valid()
        bsdf = si.bsdf(ray)
        smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        stop = active & smooth
        n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
        p[stop] = si.p
        nrm[stop] = n
        found |= stop
        bs, _ = bsdf.sample(ctx, si, sampler.next_1d(active), sampler.next_2d(active), active & ~stop)
        active &= ~stop & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        ray = si.spawn_ray(si.to_world(bs.wo))
        if _count(active) == 0:
            break
    keep = np.asarray(found)
    P = np.asarray(p).reshape(3, -1).T[keep] if np.asarray(p).ndim == 2 else np.asarray(p)[keep]
    N = np.asarray(nrm).reshape(3, -1).T[keep] if np.asarray(nrm).ndim == 2 else np.asarray(nrm)[keep]
    return P.astype(np.float64), N.astype(np.float64), rays


def cluster_points(p, alpha: float, max_clusters: int = 256, seed: int = 0):
    """Split clusters of points ``p`` (n, 3) by 2-means while a cluster's bounding radius (about
    its centroid) exceeds ``alpha`` (§4.1) → list of index arrays (one cluster per array)."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return []
    done, todo = [], [np.arange(len(p))]
    while todo:
        ids = todo.pop()
        q = p[ids]
        c = q.mean(axis=0)
        d = np.linalg.norm(q - c, axis=1)
        if d.max() <= alpha or len(ids) < 2 or len(done) + len(todo) + 2 > max_clusters:
            done.append(ids)
            continue
        a = q[np.argmax(d)]
        b = q[np.argmax(np.linalg.norm(q - a, axis=1))]
        centres = np.stack([a, b])
        for _ in range(8):
            lab = np.argmin(((q[:, None, :] - centres[None]) ** 2).sum(-1), axis=1)
            if lab.min() == lab.max():
                break
            centres = np.stack([q[lab == k].mean(axis=0) for k in range(2)])
        if lab.min() == lab.max():  # all points coincide: cannot split
            done.append(ids)
            continue
        todo += [ids[lab == 0], ids[lab == 1]]
    return done


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

    @property
    def count(self) -> int:
        return int(len(self.center))

    @property
    def nbytes(self) -> int:
        return int(self.count * (3 + 1 + 27) * 4)

    def _tables(self):
        """Dr.Jit copies of the field, built once (call outside symbolic loops: the prepass
        does, through :func:`build_radiance_cache`)."""
        if not hasattr(self, "_dr"):
            self._dr = dict(center=mi.Float(self.center.astype(np.float32).ravel()),
                            sigma=mi.Float(np.maximum(self.radius, 0.25 * self.alpha)
                                           .astype(np.float32)),
                            S=mi.Float(self.coeffs.astype(np.float32).ravel()))
            dr.eval(self._dr)
        return self._dr

    def coefficients(self, x, active=True):
        """Interpolated L_F at points ``x``: 9 ``mi.Color3f`` SH coefficients (incident radiance),
        normalised Gaussian RBF weights over all clusters (nearest-cluster fallback), plus the
        constant ``ambient`` radiance in band 0."""
        amb = [float(a) / sh._C00 for a in self.ambient]  # constant L: c_00 = L / Y_00
        if self.count == 0:
            coeffs = [mi.Color3f(0.0) for _ in range(sh.SH_COUNT)]
        else:
            acc, nearest, sum_w = self._interpolate(x, active)
            inv = dr.rcp(dr.maximum(sum_w, 1e-30))
            coeffs = [dr.select(sum_w > 1e-3, a * inv, b) for a, b in zip(acc, nearest)]
        coeffs[0] = coeffs[0] + mi.Color3f(*amb)
        return [dr.select(mi.Bool(active), c, 0.0) for c in coeffs]

    def far_field(self, x, n, active=True, coeffs=None):
        """B_D (``mi.Color3f``, irradiance W/m², clamped ≥ 0) at points ``x`` with unit normals
        ``n``: the interpolated SH (``coeffs``, else :meth:`coefficients`) dotted with the clamped
        cosine (eq. 3)."""
        if coeffs is None:
            coeffs = self.coefficients(x, active)
        E = sh.irradiance(coeffs, mi.Vector3f(n))
        return dr.select(mi.Bool(active), dr.maximum(E, 0.0), 0.0)

    @dr.syntax
    def _interpolate(self, x, active):
        """Σ_k w_k S_k / Σ_k w_k over all clusters (Gaussian RBF), nearest cluster fallback."""
        K = self.count
        t = self._tables()
        x = mi.Point3f(x)
        active = mi.Bool(active)
        sum_w = mi.Float(0.0)
        acc = [mi.Color3f(0.0) for _ in range(sh.SH_COUNT)]
        best_d = mi.Float(3e38)
        best = mi.UInt32(0)
        k = mi.UInt32(0)
        while dr.hint(active & (k < K), label="radiance_cache_rbf"):
            c = dr.gather(mi.Point3f, t["center"], k)
            s = dr.gather(mi.Float, t["sigma"], k)
            rel = dr.squared_norm(x - c) / dr.square(s)
            w = dr.exp(-0.5 * rel)
            closer = rel < best_d
            best_d = dr.select(closer, rel, best_d)
            best = dr.select(closer, k, best)
            use = active & (w > 1e-4)
            acc = _accumulate(acc, t["S"], k, dr.select(use, w, 0.0), use)
            sum_w += dr.select(use, w, 0.0)
            k += 1
        nearest = _accumulate([mi.Color3f(0.0) for _ in range(sh.SH_COUNT)], t["S"], best,
                              mi.Float(1.0), active)
        return acc, nearest, sum_w

    @dr.syntax
    def near_centre(self, x, radius, active=True):
        """``mi.Bool``: a cluster centre lies within ``radius`` of ``x`` (debug "samples")."""
        K = self.count
        t = self._tables()
        x = mi.Point3f(x)
        active = mi.Bool(active) & (K > 0)
        hit = mi.Bool(False)
        k = mi.UInt32(0)
        while dr.hint(active & (k < K), label="radiance_cache_near_centre"):
            c = dr.gather(mi.Point3f, t["center"], k)
            hit |= dr.squared_norm(x - c) < radius * radius
            k += 1
        return hit


def gather_far_field(scene, solution, p, n, clusters, alpha, rays_per_cluster=128, seed=0,
                     reg=sh.DEFAULT_REG):
    """Eq. 4: per cluster, ``rays_per_cluster`` gather rays from random shading points of the
    cluster (uniform hemisphere) read B_r/π of the patch hit; hits closer than ``alpha`` are left
    out (near field). → ``(coeffs (K, 9, 3), rays traced)``."""
    K = len(clusters)
    coeffs = np.zeros((K, sh.SH_COUNT, 3))
    if K == 0 or rays_per_cluster < 1:
        return coeffs, 0
    rng = np.random.default_rng(_mix(seed, 3))
    m = int(rays_per_cluster)
    src = np.concatenate([ids[rng.integers(0, len(ids), m)] for ids in clusters])
    owner = np.repeat(np.arange(K), m)
    o, nn = p[src], n[src]
    # uniform hemisphere about nn: local (x, y, z) then the frame of nn
    u1, u2 = rng.random(len(src)), rng.random(len(src))
    z = u1
    r = np.sqrt(np.maximum(0.0, 1 - z * z))
    phi = 2 * np.pi * u2
    tmp = np.where(np.abs(nn[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    s = np.cross(nn, tmp)
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    t = np.cross(nn, s)
    d = (r * np.cos(phi))[:, None] * s + (r * np.sin(phi))[:, None] * t + z[:, None] * nn
    eps = 1e-4 * max(1e-6, float(dr.norm(scene.bbox().extents()))) + 1e-5 * np.abs(o).max()
    f = lambda a: mi.Vector3f(*(mi.Float(a[:, k].astype(np.float32)) for k in range(3)))  # noqa
    ray = mi.Ray3f(mi.Point3f(f(o + eps * nn)), f(d))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    L = solution.reflected_radiance(si, valid)
    dist = np.asarray(dr.select(valid, si.t, np.inf))
    L = np.asarray(L)
    L = L.reshape(3, -1).T if L.shape[0] == 3 and L.ndim == 2 else L
    far = ~np.isfinite(dist) | (dist >= alpha)
    L = np.where(np.isfinite(L), L, 0.0)
    for k in range(K):  # a few hundred small least-squares fits: numpy bookkeeping
        sel = (owner == k) & far
        coeffs[k] = sh.project_least_squares(d[sel], L[sel], reg=reg)
    return coeffs, len(src)


def build_radiance_cache(scene, solution, alpha, sensor=None, max_points=4096,
                         max_clusters=256, rays_per_cluster=128, seed=0, ambient=0.0,
                         fake_gi=False):
    """Steps 1–4 of the module docstring → :class:`RadianceCache`. ``fake_gi``: no shading
    points and no gather, only the constant ``ambient`` radiance (§8.1)."""
    amb = np.broadcast_to(np.asarray(ambient, dtype=np.float64), (3,)).copy()
    if fake_gi or solution is None:
        return RadianceCache(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 9, 3)), float(alpha),
                             amb, np.zeros((0, 3)), 0)
    p, n, shading_rays = collect_shading_points(scene, sensor, max_points, seed)
    clusters = cluster_points(p, alpha, max_clusters, seed)
    coeffs, rays = gather_far_field(scene, solution, p, n, clusters, alpha, rays_per_cluster, seed)
    center = np.array([p[ids].mean(axis=0) for ids in clusters]).reshape(-1, 3)
    radius = np.array([np.linalg.norm(p[ids] - p[ids].mean(axis=0), axis=1).max()
                       for ids in clusters]).reshape(-1)
    cache = RadianceCache(center, radius, coeffs, float(alpha), amb, p, rays, shading_rays)
    cache._tables()
    return cache
