"""Radiosity of the patches by stochastic shooting (particle tracing, collision estimator).

Zimmerman & Shirley (1995) §3.3 step 2 (GSII, §2.5): "perform radiosity solution with the coarse
mesh". The radiosity equation of a diffuse patch i,

    B_i = π·Le_i + ρ_i · E_i,      E_i = (1/A_i) Σ_j B_j A_j F_ji,

is solved by Monte Carlo light tracing instead of form factors and a linear solve:

1. ``n_particles`` particles leave the emitters as ``scene.sample_emitter_ray`` would have them
   (``scene.sample_emitter``, then the emitter's ``sample_ray``: point, spot, projector,
   directional, constant and envmap emitters; infinite ones start on the scene's bounding sphere
   and carry the flux through it, which the sky test checks). Area emitters are sampled here with
   ``sample_position`` + a cosine direction, so the ray leaves the surface with a scene-relative
   offset instead of Mitsuba's absolute one (which would skip geometry in a 1e-3 m scene). Each
   particle carries flux Φ = weight / n_particles [W].
2. A particle hitting patch i deposits its flux there (collision estimator: E_i = ΣΦ / A_i
   estimates the irradiance, direct light included), then scatters by the hit's *own* BSDF
   (``bsdf.sample`` in importance mode; delta, glossy and null surfaces are followed exactly) and
   survives Russian roulette with probability q = min(1, max(bsdf weight)) — the albedo for a
   diffuse surface — its flux scaled by weight/q. Particles so keep their power; the expected path
   length is 1/(1−ρ).
3. B_reflected = ρ·E and B_emitted = π·Le (``mi_twopass.units``); the two are kept apart because
   the gather needs the reflected part alone.

Why particles rather than form factors + a linear solve (or progressive refinement): form
factors cost O(N²) visibility rays for N patches (17M rays at N = 4096 before the first
bounce), must be recomputed for every emitter type that is not a patch (point, spot, sun, sky),
and get singular for adjacent patches (the "point in a corner" hard case). Shooting particles
costs O(particles × mean path length), handles every Mitsuba emitter and every BSDF the same way,
needs no form factor, and its error is a plain Monte Carlo standard error per patch (the tests
use it). Its cost: noise of O(1/√(particles per patch)) and no exploitation of the linear system.

Bias: a path is cut after ``max_bounces`` surface interactions; the flux still carried then is
reported as ``flux_truncated`` (the energy missing from the solution). With RR by albedo the
cut-off removes a fraction ρ^max_bounces of the light in a closed enclosure of albedo ρ
(4e-5 at ρ = 0.99 with the default 1024); at ρ = 1 it is what bounds the run time.
A bounce ray starts 1e-5·(bbox diagonal + |p|) off the surface and 1e-4 of the way towards its
patch's centre (a hit exactly on a cube's edge would otherwise start on the neighbouring face's
plane and leak out): a displacement far below the patch size.

Vectorisation: particles are traced in batches (``batch_size``) as one wavefront; a symbolic
``dr.while_loop`` runs ``_CHUNK`` bounces per kernel, then the survivors are compacted
(``dr.compress``), so the long tail of RR paths at ρ ≈ 1 costs no idle SIMD lanes. Deposits
are ``dr.scatter_reduce`` additions into 64-bit fixed point (2^-28 of the batch's largest particle
flux), so the sums, hence the solution, are the same bit for bit for the same seed whatever the
order of the atomic additions (and whatever ``batch_size``, up to that rounding). They are
plain atomics (``dr.ReduceMode.Direct``): the deposits spread over thousands of receivers, so
they rarely contend, and the LLVM backend's default for small targets (``Expand``: a copy of
the target per thread, merged after every kernel) made the solve slower (Cornell box, 256²:
0.087 s against 0.110 s, median of four solves, ``tools/solve_timing.py --mode``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import units
from ..host_arrays import component_sums, id_table, jit
from ..progress import progress as progress_bar
from ..rays import spawn_ray
from ..scene.bounds import scene_bounds
from ..scene.emission import emitter_kinds, emitter_rays
from ..scene.patches import Patches, build_patches, scene_shapes
from ..scenefile import load_scene
from ..seeds import splitmix64
from . import emission_guide
from .element_grid import ElementFrames, ElementGrid, cell_areas, refinable

#: default cap on surface interactions per particle (see the module docstring for its bias)
DEFAULT_MAX_BOUNCES = 1024
#: default particles per patch when ``n_particles`` is not given
PARTICLES_PER_PATCH = 256
#: bounces traced per symbolic loop before the surviving particles are compacted
_CHUNK = 64
#: how the deposits' scatter-additions are compiled (module docstring)
_DEPOSIT_MODE = dr.ReduceMode.Direct
_FIXED_BITS = 28  # fixed-point resolution of a deposit relative to the largest particle flux
_FIXED_CLAMP = float(2 ** 34)
_NUDGE = 1e-4  # fraction of the way to the patch centre a bounce ray's origin moves


@dataclass
class RadiositySolution:
    """Radiosity of every patch (W/m²), emitted and reflected apart, plus the solver's stats."""

    patches: Patches
    B_emitted: np.ndarray  # (N, 3) π·Le
    B_reflected: np.ndarray  # (N, 3) ρ·E
    E: np.ndarray  # (N, 3) irradiance
    rays: int
    seconds: float
    particles: int
    max_bounces: int
    flux_emitted: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) W
    flux_absorbed: np.ndarray = field(default_factory=lambda: np.zeros(3))
    flux_escaped: np.ndarray = field(default_factory=lambda: np.zeros(3))
    flux_truncated: np.ndarray = field(default_factory=lambda: np.zeros(3))
    elements: Patches | None = None  # finer receiving mesh (Cohen et al. 1986), or None
    E_elements: np.ndarray | None = None  # (M, 3) irradiance of the elements
    B_reflected_elements: np.ndarray | None = None  # (M, 3) ρ_e·E_e
    #: the unevenly lit flat elements refined into cells (:mod:`.element_grid`), or None
    grid: ElementGrid | None = None
    _L_reflected: object = field(default=None, repr=False)
    _L_total: object = field(default=None, repr=False)
    _L_elements: object = field(default=None, repr=False)

    def __post_init__(self):
        def table(B):
            return id_table(units.radiance_from_radiosity(B), mi.Color3f)

        self._L_reflected = table(self.B_reflected)
        self._L_total = table(self.B_emitted + self.B_reflected)
        if self.elements is not None:
            self._L_elements = table(self.B_reflected_elements)

    @property
    def B(self) -> np.ndarray:
        """Total radiosity B_emitted + B_reflected (N, 3)."""
        return self.B_emitted + self.B_reflected

    def patch_reflected_radiance(self, patch_ids, active=True):
        """B_reflected/π of patches by id (0 for the invalid id ``patches.count``)."""
        return dr.gather(mi.Color3f, self._L_reflected, patch_ids, active)

    def cached_at(self, si, active=True):
        """``mi.Bool``: the solution represents the radiance leaving ``si`` towards its ray —
        the receiver hit (the element, with elements, else the patch) is purely diffuse on the
        side hit, not cut by geometry (:func:`mi_twopass.scene.patches.build_patches`) and not
        unevenly lit (:func:`receiver_spread`). Elsewhere a gather traces on.

        With elements only the element decides: the far gather reads the element's value, not
        its patch's, so whether the patch around it is cut does not matter. Requiring both (as
        before 2026-11-25) sent 41–52 % of the office's first gather rays on as paths because
        their patch was cut (40 % of the patch area, 11 % of the element area), and radiosity_gather's
        indirect noise per sample was twice what it is with the element's rule."""
        return self.receiver_cached(self.receiver_at(si, active), active)

    def reflected_radiance(self, si, active=True):
        """B_reflected/π at ``si`` (``mi.Color3f``), 0 where there is no patch.

        With ``elements`` the value of the element hit (the finer receiving mesh: the far gather
        reads it, see :func:`solve_radiosity`; its cell's on a refined element, :attr:`grid`),
        else the patch's."""
        return self.receiver_reflected_radiance(self.receiver_at(si, active), active, si.p)

    # the receiver hit, looked up once per vertex: cached_at and reflected_radiance read it
    def receiver_at(self, si, active=True):
        """Id of the receiver hit by ``si``: its element with elements, else its patch (the
        count, an invalid id, where none). A gather loop looks it up once and asks both
        :meth:`receiver_cached` and :meth:`receiver_reflected_radiance` (each lookup is a
        dozen gathers)."""
        receivers = self.elements if self.elements is not None else self.patches
        return receivers.lookup(si, active)

    def receiver_cached(self, rid, active=True):
        """:meth:`cached_at` of the receiver ``rid`` (:meth:`receiver_at`): diffuse, uncut and
        evenly lit, or refined into cells (:attr:`grid`; read with the point hit)."""
        receivers = self.elements if self.elements is not None else self.patches
        cached = receivers.gather("is_diffuse", rid, active)
        if self.elements is not None and self.grid is not None and self.grid.count:
            cached |= self.grid.refined(rid, active)
        return cached

    def receiver_reflected_radiance(self, rid, active=True, p=None):
        """:meth:`reflected_radiance` of the receiver ``rid`` (:meth:`receiver_at`): with
        ``p``, the point hit, the value of its cell on an element refined into a grid
        (:attr:`grid`, the unevenly lit flat elements), else the element's mean."""
        if self.elements is not None:
            mean = dr.gather(mi.Color3f, self._L_elements, rid, active)
            if p is None or self.grid is None or not self.grid.count:
                return mean
            return self.grid.reflected_radiance(rid, p, mean, active)
        return self.patch_reflected_radiance(rid, active)

    def radiosity(self, si, active=True):
        """Total radiosity B of the patch at ``si`` (W/m², for debug views), 0 where none."""
        pid = self.patches.lookup(si, active)
        return dr.gather(mi.Color3f, self._L_total, pid, active) * math.pi

    @property
    def nbytes(self) -> int:
        own = sum(v.nbytes for v in (self.B_emitted, self.B_reflected, self.E))
        total = own + 2 * 12 * (self.patches.count + 1) + self.patches.nbytes
        if self.elements is not None:
            total += self.E_elements.nbytes + self.B_reflected_elements.nbytes \
                + 12 * (self.elements.count + 1) + self.elements.nbytes
        if self.grid is not None:
            total += self.grid.nbytes
        return int(total)


