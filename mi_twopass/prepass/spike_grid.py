"""Spike lists on a regular grid (Zimmerman & Shirley 1995, §2.6, §3.2 and §4).

The structure behind the ``spike_gather`` integrator, built once per scene and settings:

**Sources** (:func:`build_sources`). Every Mitsuba emitter is one source: area lights (sampled
with the emitter's own ``sample_direction``, pdf in solid angle), point and spot lights, and the
*global* (infinite) emitters: directional, constant and envmap. The radiosity solution's bright
reflectors become sources too, as in GSII's reclassification (§2.5, §3.3 step 3): patches whose
reflected radiosity is at least ``vl_threshold`` × the brightest patch's and ``vl_contrast`` × the
mean (:func:`mi_twopass.prepass.radiosity.reclassified_patches`; "virtual luminaires", VL). Per
source we keep a bounding sphere (centre, radius), an unoccluded *intensity proxy*
I_i [W/sr] (or an irradiance for infinite emitters), an optional axis (the normal of a planar
one-sided source, the direction of a directional light) and the emittance E_i [W/m²] that
decides its band (§4):

============================  ================================  ===============================
source                        I_i                               E_i
============================  ================================  ===============================
planar area light             Φ/π along its normal (× cos)      Φ/A
other area light (sphere...)  Φ/(4π), isotropic                 Φ/A
point light                   Φ/(4π)                            ∞ (a spike everywhere)
spot light                    Φ/Ω(cutoff), isotropic            ∞
directional                   its irradiance, × cos at x        ∞
constant / envmap             ∫L dω / 4 (irradiance proxy)      ∞
virtual luminaire (patch)     B_r·A/π along its normal          B_r (always "influence" band)
============================  ================================  ===============================

Φ is an area light's flux π∫Le dA (one-sided Lambertian emission; Mitsuba's area lights emit on
the front side only), estimated from ``emitter.sample_position``; a delta light's flux is the
mean weight of ``emitter.sample_ray``.

**Estimated contribution** (:meth:`Sources.estimate`, §2.6's L'_i with the geometry term, §4):
``L'_i(x) = I_i · ĉ_x · ĉ_y / max(d², r_i²)`` with *conservative* cosines: the receiver cosine
ĉ_x = cos(max(θ_x − θ_i, 0)), where θ_i is the half-angle of the source's bounding cone seen
from x (sin θ_i = r_i/d), and likewise at a planar source. A source partly above x's horizon so
never gets L' = 0; L' = 0 only where the source cannot light x (wholly below the horizon, behind
a one-sided source, or a VL wholly nearer than ``r_thresh``, which the integrator never samples
explicitly).

**Grid** (:func:`build_spike_grid`, §4). An axis-aligned grid over the scene's bounding box,
``grid_res`` cubic cells along its longest axis. Only cells that hold geometry the camera sees
get a list: a low-resolution camera pass (``camera_res`` rays along the film's longer side,
followed through delta bounces) collects first non-delta hit points, and with ``gather_reach``
> 0 (the integrator passes its r_thresh) one cosine-distributed gather ray from each adds the
points it reaches nearer than that (:func:`bounce_points`): there the integrator recurses and
gathers explicitly again, so those cells need lists too. A cell holding some points gets a list,
and up to ``cell_points`` of them, offset along their normal, are the cell's *visibility sample
points* (the paper's "random points in a grid cell").

**Candidates** (§4): a source with E_i ≥ E_high may spike anywhere and is a candidate in every
list cell; E_low ≤ E_i < E_high (and every VL) only in the cells of its *influence region*,
where its unoccluded irradiance I_i / d_min² reaches ``influence`` (d_min: distance from the
bounding sphere to the cell's box); E_i < E_low never (it is left to implicit sampling).
Delta and infinite sources have E_i = ∞.

**Horizon cull** (:func:`can_light`): a candidate whose conservative L' is 0 at every camera
and bounce point of the cell (behind each point's horizon, or a one-sided source facing away
from all of them) gets no visibility rays: they would start into the receiving surface, and
the integrator would never choose it there. On ``many_lights.xml`` this is a quarter of the
candidate pairs and of the visibility rays (12.5 M → 9.5 M).

**Visibility** (§4, the self-refining point sampling, exactly): a candidate pair (cell, source)
gets rounds of ``VIS_ROUND`` = 10 rays from random sample points of the cell to random points
on the source (``emitter.sample_direction``; a uniform point of a VL patch). A ray *reaches*
the source when nothing blocks it and the source emits towards the point (the emitter's weight
is positive; a VL patch faces it). After round 1, 10/10 gives g = 1 and the pair is done.
After round k ≥ 2 the pair is done when more than one ray of the new round reached the source
and the new round's fraction is within ``VIS_TOL`` = 0.1 of the running estimate; g is then
the mean of all its rays ((g_new + g)/2 after two rounds, as in the paper). Otherwise the rounds
go on ("if one or fewer rays reach the light source, this process continues") up to
``visibility_max_rays`` (100), where g is the mean of all rays; g = 0 leaves the source out of
the list. One departure, for the prepass's cost: a pair none of whose first
``visibility_occluded_rays`` (20) rays reached the source is done with g = 0 (the paper traces
all 100 there, and on ``many_lights.xml`` most pairs are a light in another room); a source
visible from a few percent of the cell may then be left out, which ``complete=true``'s
defensive choice and MIS keep unbiased. ``visibility_occluded_rays`` ≥ ``visibility_max_rays``
is the paper's rule. All pairs of a round are one ``ray_test`` wavefront (chunked at ``batch_rays``); the
pairs still open are compacted with numpy between rounds.

**Lists** are stored CSR: ``offsets`` (one range per list), ``source`` ids sorted within each
list, and ``g``; a dense ``cell → list`` table (``INVALID`` where a cell has none). The
membership test :meth:`SpikeGrid.contains` is a binary search inside one list's range.

**Selection** (§2.6 and §4, the linear method of Shirley & Wang with the geometry term):
:meth:`SpikeGrid.reservoir` sweeps a list once with weighted reservoir sampling (one uniform,
rescaled at every step), which yields both a source drawn with α_i = g_i·L'_i(x) / W and the
sum W = Σ_j g_j·L'_j(x). :meth:`SpikeGrid.sample` draws from a mixture of up to two lists, x's
own (a) and that of x's cell jittered by up to ±½ cell (b, §4's boundary weighting, see
:meth:`SpikeGrid.choose_lists`), and, with ``defensive`` = ε > 0 and K > 0 delta sources of
non-zero power (point, spot, directional), of a uniform choice among those:

    P(i) = ε·[i is delta]/K + (1 − ε)·(m_a·α_a(i) + m_b·α_b(i)),

m_a = m_b = ½ when both lists have weight (else the one that has gets 1; ε = 1 where neither
has). :meth:`SpikeGrid.pmf` evaluates it (:meth:`SpikeGrid.pmf_given_sums` with known sums).
Delta sources can never be hit by an implicit (BSDF) ray, so the defensive term is what keeps
a delta source that the point-sampled visibility falsely excluded from a list from being lost
(bias) rather than merely noisy.

Randomness: every prepass random number comes from PCG32 streams seeded with the given ``seed``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..host_arrays import columns, jit, vectors
from ..progress import progress as progress_bar
from ..seeds import numpy_rng, splitmix64
from ..tables import Tables
from .radiosity import VL_CONTRAST, RadiositySettings, reclassified_patches
from .radiosity import build as build_radiosity

INVALID = 0xFFFFFFFF
#: source kinds
KIND_EMITTER, KIND_PATCH = 0, 1
#: candidate bands (§4): never in a list / in the influence region only / in every list cell
BAND_IMPLICIT, BAND_INFLUENCE, BAND_ALL = 0, 1, 2
#: rays per round of the self-refining visibility estimate and its tolerance (§4)
VIS_ROUND = 10
VIS_TOL = 0.1
#: once a round has at most this many visibility rays, the rounds left are traced in one call
#: (:func:`estimate_visibility`'s ``tail_rays``): a call's fixed part (tracing the emitters'
#: sampling code, generating the kernels) was about 14 ms on many_lights against about 4e-8 s
#: a ray, so a round of fewer than ~3.5e5 rays costs more in calls than in rays; 2^16 keeps
#: the rays traced for nothing below ~6e5 (about 25 ms)
VIS_TAIL_RAYS = 1 << 16
#: position / ray samples per emitter when estimating its flux, area and shape
SOURCE_SAMPLES = 256
#: largest dense cell table (cells); a finer grid is refused with a message naming grid_res
MAX_CELLS = 1 << 27
#: a planar source's normals agree to within this cosine
PLANAR_COS = 0.9995
_TINY = 1e-30

# salts of the PCG32 streams
_SALT_SOURCES, _SALT_CAMERA, _SALT_POINTS, _SALT_VIS, _SALT_BOUNCE = 0x51, 0xCA, 0x9E, 0x715, 0xB0


def _rng(n, seed, salt, first=0):
    # opaque: literal seeds would compile the kernels that use the stream anew for every seed
    idx = dr.arange(mi.UInt64, n) + dr.opaque(mi.UInt64, first)
    return mi.PCG32(size=n, initstate=dr.opaque(mi.UInt64, splitmix64(splitmix64(seed) ^ salt)), initseq=idx)


def _np3(v):
    """A Dr.Jit 3-vector array as a numpy (n, 3) float64 array
    (:func:`mi_twopass.host_arrays.columns`: no kernel per size)."""
    return columns(v)


def _dr3(a, cls):
    """:func:`~mi_twopass.host_arrays.vectors`, one zero row where ``a`` has none."""
    a = np.asarray(a, dtype=np.float32).reshape(-1, 3)
    return vectors(a if a.shape[0] else np.zeros((1, 3), np.float32), cls)


def _pad(a, dtype, value=0):
    a = np.asarray(a, dtype=dtype)
    return a if a.size else np.full(1, value, dtype)


def _packed4(xyz, w):
    """(S, 3) and (S,) as one flat float32 array of (x, y, z, w) records (one record of zeros
    when S = 0), for 4-wide gathers."""
    rec = np.concatenate([np.asarray(xyz, np.float32).reshape(-1, 3),
                          np.asarray(w, np.float32).reshape(-1, 1)], axis=1)
    return (rec if rec.size else np.zeros((1, 4), np.float32)).ravel()


def _flags(src):
    """Packed FLAG_* bits of every source (numpy uint32)."""
    return (np.where(src.infinite, FLAG_INFINITE, 0)
            | np.where(src.kind == KIND_PATCH, FLAG_PATCH, 0)).astype(np.uint32)


def _lum(rgb):
    """Scalar proxy of an RGB quantity: the mean of its channels."""
    return np.asarray(rgb, dtype=np.float64).reshape(-1, 3).mean(axis=1)


def conservative_cos(c, sin_sub, cos_sub):
    """cos(max(θ − θ_sub, 0)) for cos θ = ``c``: the largest cosine over a cone of half-angle
    θ_sub around the direction (Dr.Jit), clamped at 0."""
    s = dr.safe_sqrt(1.0 - dr.square(c))
    v = dr.select(c >= cos_sub, 1.0, c * cos_sub + s * sin_sub)
    return dr.maximum(v, 0.0)


# ----------------------------------------------------------------------------------------------
# Sources


@dataclass
class Sources:
    """Every source of the spike lists: the emitters, then the virtual luminaires (numpy, with
    Dr.Jit tables for the render). Source ids are ``[emitters in scene.emitters() order][VLs]``."""

    kind: np.ndarray  # (S,) KIND_EMITTER / KIND_PATCH
    emitter_index: np.ndarray  # (S,) index into scene.emitters(); -1 for patches
    patch_id: np.ndarray  # (S,) patch id; N (no patch) for emitters
    center: np.ndarray  # (S, 3) bounding-sphere centre (unused for infinite emitters)
    radius: np.ndarray  # (S,) bounding-sphere radius (0 for point lights)
    intensity: np.ndarray  # (S,) I_i [W/sr]; an irradiance [W/m²] for infinite emitters
    axis: np.ndarray  # (S, 3) normal of a planar source / direction to a directional light / 0
    infinite: np.ndarray  # (S,) bool
    delta: np.ndarray  # (S,) bool: point, spot, directional (cannot be hit by a ray)
    flux: np.ndarray  # (S,) Φ [W] (scalar proxy); 0 for infinite emitters
    emittance: np.ndarray  # (S,) E_i [W/m²]; inf for delta and infinite emitters
    band: np.ndarray  # (S,) BAND_*
    names: list
    E_high: float
    E_low: float
    _tables: Tables = field(default_factory=Tables, repr=False)

    @property
    def count(self) -> int:
        return int(self.kind.shape[0])

    @property
    def patch_count(self) -> int:
        """Number of virtual luminaires (patch sources)."""
        return int(np.count_nonzero(self.kind == KIND_PATCH))

    @property
    def delta_ids(self) -> np.ndarray:
        """Delta sources that can emit (the defensive mixture's support ``"delta"``)."""
        return np.nonzero(self.delta & (self.intensity > 0))[0]

    @property
    def emitter_ids(self) -> np.ndarray:
        """Emitters that can emit (the defensive mixture's support ``"emitters"``)."""
        return np.nonzero((self.kind == KIND_EMITTER) & (self.intensity > 0))[0]

    def support_ids(self, support) -> np.ndarray:
        return self.delta_ids if support == "delta" else self.emitter_ids

    @property
    def nbytes(self) -> int:
        own = sum(v.nbytes for v in self.__dict__.values() if isinstance(v, np.ndarray))
        return int(own + 48 * (self.count + 1))

    # -- Dr.Jit queries ---------------------------------------------------------------------
    def source_of_emitter(self, emitter, active=True):
        """Source id of an ``mi.EmitterPtr`` (``INVALID`` for a null pointer)."""
        t = self._tables
        rid = dr.reinterpret_array(mi.UInt32, emitter)
        ok = mi.Bool(active) & (rid < t["n_emitter_reg"])
        return dr.select(ok, dr.gather(mi.UInt32, t["emitter_source"], rid, ok), INVALID)

    def source_of_patch(self, patch_ids, active=True):
        """Source id of a patch (``INVALID`` unless it is a virtual luminaire)."""
        t = self._tables
        pid = mi.UInt32(patch_ids)
        ok = mi.Bool(active) & (pid < t["n_patch_slots"])
        return dr.select(ok, dr.gather(mi.UInt32, t["patch_source"], pid, ok), INVALID)

    def gather(self, name, sid, active=True):
        table = self._tables[name]
        return dr.gather(type(table), table, sid, active)

    def estimate(self, sid, p, n, two_sided, r_thresh, active=True):
        """Unoccluded contribution proxy L'_i(x) of source ``sid`` at ``p`` with receiver
        normal ``n`` (|cos| where ``two_sided``), conservative (see the module docstring)."""
        active = mi.Bool(active) & (sid != INVALID)
        sphere = dr.gather(mi.Vector4f, self._tables["sphere"], sid, active)
        axis_i = dr.gather(mi.Vector4f, self._tables["axis_intensity"], sid, active)
        flags = dr.gather(mi.UInt32, self._tables["flags"], sid, active)
        return estimate_record(sphere, axis_i, flags, p, n, two_sided, r_thresh, active)


#: bits of a source's packed ``flags``
FLAG_INFINITE, FLAG_PATCH = 1, 2


def estimate_record(sphere, axis_i, flags, p, n, two_sided, r_thresh, active=True):
    """L'(x) of one packed source record: ``sphere`` = (centre, radius), ``axis_i`` = (axis,
    intensity), ``flags`` (FLAG_INFINITE, FLAG_PATCH); the formula of :meth:`Sources.estimate`.
    The spike lists store these records per entry, with the intensity multiplied by g, so that
    a list sweep reads each entry with two 4-wide gathers and no indirection."""
    c, r = mi.Point3f(sphere.x, sphere.y, sphere.z), sphere.w
    axis, intensity = mi.Vector3f(axis_i.x, axis_i.y, axis_i.z), axis_i.w
    inf = (flags & FLAG_INFINITE) != 0
    is_patch = (flags & FLAG_PATCH) != 0
    d = c - p
    dist2 = dr.squared_norm(d)
    dist = dr.sqrt(dist2)
    has_axis = dr.squared_norm(axis) > 0
    w = dr.select(inf, axis, d / dr.maximum(dist, _TINY))
    sin_sub = dr.select(inf, 0.0, dr.minimum(r / dr.maximum(dist, _TINY), 1.0))
    cos_sub = dr.safe_sqrt(1.0 - dr.square(sin_sub))
    cx = dr.dot(n, w)
    cx = dr.select(two_sided, dr.abs(cx), cx)
    cx = dr.select(inf & ~has_axis, 1.0, conservative_cos(cx, sin_sub, cos_sub))
    cy = dr.select(has_axis & ~inf, conservative_cos(dr.dot(axis, -w), sin_sub, cos_sub), 1.0)
    falloff = dr.select(inf, 1.0, dr.rcp(dr.maximum(dr.maximum(dist2, dr.square(r)), _TINY)))
    value = intensity * cx * cy * falloff
    near = is_patch & (dist + r < r_thresh)  # a VL wholly nearer than r_thresh: path-traced
    # a point light on the receiver: huge but finite (a NaN, from 0·∞, is no estimate)
    value = dr.minimum(value, 1e20)
    return dr.select(mi.Bool(active) & ~near & (value == value), value, 0.0)


def _emitter_shapes(scene):
    """Registry id of each emitter → (bbox min, bbox max, surface area, id) of its shape."""
    out = {}
    for shape in scene.shapes():
        if shape.is_emitter():
            rid = int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(shape.emitter()))[0])
            bb = shape.bbox()
            lo = np.array([bb.min.x, bb.min.y, bb.min.z], dtype=np.float64).ravel()
            hi = np.array([bb.max.x, bb.max.y, bb.max.z], dtype=np.float64).ravel()
            out[rid] = (lo, hi, float(np.asarray(shape.surface_area()).ravel()[0]), shape.id())
    return out