# ----------------------------------------------------------------------------------------------


def _sample_emission(scene, bounds, rng, active, guide=None):
    """Particles leaving the emitters: (ray origin, direction, flux weight, cell) for each
    lane, built by :func:`mi_twopass.scene.emission.emitter_rays` (infinite emitters from a disk
    around ``bounds``, the geometry's own bounds). The emitter and its (u2, u3) samples are
    Mitsuba's choice, or drawn from ``guide`` (:mod:`mi_twopass.prepass.emission_guide`;
    ``cell``: the guide's cell, else 0)."""
    u1 = rng.next_float32()
    u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
    u3 = mi.Point2f(rng.next_float32(), rng.next_float32())
    if guide is None:
        index, sel_weight, _ = scene.sample_emitter(u1, active)
        cell = dr.zeros(mi.UInt32, dr.width(u1))
    else:
        cell, index, sel_weight, _, u2, u3 = guide.sample(u1, u2, u3, active)
    ray, weight = emitter_rays(scene, bounds, index, u2, u3, active)
    w = weight * sel_weight
    w = dr.select(active & dr.all(dr.isfinite(w)), w, 0.0)
    return ray.o, ray.d, mi.Color3f(w), cell


def _trace_batch(scene, patches, n, first_index, seed, n_total, max_bounces, elements=None,
                 guide=None, importance=None, bounds=None, deposit_flux=True, reads=None,
                 frames=None):
    """Trace ``n`` particles; returns (deposits (N+1, 3) float64, element deposits (M+1, 3)
    or None, accounting dict, rays). ``guide``: where particles start
    (:mod:`mi_twopass.prepass.emission_guide`), else as Mitsuba samples emitter rays.
    ``importance``: per receiver (+1 sentinel), a weight; the accounting then holds each
    particle's ``cell`` and ``score``, the importance-weighted mean flux of all its deposits.
    ``reads`` (with ``importance``): the camera's :class:`~.emission_guide.CameraImportance`,
    whose ``read`` weights all deposits into ``read_score`` and ``first`` a particle's first
    deposit into ``first_score`` (:func:`~.emission_guide.image_noise`).
    ``bounds``: :func:`mi_twopass.scene.bounds.scene_bounds` of ``scene`` (computed when
    ``None``). ``deposit_flux=False`` (the emission guide's pilot, which reads only ``cell`` and
    ``score``): nothing is deposited, and the deposits, the element deposits and the receivers'
    moments come back as ``None``. ``frames`` (with ``elements``): their
    :class:`~.element_grid.ElementFrames`; each element deposit lands in its cell too, and
    the accounting holds ``cell_flux`` (M, K²), the channel mean of the flux."""
    N = patches.count
    M = elements.count if elements is not None else 0
    # seed, offset and scale are opaque: as literals they would make every seed (every fresh
    # prepass) compile the particle kernel anew
    idx = dr.arange(mi.UInt64, n) + dr.opaque(mi.UInt64, first_index)
    rng = mi.PCG32(size=n, initstate=dr.opaque(mi.UInt64, splitmix64(seed)), initseq=idx)
    active = dr.full(mi.Bool, True, n)
    if bounds is None:
        bounds = scene_bounds(scene)
    o, d, flux, cell = _sample_emission(scene, bounds, rng, active, guide)
    flux = flux * dr.opaque(mi.Float, 1.0 / n_total)
    lane = dr.arange(mi.UInt32, n)
    score = dr.zeros(mi.Float, n)
    dr.make_opaque(score)
    importance_t = jit(mi.Float, np.asarray(importance, np.float32)) if importance is not None \
        else None
    read_t = first_t = read_score = first_score = None
    if importance is not None and reads is not None:
        read_t = jit(mi.Float, np.asarray(reads.read, np.float32))
        first_t = jit(mi.Float, np.asarray(reads.first, np.float32))
        read_score, first_score = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
        dr.make_opaque(read_score, first_score)
    dr.eval(o, d, flux, rng)

    # reduced in Dr.Jit: np.array of a Color3f copies it in a kernel with its width as a
    # literal, and a batch's width follows the seed (guided particle counts)
    emitted = component_sums(flux)[0]
    peak = float(np.asarray(dr.max(dr.max(flux))).reshape(-1)[0]) if n else 0.0
    result = dict(emitted=emitted, absorbed=np.zeros(3), escaped=np.zeros(3),
                  truncated=np.zeros(3))
    deposits = np.zeros((N + 1, 3))
    if not (peak > 0 and math.isfinite(peak)):
        R = (elements if elements is not None else patches).count
        result.update(moments=np.zeros((R, 3)), normal_moments=np.zeros((R, 3)),
                      cell_flux=np.zeros((M, frames.res ** 2)) if frames is not None and M
                      else None,
                      deposit_count=np.zeros(R, np.int64), deposit_w2=np.zeros(R),
                      cell=np.asarray(cell, np.int64), score=np.zeros(n))
        return deposits, (np.zeros((M + 1, 3)) if elements is not None else None), result, 0
    quantum = 2.0 ** (math.ceil(math.log2(peak)) - _FIXED_BITS)
    inv_quantum = dr.opaque(mi.Float64, 1.0 / quantum)
    # the squared deposits (receiver_spread's effective count) on their own fixed-point scale
    quantum_w2 = 2.0 ** (math.ceil(math.log2(peak * peak)) - _FIXED_BITS)
    inv_quantum_w2 = dr.opaque(mi.Float64, 1.0 / quantum_w2)
    # where on the receiving mesh (the elements, else the patches) the flux lands: Σ w·(p − c)/r
    # and the number of deposits per receiver (receiver_spread)
    recv = elements if elements is not None else patches
    R = recv.count
    if deposit_flux:
        target = dr.zeros(mi.Int64, 3 * (N + 1))
        target_e = dr.zeros(mi.Int64, 3 * (M + 1)) if elements is not None else None
        recv_inv_r = frames.inv_radius_table if frames is not None and elements is not None \
            else jit(mi.Float, np.append(1.0 / np.maximum(receiver_radius(recv), 1e-30), 0.0)
                              .astype(np.float32))
        target_m = dr.zeros(mi.Int64, 3 * (R + 1))
        target_nrm = dr.zeros(mi.Int64, 3 * (R + 1))
        target_n = dr.zeros(mi.UInt32, R + 1)
        target_w2 = dr.zeros(mi.Int64, R + 1)
    K2 = frames.res ** 2 if (frames is not None and elements is not None and deposit_flux) else 0
    if K2:
        target_c = dr.zeros(mi.Int64, M * K2 + 1)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)

    active = dr.max(flux) > 0
    depth = dr.zeros(mi.UInt32, n)
    absorbed = dr.zeros(mi.Color3f, n)
    escaped = dr.zeros(mi.Color3f, n)

    def deposit(tgt, slot, value, mask):
        for c, comp in enumerate((value.x, value.y, value.z)):
            q = dr.clip(dr.round(mi.Float64(comp) * inv_quantum), -_FIXED_CLAMP, _FIXED_CLAMP)
            dr.scatter_reduce(dr.ReduceOp.Add, tgt, mi.Int64(q), slot * 3 + c, mask,
                              mode=_DEPOSIT_MODE)

    def cond(o, d, flux, depth, rng, active, absorbed, escaped, lane, chunk_end):
        return active & (depth < chunk_end)

    def body(o, d, flux, depth, rng, active, absorbed, escaped, lane, chunk_end):
        ray = mi.Ray3f(o, d)
        si = scene.ray_intersect(ray, mi.RayFlags.All, False, active)
        hit = active & si.is_valid()
        escaped = dr.select(active & ~hit, escaped + flux, escaped)
        pid = patches.lookup(si, hit)
        if deposit_flux:
            deposit(target, pid, flux, hit & (pid < N))
        rid = pid
        if elements is not None:
            rid = elements.lookup(si, hit)
            if deposit_flux:
                deposit(target_e, rid, flux, hit & (rid < M))
        at_recv = hit & (rid < R)
        flux_mean = units.channel_mean(flux)
        if deposit_flux:
            offset = (si.p - recv.gather("center", rid, at_recv)) \
                * dr.gather(mi.Float, recv_inv_r, rid, at_recv)
            deposit(target_m, rid, offset * flux_mean, at_recv)
            if K2:
                # one channel: a cell takes its element's colour (ElementGrid)
                q = dr.clip(dr.round(mi.Float64(flux_mean) * inv_quantum), -_FIXED_CLAMP,
                            _FIXED_CLAMP)
                dr.scatter_reduce(dr.ReduceOp.Add, target_c, mi.Int64(q),
                                  rid * K2 + frames.cell_of_offset(rid, offset, at_recv),
                                  at_recv, mode=_DEPOSIT_MODE)
            # the normal of the receiver's side (the side the particle arrives on)
            side_n = dr.select(dr.dot(ray.d, si.n) < 0, si.n, -si.n)
            deposit(target_nrm, rid, side_n * flux_mean, at_recv)
            dr.scatter_reduce(dr.ReduceOp.Add, target_n, mi.UInt32(1), rid, at_recv,
                              mode=_DEPOSIT_MODE)
            w2 = dr.clip(dr.round(mi.Float64(dr.square(flux_mean)) * inv_quantum_w2), 0.0,
                         _FIXED_CLAMP)
            dr.scatter_reduce(dr.ReduceOp.Add, target_w2, mi.Int64(w2), rid, at_recv,
                              mode=_DEPOSIT_MODE)
        if importance_t is not None:
            # each lane adds to its own slot; Expand (the LLVM default for a small target)
            # would bake the batch's width into the kernel, a kernel per guide pilot size
            dr.scatter_reduce(dr.ReduceOp.Add, score,
                              flux_mean * dr.gather(mi.Float, importance_t, rid, at_recv),
                              lane, at_recv, mode=dr.ReduceMode.Direct)
        if read_t is not None:
            dr.scatter_reduce(dr.ReduceOp.Add, read_score,
                              flux_mean * dr.gather(mi.Float, read_t, rid, at_recv),
                              lane, at_recv, mode=dr.ReduceMode.Direct)
            dr.scatter_reduce(dr.ReduceOp.Add, first_score,
                              flux_mean * dr.gather(mi.Float, first_t, rid, at_recv),
                              lane, at_recv & (depth == 0), mode=dr.ReduceMode.Direct)

        bsdf = si.bsdf(ray)
        u1 = rng.next_float32()
        u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
        u_rr = rng.next_float32()
        bs, w = bsdf.sample(ctx, si, u1, u2, hit)
        w = dr.select(hit & (bs.pdf > 0) & dr.all(dr.isfinite(w)), w, 0.0)
        absorbed = dr.select(hit, absorbed + flux * (1.0 - w), absorbed)
        q = dr.minimum(dr.max(w), 1.0)
        survive = hit & (q > 0) & (u_rr < q)
        flux = dr.select(survive, flux * w / dr.maximum(q, 1e-30), 0.0)
        d_new = si.to_world(bs.wo)
        side = dr.select(dr.dot(d_new, si.n) >= 0, 1.0, -1.0)
        # off the surface along its normal, and a hair towards the patch's centre: a hit exactly
        # on an edge would otherwise start the next ray on the plane of the neighbouring face
        centre = patches.gather("center", pid, hit & (pid < N))
        nudge = dr.select(hit & (pid < N), (centre - si.p) * _NUDGE, 0.0)
        o_new = si.p + si.n * (side * patches.ray_epsilon(si.p)) + nudge
        o = dr.select(survive, o_new, o)
        d = dr.select(survive, d_new, d)
        depth = dr.select(active, depth + 1, depth)
        return o, d, flux, depth, rng, survive, absorbed, escaped, lane, chunk_end

    rays = 0
    start_depth = 0
    while True:
        chunk_end = dr.opaque(mi.UInt32, min(start_depth + _CHUNK, max_bounces))
        depth_before = int(dr.sum(mi.UInt64(depth))[0]) if dr.width(depth) else 0
        o, d, flux, depth, rng, active, absorbed, escaped, lane, _ = dr.while_loop(
            (o, d, flux, depth, rng, active, absorbed, escaped, lane, chunk_end), cond, body,
            label="radiosity_particles", mode="symbolic")
        dr.eval(o, d, flux, depth, rng, active, absorbed, escaped, lane, score,
                *((read_score, first_score) if read_t is not None else ()))
        rays += int(dr.sum(mi.UInt64(depth))[0]) - depth_before
        spent = component_sums(absorbed, escaped)
        result["absorbed"] += spent[0]
        result["escaped"] += spent[1]
        start_depth += _CHUNK
        n_alive = int(dr.count(active)[0])
        if n_alive == 0:
            break
        keep = dr.compress(active)
        o, d, flux, depth, lane = (dr.gather(type(x), x, keep)
                                   for x in (o, d, flux, depth, lane))
        rng = dr.gather(mi.PCG32, rng, keep)
        active = dr.full(mi.Bool, True, n_alive)
        absorbed = dr.zeros(mi.Color3f, n_alive)
        escaped = dr.zeros(mi.Color3f, n_alive)
        if start_depth >= max_bounces:
            result["truncated"] += component_sums(flux)[0]
            break

    result["cell"] = np.asarray(cell, np.int64)
    result["score"] = np.asarray(score, np.float64)
    if read_t is not None:
        result["read_score"] = np.asarray(read_score, np.float64)
        result["first_score"] = np.asarray(first_score, np.float64)
    if not deposit_flux:
        result.update(moments=None, normal_moments=None, deposit_count=None, deposit_w2=None)
        return None, None, result, rays
    deposits = np.array(target, dtype=np.int64).reshape(N + 1, 3).astype(np.float64) * quantum
    deposits_e = None
    if elements is not None:
        deposits_e = np.array(target_e, dtype=np.int64).reshape(M + 1, 3).astype(np.float64) \
            * quantum
    result["moments"] = np.array(target_m, dtype=np.int64).reshape(R + 1, 3)[:R] * quantum
    result["normal_moments"] = np.array(target_nrm, dtype=np.int64).reshape(R + 1, 3)[:R] \
        * quantum
    result["deposit_count"] = np.array(target_n, dtype=np.int64)[:R]
    result["cell_flux"] = np.array(target_c, dtype=np.int64)[:M * K2].reshape(M, K2) \
        * quantum if K2 else None
    result["deposit_w2"] = np.array(target_w2, dtype=np.int64)[:R].astype(np.float64) \
        * quantum_w2
    return deposits, deposits_e, result, rays