def _spot_solid_angle(emitter) -> float:
    """Solid angle of a spot light's cone (4π when the cutoff is not exposed)."""
    try:
        params = mi.traverse(emitter)
        cutoff = float(np.asarray(params["cutoff_angle"]).ravel()[0])
        return 2 * math.pi * (1 - math.cos(math.radians(min(max(cutoff, 1e-3), 180.0))))
    except Exception:  # noqa: BLE001
        return 4 * math.pi


def _emitter_properties(scene, seed, samples=SOURCE_SAMPLES):
    """Per emitter: flags, flux, area, centre, radius, intensity, axis (numpy), vectorised over
    emitters × samples (one wavefront per sampling routine)."""
    emitters = scene.emitters()
    E = len(emitters)
    if E == 0:  # a black image is the right answer: no sources at all
        return dict(names=[], center=np.zeros((0, 3)), radius=np.zeros(0),
                    intensity=np.zeros(0), axis=np.zeros((0, 3)), infinite=np.zeros(0, bool),
                    delta=np.zeros(0, bool), flux=np.zeros(0), emittance=np.zeros(0),
                    area=np.zeros(0), reg=np.zeros(0, np.int64))
    M = samples
    n = E * M
    idx = dr.arange(mi.UInt32, n) // M
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), idx)
    flags_dr = emitter.flags()
    is_area = mi.has_flag(flags_dr, mi.EmitterFlags.Surface) \
        & ~mi.has_flag(flags_dr, mi.EmitterFlags.Infinite)
    is_inf = mi.has_flag(flags_dr, mi.EmitterFlags.Infinite)
    is_other = ~is_area & ~is_inf
    rng = _rng(n, seed, _SALT_SOURCES)
    u1 = rng.next_float32()
    u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
    u3 = mi.Point2f(rng.next_float32(), rng.next_float32())

    # area lights: positions (flux π∫Le dA, area, normals)
    ps, _ = emitter.sample_position(mi.Float(0.0), u2, is_area)
    si = mi.SurfaceInteraction3f(ps, dr.zeros(mi.Color0f))
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    Le = emitter.eval(si, is_area)
    inv_pdf = dr.select(is_area & (ps.pdf > 0), dr.rcp(ps.pdf), 0.0)
    flux_area = Le * dr.pi * inv_pdf
    # delta-position lights: rays (flux = mean weight)
    ray, w_ray = emitter.sample_ray(mi.Float(0.0), u1, u2, u3, is_other)
    # infinite: directions from the scene centre
    bb = scene.bbox()
    centre = (bb.min + bb.max) * 0.5 if bb.valid() else mi.ScalarPoint3f(0.0)
    it = dr.zeros(mi.Interaction3f, n)
    it.p = mi.Point3f(centre)
    it.wavelengths = dr.zeros(mi.Color0f, n)
    ds, w_dir = emitter.sample_direction(it, u2, is_inf)

    flags = np.array(flags_dr, dtype=np.int64).reshape(E, M)[:, 0] if E else np.zeros(0, int)
    fa = _lum(_np3(flux_area)).reshape(E, M)
    wr = _lum(_np3(w_ray)).reshape(E, M)
    wd = _lum(_np3(w_dir)).reshape(E, M)
    P = _np3(ps.p).reshape(E, M, 3)
    Nrm = _np3(ps.n).reshape(E, M, 3)
    O = _np3(ray.o).reshape(E, M, 3)
    D = _np3(ds.d).reshape(E, M, 3)
    area_est = np.array(inv_pdf, dtype=np.float64).reshape(E, M).mean(axis=1) if E else np.zeros(0)
    for a in (fa, wr, wd):
        a[~np.isfinite(a)] = 0.0
    shapes = _emitter_shapes(scene)
    regs = np.array(dr.reinterpret_array(mi.UInt32, scene.emitters_dr()), dtype=np.int64) \
        if E else np.zeros(0, np.int64)

    surface, infinite = int(mi.EmitterFlags.Surface), int(mi.EmitterFlags.Infinite)
    delta_dir = int(mi.EmitterFlags.DeltaDirection)
    delta_pos = int(mi.EmitterFlags.DeltaPosition)
    names = [shapes[int(r)][3] if int(r) in shapes else (e.id() or e.class_name())
             for r, e in zip(regs, emitters)]
    props = dict(names=names, center=np.zeros((E, 3)), radius=np.zeros(E), intensity=np.zeros(E),
                 axis=np.zeros((E, 3)), infinite=np.zeros(E, bool), delta=np.zeros(E, bool),
                 flux=np.zeros(E), emittance=np.full(E, np.inf), area=np.zeros(E), reg=regs)
    for k, em in enumerate(emitters):  # bookkeeping per emitter (scalar data, no kernels)
        f = int(flags[k])
        if f & infinite:
            props["infinite"][k] = True
            if f & delta_dir:  # directional: irradiance along its direction
                props["delta"][k] = True
                props["intensity"][k] = float(np.median(wd[k]))
                d = D[k].mean(axis=0)
                props["axis"][k] = d / max(np.linalg.norm(d), _TINY)
            else:  # constant / envmap: irradiance proxy ∫L dω / 4
                props["intensity"][k] = float(wd[k].mean() / 4.0)
        elif f & surface:
            flux = float(fa[k].mean())
            lo_hi = shapes.get(int(regs[k]))
            if lo_hi is not None:
                lo, hi, area, _ = lo_hi
            else:  # no shape found: bound the sampled points
                lo, hi, area = P[k].min(axis=0), P[k].max(axis=0), float(area_est[k])
            props["center"][k] = 0.5 * (lo + hi)
            props["radius"][k] = 0.5 * float(np.linalg.norm(hi - lo))
            props["area"][k] = area
            props["flux"][k] = flux
            props["emittance"][k] = flux / area if area > 0 else (np.inf if flux > 0 else 0.0)
            m = Nrm[k].mean(axis=0)
            ml = np.linalg.norm(m)
            planar = ml > 0 and np.all(Nrm[k] @ (m / ml) >= PLANAR_COS)
            if planar:
                props["axis"][k] = m / ml
                props["intensity"][k] = flux / math.pi
            else:
                props["intensity"][k] = flux / (4 * math.pi)
        else:  # point, spot (delta position)
            props["delta"][k] = bool(f & delta_pos)
            flux = float(wr[k].mean())
            props["center"][k] = O[k].mean(axis=0)
            props["flux"][k] = flux
            omega = _spot_solid_angle(em) if em.class_name() == "SpotLight" else 4 * math.pi
            props["intensity"][k] = flux / omega
    props["intensity"] = np.where(np.isfinite(props["intensity"]),
                                  np.maximum(props["intensity"], 0.0), 0.0)
    return props


def build_sources(scene, solution=None, vl_threshold=0.5, e_high_rel=4.0, e_low_rel=0.1,
                  E_high=None, E_low=None, seed=0, samples=SOURCE_SAMPLES,
                  vl_contrast=VL_CONTRAST) -> Sources:
    """All sources of ``scene`` (emitters, then the VLs of ``solution``:
    :func:`~mi_twopass.prepass.radiosity.reclassified_patches`) and their bands.

    ``E_high``/``E_low`` default to ``e_high_rel``/``e_low_rel`` × the median emittance of the
    scene's area lights (1 W/m² when there is none)."""
    em = _emitter_properties(scene, seed, samples)
    E = em["flux"].shape[0]
    finite_area = ~em["infinite"] & ~em["delta"] & np.isfinite(em["emittance"]) \
        & (em["emittance"] > 0)
    median = float(np.median(em["emittance"][finite_area])) if finite_area.any() else 1.0
    E_high = float(E_high) if E_high is not None else e_high_rel * median
    E_low = float(E_low) if E_low is not None else e_low_rel * median

    # virtual luminaires (GSII's reclassified bright reflectors)
    if solution is not None and solution.patches.count:
        patches = solution.patches
        N = patches.count
        Br = _lum(solution.B_reflected)
        power = Br * np.asarray(patches.area)
        vl = reclassified_patches(Br, patches.area, patches.is_diffuse, vl_threshold,
                                  vl_contrast).astype(np.int64)
        tri_p = np.asarray(patches.tri_patch, dtype=np.int64)
        tv = np.asarray(patches.tri_vertices, dtype=np.float64)
        rad = np.zeros(N)
        if tri_p.size:
            dist = np.linalg.norm(tv - patches.center[tri_p][:, None, :], axis=2).max(axis=1)
            np.maximum.at(rad, tri_p, dist)
            cosn = np.einsum("ij,ij->i", np.asarray(patches.tri_normal, np.float64),
                             patches.normal[tri_p])
            mincos = np.ones(N)
            np.minimum.at(mincos, tri_p, cosn)
        else:
            mincos = np.ones(N)
        planar = mincos[vl] >= PLANAR_COS
        vl_axis = np.where(planar[:, None], patches.normal[vl], 0.0)
        vl_I = np.where(planar, Br[vl] * patches.area[vl] / math.pi,
                        Br[vl] * patches.area[vl] / (4 * math.pi))
        vl_center, vl_radius, vl_E = patches.center[vl], rad[vl], Br[vl]
        vl_flux = power[vl]
    else:
        N = 0
        vl = np.zeros(0, np.int64)
        vl_axis = vl_center = np.zeros((0, 3))
        vl_I = vl_radius = vl_E = vl_flux = np.zeros(0)
    V = vl.size

    band = np.full(E, BAND_INFLUENCE, np.int8)
    emit = em["emittance"]
    band[emit >= E_high] = BAND_ALL
    band[emit < E_low] = BAND_IMPLICIT
    band[em["infinite"] | em["delta"]] = BAND_ALL
    band[(em["intensity"] <= 0) & ~em["delta"]] = BAND_IMPLICIT  # nothing to sample
    names = list(em["names"]) + [f"patch {p}" for p in vl]

    src = Sources(
        kind=np.concatenate([np.full(E, KIND_EMITTER), np.full(V, KIND_PATCH)]).astype(np.int8),
        emitter_index=np.concatenate([np.arange(E), np.full(V, -1)]).astype(np.int64),
        patch_id=np.concatenate([np.full(E, N), vl]).astype(np.int64),
        center=np.vstack([em["center"], vl_center]),
        radius=np.concatenate([em["radius"], vl_radius]),
        intensity=np.concatenate([em["intensity"], vl_I]),
        axis=np.vstack([em["axis"], vl_axis]),
        infinite=np.concatenate([em["infinite"], np.zeros(V, bool)]),
        delta=np.concatenate([em["delta"], np.zeros(V, bool)]),
        flux=np.concatenate([em["flux"], vl_flux]),
        emittance=np.concatenate([emit, vl_E]),
        band=np.concatenate([band, np.full(V, BAND_INFLUENCE, np.int8)]),
        names=names, E_high=E_high, E_low=E_low)

    S = src.count
    regs = em["reg"]
    n_reg = int(regs.max()) + 1 if regs.size else 1
    emitter_source = np.full(n_reg, INVALID, np.uint32)
    emitter_source[regs] = np.arange(E, dtype=np.uint32)
    patch_source = np.full(N + 1, INVALID, np.uint32)
    patch_source[vl] = E + np.arange(V, dtype=np.uint32)
    src._tables = Tables(
        n_emitter_reg=n_reg, n_patch_slots=N + 1,
        emitter_source=jit(mi.UInt32, emitter_source), patch_source=jit(mi.UInt32, patch_source),
        center=_dr3(src.center, mi.Point3f), axis=_dr3(src.axis, mi.Vector3f),
        radius=jit(mi.Float, _pad(src.radius, np.float32)),
        intensity=jit(mi.Float, _pad(src.intensity, np.float32)),
        infinite=jit(mi.Bool, _pad(src.infinite, bool, False)),
        # packed per-source records for estimate(): one 4-wide (packet) gather each, which
        # Dr.Jit emits only from an aligned buffer (host_arrays.jit): handed numpy's own
        # buffer, the kernel was a packet load or four loads as the allocation fell, and was
        # compiled again between prepass seeds (tests/prepass/test_kernel_reuse.py)
        sphere=jit(mi.Float, _packed4(src.center, src.radius)),
        axis_intensity=jit(mi.Float, _packed4(src.axis, src.intensity)),
        flags=jit(mi.UInt32, _pad(_flags(src), np.uint32)),
        in_delta=jit(mi.Bool, _pad(np.isin(np.arange(S), src.delta_ids), bool, False)),
        in_emitters=jit(mi.Bool, _pad(np.isin(np.arange(S), src.emitter_ids), bool, False)),
        is_patch=jit(mi.Bool, _pad(src.kind == KIND_PATCH, bool, False)),
        emitter_index=jit(mi.UInt32, _pad(np.maximum(src.emitter_index, 0), np.uint32)),
        patch_id=jit(mi.UInt32, _pad(src.patch_id, np.uint32, N)),
        delta_ids=jit(mi.UInt32, _pad(src.delta_ids, np.uint32, INVALID)),
        n_delta=int(src.delta_ids.size),
        emitters_ids=jit(mi.UInt32, _pad(src.emitter_ids, np.uint32, INVALID)),
        n_emitters=int(src.emitter_ids.size), count=S)
    return src