def _receiving_area(patches, flux):
    """The area E = ΣΦ/A divides by: the exposed ``area`` (see ``mi_twopass.scene.patches``),
    or the geometric area of a patch the exposure probe found buried but that particles reached
    (an open sliver the probe missed: the geometric area is the only estimate left)."""
    area = np.asarray(patches.area, dtype=np.float64)
    geometric = getattr(patches, "geometric_area", None)
    if geometric is None:
        return area
    reached = np.asarray(flux).max(axis=1) > 0
    return np.where((area <= 0) & reached, geometric, area)


#: property / exposure / split-probe samples per receiving element, as many as a patch's: with 4,
#: an element cut by a wall had all its points on one side one time in eight (a 50/50 cut), and
#: its light leaked to the other side (tests/integrators/test_far_gather_correctness.py)
ELEMENT_SAMPLES = 16


def receiving_elements(scene, max_patches: int, elements_per_patch: int, seed: int = 0,
                       shapes=None):
    """The receiving mesh of :func:`solve_radiosity` (Cohen et al. 1986 patch/element
    substructuring): patches of ``elements_per_patch`` × ``max_patches`` budget, each probed at
    ``ELEMENT_SAMPLES`` points; ``None`` for ``elements_per_patch`` ≤ 1 (elements off).
    ``shapes``: :func:`~mi_twopass.scene.patches.scene_shapes` of ``scene``, where the caller
    has them."""
    if int(elements_per_patch) <= 1:
        return None
    return build_patches(scene, max_patches=int(elements_per_patch) * int(max_patches),
                         seed=seed, samples=ELEMENT_SAMPLES, shapes=shapes)