# ----------------------------------------------------------------------------------------------
# Camera pass


def camera_points(scene, sensor=None, res=64, seed=0, max_delta=8):
    """First non-delta hit points of a ``res``-ray (longer film side) jittered camera pass,
    followed through delta bounces: ``(points (n, 3), normals (n, 3) facing the ray, rays)``;
    a point on a transmissive surface comes twice, once per side."""
    sensor = sensor if sensor is not None else scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    nx = res if w >= h else max(1, round(res * w / h))
    ny = res if h >= w else max(1, round(res * h / w))
    n = nx * ny
    idx = dr.arange(mi.UInt32, n)
    rng = _rng(n, seed, _SALT_CAMERA)
    pos = mi.Point2f((mi.Float(idx % nx) + rng.next_float32()) / nx,
                     (mi.Float(idx // nx) + rng.next_float32()) / ny)
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), pos, mi.Point2f(0.5, 0.5))
    ray = mi.Ray3f(ray)
    ctx = mi.BSDFContext()
    found = dr.full(mi.Bool, False, n)
    P = dr.zeros(mi.Point3f, n)
    Nrm = dr.zeros(mi.Vector3f, n)
    T = dr.zeros(mi.Bool, n)  # transmissive: a receiver on both sides
    active = dr.full(mi.Bool, True, n)
    rays = 0
    n_active = n
    for _ in range(max_delta + 1):  # bounce depth, each a wavefront over all rays
        rays += n_active
        si = scene.ray_intersect(ray, active)
        valid = active & si.is_valid()
        bsdf = si.bsdf(ray)
        smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        record = valid & smooth
        facing = dr.select(dr.dot(si.n, -ray.d) >= 0, 1.0, -1.0)
        P[record] = si.p
        Nrm[record] = si.n * facing
        T[record] = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission)
        found |= record
        bs, _ = bsdf.sample(ctx, si, rng.next_float32(),
                            mi.Point2f(rng.next_float32(), rng.next_float32()), valid & ~smooth)
        ray = si.spawn_ray(si.to_world(bs.wo))
        active = valid & ~smooth & (bs.pdf > 0)
        dr.eval(P, Nrm, T, found, ray, active)
        n_active = int(dr.count(active)[0])  # the rays of the next bounce
        if n_active == 0:
            break
    keep = np.array(found, dtype=bool)
    return _both_sides(_np3(P)[keep], _np3(Nrm)[keep], np.array(T, dtype=bool)[keep]) + (rays,)


def _both_sides(P, N, two_sided):
    """Points with their normals, a transmissive point once more with the normal flipped."""
    return (np.concatenate([P, P[two_sided]]), np.concatenate([N, -N[two_sided]]))


def bounce_points(scene, P, Nrm, reach, seed=0):
    """Where the image's *near* gather rays land: one cosine-distributed ray about the normal
    from each camera point ``P``; hits on non-delta surfaces closer than ``reach`` (the
    integrator's r_thresh, below which a gather recurses and gathers explicitly again) →
    ``(points, normals facing the ray, rays)``. Their cells need lists too, else those
    explicit gathers fall back to choosing among all emitters."""
    n = int(P.shape[0])
    if n == 0 or not reach > 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), 0
    rng = _rng(n, seed, _SALT_BOUNCE)
    p = _dr3(P, mi.Point3f)
    frame = mi.Frame3f(_dr3(Nrm, mi.Vector3f))
    d = frame.to_world(mi.warp.square_to_cosine_hemisphere(
        mi.Point2f(rng.next_float32(), rng.next_float32())))
    eps = 1e-4 * max(float(reach), _TINY)
    ray = mi.Ray3f(p + frame.n * eps, d)
    ray.maxt = dr.opaque(mi.Float, float(reach))
    si = scene.ray_intersect(ray)
    bsdf = si.bsdf(ray)
    keep = si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    facing = dr.select(dr.dot(si.n, -ray.d) >= 0, 1.0, -1.0)
    two = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission)
    k = np.array(keep, dtype=bool)
    return _both_sides(_np3(si.p)[k], _np3(si.n * facing)[k], np.array(two, dtype=bool)[k]) \
        + (n,)


# ----------------------------------------------------------------------------------------------
# The grid