#: a receiver (element, else patch) whose deposited flux covers it unevenly by more than this
#: (:func:`receiver_spread`: the flux centroid's offset in radii, or the flux-weighted normal's
#: turn, beyond the particle noise) is not cached: its irradiance varies strongly across it (a
#: small bright light beside it, a shadow edge, a curved surface whose faces turned towards a
#: light are hidden from the room), so its mean is no stand-in for the irradiance where far
#: gather rays land. veach-bidir: elements of the lamp beside its small bright panel read 1.76×
#: the light the gather rays should see there (their area mean was right: the rays land on the
#: faces turned away), and the far reads of the whole image were 1.058× a path-traced estimate
#: at the same hits (``tools/far_gather_hits.py``); with this bound 1.006–1.010× (±1 %). The
#: receivers it uncaches are at most ~1 % of the receiving area of every scene of scenes_xml/
#: and ../shared/scenes (tut-cbox 1.0 %, caustic 0.8 %, the others ≤ 0.5 %; 0 on the Cornell
#: box, window_interior and the furnace). Chosen from those measurements: the bias left grows
#: as it rises (0.1: 1.017×), the cost (gather rays traced on) as it falls.
SPREAD_MAX = 0.05
#: the noise floor of that offset: about 0.57 / sqrt(deposits) for uniform irradiance (the
#: deposits' offsets, in units of the radius, have a spread of about 0.4 per axis); an offset
#: counts only beyond this many times it
SPREAD_Z = 4.0


def receiver_radius(recv) -> np.ndarray:
    """Per patch: the largest distance of its triangles' vertices from its centre."""
    radius = np.zeros(recv.count)
    if recv.count and len(recv.tri_patch):
        tp = np.asarray(recv.tri_patch, np.int64)
        tv = np.asarray(recv.tri_vertices, np.float64)
        reach = np.linalg.norm(tv - np.asarray(recv.center)[tp][:, None, :], axis=2).max(axis=1)
        np.maximum.at(radius, tp, reach)
    return radius