@dataclass
class SpikeGrid:
    """Spike lists (CSR) of the cells the camera sees, over a regular grid (§4)."""

    sources: Sources
    bbox_min: np.ndarray  # (3,)
    cell_size: float
    dims: np.ndarray  # (3,) cells per axis
    list_cell: np.ndarray  # (L,) linear cell id of each list
    offsets: np.ndarray  # (L+1,) CSR
    source: np.ndarray  # (nnz,) source ids, ascending within a list
    g: np.ndarray  # (nnz,) visibility fractions in (0, 1]
    points: np.ndarray  # (P, 3) visibility sample points (offset), grouped by list
    point_offsets: np.ndarray  # (L+1,)
    stats: dict = field(default_factory=dict)
    _tables: Tables = field(default_factory=Tables, repr=False)

    @property
    def count(self) -> int:
        """Number of lists (cells with a list)."""
        return int(self.list_cell.shape[0])

    @property
    def lengths(self) -> np.ndarray:
        return np.diff(self.offsets)

    @property
    def nbytes(self) -> int:
        """Memory of the render-time structure: dense cell table, CSR lists and keys."""
        n_cells = int(np.prod(self.dims))
        nnz = int(self.source.shape[0])
        return int(4 * n_cells + 4 * (self.count + 1) + nnz * (4 + 4 + 32 + 4 + 8)
                   + 4 * self.count + self.sources.nbytes)

    def list_of_source(self, lid) -> dict:
        """{source id: g} of list ``lid`` (numpy; for tests and inspection)."""
        a, b = int(self.offsets[lid]), int(self.offsets[lid + 1])
        return dict(zip(self.source[a:b].tolist(), self.g[a:b].tolist()))

    def cell_of_np(self, p) -> np.ndarray:
        """numpy twin of :meth:`cell_index` (clamped)."""
        ijk = np.floor((np.asarray(p, np.float64) - self.bbox_min) / self.cell_size)
        ijk = np.clip(ijk, 0, self.dims - 1).astype(np.int64)
        return (ijk[..., 2] * self.dims[1] + ijk[..., 1]) * self.dims[0] + ijk[..., 0]

    # -- Dr.Jit queries ---------------------------------------------------------------------
    def _cell(self, p, clamp):
        inv_h = 1.0 / self.cell_size
        nx, ny, nz = (int(v) for v in self.dims)
        q = (p - mi.Point3f(*(float(v) for v in self.bbox_min))) * inv_h
        f = dr.floor(q)
        inside = (f.x >= 0) & (f.y >= 0) & (f.z >= 0) & (f.x < nx) & (f.y < ny) & (f.z < nz)
        ix = mi.UInt32(dr.clip(f.x, 0, nx - 1))
        iy = mi.UInt32(dr.clip(f.y, 0, ny - 1))
        iz = mi.UInt32(dr.clip(f.z, 0, nz - 1))
        cell = (iz * ny + iy) * nx + ix
        ok = dr.isfinite(q.x) & dr.isfinite(q.y) & dr.isfinite(q.z)
        return cell, ok & (inside | clamp)

    def cell_index(self, p):
        """Linear id of the cell holding ``p`` (clamped to the grid)."""
        return self._cell(p, True)[0]

    def list_at(self, p, active=True, clamp=True):
        """List id of the cell holding ``p``; ``INVALID`` where it has none (or, unless
        ``clamp``, where ``p`` is outside the grid)."""
        cell, ok = self._cell(p, clamp)
        ok &= mi.Bool(active)
        return dr.select(ok, dr.gather(mi.UInt32, self._tables["cell_list"], cell, ok), INVALID)

    def choose_lists(self, p, u3, active=True, jitter=1.0):
        """§4's boundary weighting, as a pair of lists ``(a, b)``: ``a`` is the list of ``p``'s
        cell, ``b`` the list of the cell of ``p`` jittered by up to ±``jitter``/2 cell per axis
        (``u3`` uniform in [0,1)³) where that differs; ``b`` is ``INVALID`` otherwise, and a
        missing ``a`` is replaced by ``b``. :meth:`sample` draws from the mixture of both."""
        own = self.list_at(p, active)
        offset = (mi.Vector3f(u3) - 0.5) * (self.cell_size * jitter)
        other = self.list_at(p + offset, active, clamp=False)
        other = dr.select(other == own, INVALID, other)
        swap = own == INVALID
        return dr.select(swap, other, own), dr.select(swap, INVALID, other)

    def list_range(self, lid, active=True):
        """``(start, count)`` of list ``lid`` in the CSR arrays (count 0 for ``INVALID``)."""
        ok = mi.Bool(active) & (lid != INVALID)
        start = dr.gather(mi.UInt32, self._tables["offsets"], lid, ok)
        end = dr.gather(mi.UInt32, self._tables["offsets"], lid + 1, ok)
        return dr.select(ok, start, 0), dr.select(ok, end - start, 0)

    def contains(self, lid, sid, active=True):
        """``(found, g)``: is source ``sid`` in list ``lid``, and its visibility fraction."""
        found, e = self.entry_of(lid, sid, active)
        return found, dr.select(found, dr.gather(mi.Float, self._tables["g"], e, found), 0.0)

    def entry_of(self, lid, sid, active=True):
        """``(found, e)``: is source ``sid`` in list ``lid``, and its entry index in the CSR
        arrays. A binary search inside the list's range (sources ascend within a list), as a
        symbolic loop: no table size enters the kernel, so a new prepass (other list lengths)
        reuses the compiled render kernel."""
        t = self._tables
        ok = mi.Bool(active) & (lid != INVALID) & (sid != INVALID)
        start, count = self.list_range(lid, ok)
        sid = mi.UInt32(sid)
        src_table = t["source"]

        def cond(lo, hi):
            return lo < hi

        def body(lo, hi):  # first index in [lo, hi) whose source is >= sid
            mid = lo + (hi - lo) // 2
            less = dr.gather(mi.UInt32, src_table, mid, lo < hi) < sid
            return dr.select(less, mid + 1, lo), dr.select(less, hi, mid)

        lo, _ = dr.while_loop((mi.UInt32(start), dr.select(ok, start + count, start)), cond, body,
                              label="spike_contains")
        found = ok & (lo < start + count)
        found &= dr.gather(mi.UInt32, src_table, lo, found) == sid
        return found, lo

    # -- selection by cell (the per-cell CDF) ----------------------------------------------
    def cell_pick(self, lid, u, active=True):
        """``(source, entry)`` drawn from list ``lid`` with the cell's fixed probabilities
        (:func:`cell_weights`): the first entry whose cumulative probability exceeds ``u``, a
        binary search over the list's CDF (no source is estimated at the shading point)."""
        t = self._tables
        ok = mi.Bool(active) & (lid != INVALID)
        start, count = self.list_range(lid, ok)
        cdf = t["cell_cdf"]
        u = mi.Float(u)

        def cond(lo, hi):
            return lo < hi

        def body(lo, hi):  # first index in [lo, hi) whose cdf is > u
            mid = lo + (hi - lo) // 2
            below = dr.gather(mi.Float, cdf, mid, lo < hi) <= u
            return dr.select(below, mid + 1, lo), dr.select(below, hi, mid)

        end = dr.select(ok, start + count, start)
        lo, _ = dr.while_loop((mi.UInt32(start), end), cond, body, label="spike_cell_pick")
        e = dr.minimum(lo, dr.maximum(end, 1) - 1)  # u at the very top: the last entry
        ok &= count > 0
        return dr.select(ok, dr.gather(mi.UInt32, t["source"], e, ok), INVALID), e

    def cell_prob(self, lid, sid, active=True):
        """The probability :meth:`cell_pick` draws ``sid`` from list ``lid`` (0 if unlisted)."""
        found, e = self.entry_of(lid, sid, active)
        return dr.select(found, dr.gather(mi.Float, self._tables["cell_prob"], e, found), 0.0)

    def cell_mixture(self, lid_a, lid_b, defensive, support="delta"):
        """``(ε, m_a, m_b)`` of the per-cell selection: as :meth:`mixture`, a list counting
        where its cell weights sum above 0."""
        t = self._tables
        W_a = dr.gather(mi.Float, t["list_W"], lid_a, lid_a != INVALID)
        W_b = dr.gather(mi.Float, t["list_W"], lid_b, lid_b != INVALID)
        return self.mixture(lid_a, lid_b, W_a, W_b, defensive, support)

    # -- selection (§2.6, §4) ---------------------------------------------------------------
    def reservoir(self, lid, p, n, two_sided, u, r_thresh, active=True):
        """One pass of weighted reservoir sampling over list ``lid`` with weights
        w_j = g_j·L'_j(x): ``(source, w_source, W = Σ w_j)``; ``INVALID`` where W = 0.

        A functional ``dr.while_loop`` whose state is the reservoir alone: the tables are read
        through the closure, so an enclosing symbolic loop never sees them rewritten."""
        start, count = self.list_range(lid, active)
        t = self._tables
        src_table, sphere_table, axis_table, flag_table = (
            t["source"], t["entry_sphere"], t["entry_axis_gI"], t["entry_flags"])
        p, n = mi.Point3f(p), mi.Vector3f(n)
        two_sided, r_thresh = mi.Bool(two_sided), mi.Float(r_thresh)

        def cond(j, W, chosen, w_chosen, u, run):
            return run

        def body(j, W, chosen, w_chosen, u, run):
            e = start + j
            sid = dr.gather(mi.UInt32, src_table, e, run)
            w = estimate_record(dr.gather(mi.Vector4f, sphere_table, e, run),
                                dr.gather(mi.Vector4f, axis_table, e, run),
                                dr.gather(mi.UInt32, flag_table, e, run),
                                p, n, two_sided, r_thresh, run)  # g_j·L'_j(x)
            W = W + w
            q = dr.select(W > 0, w / dr.maximum(W, _TINY), 0.0)
            take = run & (w > 0) & (u < q)
            chosen = dr.select(take, sid, chosen)
            w_chosen = dr.select(take, w, w_chosen)
            # reuse the uniform: rescale it to [0, 1) within the branch taken
            u = dr.select(take, u / dr.maximum(q, _TINY), (u - q) / dr.maximum(1.0 - q, _TINY))
            u = dr.clip(u, 0.0, 0.99999994)
            j = j + 1
            return j, W, chosen, w_chosen, u, run & (j < count)

        width = max(dr.width(lid), dr.width(p), dr.width(u), dr.width(count))
        j = dr.zeros(mi.UInt32, width)
        state = (j, dr.zeros(mi.Float, width), dr.full(mi.UInt32, INVALID, width),
                 dr.zeros(mi.Float, width), mi.Float(u), mi.Bool(active) & (j < count))
        _, W, chosen, w_chosen, _, _ = dr.while_loop(state, cond, body, label="spike_reservoir")
        return chosen, w_chosen, W

    def support_tables(self, support):
        """(ids table, count, membership table) of a defensive support."""
        if support not in ("delta", "emitters"):
            raise ValueError(f"support={support!r}: expected 'delta' or 'emitters'")
        t = self.sources._tables
        return t[support + "_ids"], t["n_" + support], t["in_" + support]

    def mixture(self, lid_a, lid_b, W_a, W_b, defensive, support="delta"):
        """Weights ``(ε, m_a, m_b)`` of the selection mixture: a source of the defensive
        ``support`` uniformly with ε (0 when it is empty; 1 where neither list has weight),
        else list a or b, equally among those with W > 0."""
        has_a = (lid_a != INVALID) & (W_a > 0)
        has_b = (lid_b != INVALID) & (W_b > 0)
        n_lists = mi.Float(dr.select(has_a, 1, 0) + dr.select(has_b, 1, 0))
        if self.support_tables(support)[1] == 0:
            eps = mi.Float(0.0)
        else:
            eps = dr.select(n_lists > 0, mi.Float(max(float(defensive), 0.0)), 1.0)
        share = (1.0 - eps) / dr.maximum(n_lists, 1.0)
        return eps, dr.select(has_a, share, 0.0), dr.select(has_b, share, 0.0)

    def sample(self, lid_a, lid_b, p, n, two_sided, u_a, u_b, u_mix, r_thresh, defensive=0.0,
               active=True, support="delta"):
        """Choose one source for an explicit sample at ``p`` from the mixture of lists a and b
        and of the defensive component (uniform over ``support``: "delta" sources or all
        "emitters"): ``(sid, P(sid), scale_a, scale_b, eps)``.

        ``P`` is the full selection probability; ``scale_c`` = m_c/W_c, so that a source's
        P = ε·[in support]/K + (scale_a·g_a + scale_b·g_b)·L' (g_c = 0 where it is not in
        list c). ``sid`` is ``INVALID`` where there is nothing to sample."""
        active = mi.Bool(active)
        chosen_a, _, W_a = self.reservoir(lid_a, p, n, two_sided, u_a, r_thresh,
                                          active & (lid_a != INVALID))
        chosen_b, _, W_b = self.reservoir(lid_b, p, n, two_sided, u_b, r_thresh,
                                          active & (lid_b != INVALID))
        eps, m_a, m_b = self.mixture(lid_a, lid_b, W_a, W_b, defensive, support)
        pick_def = active & (u_mix < eps)
        pick_b = active & ~pick_def & (u_mix >= eps + m_a) & (m_b > 0)
        pick_a = active & ~pick_def & ~pick_b & (m_a > 0)
        sid = dr.select(pick_a, chosen_a, dr.select(pick_b, chosen_b, INVALID))
        ids, K, _ = self.support_tables(support)
        if K > 0:
            k = mi.UInt32(dr.minimum(u_mix / dr.maximum(eps, _TINY) * K, K - 1))
            sid = dr.select(pick_def, dr.gather(mi.UInt32, ids, k, pick_def), sid)
        P = self.pmf_given_sums(lid_a, lid_b, W_a, W_b, p, n, two_sided, sid, r_thresh,
                                defensive, active & (sid != INVALID), support)
        scale_a = dr.select(m_a > 0, m_a / dr.maximum(W_a, _TINY), 0.0)
        scale_b = dr.select(m_b > 0, m_b / dr.maximum(W_b, _TINY), 0.0)
        return sid, P, scale_a, scale_b, eps

    def pmf_given_sums(self, lid_a, lid_b, W_a, W_b, p, n, two_sided, sid, r_thresh,
                       defensive=0.0, active=True, support="delta"):
        """P(sid) of :meth:`sample` when the lists' weight sums are known."""
        active = mi.Bool(active) & (sid != INVALID)
        eps, m_a, m_b = self.mixture(lid_a, lid_b, W_a, W_b, defensive, support)
        found_a, g_a = self.contains(lid_a, sid, active)
        found_b, g_b = self.contains(lid_b, sid, active)
        Lp = self.sources.estimate(sid, p, n, two_sided, r_thresh, found_a | found_b)
        P = Lp * (dr.select(found_a & (m_a > 0), m_a * g_a / dr.maximum(W_a, _TINY), 0.0)
                  + dr.select(found_b & (m_b > 0), m_b * g_b / dr.maximum(W_b, _TINY), 0.0))
        _, K, member = self.support_tables(support)
        if K > 0:
            P += dr.select(dr.gather(mi.Bool, member, sid, active), eps / K, 0.0)
        return dr.select(active, P, 0.0)

    def list_sum(self, lid, p, n, two_sided, r_thresh, active=True):
        """W = Σ_j g_j·L'_j(x) of list ``lid`` (a reservoir pass)."""
        active = mi.Bool(active) & (lid != INVALID)
        return self.reservoir(lid, p, n, two_sided, mi.Float(0.5), r_thresh, active)[2]

    def pmf(self, lid_a, lid_b, p, n, two_sided, sid, r_thresh, defensive=0.0, active=True,
            support="delta"):
        """P(sid) of :meth:`sample` (computes the lists' sums with reservoir passes)."""
        W_a = self.list_sum(lid_a, p, n, two_sided, r_thresh, active)
        W_b = self.list_sum(lid_b, p, n, two_sided, r_thresh, active)
        return self.pmf_given_sums(lid_a, lid_b, W_a, W_b, p, n, two_sided, sid, r_thresh,
                                   defensive, active, support)