def mean_normals(recv) -> np.ndarray:
    """Per patch: the area-weighted mean of its triangles' normals (on its own side); its
    length is 1 on a flat patch, less on a curved one."""
    out = np.zeros((recv.count, 3))
    if recv.count and len(recv.tri_patch):
        tp = np.asarray(recv.tri_patch, np.int64)
        tv = np.asarray(recv.tri_vertices, np.float64)
        a = 0.5 * np.linalg.norm(np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), axis=1)
        for c in range(3):
            out[:, c] = np.bincount(tp, weights=a * np.asarray(recv.tri_normal)[:, c],
                                    minlength=recv.count)
        total = np.bincount(tp, weights=a, minlength=recv.count)
        out /= np.where(total > 0, total, 1.0)[:, None]
    return out


def effective_count(flux, sum_w2, count) -> np.ndarray:
    """Per receiver: the effective number of its deposits, n_eff = (Σw)² / Σw², w a deposit's
    (channel-mean) flux: the count whose equal-weight noise the weighted centroid has. Particles
    of unequal flux (a sun's and a small lamp's, or after roulette) make it far smaller than the
    count; counting every deposit as one set receiver_spread's noise floor too low where one
    heavy particle landed, uncached exactly the receivers that had drawn more light than their
    share and left the far gather reading the others, 7.5 % dark on scenes_xml/mixed_room.xml
    (``tools/far_gather_hits.py``; 0.98 with no receiver uncached). ``count`` where Σw² is 0
    (deposits below its fixed-point resolution)."""
    n_eff = np.where(sum_w2 > 0, flux ** 2 / np.where(sum_w2 > 0, sum_w2, 1.0), count)
    return np.minimum(n_eff, count)


def receiver_spread(moments, normal_moments, count, flux, area_normal) -> np.ndarray:
    """Per receiver: how unevenly its deposited flux covers it, beyond the particle noise — the
    larger of (1) the distance of the flux centroid from the receiver's centre in units of its
    radius, |Σ w·(p − c)/r| / Σ w (a gradient across it), and (2) the distance of the flux-
    weighted mean normal from the area-weighted mean normal, |Σ w·n / Σ w − n̄| (on a curved
    receiver: light arriving on the faces turned towards a light), each less SPREAD_Z times
    its noise (0.57 / sqrt(deposits); for (2) scaled by the receiver's curvature,
    sqrt(1 − |n̄|²)); ``count``: the deposits, effective ones where their fluxes differ
    (:func:`effective_count`); 0 where nothing landed."""
    w = np.where(flux > 0, flux, 1.0)
    root_n = np.sqrt(np.maximum(count, 1))
    offset = np.linalg.norm(moments, axis=1) / w - SPREAD_Z * 0.57 / root_n
    bend = np.sqrt(np.maximum(1.0 - np.sum(area_normal ** 2, axis=1), 0.0))
    turn = np.linalg.norm(normal_moments / w[:, None] - area_normal, axis=1) \
        - SPREAD_Z * bend / root_n
    spread = np.maximum(np.maximum(offset, turn), 0.0)
    return np.where((flux > 0) & (count > 0), spread, 0.0)


def solve_radiosity(scene, patches: Patches | None = None, n_particles: int | None = None,
                    seed: int = 0, max_bounces: int = DEFAULT_MAX_BOUNCES, progress: bool = True,
                    batch_size: int = 1 << 18, elements: Patches | None = None,
                    guide=None) -> RadiositySolution:
    """Stochastic shooting radiosity of ``patches`` (built with defaults when ``None``).

    ``elements``: a finer patch mesh of the same scene (``build_patches`` with a larger budget)
    that receives the same particles — the patch/element substructuring of Cohen, Greenberg,
    Immel & Brock (1986). Each hit deposits its flux in its patch *and* its element, so the
    patch solution is unchanged and ``E_elements`` / ``B_reflected_elements`` resolve the
    irradiance inside patches; :meth:`RadiositySolution.reflected_radiance` reads them. Why the
    far gather needs them: a patch value is the *area* mean of E over the patch, but gather rays
    do not land uniformly in area — the parts of a patch open to the room (where gather rays
    come from) are also the parts the light reaches, the parts under a desk or behind a
    partition are dark and rarely hit. Irradiance and hit density covary positively inside
    every patch, so the area mean reads dark, by an amount proportional to the patch edge
    (office: 12 % of the one-bounce indirect at 1024 patches). Elements shrink the edge without
    more particles: the per-element noise is averaged by the many gather rays of a pixel, the
    bias is not.

    ``guide``: where the particles start (:func:`guide_emission`), else as Mitsuba samples
    emitter rays.

    ``n_particles`` defaults to ``PARTICLES_PER_PATCH`` × patch count (at least 2^16). Same seed,
    same solution bit for bit. A scene without emitters (or with emitters of zero power) gives
    B_reflected = 0 and no error."""
    if patches is None:
        patches = build_patches(scene, seed=seed)
    if n_particles is None:
        n_particles = max(1 << 16, PARTICLES_PER_PATCH * patches.count)
    n_particles, max_bounces = int(n_particles), int(max_bounces)
    if n_particles < 1:
        raise ValueError(f"n_particles={n_particles}: must be >= 1")
    if max_bounces < 1:
        raise ValueError(f"max_bounces={max_bounces}: must be >= 1")
    batch_size = max(1, int(batch_size))
    N = patches.count
    t0 = time.perf_counter()
    flux = np.zeros((N + 1, 3))
    flux_e = np.zeros((elements.count + 1, 3)) if elements is not None else None
    acc = dict(emitted=np.zeros(3), absorbed=np.zeros(3), escaped=np.zeros(3),
               truncated=np.zeros(3))
    recv = elements if elements is not None else patches
    moments = np.zeros((recv.count, 3))
    normal_moments = np.zeros((recv.count, 3))
    deposit_count = np.zeros(recv.count, np.int64)
    deposit_w2 = np.zeros(recv.count)
    frames = ElementFrames(elements) if elements is not None else None
    cell_flux = np.zeros((elements.count, frames.res ** 2)) if elements is not None else None
    rays = 0
    traced = 0
    if len(scene.emitters()) > 0 and N >= 0:
        bounds = scene_bounds(scene)
        with progress_bar(total=n_particles, desc="radiosity", unit="particle",
                          show=progress) as bar:
            for first in range(0, n_particles, batch_size):
                n = min(batch_size, n_particles - first)
                try:
                    deposits, deposits_e, result, batch_rays = _trace_batch(
                        scene, patches, n, first, seed, n_particles, max_bounces, elements,
                        guide, bounds=bounds, frames=frames)
                except (RuntimeError, NotImplementedError) as exc:
                    names = ", ".join(sorted({e.class_name() for e in scene.emitters()}))
                    raise RuntimeError(
                        f"solve_radiosity: tracing particles from the emitters ({names}) failed: "
                        f"{exc}. An emitter that cannot sample rays (sample_ray) is not supported "
                        "by the radiosity prepass: remove or replace it.") from exc
                flux += deposits
                if elements is not None:
                    flux_e += deposits_e
                for k in acc:
                    acc[k] += result[k]
                moments += result["moments"]
                normal_moments += result["normal_moments"]
                deposit_count += result["deposit_count"]
                deposit_w2 += result["deposit_w2"]
                if result.get("cell_flux") is not None:
                    cell_flux += result["cell_flux"]
                rays += batch_rays
                traced += n
                bar.update(n)
    dr.sync_thread()
    seconds = time.perf_counter() - t0
    recv_flux = (flux_e if elements is not None else flux)[:recv.count].mean(axis=1)
    was_diffuse = np.asarray(recv.is_diffuse, dtype=bool).copy()
    area_normal = mean_normals(recv)
    uneven = receiver_spread(moments, normal_moments, effective_count(recv_flux, deposit_w2,
                                                                      deposit_count),
                             recv_flux, area_normal) > SPREAD_MAX
    recv.uncache(uneven)
    E = units.irradiance_from_flux(flux[:N], _receiving_area(patches, flux[:N]))
    extra = {}
    if elements is not None:
        E_e = units.irradiance_from_flux(flux_e[:elements.count],
                                         _receiving_area(elements, flux_e[:elements.count]))
        bend = np.sqrt(np.maximum(1.0 - np.sum(area_normal ** 2, axis=1), 0.0))
        refine = refinable(elements, uneven & was_diffuse, bend)
        grid = ElementGrid(elements, frames, refine, cell_flux[refine],
                           cell_areas(elements, frames, refine), E_e[refine])
        extra = dict(elements=elements, E_elements=E_e, grid=grid,
                     B_reflected_elements=units.reflected_radiosity(elements.albedo, E_e))
    return RadiositySolution(
        patches=patches,
        B_emitted=units.radiosity_from_radiance(patches.Le),
        B_reflected=units.reflected_radiosity(patches.albedo, E),
        E=E, rays=int(rays), seconds=seconds, particles=traced, max_bounces=max_bounces,
        flux_emitted=acc["emitted"], flux_absorbed=acc["absorbed"],
        flux_escaped=acc["escaped"], flux_truncated=acc["truncated"], **extra)


#: seed offset of the emission guide's pilot particles (apart from the solve's)
_GUIDE_SEED = 0x5EED
#: the relative standard deviation of the image's mean a guided solve is given particles for
#: (:func:`guided_particles`, :func:`emission_guide.image_noise`): half of the 1 % bound on an
#: image's mean, which a prepass's noise does not average away with samples per pixel (one
#: render's mean within it at 2 σ, the two renders of ``check`` at 2.8 σ). Until session 19 it
#: bounded the noise of the camera-weighted flux of every deposit, the first vertex's direct
#: light included, which emitter sampling renders without the solution: window_interior at 256²
#: took the 8× cap, 2.03 M particles. Until session 22 it was a quarter of the bound (1.40–1.47
#: M particles there, the only scene of scenes_xml/ and ../shared/scenes above the floor of
#: ``particles_per_patch`` × patches). Measured on window_interior at 256², radiosity_gather,
#: 0.0025 → 0.005 (``tools/flux_noise.py scenes_xml/window_interior.xml radiosity_gather``):
#: particles 1.47 M → 0.37 M, prepass 0.58 → 0.34 s, the spread of the image mean between
#: prepass seeds 0.26 → 0.45 % (10 seeds), the bias part 7.73e-4 → 7.71e-4 and one 128-spp
#: render's relMSE 3.97e-3 → 4.07e-3 (4 seeds); radiance_cache's bias part 1.35e-3 → 1.36e-3,
#: its mean's spread 0.47 → 0.51 % (its other prepass parts dominate)
FLUX_NOISE = 0.005
#: most particles a guided solve adds, as a multiple of ``particles_per_patch`` x patches
MAX_PARTICLE_GROWTH = 8


@dataclass
class GuidePilot:
    """The emission guide's pilot particles (:func:`guide_pilot`): per particle its cell and
    its scores on the common scale of :mod:`.emission_guide` step 3 (``score``: W-weighted,
    ``read`` and ``first``: :class:`~.emission_guide.CameraImportance`'s), the camera pass,
    the cells and how many particles were traced."""

    cells: object
    camera: object
    cell_of: np.ndarray
    score: np.ndarray
    read: np.ndarray
    first: np.ndarray
    traced: int


def pilot_trace(scene, patches, elements, camera, guide, n, seed, bounds=None):
    """``n`` particles drawn with ``guide``, traced without deposits: (cells, score, read,
    first), the scores on :mod:`.emission_guide` step 3's common scale (× the guide's
    probability of the particle's cell × ``n``)."""
    _, _, result, _ = _trace_batch(scene, patches, n, 0, seed, n, DEFAULT_MAX_BOUNCES, elements,
                                   guide=guide, importance=camera.hits, bounds=bounds,
                                   deposit_flux=False, reads=camera)
    scale = guide.pmf[result["cell"]] * n
    zeros = np.zeros(len(result["cell"]))
    return (result["cell"], result["score"] * scale, result.get("read_score", zeros) * scale,
            result.get("first_score", zeros) * scale)


def guide_pilot(scene, sensor, patches, elements=None, seed: int = 0) -> GuidePilot | None:
    """The pilot of :func:`guide_emission`, in its two stages: every cell
    (``emission_guide.PILOT_PER_CELL`` particles per cell on average), then the cells that
    scored and their neighbours (:func:`emission_guide.focus_cells`). ``None`` where every
    emitter is an area light, there is no sensor or the camera reads nothing."""
    emitters = scene.emitters()
    if sensor is None or not emitters or \
            all(kind == "surface" for kind in emitter_kinds(scene)):
        return None
    receivers = elements if elements is not None else patches
    camera = emission_guide.camera_importance(scene, sensor, receivers, seed)
    if not camera.hits.sum() > 0:
        return None
    bounds = scene_bounds(scene)
    cells = emission_guide.cells(scene)
    first_n = max(emission_guide.PILOT_PER_CELL * cells.count, 1 << 13)
    runs = [pilot_trace(scene, patches, elements, camera, emission_guide.uniform(cells),
                        first_n, seed + _GUIDE_SEED, bounds)]
    lit = emission_guide.focus_cells(cells, runs[0][0], runs[0][1])
    traced = first_n
    if lit.any():
        focus_n = emission_guide.PILOT_FOCUS * int(lit.sum())
        runs.append(pilot_trace(scene, patches, elements, camera,
                                emission_guide.EmissionGuide(cells, lit.astype(np.float64)),
                                focus_n, seed + _GUIDE_SEED + 1, bounds))
        traced += focus_n
    cell_of, score, read, first = (np.concatenate(parts) for parts in zip(*runs))
    return GuidePilot(cells, camera, cell_of, score, read, first, traced)


def guide_emission(scene, sensor, patches, elements=None, seed: int = 0):
    """The importance-driven emission of :mod:`mi_twopass.prepass.emission_guide` for ``scene``
    seen by ``sensor``: (guide, pilot particles, the relative standard deviation of the image's
    mean that one guided particle's noise leaves, as the pilot predicts it:
    :func:`emission_guide.image_noise`), or (None, pilot particles, 0.0) where every emitter is
    an area light, there is no sensor, the camera reads nothing the pilot's particles reach, or
    the guide would not divide the variance of the camera-weighted flux by
    ``emission_guide.MIN_GAIN`` (scenes_xml/caustic.xml's sky: 1.8×). The pilot:
    :func:`guide_pilot`."""
    pilot = guide_pilot(scene, sensor, patches, elements, seed)
    if pilot is None:
        return None, 0, 0.0
    cells, cell_of, score = pilot.cells, pilot.cell_of, pilot.score
    guide = emission_guide.fitted(cells, cell_of, score)
    if guide is None:
        return None, pilot.traced, 0.0
    guided = emission_guide.predicted_noise(cells, guide.pmf, cell_of, score, 1)
    plain = emission_guide.predicted_noise(cells, cells.default / cells.default.sum(),
                                           cell_of, score, 1)
    if guided ** 2 * emission_guide.MIN_GAIN > plain ** 2:
        return None, pilot.traced, 0.0  # Mitsuba's own emission is about as good: no guide
    return guide, pilot.traced, emission_guide.image_noise(cells, guide.pmf, cell_of, pilot.read,
                                                           pilot.first, 1)