# ----------------------------------------------------------------------------------------------
# Building


def cell_weights(sources: Sources, lists_l, lists_s, lists_g, points, normals, point_offsets):
    """Per list entry the weight of the per-cell selection, w_e = g_e · mean_j L'_e(x_j, n_j)
    over the cell's visibility points x_j (their surface normals n_j; §4's point weights
    averaged over the cell, so that a shading point draws by a table instead of estimating
    every listed source), and per entry its probability within the list (w_e / Σ_list w) and
    the list's CDF. Returns ``(prob, cdf, W)`` (numpy; W per list)."""
    n_entries = int(lists_s.size)
    L = int(point_offsets.size - 1)
    if n_entries == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(L, np.float64)
    n_pts = np.diff(point_offsets)[lists_l]
    e_idx = np.repeat(np.arange(n_entries), n_pts)
    j_idx = point_offsets[lists_l][e_idx] + (np.arange(e_idx.size)
                                              - np.repeat(np.cumsum(n_pts) - n_pts, n_pts))
    # the sources and points uploaded once, gathered per (entry, point) pair on the device
    sid = jit(mi.UInt32, lists_s[e_idx].astype(np.uint32))
    j = jit(mi.UInt32, j_idx.astype(np.uint32))
    sphere = mi.Vector4f(*_dr_cols(np.column_stack([sources.center, sources.radius])))
    axis_i = mi.Vector4f(*_dr_cols(np.column_stack([sources.axis, sources.intensity])))
    value = estimate_record(
        dr.gather(mi.Vector4f, sphere, sid), dr.gather(mi.Vector4f, axis_i, sid),
        dr.gather(mi.UInt32, jit(mi.UInt32, _flags(sources).astype(np.uint32)), sid),
        dr.gather(mi.Point3f, vectors(points, mi.Point3f), j),
        dr.gather(mi.Vector3f, vectors(normals, mi.Vector3f), j),
        mi.Bool(False), mi.Float(0.0))
    value = np.asarray(value, dtype=np.float64)
    mean = np.bincount(e_idx, weights=value, minlength=n_entries) / np.maximum(
        np.bincount(e_idx, minlength=n_entries), 1)
    w = np.asarray(lists_g, np.float64) * mean
    W = np.bincount(lists_l, weights=w, minlength=L)
    prob = w / np.where(W[lists_l] > 0, W[lists_l], 1.0)
    # CDF within each list (ascending entries), its last entry exactly 1
    csum = np.cumsum(prob)
    first = np.concatenate([[0], np.cumsum(np.bincount(lists_l, minlength=L))])[:-1]
    base = np.where(first > 0, csum[np.maximum(first - 1, 0)], 0.0)
    cdf = csum - base[lists_l]
    last = np.concatenate([first[1:], [n_entries]]) - 1
    has = (np.bincount(lists_l, minlength=L) > 0) & (W > 0)
    cdf[last[has]] = 1.0
    return prob.astype(np.float32), cdf.astype(np.float32), W


def _dr_cols(a):
    """Columns of a numpy (n, k) array as Dr.Jit Floats."""
    return [jit(mi.Float, np.ascontiguousarray(a[:, i], dtype=np.float32)) for i in range(a.shape[1])]


@dataclass(frozen=True)
class SpikeSettings:
    """Parameters of :func:`build_spike_grid` (see the module docstring)."""

    grid_res: int = 32
    camera_res: int = 128
    cell_points: int = 8
    influence: float | None = None  # absolute irradiance threshold of influence regions
    influence_rel: float = 0.01  # ... else this × the median patch irradiance
    visibility_max_rays: int = 100
    #: a pair none of whose first this many rays reached the source is excluded (g = 0)
    visibility_occluded_rays: int = 20
    batch_rays: int = 1 << 21
    point_offset_rel: float = 1e-4  # sample-point offset along the normal, × bbox diagonal
    gather_reach: float = 0.0  # > 0: cells where near gather rays (shorter than this) land too
    # the sources (build_sources): virtual-luminaire threshold, E_high / E_low relative or absolute
    vl_threshold: float = 0.5
    vl_contrast: float = VL_CONTRAST
    e_high_rel: float = 4.0
    e_low_rel: float = 0.1
    E_high: float | None = None
    E_low: float | None = None

    def validate(self):
        if int(self.grid_res) < 1:
            raise ValueError(f"grid_res={self.grid_res}: must be > 0")
        if int(self.camera_res) < 1:
            raise ValueError(f"camera_res={self.camera_res}: must be > 0")
        if int(self.cell_points) < 1:
            raise ValueError(f"cell_points={self.cell_points}: must be > 0")
        if int(self.visibility_max_rays) < VIS_ROUND:
            raise ValueError(f"visibility_max_rays={self.visibility_max_rays}: must be >= "
                             f"{VIS_ROUND}")
        if int(self.visibility_occluded_rays) < VIS_ROUND:
            raise ValueError(f"visibility_occluded_rays={self.visibility_occluded_rays}: must "
                             f"be >= {VIS_ROUND}")


def grid_geometry(scene, grid_res):
    """``(bbox_min, cell_size, dims)`` of a grid with ``grid_res`` cubic cells along the
    longest axis of the scene's bounding box."""
    if int(grid_res) < 1:
        raise ValueError(f"grid_res={grid_res}: must be > 0")
    bb = scene.bbox()
    lo = np.array([bb.min.x, bb.min.y, bb.min.z], dtype=np.float64).ravel()
    hi = np.array([bb.max.x, bb.max.y, bb.max.z], dtype=np.float64).ravel()
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))) or np.any(hi < lo):
        lo, hi = np.zeros(3), np.ones(3)
    extent = hi - lo
    longest = float(extent.max())
    if longest <= 0:
        longest = 1.0
    h = longest / int(grid_res)
    pad = 1e-4 * h
    lo = lo - pad
    extent = extent + 2 * pad
    dims = np.maximum(1, np.ceil(extent / h - 1e-9)).astype(np.int64)
    if int(np.prod(dims)) > MAX_CELLS:
        raise ValueError(f"grid_res={grid_res}: a grid of {int(np.prod(dims))} cells is too "
                         f"large (at most {MAX_CELLS})")
    return lo, h, dims


def _cell_boxes(bbox_min, h, dims, cells):
    nx, ny = int(dims[0]), int(dims[1])
    ix = cells % nx
    iy = (cells // nx) % ny
    iz = cells // (nx * ny)
    lo = bbox_min + h * np.stack([ix, iy, iz], axis=1)
    return lo, lo + h


def candidate_pairs(sources: Sources, box_lo, box_hi, influence: float, chunk=1 << 24):
    """Candidate (list, source) pairs of the bands (§4), list-major, sources ascending: every
    source of BAND_ALL, and those of BAND_INFLUENCE whose influence region (intensity ≥
    ``influence`` · d², d the distance from the cell's box to the source's sphere) meets the
    cell. One Dr.Jit kernel over the (cell, source) pairs, ``chunk`` at most at a time, then
    compressed, in float32 (:func:`_candidate_pairs_numpy`, the float64 reference, may
    differ on a pair at the region's very edge). The numpy version it replaces took 1.1 s
    with 1000 lights; sizes and offsets are opaque, so no kernel is compiled per scene."""
    L, S = int(box_lo.shape[0]), int(sources.count)
    if L == 0 or S == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    band = jit(mi.UInt32, np.asarray(sources.band, np.uint32))
    sphere = mi.Vector4f(*_dr_cols(np.column_stack([sources.center, sources.radius])))
    intensity = jit(mi.Float, np.asarray(sources.intensity, np.float32))
    lo_t, hi_t = vectors(box_lo, mi.Point3f), vectors(box_hi, mi.Point3f)
    S_o, infl = dr.opaque(mi.UInt32, S), dr.opaque(mi.Float, float(influence))
    cells = max(1, int(chunk) // S)
    out_l, out_s = [], []
    for a in range(0, L, cells):  # chunks of cells (memory)
        n = min(cells, L - a)
        a_o = dr.opaque(mi.UInt32, a)
        idx = dr.arange(mi.UInt32, n * S)
        li = idx // S_o
        si = idx - li * S_o
        li += a_o
        b = dr.gather(mi.UInt32, band, si)
        sp = dr.gather(mi.Vector4f, sphere, si)
        c = mi.Point3f(sp.x, sp.y, sp.z)
        q = dr.clip(c, dr.gather(mi.Point3f, lo_t, li), dr.gather(mi.Point3f, hi_t, li))
        d = dr.maximum(dr.norm(c - q) - sp.w, 0.0)
        reach = (d <= 0) | (dr.gather(mi.Float, intensity, si) >= infl * d * d)
        keep = (b == BAND_ALL) | ((b == BAND_INFLUENCE) & reach)
        sel = dr.compress(keep)
        if dr.width(sel) == 0:
            continue
        sel_l = sel // S_o
        out_l.append(np.asarray(sel_l + a_o).astype(np.int64))
        out_s.append(np.asarray(sel - sel_l * S_o).astype(np.int64))
    if not out_l:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_l), np.concatenate(out_s)


def _candidate_pairs_numpy(sources: Sources, box_lo, box_hi, influence: float, chunk=4096):
    """numpy (float64) twin of :func:`candidate_pairs`, for tests."""
    band = sources.band
    all_ids = np.nonzero(band == BAND_ALL)[0]
    infl_ids = np.nonzero(band == BAND_INFLUENCE)[0]
    c = sources.center[infl_ids]
    r = sources.radius[infl_ids]
    intensity = sources.intensity[infl_ids]
    out_l, out_s = [], []
    L = box_lo.shape[0]
    for a in range(0, L, chunk):  # chunks of cells (memory), vectorised inside
        lo, hi = box_lo[a:a + chunk], box_hi[a:a + chunk]
        n = lo.shape[0]
        if infl_ids.size:
            q = np.clip(c[None, :, :], lo[:, None, :], hi[:, None, :])
            d = np.linalg.norm(c[None, :, :] - q, axis=2) - r[None, :]
            d = np.maximum(d, 0.0)
            reach = (d <= 0) | (intensity[None, :] >= influence * d * d)
        else:
            reach = np.zeros((n, 0), bool)
        mask = np.zeros((n, sources.count), bool)
        mask[:, all_ids] = True
        mask[:, infl_ids] = reach
        li, si = np.nonzero(mask)
        out_l.append(li + a)
        out_s.append(si)
    if not out_l:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_l).astype(np.int64), np.concatenate(out_s).astype(np.int64)