def guided_particles(n_particles: int, noise_per_particle: float) -> int:
    """The particle count that brings the predicted relative standard deviation of the image's
    mean (:func:`guide_emission`) to ``FLUX_NOISE``: at least ``n_particles``, at most
    ``MAX_PARTICLE_GROWTH`` times it."""
    need = math.ceil((noise_per_particle / FLUX_NOISE) ** 2) if noise_per_particle > 0 else 0
    return int(min(max(n_particles, need), MAX_PARTICLE_GROWTH * n_particles))


# ---------------------------------------------------------------------------------------------
# The radiosity prepass as one step: patches, receiving elements, the solve, virtual luminaires
# ---------------------------------------------------------------------------------------------
#: fewest particles a solve shoots, whatever the patch count (a handful of patches would
#: otherwise get a noisy solution from a few thousand particles)
MIN_PARTICLES = 1 << 16


#: a patch is reclassified only where its B_r is at least this many times the area-weighted
#: mean B_r of the cached (diffuse, reflecting) patches: a far gather ray reading a patch near
#: that mean has little variance, explicit sampling pays for small bright reflectors only. With
#: GSII's rule alone (B_r ≥ vl_threshold × max B_r) the count followed the noise of the
#: brightest patch: on scenes_xml/office.xml (max/mean 2.9–8.0 over four solve seeds) 1, 187, 3
#: or 300 patches, window_interior's sunlit floor 327–350 (13 % of the area); with many of them
#: spike_gather's relMSE at 16 and 32 spp (256²) was 1.4–1.8× that with one, radiosity_gather's
#: equal-time ratio on the office 1.73 against 3.49 with none (``bench --integrators
#: radiosity_gather,radiosity_gather:vl_threshold=2``, 6 s budget). With 4: the office 0–3,
#: window_interior 1–3, the Cornell box 38–40 (as before; radiosity_gather's equal-spp ratio
#: 2.44 against 1.59 without any in that run), veach-bidir's lamp 18 and many_lights 2–4 (as
#: before) (``tools/virtual_luminaires.py``)
VL_CONTRAST = 4.0
#: ... and only where the patches chosen carry at least this share of the reflected power of
#: the cached patches: the code that samples them costs about a quarter of a render's time per
#: sample (spike_gather on many_lights at 128², ``tools/render_cost.py``), which light that
#: faint cannot pay back. On many_lights (2–4 patches beside the lights, 0.0 % of the power)
#: spike_gather's relMSE at equal spp was the same with and without them at 256² (equal-spp
#: ratio 4.55 and 4.50), its equal-time ratio 2.76 against 3.51 without. Below it too: caustic
#: (1.1 %), tut-cbox (0.3 %), staircase2 (0.0 %); above: the Cornell box (7.7 %), mixed_room
#: (6–8 %), veach-bidir's lamp (46 %)
VL_MIN_POWER = 0.02


@dataclass(frozen=True)
class RadiositySettings:
    """What the radiosity prepass reads from an integrator's XML (bounds checked there, by
    :func:`mi_twopass.integrators.base.read_radiosity_budget`)."""

    max_patches: int = 1024
    particles_per_patch: int = PARTICLES_PER_PATCH
    #: receiving elements per patch (1: none)
    elements_per_patch: int = 16
    min_particles: int = MIN_PARTICLES
    #: GSII's reclassification: patches whose reflected radiosity is at least this fraction of
    #: the largest become virtual luminaires (∞: none)
    vl_threshold: float = math.inf
    #: ... and at least this many times the area-weighted mean B_r of the cached patches
    #: (:func:`reclassified_patches`)
    vl_contrast: float = VL_CONTRAST
    #: a simplified scene file the prepass runs on instead of the render's (GSII §2.5)
    prepass_scene: str = ""




def reclassified_patches(Br, area, is_diffuse, vl_threshold: float,
                         contrast: float = VL_CONTRAST) -> np.ndarray:
    """Ids of the patches GSII reclassifies as virtual luminaires (Zimmerman & Shirley §2.5):
    diffuse (cached) patches of reflected radiosity ``Br`` (one value per patch) with
    B_r ≥ ``vl_threshold`` × max B_r and B_r ≥ ``contrast`` × the area-weighted mean B_r of
    the cached patches (:data:`VL_CONTRAST`), none where together they carry less than
    :data:`VL_MIN_POWER` of the cached patches' reflected power, and none for a non-finite
    threshold. ``contrast`` = 0 is GSII's rule alone (no mean, no power floor)."""
    Br = np.asarray(Br, np.float64)
    area = np.asarray(area, np.float64)
    is_diffuse = np.asarray(is_diffuse, bool)
    if not Br.size or not math.isfinite(vl_threshold):
        return np.zeros(0, np.uint32)
    ok = is_diffuse & (Br > 0) & (area > 0)
    mean = float(np.sum(Br[ok] * area[ok]) / np.sum(area[ok])) if ok.any() else 0.0
    limit = max(vl_threshold * Br.max(), float(contrast) * mean)
    chosen = np.nonzero(ok & (Br >= limit))[0].astype(np.uint32)
    power = Br * area
    if contrast > 0 and chosen.size and power[chosen].sum() < VL_MIN_POWER * power[ok].sum():
        return np.zeros(0, np.uint32)
    return chosen


class VirtualLuminaires:
    """GSII's reclassified bright reflectors (Zimmerman & Shirley §2.5) as a light sampler: a
    power-proportional choice among the patches :func:`reclassified_patches` picks (B_r ≥
    ``vl_threshold`` × max B_r and ≥ ``vl_contrast`` × the mean; Lambertian, uncut patches
    only: the cached ones). :meth:`sample` and :meth:`pmf` agree
    (tests/prepass/test_radiosity.py)."""

    def __init__(self, solution: RadiositySolution, vl_threshold: float,
                 vl_contrast: float = VL_CONTRAST):
        patches = solution.patches
        Br = np.asarray(solution.B_reflected).mean(axis=1)
        power = Br * np.asarray(patches.area)
        chosen = reclassified_patches(Br, patches.area, patches.is_diffuse, vl_threshold,
                                      vl_contrast)
        self.count = int(chosen.size)
        is_vl = np.zeros(patches.count + 1, dtype=bool)
        is_vl[chosen] = True
        #: per patch (+1 sentinel): is it a virtual luminaire
        self.mask = jit(mi.Bool, is_vl)
        self.ids = self.distr = self.pmf_table = None
        if chosen.size:
            self.ids = jit(mi.UInt32, chosen)
            self.distr = mi.DiscreteDistribution(jit(mi.Float, power[chosen].astype(np.float32)))
            pmf = np.zeros(patches.count + 1, dtype=np.float32)
            pmf[chosen] = power[chosen] / power[chosen].sum()
            self.pmf_table = jit(mi.Float, pmf)

    def sample(self, u, active=True):
        """A virtual luminaire's patch id, chosen ∝ its power from the uniform ``u``."""
        idx, _ = self.distr.sample_reuse(u, active)
        return dr.gather(mi.UInt32, self.ids, idx, active)

    def pmf(self, pid, active=True):
        """The probability :meth:`sample` picks patch ``pid`` (0 for other patches)."""
        return dr.gather(mi.Float, self.pmf_table, pid, active)

    def contains(self, pid, active=True):
        return dr.gather(mi.Bool, self.mask, pid, active)


def virtual_point_reached(scene, sol, si, wo, pid, dist, scale, active):
    """The explicit (virtual-luminaire) strategy's visibility test at a point sampled on patch
    ``pid``, distance ``dist`` along ``wo``: the ray from ``si`` first meets that patch (nothing
    in between; a sample point of a curved patch may lie a hair off the surface, so up to 5 % of
    the patch's size short of it) and meets it where the radiosity is *cached*. Where an
    element of the patch is not cached (cut by geometry, unevenly lit) the implicit gather ray
    traces on instead, so the explicit strategy must leave those points out: sampling them too
    counted their light twice (veach-bidir's lamp: +2.6 % on the image)."""
    si_y = scene.ray_intersect(spawn_ray(si, wo, scale), active)
    size = dr.sqrt(sol.patches.gather("area", pid, active))
    hit = active & si_y.is_valid() & (si_y.t >= dist - 0.05 * size)
    hit &= sol.patches.lookup(si_y, hit) == pid
    return hit & sol.cached_at(si_y, hit)


@dataclass
class RadiosityPrepass:
    """What :func:`build` makes: the ``scene`` the patches belong to (the render's, or the
    simplified ``prepass_scene``), the ``solution`` (patches, elements, radiosities) and the
    ``virtual`` luminaires; ``stats`` and ``nbytes`` for the integrators' tables."""

    scene: object
    solution: RadiositySolution
    virtual: VirtualLuminaires
    seconds: float
    simplified: bool = False
    #: importance-driven emission (:func:`guide_emission`): its cells and pilot particles
    guide_cells: int = 0
    guide_particles: int = 0
    #: the relative standard deviation of the image's mean the pilot predicts the solution's
    #: noise leaves (:func:`emission_guide.image_noise`)
    mean_noise: float = 0.0
    #: taken from a memo another prepass of the same scene and camera filled (:func:`build`)
    reused: bool = False

    @property
    def patches(self):
        return self.solution.patches

    @property
    def elements(self):
        return self.solution.elements

    @property
    def nbytes(self) -> int:
        return int(self.solution.nbytes)

    @property
    def stats(self) -> dict:
        sol = self.solution
        probe = sol.patches.probe_rays + (sol.elements.probe_rays if sol.elements is not None
                                          else 0)
        return {"radiosity_rays": int(sol.rays), "probe_rays": int(probe),
                "radiosity_seconds": self.seconds,
                "patches": int(sol.patches.count),
                "elements": int(sol.elements.count) if sol.elements is not None else 0,
                "virtual_luminaires": self.virtual.count,
                "guided_emission_cells": self.guide_cells,
                "guide_pilot_particles": self.guide_particles,
                "radiosity_particles": int(sol.particles),
                "predicted_mean_noise": self.mean_noise,
                "radiosity_reused": self.reused,
                # patches / elements cut by geometry: traced on, not read (light-leak guard)
                "split_patches": int(np.sum(sol.patches.is_split)),
                "split_elements": int(np.sum(sol.elements.is_split))
                if sol.elements is not None else 0}


class SolveMemo:
    """Radiosity solves that prepasses of one scene and camera share (``twopass``'s candidates,
    :func:`build`). A plain class, not a dict: Dr.Jit traverses the dicts and dataclasses an
    integrator holds when it records a loop, and took the solves' tables for loop state."""

    def __init__(self):
        self._solves = {}

    def get(self, key):
        return self._solves.get(key)

    def put(self, key, prepass) -> None:
        self._solves[key] = prepass

    def clear(self) -> None:
        self._solves.clear()

    def __len__(self) -> int:
        return len(self._solves)


def build(scene, settings: RadiositySettings, seed: int, progress: bool = True,
          sensor=None, memo: SolveMemo | None = None) -> RadiosityPrepass:
    """The radiosity prepass shared by radiosity_gather, spike_gather and radiance_cache (GSII
    steps 1–2, Zimmerman & Shirley §2.5 / §3.3 step 2): patches of at most ``max_patches``,
    receiving elements, max(``min_particles``, ``particles_per_patch`` × patches) particles
    (the count follows the patches, not the elements; where the emission is guided, more —
    up to ``MAX_PARTICLE_GROWTH`` times — until the camera-weighted flux's predicted noise is
    ``FLUX_NOISE``, :func:`guided_particles`), then the virtual luminaires. With
    ``prepass_scene`` it all runs on that simplified scene. ``progress``: a bool (bars on the
    solve), as :func:`solve_radiosity`'s. ``sensor``: the camera whose reads the particles of
    emitters other than area lights are guided to (:func:`guide_emission`); ``None``: not
    guided. ``memo``: a :class:`SolveMemo` that prepasses of one scene and camera share
    (``twopass``'s candidates): a solve with the same budget and seed is taken from it, and
    only the virtual luminaires (the one setting the solve does not read) are made anew."""
    t0 = time.perf_counter()
    key = (replace(settings, vl_threshold=math.inf, vl_contrast=VL_CONTRAST), int(seed),
           id(sensor))
    done = memo.get(key) if memo is not None else None
    if done is not None:
        return replace(done, virtual=VirtualLuminaires(done.solution, settings.vl_threshold,
                                                       settings.vl_contrast),
                       seconds=time.perf_counter() - t0, reused=True)
    simplified = bool(settings.prepass_scene)
    target = load_scene(settings.prepass_scene) if simplified else scene
    shapes = scene_shapes(target)  # read once for the patches and the elements
    patches = build_patches(target, max_patches=settings.max_patches, seed=seed, shapes=shapes)
    elements = receiving_elements(target, settings.max_patches, settings.elements_per_patch,
                                  seed, shapes=shapes)
    n_particles = max(settings.min_particles, settings.particles_per_patch * patches.count)
    guide, pilot, noise = guide_emission(target, sensor, patches, elements, seed)
    n_particles = guided_particles(n_particles, noise)
    solution = solve_radiosity(target, patches, n_particles=n_particles, seed=seed,
                               elements=elements, progress=bool(progress), guide=guide)
    virtual = VirtualLuminaires(solution, settings.vl_threshold, settings.vl_contrast)
    pre = RadiosityPrepass(scene=target, solution=solution, virtual=virtual,
                           seconds=time.perf_counter() - t0, simplified=simplified,
                           guide_cells=guide.cells.count if guide is not None else 0,
                           guide_particles=pilot,
                           mean_noise=noise / math.sqrt(n_particles) if guide else 0.0)
    if memo is not None:
        memo.put(key, pre)
    return pre