def _trace_visibility(scene, sources, patches, pts, pt_off, pair_list, pair_src, seed,
                      round_index, first, per_pair=VIS_ROUND):
    """``per_pair`` rays (one round's ``VIS_ROUND``, or several rounds') for each pair of a
    chunk, from random sample points of the pair's cell to random points of its source, pair
    by pair. Returns (reached per ray (numpy bool), rays traced)."""
    n = pair_list.size * per_pair
    pair = dr.arange(mi.UInt32, n) // dr.opaque(mi.UInt32, per_pair)
    lid = dr.gather(mi.UInt32, jit(mi.UInt32, pair_list.astype(np.uint32)), pair)
    sid = dr.gather(mi.UInt32, jit(mi.UInt32, pair_src.astype(np.uint32)), pair)
    rng = _rng(n, seed ^ (round_index * 0x9E3779B1), _SALT_VIS, first)
    off = dr.gather(mi.UInt32, pt_off, lid)
    cnt = dr.gather(mi.UInt32, pt_off, lid + 1) - off
    k = dr.minimum(mi.UInt32(rng.next_float32() * mi.Float(cnt)), cnt - 1)
    o = dr.gather(mi.Point3f, pts, off + k)
    u2 = mi.Point2f(rng.next_float32(), rng.next_float32())

    is_patch = sources.gather("is_patch", sid)
    is_em = ~is_patch
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(),
                        sources.gather("emitter_index", sid, is_em), is_em)
    it = dr.zeros(mi.Interaction3f, n)
    it.p = o
    it.wavelengths = dr.zeros(mi.Color0f, n)
    ds, w = emitter.sample_direction(it, u2, is_em)
    ok_em = is_em & (ds.pdf > 0) & (dr.max(w) > 0) & dr.all(dr.isfinite(w))
    if patches is not None:
        pid = sources.gather("patch_id", sid, is_patch)
        p_y, n_y, pdf_a = patches.sample_points(pid, u2, is_patch)
        ok_vl = is_patch & (pdf_a > 0) & (dr.dot(n_y, o - p_y) > 0)
        margin = 0.05 * sources.gather("radius", sid, is_patch)
    else:
        p_y, ok_vl, margin = mi.Point3f(0.0), mi.Bool(False), mi.Float(0.0)
    target = dr.select(is_em, ds.p, p_y)
    d = target - o
    dist = dr.norm(d)
    maxt = dr.select(is_em, dist * (1.0 - 1e-4), dist - dr.maximum(margin, 1e-4 * dist))
    # an infinite emitter's point lies 2R from the scene.bbox() centre, and that box can miss
    # merged walls (mi_twopass.rays.shadow_ray): its rays go on to infinity
    maxt = dr.select(is_em & mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite), dr.inf,
                     maxt)
    ok = (ok_em | ok_vl) & (dist > 0) & (maxt > 0) & dr.isfinite(dist)
    ray = mi.Ray3f(o, d / dr.maximum(dist, _TINY))
    ray.maxt = dr.maximum(maxt, 0.0)
    blocked = scene.ray_test(ray, ok)
    reached = ok & ~blocked
    dr.eval(reached, ok)  # one kernel for both (a dr.count of ok launched its own)
    return np.array(reached, dtype=bool), int(np.count_nonzero(np.array(ok, dtype=bool)))


def can_light(sources: Sources, pair_list, pair_src, pts, pt_off, chunk=1 << 20):
    """For each candidate pair (list, source): can the source light any of the list's cell
    points ``pts[pt_off[l]:pt_off[l+1]]`` (numpy (P, 3) positions and (P, 3) normals facing the
    viewer), i.e. is its conservative L' > 0 at one of them (:meth:`Sources.estimate`, one-sided:
    a point of a transmissive surface is given once per side)? A source behind every point's
    horizon, or facing away from all of them, cannot; its visibility rays would start into the
    surface. One symbolic loop per chunk of pairs over the cell's points. → bool (n_pairs,)."""
    P, N = pts
    out = np.zeros(pair_list.size, bool)
    if pair_list.size == 0 or P.shape[0] == 0:
        return out
    p_tab, n_tab = _dr3(P, mi.Point3f), _dr3(N, mi.Vector3f)
    off = jit(mi.UInt32, np.asarray(pt_off, np.uint32))
    for a in range(0, pair_list.size, chunk):
        lid = jit(mi.UInt32, pair_list[a:a + chunk].astype(np.uint32))
        sid = jit(mi.UInt32, pair_src[a:a + chunk].astype(np.uint32))
        start = dr.gather(mi.UInt32, off, lid)
        end = dr.gather(mi.UInt32, off, lid + 1)

        def cond(k, found):
            return (k < end) & ~found

        def body(k, found):
            x = dr.gather(mi.Point3f, p_tab, k)
            n = dr.gather(mi.Vector3f, n_tab, k)
            found |= sources.estimate(sid, x, n, mi.Bool(False), mi.Float(0.0)) > 0
            return k + 1, found

        _, found = dr.while_loop((mi.UInt32(start), dr.zeros(mi.Bool, dr.width(lid))), cond,
                                 body, label="spike_can_light")
        out[a:a + chunk] = np.array(found, dtype=bool)
    return out


def estimate_visibility(trace, n_pairs, max_rays=100, chunk_pairs=None, occluded_rays=None,
                        tail_rays=None):
    """The self-refining visibility estimate of §4 for ``n_pairs`` pairs; a pair with no ray
    through after ``occluded_rays`` rays (None: never; the paper's rule) is done with g = 0.

    ``trace(pairs, round_index) -> hits`` returns, for the pair indices given (numpy int64),
    how many of ``VIS_ROUND`` rays reached the source. Returns ``(g (n_pairs,), rays_per_pair)``.

    ``tail_rays``: once a round's rays (open pairs × ``VIS_ROUND``) are at most this many,
    every round left is traced in one call, ``trace(pairs, round_index, rounds) -> hits
    (pairs, rounds)``, and the rule is applied to its rounds in turn. Each round's rays are
    drawn independently of the others' either way, so the estimate is the same; the rays of
    rounds a pair does not reach are traced for nothing (at most ``tail_rays`` × the rounds
    left), for one call's fixed cost instead of one per round: on many_lights at 256² rounds
    3–10 held 4k to 600 pairs and took 14–17 ms each, 0.5–2 ms of it tracing rays
    (:data:`VIS_TAIL_RAYS`).
    """
    rounds = max(1, int(max_rays) // VIS_ROUND)
    H = np.zeros(n_pairs, np.int64)
    n = np.zeros(n_pairs, np.int64)
    g = np.zeros(n_pairs)
    open_ = np.arange(n_pairs)
    k = 0
    while k < rounds and open_.size:  # ≤ 10 rounds; each is one wavefront over every open pair
        batch = rounds - k if tail_rays is not None and \
            open_.size * VIS_ROUND <= tail_rays else 1
        hits = np.asarray(trace(open_, k) if batch == 1 else trace(open_, k, batch),
                          dtype=np.int64).reshape(open_.size, batch)
        row = np.arange(open_.size)  # each open pair's row of hits
        for j in range(batch):
            if open_.size == 0:
                break
            h = hits[row, j]
            prev = np.where(n[open_] > 0, H[open_] / np.maximum(n[open_], 1), 0.0)
            H[open_] += h
            n[open_] += VIS_ROUND
            if k == 0:
                done = h == VIS_ROUND
            else:
                done = (h > 1) & (np.abs(h / VIS_ROUND - prev) <= VIS_TOL + 1e-9)
            if occluded_rays is not None:
                done |= (H[open_] == 0) & (n[open_] >= int(occluded_rays))
            if k == rounds - 1:
                done[:] = True
            fin = open_[done]
            g[fin] = H[fin] / n[fin]
            open_, row = open_[~done], row[~done]
            k += 1
    return g, n


@dataclass
class SpikePrepass:
    """Everything the ``spike_gather`` integrator reads at render time."""

    solution: object  # RadiositySolution or None
    sources: Sources
    grid: SpikeGrid
    stats: dict

    @property
    def nbytes(self) -> int:
        rad = int(self.solution.nbytes) if self.solution is not None else 0
        return rad + self.grid.nbytes


def build_spike_grid(scene, sources: Sources, settings: SpikeSettings, seed=0, sensor=None,
                     solution=None, bar=None) -> SpikeGrid:
    """Lists of the camera-seen cells: camera pass, candidates, visibility, CSR (§4). ``bar``
    (a tqdm-like bar, optional) is advanced once per visibility round."""
    settings.validate()
    t0 = time.perf_counter()
    bbox_min, h, dims = grid_geometry(scene, settings.grid_res)
    diag = float(np.linalg.norm(dims * h))
    if len(scene.sensors()) or sensor is not None:
        P, Nrm, camera_rays = camera_points(scene, sensor, settings.camera_res, seed)
    else:
        P, Nrm, camera_rays = np.zeros((0, 3)), np.zeros((0, 3)), 0
    n_camera = P.shape[0]
    Pb, Nb, bounce_rays = bounce_points(scene, P, Nrm, settings.gather_reach, seed)
    P, Nrm = np.concatenate([P, Pb]), np.concatenate([Nrm, Nb])
    camera_rays += bounce_rays
    t_camera = time.perf_counter() - t0

    grid = SpikeGrid(sources=sources, bbox_min=bbox_min, cell_size=h, dims=dims,
                     list_cell=np.zeros(0, np.int64), offsets=np.zeros(1, np.int64),
                     source=np.zeros(0, np.int64), g=np.zeros(0, np.float32),
                     points=np.zeros((0, 3)), point_offsets=np.zeros(1, np.int64))
    cells = grid.cell_of_np(P) if P.shape[0] else np.zeros(0, np.int64)
    list_cell, inverse = np.unique(cells, return_inverse=True)
    L = list_cell.size
    # visibility sample points: up to cell_points random hits per cell, offset along the normal
    rng = numpy_rng(seed, _SALT_POINTS)
    perm = rng.permutation(cells.size)
    order = perm[np.argsort(inverse[perm], kind="stable")]
    lst = inverse[order]
    first = np.searchsorted(lst, np.arange(L))
    rank = np.arange(lst.size) - first[lst]
    keep = order[rank < settings.cell_points]
    keep = keep[np.argsort(inverse[keep], kind="stable")]
    points = P[keep] + Nrm[keep] * (settings.point_offset_rel * diag)
    point_normals = Nrm[keep]
    point_offsets = np.concatenate([[0], np.cumsum(np.bincount(inverse[keep], minlength=L))])

    # influence threshold: a fraction of the typical (median) patch irradiance
    if settings.influence is not None:
        influence = float(settings.influence)
    elif solution is not None and solution.patches.count:
        E = _lum(solution.E)
        influence = settings.influence_rel * float(np.median(E[E > 0])) if (E > 0).any() else 0.0
    else:
        influence = 0.0
    box_lo, box_hi = _cell_boxes(bbox_min, h, dims, list_cell)
    pair_list, pair_src = candidate_pairs(sources, box_lo, box_hi, influence)
    n_candidates = int(pair_list.size)
    # candidates that cannot light any of the cell's points need no visibility rays
    by_list = np.argsort(inverse, kind="stable")
    all_off = np.concatenate([[0], np.cumsum(np.bincount(inverse, minlength=L))])
    lit = can_light(sources, pair_list, pair_src, (P[by_list], Nrm[by_list]), all_off)
    pair_list, pair_src = pair_list[lit], pair_src[lit]
    t_cand = time.perf_counter() - t0 - t_camera

    # self-refining visibility, one wavefront per round (chunked)
    pts_dr = _dr3(points, mi.Point3f)
    pt_off_dr = jit(mi.UInt32, point_offsets.astype(np.uint32))
    patches = solution.patches if solution is not None else None
    counter = {"rays": 0, "first": 0}

    def trace(pairs, k, rounds=1):
        per_pair = VIS_ROUND * rounds
        chunk = max(1, settings.batch_rays // per_pair)
        hits = np.zeros((pairs.size, rounds), np.int64)
        for a in range(0, pairs.size, chunk):  # chunks bound memory; each is one ray_test
            sel = pairs[a:a + chunk]
            reached, rays = _trace_visibility(scene, sources, patches, pts_dr, pt_off_dr,
                                              pair_list[sel], pair_src[sel], seed, k,
                                              counter["first"], per_pair)
            counter["first"] += sel.size * per_pair
            counter["rays"] += rays
            hits[a:a + chunk] = reached.reshape(-1, rounds, VIS_ROUND).sum(axis=2)
        if bar is not None:
            bar.update(rounds)
        return hits

    g, rays_per_pair = estimate_visibility(trace, pair_list.size, settings.visibility_max_rays,
                                           occluded_rays=settings.visibility_occluded_rays,
                                           tail_rays=VIS_TAIL_RAYS)
    t_vis = time.perf_counter() - t0 - t_camera - t_cand

    keep = g > 0
    lists_l, lists_s, lists_g = pair_list[keep], pair_src[keep], g[keep].astype(np.float32)
    offsets = np.concatenate([[0], np.cumsum(np.bincount(lists_l, minlength=L))]).astype(np.int64)
    grid.list_cell, grid.offsets = list_cell.astype(np.int64), offsets
    grid.source, grid.g = lists_s, lists_g
    grid.points, grid.point_offsets = points, point_offsets.astype(np.int64)

    n_cells = int(np.prod(dims))
    cell_list = np.full(n_cells, INVALID, np.uint32)
    cell_list[list_cell] = np.arange(L, dtype=np.uint32)
    prob, cdf, W_cell = cell_weights(sources, lists_l, lists_s, lists_g, points, point_normals,
                                     point_offsets)
    grid._tables = Tables(
        cell_list=mi.UInt32(cell_list),
        offsets=jit(mi.UInt32, offsets.astype(np.uint32)),
        source=jit(mi.UInt32, _pad(lists_s, np.uint32, INVALID)),
        g=jit(mi.Float, _pad(lists_g, np.float32)),
        # per-entry source records for the list sweep (intensity × g)
        entry_sphere=jit(mi.Float, _packed4(sources.center[lists_s], sources.radius[lists_s])),
        entry_axis_gI=jit(mi.Float, _packed4(sources.axis[lists_s],
                                             sources.intensity[lists_s] * lists_g)),
        entry_flags=jit(mi.UInt32, _pad(_flags(sources)[lists_s], np.uint32)),
        # the per-cell selection (cell_weights): entry probabilities, CDFs, list sums
        cell_prob=jit(mi.Float, _pad(prob, np.float32)), cell_cdf=jit(mi.Float, _pad(cdf, np.float32)),
        list_W=jit(mi.Float, _pad(W_cell.astype(np.float32), np.float32)))
    lengths = np.diff(offsets)
    grid.stats = dict(
        grid_dims=[int(v) for v in dims], cell_size=float(h), cells_with_lists=int(L),
        spike_list_mean=float(lengths.mean()) if L else 0.0,
        spike_list_max=int(lengths.max()) if L else 0,
        spike_entries=int(lengths.sum()), candidate_pairs=int(n_candidates),
        behind_horizon=int(n_candidates - pair_list.size),
        visibility_rays=int(counter["rays"]), camera_rays=int(camera_rays),
        camera_points=int(n_camera), bounce_points=int(P.shape[0] - n_camera),
        influence=float(influence),
        visibility_full=int(np.count_nonzero(g == 1.0)),
        visibility_excluded=int(np.count_nonzero(g == 0)),
        camera_seconds=t_camera, visibility_seconds=t_vis,
        grid_bytes=0)
    grid.stats["grid_bytes"] = grid.nbytes
    return grid


def build_spike_prepass(scene, settings: SpikeSettings, solution=None, vl_threshold=0.5,
                        e_high_rel=4.0, e_low_rel=0.1, E_high=None, E_low=None, seed=0,
                        sensor=None, progress: bool = True,
                        vl_contrast=VL_CONTRAST) -> SpikePrepass:
    """Sources and grid of ``scene`` on top of a radiosity ``solution`` (may be ``None``).

    ``progress``: a bar over the visibility rounds (shown on a terminal,
    :func:`mi_twopass.progress.progress`)."""
    t0 = time.perf_counter()
    sources = build_sources(scene, solution, vl_threshold=vl_threshold, e_high_rel=e_high_rel,
                            e_low_rel=e_low_rel, E_high=E_high, E_low=E_low, seed=seed,
                            vl_contrast=vl_contrast)
    t_sources = time.perf_counter() - t0
    with progress_bar(total=settings.visibility_max_rays // VIS_ROUND, desc="spike lists",
                      unit="round", show=progress) as bar:
        grid = build_spike_grid(scene, sources, settings, seed=seed, sensor=sensor,
                                solution=solution, bar=bar)
    stats = dict(grid.stats)
    stats.update(sources=sources.count, virtual_luminaires=int((sources.kind == KIND_PATCH).sum()),
                 delta_sources=int(sources.delta_ids.size), E_high=float(sources.E_high),
                 E_low=float(sources.E_low), sources_seconds=t_sources,
                 bands={"all": int((sources.band == BAND_ALL).sum()),
                        "influence": int((sources.band == BAND_INFLUENCE).sum()),
                        "implicit": int((sources.band == BAND_IMPLICIT).sum())})
    return SpikePrepass(solution=solution, sources=sources, grid=grid, stats=stats)


__all__ = ["INVALID", "Sources", "SpikeGrid", "SpikeSettings", "SpikePrepass", "build_sources",
           "build_spike_grid", "build_spike_prepass", "bounce_points", "camera_points",
           "can_light", "candidate_pairs",
           "estimate_visibility", "grid_geometry", "conservative_cos"]


def build(scene, settings: SpikeSettings, radiosity: RadiositySettings, seed: int,
          progress: bool = True, sensor=None, memo=None) -> SpikePrepass:
    """The whole spike_gather prepass (Zimmerman & Shirley §3.3 steps 1–3): the shared
    radiosity prepass (:func:`mi_twopass.prepass.radiosity.build`; its own virtual luminaires
    off: the spike sources reclassify patches by ``settings.vl_threshold``), then the sources
    and the spike lists. ``progress``: bars on the solve and the visibility rounds;
    ``sensor``: the camera that guides the solve's emission and ``memo`` solves shared with
    other prepasses (``radiosity.build``)."""
    t0 = time.perf_counter()
    rad = build_radiosity(scene, replace(radiosity, vl_threshold=math.inf), seed, progress,
                          sensor=sensor, memo=memo)
    pre = build_spike_prepass(scene, settings, solution=rad.solution,
                              vl_threshold=settings.vl_threshold,
                              vl_contrast=settings.vl_contrast,
                              e_high_rel=settings.e_high_rel, e_low_rel=settings.e_low_rel,
                              E_high=settings.E_high, E_low=settings.E_low, seed=seed,
                              sensor=sensor, progress=progress)
    rad_stats = {k: v for k, v in rad.stats.items() if k != "virtual_luminaires"}
    pre.stats.update(rad_stats, spike_seconds=time.perf_counter() - t0 - rad.seconds)
    return pre
