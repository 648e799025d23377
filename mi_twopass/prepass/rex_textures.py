"""Adaptive radiosity textures (rexes) and the passes that fill them.

Heckbert, "Adaptive Radiosity Textures for Bidirectional Ray Tracing", SIGGRAPH 1990
(docs/design.md "Papers"). Names follow the paper: a *rex* is a quadtree histogram over the (u, v)
parameter square of one diffuse surface region; its leaves are *buckets* that count photons and
add up their power (flux); the *light quadtree* stratifies the emission of every light.

The build (:func:`build`) runs three steps, each a Dr.Jit wavefront:

1. **Size pass** (§3.4.1, :func:`size_pass`): rays from the eye, through delta and glossy
   bounces, record at their first diffuse hit the size of a pixel's preimage in that surface's
   parameter space (ray differentials spread over the path length, projected on the tangent plane,
   divided by the parameterisation's Jacobian |∂p/∂u × ∂p/∂v|). The coarsest level at which a
   rex bucket is at most ``bucket_pixels`` pixels wide (so more than half of that) becomes the
   bucket's *cap*, per 8×8 size cell of an analytic shape and per triangle of a mesh. Regions
   no eye ray saw are capped at level 0. The cap is soft (step 3): it saves photons where finer
   buckets would not show, but a surface seen only in part (a lamp shade's rim) or missed by
   the size pass must still converge.
2. **Light pass** (§3.4.2, §4.1, :func:`light_pass`): per light, an adaptive quadtree over one 2-D
   factor of Mitsuba's ``Emitter.sample_ray`` primary sample space (the direction of point and
   area lights and of the environment, the direction of a spot, the beam cross-section of a
   directional light; photons of area and infinite emitters are built by :func:`emitter_rays`).
   Level by level, every new node sends one jittered *pilot* ray to its first
   diffuse hit; a node is split when one of its four neighbours reached another surface or
   specular chain (a different path signature: silhouettes, shadow and caustic edges) or landed
   farther away than ``light_split_dist``, and only where one of the two hits is seen by the eye
   (size pass). Neighbours of split nodes one level coarser are split too (the paper's restricted
   quadtree). The other 2-D factor (the position on an area light) is stratified by padding: one
   jittered stratum of a randomly permuted grid per ray. The tree grows to 1/:data:`LEAF_PHOTONS`
   of the light's photon budget (shared among lights by power; the nodes of the deepest level
   send no pilot, nothing would read it); then every leaf shoots its final photons afresh, ``reps``
   jittered photons per quadrant (unbiased: the tree depends only on the pilot rays), each
   carrying Φ = weight · |quadrant| / reps. With the light guide (the default,
   :mod:`mi_twopass.prepass.light_guide`) a leaf's reps follow its area × √(the probe shoot's
   deposits on seen rexes per photon there), and each light's budget its power × its mean √.
   Photons follow delta and glossy bounces (``bsdf.sample`` in ``TransportMode.Importance``:
   Fresnel-weighted reflection or refraction) and, at every diffuse vertex, deposit their flux and
   continue diffusely with Russian roulette: L(S*D)*S*E is complete (the simple alternative to
   §4's progressive shooting from bright rexes).
3. **Rex build** (§4.0.5, :func:`build_rex_tree`): the histogram-redistribution problem of §4.1
   is avoided by keeping the photon records (rex, u, v, Φ) of the final shoot — the paper's own
   suggestion in §5 — and building every rex quadtree from them: a bucket splits while it holds
   more than ``split_limit`` photons, or, past its cap, more than split_limit·4^(levels past the
   cap): the buckets still shrink as the photon count grows. No photon is shot twice and no bucket
   mass is ever redistributed: each bucket's sum is exact for its final extent. (The split uses
   the same photons as the estimate; by symmetry the estimate at a point stays unbiased, though
   split buckets lean high and unsplit ones low.) The records are sorted once by a Morton key
   (:func:`quadtree_cells`), so that every node's records are one run of them and a level costs
   its nodes, not its records. The deposit into the leaves sums fixed-point quanta exactly (as
   float64 integers below 2^53), so that the sums, hence the images, do not depend on the order
   in which the light pass's atomic counter recorded them. A bucket's irradiance is E = ΣΦ / area
   (:mod:`mi_twopass.units`), with the exact world area of its parameter square times the
   fraction of it that closed objects resting on the surface leave open (:func:`probe_exposure`:
   no dark seam along the foot of a box). Deposits are weighted by |cos θ_shading| /
   |cos θ_geometric| of the arriving photon (the irradiance a diffuse BSDF integrates), and
   keep their photon's depth: under a finite max_depth each bucket holds one irradiance per eye
   depth (:func:`depth_classes`).

Rays spawned here are offset relative to the scene's size (:func:`mi_twopass.rays.spawn_ray`); lengths are
relative to :func:`scene_bounds`, the shapes' own bounds (Mitsuba's ``scene.bbox()`` misses
rectangles it merged into one mesh). Scenes with participating media are refused
(:func:`check_no_media`).

Lookups (:meth:`Rexes.irradiance`) descend the quadtree and interpolate bilinearly between the
centres of the leaf and its three neighbours towards the query point (neighbours found by
descending at the centre ± one leaf size; outside the parameter domain, or on a zero-area bucket,
the leaf's own value is used), so neither blocks nor seams between buckets of one rex show. Mesh
regions are single triangles in barycentric coordinates (b1, b2) ∈ [0,1]², b1 + b2 ≤ 1; their
rexes do not interpolate across triangle edges.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import units
from ..evaluation.metrics import BLOCK, BLOCK_RELMSE_MAX, RELMSE_EPS
from ..host_arrays import jit, vectors
from ..progress import progress
from ..rays import shadow_ray, spawn_ray
from ..scene.bounds import infinite_light_leaks, scene_bounds
from ..scene.emission import emitter_rays, has_infinite_emitters
from ..scene.lambertian import is_lambertian
from ..scene.order import registry_id, stable_shapes
from ..seeds import hash31
from .light_guide import LightGuide

#: child index of a leaf
LEAF = 0xFFFFFFFF
NO_SHAPE = 0xFFFFFFFF
KIND_NONE, KIND_UV, KIND_TRI = 0, 1, 2
#: how a bucket's world area follows from its parameter square
AREA_FLAT, AREA_SPHERE, AREA_DISK, AREA_TRI = 0, 1, 2, 3
WRAP_U, WRAP_V = 1, 2
#: analytic shapes record the size pass on 2^3 × 2^3 cells of their parameter square
SIZE_GRID_LEVEL = 3
#: deepest rex level (bucket side 2^-20 of the parameter square)
MAX_LEVEL = 20
#: deepest light-quadtree level (keys hold 19 bits per axis)
MAX_LIGHT_LEVEL = 18
ONE_MINUS_EPS = 1.0 - 2.0**-24
#: at most this many eye depths read rexes under a finite max_depth (deeper ones path-trace)
MAX_DEPTH_CLASSES = 8
#: a photon survives Russian roulette with q = min(max(β), PHOTON_RR_MAX). Mitsuba's eye paths
#: cap q at 0.95, so at an albedo ρ > 0.95 each bounce multiplies the weight by ρ/0.95 and the second
#: moment by ρ²/0.95: at ρ = 0.99 that is > 1, the flux estimate has infinite variance and its
#: sample mean runs low (a furnace of ρ = 0.99 read 0.94 of Le/(1 − ρ) at 65536 photons). With the
#: cap above any physical albedo the weight stays ≤ 1 and the mean path length is 1/(1 − ρ).
PHOTON_RR_MAX = 0.999
#: final photons per Dr.Jit launch
PHOTON_BATCH = 1 << 20
#: a batch's record buffer holds at least this many records per photon
RECORDS_PER_PHOTON = 3
#: and the records per photon expected (the probe's, then the last batch's) times this
RECORD_MARGIN = 1.15
#: a batch whose records the probe's light-tree cells predict (:meth:`FinalShoot.
#: expected_records`) reserves this many times them plus EXPECTED_SLACK per photon: a cell
#: holds few probe photons, and window_interior's batches read up to 1.5× their prediction
EXPECTED_MARGIN = 1.5
EXPECTED_SLACK = 0.25
#: the photon budget's noise model reads at most about this many 8×8 blocks of the film
MODEL_BLOCKS = 4096
#: the bit of a probe record's lane that marks sharp light (:func:`_photon_trace`)
SHARP_BIT = 1 << 31
#: the probe shoot's buffers hold this many records per photon (a closed room of albedo 0.8
#: leaves 4–5; the probe is small, so room to spare costs little)
PROBE_RECORDS = 8.0
#: final photons per light-quadtree leaf (4 per quadrant): the tree's size is the budget / this
LEAF_PHOTONS = 16
#: the light quadtrees of all emitters together have at most about this many leaves (pilot
#: rays and numpy bookkeeping per node; more photons shoot more rounds per leaf)
MAX_LIGHT_LEAVES = 1 << 18
#: steps of the final shoot's search for a lane's leaf (at most 2^this leaves; the restricted
#: quadtree's extra splits take a tree a little past MAX_LIGHT_LEAVES)
LEAF_SEARCH_STEPS = 20
#: a bucket holding more photons than this splits (the default of rex's ``split_limit``): 32,
#: not 16, for the automatic budget's sake (CAP_FILL × split_limit photons per visible bucket):
#: with 16 the office's rexes at 128² left a block relMSE of 1.8e-3, 3.3e-3, 2.2e-3 and 3.1e-3
#: over four builds (``check --renders 2``: the part two renders of one build share; check's
#: bound 3e-3), with 32 7.4e-4, 7.0e-4 and 1.2e-3 over three; the check's seconds (prepass
#: and 64 spp) went from 1.6–2.6 s to 2.8–3.9 s
SPLIT_LIMIT = 32
#: without the noise model's inputs, the automatic budget fills every visible bucket at its
#: cap to this × split_limit photons (the soft cap's threshold one level past the cap): the
#: rule of sessions 12–28
CAP_FILL = 4
#: the automatic budget holds the block relMSE its photon noise is predicted to leave
#: (:func:`predicted_noise`) to this share of ``check``'s bound. A third, because the
#: prediction is that close and no closer: against the bias part ``check --renders 2``
#: measured at 128², 64 spp with session 28's budget (session 29,
#: docs/results/rex-noise-budget-2026-11-28), it read 0.5× on window_interior, 0.8× on
#: mixed_room, 1.2–1.5× on the Cornell box, the office and the furnace, 2.4× on tut-cbox; so
#: a prediction half the truth leaves two thirds of the bound to the noise. caustic.xml read
#: 0.17×: its error is the blur of a sharp caustic in buckets the photons leave coarse,
#: which the split floor of :func:`photon_need` answers
NOISE_SHARE = 1.0 / 3.0
#: the image's share of sharp light (:func:`predicted_noise`) at which the resolution rule of
#: :func:`photon_need` asks its full CAP_FILL × split_limit photons per visible bucket; below
#: it, in proportion, down to none where no light in the rexes is sharp. Smooth light's error
#: is the photon noise, which the noise model predicts; sharp light's is also the blur of
#: buckets left coarse, which it does not. Measured with ``check --res 128 --spp 64
#: --renders 2`` and the photons forced to 1, 1/2, 1/4 and 1/8 of session 29's budget (its
#: fill 1 + 3 × sharp share): on window_interior (sharp share 0.000) the bias part went 5.1e-4,
#: 1.1e-3, 2.0e-3, 3.2e-3, as 1/N, and the model predicted 4.0e-4 at the first; on many_lights
#: (0.000) 8e-5, 1.8e-4, 8.8e-4, 1.9e-3 (predicted 3.1e-4 at the first); on caustic.xml
#: (0.086) 7.0e-4, 1.6e-3, 5.0e-3, 7.1e-3 (predicted 2.7e-4 at the first): blur, faster than
#: 1/N, in bounds (3e-3) down to a fill of about 0.5 and out at 0.31. A third gives the caustic
#: a fill of 1.03, twice that margin, and lets the split rule go where the light is smooth
SHARP_FULL = 1.0 / 3.0
#: where pixels read more than this share of the image's radiance from rexes at level 0 (a
#: rex no larger than its pixel: one bucket, refined only past the size-pass cap, by the soft
#: cap's 4^k rule), the automatic budget keeps CAP_FILL × split_limit photons per bucket as
#: its floor. Those reads' bias falls as photons let such rexes split past the cap, which the
#: noise model does not see: veach-bidir's lamp (3.2 % of its image; every other scene of
#: scenes_xml/ and ../shared/scenes ≤ 0.3 %) read the image mean at +0.98 %, +0.77 %, +0.70 %
#: and +0.64 % of the reference with 0.34M, 0.45M, 0.49M and 0.6M photons (three seeds each,
#: ``check … --res 128 --renders 2 --seed S``; +0.60 % at 2.4M)
WHOLE_REX_SHARE = 0.01
#: the default of rex's ``bucket_pixels``: the size-pass cap stops at buckets at most this many
#: pixels wide (more than half of it). 2, not 1: at 1 the buckets (½–1 pixel wide, 2.4 per
#: visible pixel) asked 4× the photons for no error the harness or ``check`` could see, and
#: the record cap then cut them; at 256² (``bench --res 256``) rex reached relMSE 0.01 on
#: tut-cbox in 1.58 s, not 3.63 s, on the Cornell box in 1.60 s where 1 did not within 15 s,
#: and its prepass fell 3.6 → 1.8 s there. At 4 the office and mixed_room failed ``check
#: --renders 2`` (block bias part 3.4e-3 and 4.7e-3, the bound 3e-3; 2.5e-3 and 1.8e-3 at 2)
BUCKET_PIXELS = 2.0
#: photons of the probe shoot that measures the deposits per photon (:func:`photon_need`)
PROBE_PHOTONS = 1 << 16
#: bounds of an automatic photon budget
MIN_PHOTONS = 1 << 16
MAX_AUTO_PHOTONS = 1 << 24
#: an automatic budget keeps the photon records below this many (26 bytes each, and the
#: build's sort keys and indices: ~100 bytes per record at the build's peak)
MAX_RECORDS = 8_000_000
#: stratified points per rex leaf that test whether closed geometry buries it
EXPOSURE_PROBES = 4
#: rex leaves probed per batch (× EXPOSURE_PROBES lanes, ~100 bytes each in numpy)
EXPOSURE_BATCH = 1 << 17
#: delta / glossy bounces a pilot or size ray follows before giving up
MAX_CHAIN = 16
#: how the deposit's scatter-additions are compiled (:func:`deposit`): sorted records share bins
#: within a packet, which Local pre-reduces
_DEPOSIT_MODE = dr.ReduceMode.Local

_BACK = int(mi.BSDFFlags.BackSide)
#: analytic shapes whose (u, v) square has an exact area rule (bucket_area)
_UV_SHAPES = ("Rectangle", "Sphere", "Disk", "Cylinder")

# seeds of the independent streams, so that passes never share random numbers
_SALT_SIZE, _SALT_PROBE, _SALT_PILOT, _SALT_PHOTON, _SALT_NUMPY, _SALT_PROBE_PHOTON = 1, 2, 3, 4, 5, 6


def depth_classes(max_depth: int) -> int:
    """How many eye depths read a rex under ``max_depth`` (Mitsuba's meaning: a path has at most
    max_depth segments; -1 unbounded). A photon deposited at its k-th hit (k + 1 segments from
    the light) and read at an eye vertex of depth d (d + 1 segments from the camera) makes a path
    of k + d + 2 segments, so class d of a bucket holds the photons with k ≤ max_depth − 2 − d;
    unbounded, one class holds them all."""
    if max_depth < 0:
        return 1
    return int(max(1, min(max_depth - 1, MAX_DEPTH_CLASSES)))


def _sampler(seed, n):
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, seed), int(n))  # a literal seed: kernels per seed
    return sampler


@dataclass(frozen=True)
class RexSettings:
    """Every parameter of the rex prepass (the integrator's docstring explains each)."""

    photons: int = 0  # ≤ 0: what the image needs (photon_need)
    split_limit: int = SPLIT_LIMIT
    max_level: int = 14
    bucket_pixels: float = BUCKET_PIXELS
    direct: str = "rex"  # "rex": rexes hold direct light; "shadow": indirect + caustics only
    max_depth: int = -1
    rr_depth: int = 5
    light_levels: int = 3
    light_split_dist: float = 0.05  # fraction of the bounding-box diagonal
    size_spp: int = 4
    light_guide: bool = True  # photons shared out by the probe's yield (light_guide.py)


# ---------------------------------------------------------------------------------------------
# Scene tables: which surfaces carry rexes and how a hit maps to (rex, u, v)
# ---------------------------------------------------------------------------------------------
class RexTables:
    """Per shape and per rex bookkeeping, in numpy and as Dr.Jit arrays for the hot paths.

    A rex is one parameter square: a whole analytic shape (rectangle, sphere, disk, cylinder, ...)
    over its (u, v), or one triangle of a mesh over its barycentrics. Two-sided BSDFs get one rex
    per side (the two sides of a sheet are lit differently).
    """

    def __init__(self, scene):
        # rexes numbered alike in every load of the scene (Mitsuba's own order varies)
        shapes = [shape for _, shape in stable_shapes(scene)]
        self.bounds = scene_bounds(scene)
        #: the length ray offsets are relative to (:func:`mi_twopass.rays.spawn_ray`)
        self.scale = float(self.bounds.radius)
        ids = np.array([registry_id(shape) for shape in shapes], dtype=np.int64)
        # ids past the scene's shapes (those inside instanced shape groups) map to the sentinel
        # entry n_ids: NO_SHAPE, so they are path traced and never alias a real shape
        self.n_ids = int(ids.max()) + 1 if ids.size else 1
        id_to_shape = np.full(self.n_ids + 1, NO_SHAPE, np.uint32)
        id_to_shape[ids] = np.arange(len(shapes), dtype=np.uint32)

        n = len(shapes)
        # per shape: its KIND_*, sides (1 or 2), AREA_* rule and WRAP_* flags; its number of
        # regions (triangles, or 1 for an analytic shape) and first triangle; its analytic area
        kind, sides, area_rule, wrap = np.zeros((4, n), np.uint32)
        regions, tri_base = np.zeros((2, n), np.int64)
        shape_area = np.zeros(n, np.float64)
        sides[:] = 1
        tris_p0, tris_e1, tris_e2 = [], [], []
        n_tris = 0
        for i, shape in enumerate(shapes):  # setup over shapes, not a hot path
            bsdf = shape.bsdf()
            name = shape.class_name()
            # instances (their shapes live in a shape group) and shapes with no exact (u, v)
            # area rule carry no rex: the eye pass path-traces them
            if bsdf is None or not is_lambertian(bsdf) or name == "Instance" or \
                    not (shape.is_mesh() or name in _UV_SHAPES):
                continue
            flags = int(bsdf.flags())
            sides[i] = 2 if flags & _BACK else 1
            if shape.is_mesh() and name != "Rectangle":
                kind[i] = KIND_TRI
                area_rule[i] = AREA_TRI
                V = np.asarray(shape.vertex_positions_buffer(), np.float64).reshape(-1, 3)
                F = np.asarray(shape.faces_buffer(), np.int64).reshape(-1, 3)
                p0 = V[F[:, 0]]
                tris_p0.append(p0)
                tris_e1.append(V[F[:, 1]] - p0)
                tris_e2.append(V[F[:, 2]] - p0)
                tri_base[i] = n_tris
                regions[i] = F.shape[0]
                n_tris += F.shape[0]
            else:
                kind[i] = KIND_UV
                regions[i] = 1
                shape_area[i] = float(dr.sum(shape.surface_area())[0]) \
                    if dr.width(shape.surface_area()) else 0.0
                area_rule[i] = {"Sphere": AREA_SPHERE, "Disk": AREA_DISK}.get(name, AREA_FLAT)
                wrap[i] = {"Sphere": WRAP_U, "Cylinder": WRAP_U, "Disk": WRAP_V}.get(name, 0)

        p0 = np.concatenate(tris_p0) if tris_p0 else np.zeros((0, 3))
        e1 = np.concatenate(tris_e1) if tris_e1 else np.zeros((0, 3))
        e2 = np.concatenate(tris_e2) if tris_e2 else np.zeros((0, 3))
        tri_area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)

        rex_count = regions * sides
        rex_base = np.concatenate([[0], np.cumsum(rex_count)[:-1]]).astype(np.int64) if n else \
            np.zeros(0, np.int64)
        R = int(rex_count.sum())
        self.count = R
        self.shapes = shapes
        self.shape_kind, self.shape_sides, self.shape_rex_base = kind, sides, rex_base
        self.shape_tri_base, self.shape_wrap = tri_base, wrap

        # per rex: its shape, region and side
        rex_shape = np.repeat(np.arange(n, dtype=np.int64), rex_count)
        local = np.arange(R, dtype=np.int64) - np.repeat(rex_base, rex_count)
        rex_region = local // np.repeat(sides.astype(np.int64), rex_count)
        self.rex_shape = rex_shape.astype(np.uint32)
        self.rex_side = (local % np.repeat(sides.astype(np.int64), rex_count)).astype(np.uint8)
        self.rex_tri = np.where(kind[rex_shape] == KIND_TRI, tri_base[rex_shape] + rex_region, -1)
        self.tri_p0, self.tri_e1, self.tri_e2 = p0, e1, e2
        self.rex_kind = kind[rex_shape]
        self.rex_area_rule = area_rule[rex_shape]
        self.rex_wrap = wrap[rex_shape]
        is_tri = self.rex_kind == KIND_TRI
        self.rex_area = np.where(
            is_tri, tri_area[np.minimum(tri_base[rex_shape] + rex_region, max(n_tris - 1, 0))]
            if n_tris else 0.0, shape_area[rex_shape])
        self.rex_size_level = np.where(is_tri, 0, SIZE_GRID_LEVEL).astype(np.uint32)
        cells = 4 ** self.rex_size_level.astype(np.int64)
        self.rex_size_offset = np.concatenate([[0], np.cumsum(cells)[:-1]]).astype(np.int64) \
            if R else np.zeros(0, np.int64)
        self.size_cells = int(cells.sum())
        self.tri_area = tri_area
        self.tri_count = n_tris

        # Dr.Jit copies (padded by one entry: a gather never reads an empty array)
        def u32(a):
            return jit(mi.UInt32, np.append(np.asarray(a, np.uint32), 0))

        def f32(a):
            return jit(mi.Float, np.append(np.asarray(a, np.float32).ravel(), np.zeros(3, np.float32)))

        self.d_id_to_shape = jit(mi.UInt32, id_to_shape)
        self.d_kind = u32(kind)
        self.d_sides = u32(sides)
        self.d_rex_base = u32(rex_base)
        self.d_tri_base = u32(tri_base)
        self.d_tri_p0, self.d_tri_e1, self.d_tri_e2 = f32(p0), f32(e1), f32(e2)
        self.d_tri_area2 = f32(2.0 * tri_area)
        self.d_size_offset = u32(self.rex_size_offset)
        self.d_size_level = u32(self.rex_size_level)
        self.d_wrap = u32(self.rex_wrap)

    @property
    def nbytes(self) -> int:
        return int(self.n_ids * 4 + len(self.shapes) * 20 + self.tri_count * 40 + self.count * 28)

    def shape_rexes(self, shape) -> np.ndarray:
        """The rex ids of a shape (a ``mi.Shape``, its index in ``shapes`` or its id)."""
        if isinstance(shape, str):
            matches = [i for i, s in enumerate(self.shapes) if s.id() == shape]
            if not matches:
                raise KeyError(f"no shape with id {shape!r}")
            shape = matches[0]
        elif not isinstance(shape, (int, np.integer)):
            shape = next(i for i, s in enumerate(self.shapes) if s == shape)
        return np.nonzero(self.rex_shape == shape)[0]

    def locate(self, si, active=True):
        """(rex, uv, ok) of a surface hit: ok where the hit lies on the lit side of a rex surface.

        ``uv`` is the analytic shape's ``si.uv`` or the triangle's barycentrics (b1, b2), clamped
        into [0, 1)²; ``shape`` is the hit's shape index (``NO_SHAPE`` where none)."""
        ok = mi.Bool(active) & si.is_valid()
        sid = dr.minimum(dr.reinterpret_array(mi.UInt32, si.shape), self.n_ids)
        shape = dr.gather(mi.UInt32, self.d_id_to_shape, sid, ok)
        shape = dr.select(ok, shape, NO_SHAPE)
        ok &= shape != NO_SHAPE
        kind = dr.gather(mi.UInt32, self.d_kind, shape, ok)
        ok &= kind != KIND_NONE
        sides = dr.gather(mi.UInt32, self.d_sides, shape, ok)
        cos_wi = mi.Frame3f.cos_theta(si.wi)
        back = cos_wi < 0
        ok &= (cos_wi != 0) & (~back | (sides == 2))
        is_tri = kind == KIND_TRI
        region = dr.select(is_tri, si.prim_index, 0)
        rex = dr.gather(mi.UInt32, self.d_rex_base, shape, ok) + region * sides \
            + dr.select(back & (sides == 2), mi.UInt32(1), mi.UInt32(0))

        tri_ok = ok & is_tri
        tid = dr.gather(mi.UInt32, self.d_tri_base, shape, tri_ok) + si.prim_index
        p0 = dr.gather(mi.Point3f, self.d_tri_p0, tid, tri_ok)
        e1 = dr.gather(mi.Vector3f, self.d_tri_e1, tid, tri_ok)
        e2 = dr.gather(mi.Vector3f, self.d_tri_e2, tid, tri_ok)
        d = si.p - p0
        d00, d01, d11 = dr.dot(e1, e1), dr.dot(e1, e2), dr.dot(e2, e2)
        d20, d21 = dr.dot(d, e1), dr.dot(d, e2)
        den = d00 * d11 - d01 * d01
        good = den > 0
        inv = dr.select(good, dr.rcp(dr.select(good, den, 1.0)), 0.0)
        b1 = dr.select(good, (d11 * d20 - d01 * d21) * inv, 1.0 / 3.0)
        b2 = dr.select(good, (d00 * d21 - d01 * d20) * inv, 1.0 / 3.0)
        u = dr.select(is_tri, b1, si.uv.x)
        v = dr.select(is_tri, b2, si.uv.y)
        u = dr.clip(dr.select(dr.isfinite(u), u, 0.5), 0.0, ONE_MINUS_EPS)
        v = dr.clip(dr.select(dr.isfinite(v), v, 0.5), 0.0, ONE_MINUS_EPS)
        return dr.select(ok, rex, 0), mi.Point2f(u, v), ok

    def jacobian(self, si, rex, active):
        """World area per unit parameter area at a hit: |∂p/∂u × ∂p/∂v| or 2·A(triangle)."""
        shape = dr.gather(mi.UInt32, self.d_id_to_shape,
                          dr.minimum(dr.reinterpret_array(mi.UInt32, si.shape), self.n_ids),
                          active)
        kind = dr.gather(mi.UInt32, self.d_kind, shape, active)
        tid = dr.gather(mi.UInt32, self.d_tri_base, shape, active) + si.prim_index
        tri = dr.gather(mi.Float, self.d_tri_area2, tid, active & (kind == KIND_TRI))
        return dr.select(kind == KIND_TRI, tri, dr.norm(dr.cross(si.dp_du, si.dp_dv)))

    def shape_index(self, si, active):
        sid = dr.minimum(dr.reinterpret_array(mi.UInt32, si.shape), self.n_ids)
        return dr.select(active & si.is_valid(),
                         dr.gather(mi.UInt32, self.d_id_to_shape, sid, active), NO_SHAPE)

    def size_cell(self, rex, uv, active):
        """Index of the size-pass cell of ``rex`` holding ``uv``."""
        level = dr.gather(mi.UInt32, self.d_size_level, rex, active)
        res = mi.UInt32(1) << level
        fres = mi.Float(res)
        ix = dr.minimum(mi.UInt32(uv.x * fres), res - 1)
        iy = dr.minimum(mi.UInt32(uv.y * fres), res - 1)
        return dr.gather(mi.UInt32, self.d_size_offset, rex, active) + iy * res + ix

    def bucket_area(self, rex, level, ix, iy):
        """Exact world area of the parameter square [ix, ix+1]·h × [iy, iy+1]·h, h = 2^-level."""
        rex = np.asarray(rex, np.int64)
        level = np.asarray(level, np.int64)
        ix = np.asarray(ix, np.float64)
        iy = np.asarray(iy, np.float64)
        h = np.ldexp(1.0, -level)
        u0, v0 = ix * h, iy * h
        A = self.rex_area[rex]
        rule = self.rex_area_rule[rex]
        flat = A * h * h
        sphere = 0.5 * A * h * (np.cos(np.pi * v0) - np.cos(np.pi * (v0 + h)))
        disk = A * ((u0 + h) ** 2 - u0**2) * h
        # barycentric square: the triangle b1 + b2 ≤ 1 covers a dyadic cell fully, half or not
        s = np.asarray(ix + iy, np.float64)
        n = np.ldexp(1.0, level)
        frac = np.where(s + 2 <= n, 1.0, np.where(s + 1 == n, 0.5, 0.0))
        tri = 2.0 * A * h * h * frac
        return np.select([rule == AREA_SPHERE, rule == AREA_DISK, rule == AREA_TRI],
                         [sphere, disk, tri], flat)


# ---------------------------------------------------------------------------------------------
# Size pass (§3.4.1)
# ---------------------------------------------------------------------------------------------
class SizeHit:
    """What an eye sample of the size pass found (:func:`_size_trace`), for the photon budget's
    noise model (:func:`predicted_noise`): its first rex (``found``), with its (u, v), cap
    level, world area per unit parameter area, the throughput of the specular chain that
    reached it and the surface's albedo (channel mean); and ``known``, the radiance the eye
    pass takes from elsewhere than the rexes where the chain ends (one sample of the emitted
    and, where shadow rays compute it, the direct light)."""

    DRJIT_STRUCT = {"rex": mi.UInt32, "uv": mi.Point2f, "level": mi.Float, "jac": mi.Float,
                    "beta": mi.Float, "albedo": mi.Float, "known": mi.Float, "found": mi.Bool}

    def __init__(self, rex=None, uv=None, level=None, jac=None, beta=None, albedo=None,
                 known=None, found=None):
        self.rex, self.uv, self.level, self.jac, self.beta = rex, uv, level, jac, beta
        self.albedo, self.known, self.found = albedo, known, found


@dr.syntax
def _size_trace(scene, tables, ray, spread_o, spread_d, caps, bucket_pixels, max_level, sampler,
                shadow, modelled):
    """Follow delta/glossy bounces to the first rex hit; scatter-max its cap level + 1.

    Returns (rays, cap-level buckets per pixel, a :class:`SizeHit` per sample). ``shadow``
    (a Bool): rexes hold no direct light, so the direct light at a rex hit is ``known``.
    ``modelled`` (a Bool per sample): the samples whose ``known`` the noise model reads (one
    per pixel, the others' stays 0).
    Where the chain ends (a rex, another surface, or nothing), ``known`` adds the emitted
    radiance there and, on a surface, one emitter sample of the direct light with its shadow
    ray; the samples it draws come after the chain's, so the caps are those of the chain
    alone."""
    ctx = mi.BSDFContext()
    ray = mi.Ray3f(ray)
    t_total = mi.Float(0.0)
    depth = mi.UInt32(0)
    n_rays = mi.UInt32(0)
    buckets = mi.Float(0.0)  # cap-level buckets per pixel where the ray met a rex
    hit = SizeHit(rex=mi.UInt32(0), uv=mi.Point2f(0.0), level=mi.Float(0.0), jac=mi.Float(0.0),
                  beta=mi.Float(0.0), albedo=mi.Float(0.0), known=mi.Float(0.0),
                  found=mi.Bool(False))
    throughput = mi.Float(1.0)
    infinite = has_infinite_emitters(scene)
    active = mi.Bool(True)
    while dr.hint(active, label="rex_size_pass"):
        si = scene.ray_intersect(ray, active)
        traced = mi.Bool(active)
        n_rays += dr.select(active, mi.UInt32(1), mi.UInt32(0))
        valid = active & si.is_valid()
        t_total += dr.select(valid, si.t, 0.0)
        rex, uv, at_rex = tables.locate(si, valid)
        # the pixel's footprint: its differential spread carried over the path length,
        # projected along the ray onto the tangent plane (curvature of mirrors ignored)
        n = si.sh_frame.n
        dn = dr.dot(ray.d, n)
        dn = dr.select(dr.abs(dn) > 1e-6, dn, 1e-6)
        vx = spread_o[0] + t_total * spread_d[0]
        vy = spread_o[1] + t_total * spread_d[1]
        vx = vx - ray.d * (dr.dot(vx, n) / dn)
        vy = vy - ray.d * (dr.dot(vy, n) / dn)
        area_world = dr.norm(dr.cross(vx, vy))
        J = tables.jacobian(si, rex, at_rex)
        pixel = dr.sqrt(dr.maximum(area_world, 1e-30) / dr.maximum(J, 1e-30))
        side = pixel * bucket_pixels
        level = dr.ceil(dr.log2(dr.rcp(dr.maximum(side, 1e-30))))
        level = dr.clip(dr.select(dr.isfinite(level), level, 0.0), 0.0, max_level)
        # buckets of side 2^-level per pixel of side `pixel` (both in the parameter square;
        # at most the whole square per pixel)
        per_pixel = dr.minimum(pixel, 1.0) * dr.exp2(level)
        buckets = dr.select(at_rex, dr.minimum(per_pixel * per_pixel, 1e6), buckets)
        bsdf = si.bsdf(ray)
        hit = dr.select(at_rex, SizeHit(
            rex=rex, uv=uv, level=level, jac=J, beta=throughput,
            albedo=units.channel_mean(bsdf.eval_diffuse_reflectance(si, at_rex)),
            known=hit.known, found=mi.Bool(True)), hit)
        level = mi.UInt32(level)
        cell = tables.size_cell(rex, uv, at_rex)
        dr.scatter_reduce(dr.ReduceOp.Max, caps, level + 1, cell, at_rex)

        go_on = valid & ~at_rex & (tables.shape_index(si, valid) != NO_SHAPE) \
            & (depth + 1 < MAX_CHAIN)
        bs, w = bsdf.sample(ctx, si, sampler.next_1d(go_on), sampler.next_2d(go_on), go_on)
        ray_next = spawn_ray(si, si.to_world(bs.wo), tables.scale)
        depth += 1
        active = go_on & (bs.pdf > 0) & (dr.max(w) > 0)
        active &= ~mi.has_flag(bsdf.flags(), mi.BSDFFlags.Diffuse) | \
            mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta) | \
            mi.has_flag(bs.sampled_type, mi.BSDFFlags.Glossy)
        # where the chain ends: what the eye pass adds there besides the rex
        ends = traced & ~active & modelled
        lit = ends & valid & (~at_rex | shadow)
        ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(lit), False, lit)
        cast = lit & (ds.pdf != 0.0) & dr.any(em_weight != 0.0)
        visible = cast & ~scene.ray_test(shadow_ray(si, ds, tables.scale, infinite), cast)
        direct = bsdf.eval(ctx, si, si.to_local(ds.d), visible) * em_weight
        emitted = si.emitter(scene).eval(si, ends)
        hit.known = dr.select(ends, throughput * units.channel_mean(
            emitted + dr.select(visible, direct, 0.0)), hit.known)
        ray = ray_next
        throughput *= units.channel_mean(w)
    return n_rays, buckets, hit


def _blocks(width: int, height: int):
    """The noise model's 8×8 blocks of a width × height film (``check``'s): (blocks across,
    blocks down, the block of each pixel in raster order)."""
    bw, bh = -(-width // BLOCK), -(-height // BLOCK)
    every = np.arange(width * height)
    return bw, bh, (every // width // BLOCK) * bw + (every % width) // BLOCK


def noise_model_pixels(width: int, height: int) -> np.ndarray:
    """The pixels the photon budget's noise model reads (:func:`predicted_noise`): all of
    every 8×8 block of the film, or, past :data:`MODEL_BLOCKS` blocks, of a fixed
    pseudo-random subset of about that many. The model is a mean over blocks, so a subset
    estimates it; at 1920×1920 reading them all took 1.5 s of a 5 s prepass."""
    bw, bh, block = _blocks(width, height)
    n_blocks = bw * bh
    if n_blocks <= MODEL_BLOCKS:
        return np.arange(width * height)
    stride = -(-n_blocks // MODEL_BLOCKS)
    chosen = (np.arange(n_blocks, dtype=np.uint64) * np.uint64(2654435761) >> np.uint64(8)) \
        % np.uint64(stride) == 0
    return np.flatnonzero(chosen[block])


def size_pass(scene, tables: RexTables, settings: RexSettings, seed: int, sensor=None):
    """Per size cell, the finest rex level worth resolving: the finest any eye sample there asked
    for (footprints through curved mirrors and lenses are underestimated: finer, never coarser).

    Returns (cap level per size cell, seen per rex, eye rays traced, the image's need): the
    need is a dict of ``visible_pixels`` (pixels whose eye ray reaches a rex, through specular
    and glossy bounces) and ``visible_buckets`` (the rex buckets at the cap those pixels cover:
    Σ over them of (pixel side / bucket side)², both in the rex's parameter square), the film's
    ``(width, height)``, and for :func:`predicted_noise`, from the first eye sample of each
    pixel, ``known`` (per pixel, :class:`SizeHit`'s) and ``hits``: numpy arrays of the
    pixel index and the :class:`SizeHit` fields of those that met a rex."""
    if sensor is None:
        sensors = scene.sensors()
        sensor = sensors[0] if len(sensors) else None
    if sensor is None or tables.count == 0:
        cap = np.full(tables.size_cells, min(8, settings.max_level), np.int64)
        return cap, np.ones(tables.count, bool), 0, {"visible_pixels": 0.0,
                                                     "visible_buckets": 0.0}
    film = sensor.film()
    w, h = (int(x) for x in film.crop_size())
    spp = settings.size_spp
    n = w * h * spp
    sampler = _sampler(hash31(seed, _SALT_SIZE), n)
    idx = dr.arange(mi.UInt32, n)
    # the lanes run sample by sample over the film: the first w·h are the noise model's, and
    # only their packets sample emitters at the chain's end
    # (the film's sizes opaque: as literals they compiled the size pass per resolution)
    n_pixels, width = dr.opaque(mi.UInt32, w * h), dr.opaque(mi.UInt32, w)
    pixel = idx % n_pixels
    pos = mi.Vector2f(mi.Float(pixel % width), mi.Float(pixel // width)) + sampler.next_2d()
    pos = pos / mi.ScalarVector2f(w, h)
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f(pos), mi.Point2f(0.5, 0.5))
    spread_o = (ray.o_x - ray.o, ray.o_y - ray.o)
    spread_d = (ray.d_x - ray.d, ray.d_y - ray.d)
    caps = dr.zeros(mi.UInt32, tables.size_cells + 1)
    model_pixels = noise_model_pixels(w, h)
    modelled = np.zeros(w * h, bool)
    modelled[model_pixels] = True
    modelled = (idx < n_pixels) & dr.gather(mi.Bool, jit(mi.Bool, modelled), pixel)
    n_rays, buckets, hit = _size_trace(scene, tables, mi.Ray3f(ray), spread_o, spread_d, caps,
                                       mi.Float(settings.bucket_pixels),
                                       float(settings.max_level), sampler,
                                       mi.Bool(settings.direct == "shadow"), modelled)
    dr.eval(caps, n_rays, buckets, hit)  # one launch of the loop (each read would run it again)
    caps_np = np.asarray(caps, np.int64)[:-1] - 1  # −1: unseen
    rays = int(dr.sum(n_rays)[0])
    need = {"visible_pixels": float(dr.count(buckets > 0)[0]) / spp,
            "visible_buckets": float(dr.sum(buckets)[0]) / spp,
            "film": (w, h)}
    # the first sample of each pixel of the noise model's blocks
    hit = dr.gather(SizeHit, hit, jit(mi.UInt32, model_pixels.astype(np.uint32)))
    found = np.asarray(hit.found, bool)
    need["model_pixels"] = model_pixels
    need["known"] = np.asarray(hit.known, np.float64)
    need["hits"] = {"pixel": model_pixels[found]}
    for name, value in (("rex", hit.rex), ("u", hit.uv.x), ("v", hit.uv.y),
                        ("level", hit.level), ("jac", hit.jac), ("beta", hit.beta),
                        ("albedo", hit.albedo)):
        need["hits"][name] = np.asarray(value, np.int64 if name in ("rex", "level")
                                        else np.float64)[found]

    # unseen cells of a seen rex take the rex's coarsest seen level; unseen rexes level 0
    rex_of_cell = np.repeat(np.arange(tables.count), 4 ** tables.rex_size_level.astype(np.int64))
    seen_cell = caps_np >= 0
    coarsest = np.full(tables.count, np.iinfo(np.int64).max)
    np.minimum.at(coarsest, rex_of_cell[seen_cell], caps_np[seen_cell])
    seen = coarsest != np.iinfo(np.int64).max
    fill = np.where(seen, coarsest, 0)
    cap = np.where(seen_cell, caps_np, fill[rex_of_cell])
    return cap, seen, rays, need


# ---------------------------------------------------------------------------------------------
# Light pass (§3.3.1, §4.1): emitters, light quadtree, pilot rays, photons
# ---------------------------------------------------------------------------------------------
def probe_emitters(scene, seed, bounds, n_probe=256):
    """Power of every emitter (mean photon weight of :func:`emitter_rays`) and which 2-D
    sample the light quadtree adapts: 3 (``sample3``) where it changes the ray, else 2."""
    emitters = scene.emitters()
    E = len(emitters)
    if E == 0:
        return np.zeros(0), np.zeros(0, np.int64)
    idx = dr.arange(mi.UInt32, E * n_probe) // n_probe
    sampler = _sampler(hash31(seed, _SALT_PROBE), E * n_probe)
    s2, s3, s3b = sampler.next_2d(), sampler.next_2d(), sampler.next_2d()
    ray_a, w = emitter_rays(scene, bounds, idx, s2, s3)
    ray_b, _ = emitter_rays(scene, bounds, idx, s2, s3b)
    moved = dr.norm(ray_a.d - ray_b.d) + dr.norm(ray_a.o - ray_b.o)
    dr.eval(w, moved)
    w_np = np.stack([np.asarray(w[c], np.float64) for c in range(3)], axis=1)
    w_np = np.where(np.isfinite(w_np), w_np, 0.0)
    power = w_np.mean(axis=1).reshape(E, n_probe).mean(axis=1)
    moved_np = np.asarray(moved, np.float64).reshape(E, n_probe)
    uses3 = (moved_np > 1e-6 * bounds.diagonal).any(axis=1)
    return power, np.where(uses3, 3, 2)


@dr.syntax
def _pilot_trace(scene, tables, ray, sampler):
    """A light ray to its first rex hit: (path signature, hit point, rex, hit?)."""
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    ray = mi.Ray3f(ray)
    sig = mi.UInt32(2166136261)
    pos = mi.Point3f(0.0)
    rex_hit = mi.UInt32(0)
    hit = mi.Bool(False)
    depth = mi.UInt32(0)
    n_rays = mi.UInt32(0)
    active = mi.Bool(True)
    while dr.hint(active, label="rex_pilot"):
        si = scene.ray_intersect(ray, active)
        n_rays += dr.select(active, mi.UInt32(1), mi.UInt32(0))
        valid = active & si.is_valid()
        shape = tables.shape_index(si, valid)
        sig = dr.select(active, (sig ^ dr.select(valid, shape + 1, 0x9E3779B9)) * 16777619, sig)
        rex, uv, at_rex = tables.locate(si, valid)
        pos = dr.select(at_rex, si.p, pos)
        rex_hit = dr.select(at_rex, rex, rex_hit)
        hit |= at_rex
        bsdf = si.bsdf(ray)
        go_on = valid & ~at_rex & (depth + 1 < MAX_CHAIN)
        bs, w = bsdf.sample(ctx, si, sampler.next_1d(go_on), sampler.next_2d(go_on), go_on)
        ray = spawn_ray(si, si.to_world(bs.wo), tables.scale)
        depth += 1
        alive = (bs.pdf > 0) & (dr.max(w) > 0)
        sig = dr.select(go_on & ~alive, (sig ^ 0x85EBCA6B) * 16777619, sig)
        active = go_on & alive
    return sig, pos, rex_hit, hit, n_rays


def photon_scatter_weight(bsdf, si, bs, w, wi_geo, ctx_radiance):
    """``(factor, good, smooth)``: what a photon's weight is multiplied by when it scatters at
    ``si`` in the direction ``bs`` sampled (``bsdf.sample`` in importance mode, weight ``w``),
    whether the sample is geometrically consistent (``good``: both directions on the sides
    their shading and geometric normals agree on) and whether it is a non-delta one.

    The factor is the adjoint of what Mitsuba's path integrates: the BSDF evaluated (radiance
    mode) with the new direction on the eye side, times |cos_g(new)| / |cos_g(incoming)|, over
    the density of the sample. For a delta sample, Mitsuba's importance-mode weight with the
    adjoint shading-normal correction (Veach p. 155); for the others the direct evaluation,
    which also holds for BSDFs that are not symmetric (normalmap and bumpmap tilt one side's
    frame: with the correction for the surface's own normal, a floor lit by a normal-mapped
    wall was 4.5 % too bright).

    The density is the sample's own, ``bs.pdf``: for every sample Mitsuba keeps it equals
    ``bsdf.pdf`` of the direction (every BSDF of the hard-case matrix, 65,536 samples each:
    relative difference ≤ 2.4e-4). Reading it saves a BSDF call per bounce but no time that
    could be measured: alternating builds of the old code and this, best of three each, read
    the light pass on caustic.xml at 1.349 and 1.322 s against 1.325 and 1.315 s. Where
    Mitsuba's own weight is 0 the sample is one its sampling discards, and so does the
    photon: a rough
    dielectric's microfacet event whose direction lands on the other side (1.4 % of
    roughdielectric's glossy samples for incident directions uniform over the sphere) has a
    non-zero evaluation there, and weighting it by the density of the event that does reach
    that side gave it 0.2 on average where it is worth 0 (0.6 % more light out of a glass
    bounce from inside; ``test_a_photon_scatters_as_mitsuba_samples``)."""
    cos_wi = mi.Frame3f.cos_theta(si.wi)
    wo_geo = dr.dot(si.n, si.to_world(bs.wo))
    cos_wo = mi.Frame3f.cos_theta(bs.wo)
    good = (wi_geo * cos_wi > 0) & (wo_geo * cos_wo > 0)
    corr = dr.abs((cos_wi * wo_geo) / dr.select(good, cos_wo * wi_geo, 1.0))
    smooth = good & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    kept = smooth & (dr.max(w) > 0) & (bs.pdf > 0)
    si_adj = mi.SurfaceInteraction3f(si)
    si_adj.wi = bs.wo
    f_adj = bsdf.eval(ctx_radiance, si_adj, si.wi, kept)
    w_adj = f_adj * dr.abs(wo_geo / dr.select(kept, wi_geo * bs.pdf, 1.0))
    w_adj = dr.select(kept, w_adj, 0.0)
    return dr.select(good, dr.select(smooth, w_adj, w * corr), 0.0), good, smooth


@dr.syntax
def _photon_trace(scene, tables, ray, flux, sampler, records, counter, capacity, keep_direct,
                  max_depth, rr_depth, seen, keep_lanes):
    """Photons from the lights: deposit Φ at every rex hit, scatter by the hit's BSDF.

    Returns per photon its rays, whether its first ray hit the scene and its deposits on
    rexes flagged in ``seen`` (a Bool per rex: the light guide's yield).

    Records (rex, u, v, Φ, depth k of the hit) go to slot ``scatter_inc(counter)`` when below
    ``capacity``. Φ is weighted by |cos θ_shading| / |cos θ_geometric| of the arriving photon:
    a bucket then holds the irradiance that Mitsuba's diffuse BSDF integrates (in the shading
    frame), not the flux density across the geometric surface (they differ on meshes with
    interpolated normals)."""
    rec_rex, rec_u, rec_v, rec_flux, rec_depth, rec_lane = records
    # rec_lane: each record's lane where ``keep_lanes`` (an opaque Bool: the probe's, for the
    # budget's noise model; the final shoot passes a one-entry array and False, so both run
    # one kernel), its top bit set where the photon came straight from the light through
    # delta bounces only (sharp light: caustics, sun patches through glass, and direct light
    # when kept)
    lane = dr.arange(mi.UInt32, dr.width(ray.o))
    sharp = mi.Bool(True)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    ctx_radiance = mi.BSDFContext()
    ray = mi.Ray3f(ray)
    flux = mi.Color3f(flux)
    beta = mi.Color3f(1.0)
    depth = mi.UInt32(0)
    n_rays = mi.UInt32(0)
    first_hit = mi.Bool(False)
    n_seen = mi.UInt32(0)
    active = dr.max(flux) > 0
    while dr.hint(active, label="rex_photons"):
        si = scene.ray_intersect(ray, active)
        n_rays += dr.select(active, mi.UInt32(1), mi.UInt32(0))
        valid = active & si.is_valid()
        first_hit |= valid & (depth == 0)
        rex, uv, at_rex = tables.locate(si, valid)
        wi_geo = dr.dot(si.n, -ray.d)
        cos_wi = mi.Frame3f.cos_theta(si.wi)
        deposit = at_rex & (keep_direct | (depth > 0)) & (depth + 2 <= max_depth) \
            & (wi_geo != 0)
        slot = dr.scatter_inc(counter, mi.UInt32(0), deposit)
        n_seen += dr.select(deposit & dr.gather(mi.Bool, seen, rex, deposit), mi.UInt32(1),
                            mi.UInt32(0))
        write = deposit & (slot < capacity)
        dr.scatter(rec_rex, rex, slot, write)
        dr.scatter(rec_u, uv.x, slot, write)
        dr.scatter(rec_v, uv.y, slot, write)
        Phi = flux * beta * dr.abs(cos_wi / dr.select(write, wi_geo, 1.0))
        for c in range(3):
            dr.scatter(rec_flux, Phi[c], slot * 3 + c, write)
        dr.scatter(rec_depth, depth, slot, write)
        dr.scatter(rec_lane, lane | dr.select(sharp, mi.UInt32(SHARP_BIT), 0), slot,
                   write & keep_lanes)

        bsdf = si.bsdf(ray)
        bs, w = bsdf.sample(ctx, si, sampler.next_1d(valid), sampler.next_2d(valid), valid)
        wo = si.to_world(bs.wo)
        factor, good, smooth = photon_scatter_weight(bsdf, si, bs, w, wi_geo, ctx_radiance)
        sharp &= ~smooth
        beta *= factor
        ray = spawn_ray(si, wo, tables.scale)
        depth += 1
        alive = valid & good & (bs.pdf > 0) & (dr.max(beta) > 0) & (depth + 2 <= max_depth)
        rr = alive & (depth >= rr_depth)
        q = dr.minimum(dr.max(beta), PHOTON_RR_MAX)
        survive = ~rr | (sampler.next_1d(rr) < q)
        beta = dr.select(rr, beta * dr.rcp(dr.maximum(q, 1e-30)), beta)
        active = alive & survive
    return n_rays, first_hit, n_seen


class LightTree:
    """Adaptive light quadtrees of all emitters, as flat numpy arrays (§4.0.5, Fig. 6).

    Node (emitter e, level, ix, iy) covers [ix, ix+1]·2^-level × [iy, iy+1]·2^-level of the
    emitter's adapted 2-D sample; each node sends one jittered pilot ray when created."""

    def __init__(self):
        self.em = np.zeros(0, np.int64)
        self.lev = np.zeros(0, np.int64)
        self.ix = np.zeros(0, np.int64)
        self.iy = np.zeros(0, np.int64)
        self.leaf = np.zeros(0, bool)
        self.sig = np.zeros(0, np.uint32)
        self.pos = np.zeros((0, 3), np.float32)
        self.hit = np.zeros(0, bool)
        self.seen = np.zeros(0, bool)
        self._keys = np.zeros(0, np.int64)
        self._order = np.zeros(0, np.int64)

    @staticmethod
    def key(em, lev, ix, iy):
        return (np.asarray(em, np.int64) << 43) | (np.asarray(lev, np.int64) << 38) \
            | (np.asarray(ix, np.int64) << 19) | np.asarray(iy, np.int64)

    def append(self, em, lev, ix, iy, sig, pos, hit, seen):
        self.em = np.concatenate([self.em, em])
        self.lev = np.concatenate([self.lev, lev])
        self.ix = np.concatenate([self.ix, ix])
        self.iy = np.concatenate([self.iy, iy])
        self.leaf = np.concatenate([self.leaf, np.ones(len(em), bool)])
        self.sig = np.concatenate([self.sig, sig])
        self.pos = np.concatenate([self.pos, pos])
        self.hit = np.concatenate([self.hit, hit])
        self.seen = np.concatenate([self.seen, seen])
        keys = self.key(self.em, self.lev, self.ix, self.iy)
        self._order = np.argsort(keys, kind="stable")
        self._keys = keys[self._order]

    def find(self, em, lev, ix, iy):
        """Index of the node (em, lev, ix, iy), −1 where there is none."""
        k = self.key(em, lev, ix, iy)
        if len(self._keys) == 0:
            return np.full(len(k), -1, np.int64)
        i = np.minimum(np.searchsorted(self._keys, k), len(self._keys) - 1)
        return np.where(self._keys[i] == k, self._order[i], -1)

    def find_covering(self, em, lev, ix, iy, min_lev):
        """The deepest existing node at level ≤ ``lev`` covering the square (em, lev, ix, iy)."""
        res = np.full(len(em), -1, np.int64)
        for up in range(0, int(lev.max() - min_lev.min()) + 1 if len(lev) else 0):
            todo = (res < 0) & (lev - up >= min_lev)
            if not todo.any():
                break
            j = self.find(em[todo], lev[todo] - up, ix[todo] >> up, iy[todo] >> up)
            res[np.nonzero(todo)[0]] = j
        return res


def _padded(rng, em, n_em):
    """A stratified 2-D sample per lane: lanes of one emitter take distinct jittered strata of a
    ⌈√n⌉² grid in random order (uniform marginals, hence unbiased)."""
    u = np.empty((len(em), 2))
    order = np.argsort(em, kind="stable")
    counts = np.bincount(em, minlength=n_em)
    start = 0
    for e in np.nonzero(counts)[0]:  # per emitter, not per photon
        c = int(counts[e])
        m = int(math.ceil(math.sqrt(c)))
        strata = rng.permutation(m * m)[:c]
        lanes = order[start:start + c]
        u[lanes, 0] = (strata % m + rng.random(c)) / m
        u[lanes, 1] = (strata // m + rng.random(c)) / m
        start += c
    return u


def _emitter_rays(scene, bounds, em, adapt_dim, s_adapt, s_other):
    use3 = adapt_dim[em] == 3
    s2 = np.where(use3[:, None], s_other, s_adapt)
    s3 = np.where(use3[:, None], s_adapt, s_other)
    s2 = np.clip(s2, 0.0, ONE_MINUS_EPS).astype(np.float32)
    s3 = np.clip(s3, 0.0, ONE_MINUS_EPS).astype(np.float32)
    return emitter_rays(scene, bounds, jit(mi.UInt32, em.astype(np.uint32)),
                        jit(mi.Point2f, s2[:, 0], s2[:, 1]),
                        jit(mi.Point2f, s3[:, 0], s3[:, 1]))


def _pilot(scene, bounds, tables, seen_rex, adapt_dim, em, lev, ix, iy, rng, seed, n_em):
    """Trace one jittered pilot ray per new light node."""
    h = np.ldexp(1.0, -lev)
    s_adapt = np.stack([(ix + rng.random(len(ix))) * h, (iy + rng.random(len(iy))) * h], 1)
    s_other = _padded(rng, em, n_em)
    ray, _ = _emitter_rays(scene, bounds, em, adapt_dim, s_adapt, s_other)
    sampler = _sampler(seed, len(em))
    sig, pos, rex, hit, n_rays = _pilot_trace(scene, tables, ray, sampler)
    dr.eval(sig, pos, rex, hit, n_rays)  # one kernel for all outputs
    sig = np.asarray(sig, np.uint32)
    pos = np.stack([np.asarray(pos[c], np.float32) for c in range(3)], 1)
    hit = np.asarray(hit, bool)
    rex = np.asarray(rex, np.int64)
    seen = hit & (seen_rex[np.minimum(rex, len(seen_rex) - 1)] if len(seen_rex) else False)
    return sig, pos, hit, seen, int(dr.sum(n_rays)[0])


def _children(em, lev, ix, iy):
    e4 = np.repeat(em, 4)
    l4 = np.repeat(lev + 1, 4)
    q = np.tile(np.arange(4), len(em))
    return e4, l4, np.repeat(ix * 2, 4) + (q & 1), np.repeat(iy * 2, 4) + (q >> 1)


def build_light_tree(scene, tables, seen_rex, settings, seed, budgets, adapt_dim, bounds):
    """Adapt every emitter's light quadtree level by level (§4.1 steps 2–3 on pilot rays).

    Returns the tree and the number of pilot rays."""
    rng = np.random.default_rng(hash31(seed, _SALT_NUMPY, 1))
    n_em = len(budgets)
    active_em = np.nonzero(budgets > 0)[0]
    base = np.clip(np.floor(np.log(np.maximum(budgets, 1) / 4.0) / np.log(4.0)), 0,
                   MAX_LIGHT_LEVEL).astype(np.int64)
    top = np.minimum(base + settings.light_levels, MAX_LIGHT_LEVEL)
    tree = LightTree()
    counts = 4 ** base[active_em]
    em = np.repeat(active_em, counts)
    local = np.arange(len(em)) - np.repeat(np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    lev = base[em]
    res = np.left_shift(1, lev)
    ix, iy = local % res, local // res
    pilot_rays = 0
    thresh2 = (settings.light_split_dist * bounds.diagonal) ** 2
    for step in range(settings.light_levels + 1):
        first = len(tree.em)
        if step == settings.light_levels:  # the deepest nodes are never marked: no pilot
            z = np.zeros(len(em))
            tree.append(em, lev, ix, iy, z.astype(np.uint32), np.zeros((len(em), 3), np.float32),
                        z.astype(bool), z.astype(bool))
            break
        sig, pos, hit, seen, nr = _pilot(scene, bounds, tables, seen_rex, adapt_dim, em, lev,
                                         ix, iy, rng, hash31(seed, _SALT_PILOT, step), n_em)
        pilot_rays += nr
        tree.append(em, lev, ix, iy, sig, pos, hit, seen)
        # light marking (§4.1): the nodes just traced, against their four neighbours
        cand = np.arange(first, len(tree.em))
        cand = cand[tree.lev[cand] < top[tree.em[cand]]]
        mark = np.zeros(len(cand), bool)
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nx, ny = tree.ix[cand] + dx, tree.iy[cand] + dy
            n = np.left_shift(1, tree.lev[cand])
            inside = (nx >= 0) & (ny >= 0) & (nx < n) & (ny < n)
            j = np.full(len(cand), -1, np.int64)
            j[inside] = tree.find_covering(tree.em[cand][inside], tree.lev[cand][inside],
                                           nx[inside], ny[inside], base[tree.em[cand][inside]])
            ok = j >= 0
            jj = np.where(ok, j, 0)
            differ = tree.sig[cand] != tree.sig[jj]
            both = tree.hit[cand] & tree.hit[jj]
            far = both & (np.sum((tree.pos[cand] - tree.pos[jj]) ** 2, 1) > thresh2)
            relevant = tree.seen[cand] | tree.seen[jj]
            mark |= ok & (differ | far) & relevant
        marked = cand[mark]
        # the photon budget: at most (budget − leaves)/3 splits per emitter, chosen at random
        leaves = np.bincount(tree.em[tree.leaf], minlength=n_em)
        allowed = np.maximum((budgets - leaves) // 3, 0)
        pri = rng.random(len(marked))
        order = np.lexsort((pri, tree.em[marked]))
        marked = marked[order]
        e_m = tree.em[marked]
        start = np.searchsorted(e_m, np.arange(n_em))
        rank = np.arange(len(marked)) - start[e_m]
        marked = marked[rank < allowed[e_m]]
        if len(marked) == 0:
            break
        # restricted quadtree: coarser leaves beside a split node split as well
        extra = []
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nx, ny = tree.ix[marked] + dx, tree.iy[marked] + dy
            n = np.left_shift(1, tree.lev[marked])
            inside = (nx >= 0) & (ny >= 0) & (nx < n) & (ny < n)
            mk = marked[inside]
            same = tree.find(tree.em[mk], tree.lev[mk], nx[inside], ny[inside])
            coarse = tree.find(tree.em[mk], tree.lev[mk] - 1, nx[inside] >> 1, ny[inside] >> 1)
            extra.append(coarse[(same < 0) & (coarse >= 0)])
        extra = np.unique(np.concatenate(extra)) if extra else np.zeros(0, np.int64)
        extra = extra[tree.leaf[extra]]
        split = np.unique(np.concatenate([marked, extra]))
        tree.leaf[split] = False
        em, lev, ix, iy = _children(tree.em[split], tree.lev[split], tree.ix[split],
                                    tree.iy[split])
    return tree, pilot_rays


class FinalShoot:
    """The final photons of the light pass, generated in Dr.Jit batch by batch.

    Emitter e owns the lanes [off_e, off_e+1), leaf by leaf: ``reps_l`` rounds of one photon
    per quadrant of each of its light-quadtree leaves l, reps_l the emitter's budget shared out
    over its leaves by their importance (:class:`~mi_twopass.prepass.light_guide.LightGuide`;
    evenly without one), at least 1. A lane's adapted 2-D sample is jittered in its
    quadrant; the other 2-D sample (the position on an area light, the disk of an environment)
    takes one stratum of a ⌈√c_e⌉² grid (c_e the emitter's lanes): lane k of the emitter the
    k-th of a random permutation of the strata (:func:`permute`, keyed per emitter; each lane's
    stratum uniform, hence unbiased, as the random padding of :func:`_padded`), jittered inside
    it. Nothing is built per photon in numpy."""

    def __init__(self, tree, budgets, adapt_dim, seed, importance=None, records=None):
        rng = np.random.default_rng(seed)
        E = len(budgets)
        leaves = np.nonzero(tree.leaf)[0]
        leaves = leaves[np.argsort(tree.em[leaves], kind="stable")]  # grouped by emitter
        leaf_em = tree.em[leaves]
        n_leaves = np.bincount(leaf_em, minlength=E)
        # reps per leaf: the emitter's budget over its leaves evenly, or with a guide in
        # proportion to the leaf's area × importance (light_guide.LightGuide: Neyman's
        # allocation), at least one per quadrant
        g = np.ones(len(leaves)) if importance is None else \
            np.asarray(importance)[leaves] * np.ldexp(1.0, -2 * tree.lev[leaves])
        g_sum = np.bincount(leaf_em, weights=g, minlength=E)
        share = g / np.maximum(g_sum[leaf_em], 1e-300)
        reps = np.maximum(1, np.round(budgets[leaf_em] * share / 4.0)).astype(np.int64)
        lanes = 4 * reps
        self.leaf_reps = reps
        self.leaf_lanes = lanes
        per_em = np.bincount(leaf_em, weights=lanes, minlength=E).astype(np.int64)
        off = np.concatenate([[0], np.cumsum(per_em)]).astype(np.int64)
        leaf_off = np.concatenate([[0], np.cumsum(lanes)]).astype(np.int64)
        self.lanes = int(off[-1])
        # records expected before each leaf's first lane (``records``: per tree node, the
        # records per photon the probe measured there)
        self._lane_off = leaf_off
        self._records_before = None if records is None else np.concatenate(
            [[0.0], np.cumsum(lanes * np.asarray(records, np.float64)[leaves])])
        if len(leaves) > 1 << LEAF_SEARCH_STEPS:
            raise ValueError(f"{len(leaves)} light-tree leaves: at most 2^{LEAF_SEARCH_STEPS}")
        if self.lanes >= 1 << 32:
            raise ValueError(f"{self.lanes} photons: at most 2^32 - 1")
        m = np.ceil(np.sqrt(np.maximum(per_em, 1))).astype(np.int64)
        strata = m * m
        if strata.max(initial=0) >= 1 << 32:
            raise ValueError("too many photons for one emitter (at most 2^32 strata)")

        def u32(a):
            return jit(mi.UInt32, np.asarray(a, np.uint32))
        self.E = E
        self.n_leaves = len(leaves)
        self.leaves = leaves
        self.d_off = u32(off)
        self.d_leaf_off = u32(leaf_off)
        self.d_leaf_em = u32(leaf_em)
        self.d_reps = u32(reps)
        self.d_m, self.d_strata = u32(m), u32(strata)
        self.d_key = u32(rng.integers(0, 1 << 32, E, dtype=np.uint64))
        self.d_adapt3 = jit(mi.Bool, np.asarray(adapt_dim) == 3)
        self.d_lev, self.d_ix, self.d_iy = u32(tree.lev[leaves]), u32(tree.ix[leaves]), \
            u32(tree.iy[leaves])

    def expected_records(self, start, size):
        """The records lanes [start, start + size) are expected to deposit (the probe's
        records per photon of their leaves); None where the shoot was not given them. Lanes
        run leaf by leaf and emitter by emitter, so a batch's rate follows the lights and
        leaves it covers (mixed_room's batches: 0.01 to 4.4 records per photon)."""
        if self._records_before is None:
            return None
        return float(np.diff(np.interp([start, start + size], self._lane_off,
                                       self._records_before))[0])

    def samples(self, start, size, sampler):
        """(emitter, sample2, sample3, weight scale |quadrant| / reps) of lanes
        [start, start + size); the jitter comes from ``sampler``."""
        # the batch's first lane opaque: a literal start compiled a new kernel per batch and
        # per photon budget (every render seed's budget differs), ~0.1 s each
        g = dr.arange(mi.UInt32, size) + dr.opaque(mi.UInt32, int(start))
        # the leaf holding lane g: a binary search of LEAF_SEARCH_STEPS steps whatever the
        # leaf count (dr.binary_search unrolls log2 of it: a kernel per tree size and seed)
        leaf_off = self.d_leaf_off
        lo = mi.UInt32(0)
        hi = dr.opaque(mi.UInt32, max(self.n_leaves - 1, 0))
        for _ in range(LEAF_SEARCH_STEPS):
            mid = (lo + hi) >> 1
            right = dr.gather(mi.UInt32, leaf_off, mid + 1) <= g
            lo = dr.select(right & (lo < hi), mid + 1, lo)
            hi = dr.select(right | (lo >= hi), hi, mid)
        leaf = lo
        e = dr.gather(mi.UInt32, self.d_leaf_em, leaf)
        local = g - dr.gather(mi.UInt32, self.d_off, e)
        # (divisors kept ≥ 1: LLVM divides masked-off lanes of a packet too, and an integer
        # division by zero there is a SIGFPE)
        reps = dr.maximum(dr.gather(mi.UInt32, self.d_reps, leaf), 1)
        q = (g - dr.gather(mi.UInt32, leaf_off, leaf)) & 3
        lev = dr.gather(mi.UInt32, self.d_lev, leaf)
        h = dr.rcp(mi.Float(mi.UInt32(2) << lev))
        j = sampler.next_2d()
        s_adapt = mi.Point2f((mi.Float(2 * dr.gather(mi.UInt32, self.d_ix, leaf) + (q & 1)) + j.x) * h,
                             (mi.Float(2 * dr.gather(mi.UInt32, self.d_iy, leaf) + (q >> 1)) + j.y) * h)
        m = dr.maximum(dr.gather(mi.UInt32, self.d_m, e), 1)
        stratum = permute(local, dr.maximum(dr.gather(mi.UInt32, self.d_strata, e), 1),
                          dr.gather(mi.UInt32, self.d_key, e))
        j = sampler.next_2d()
        fm = mi.Float(m)
        s_other = mi.Point2f((mi.Float(stratum % m) + j.x) / fm, (mi.Float(stratum // m) + j.y) / fm)
        s_adapt = dr.minimum(s_adapt, ONE_MINUS_EPS)
        s_other = dr.minimum(s_other, ONE_MINUS_EPS)
        use3 = dr.gather(mi.Bool, self.d_adapt3, e)
        s2 = dr.select(use3, s_other, s_adapt)
        s3 = dr.select(use3, s_adapt, s_other)
        return e, s2, s3, h * h / mi.Float(reps)


@dr.syntax
def permute(i, n, key):
    """Kensler's hashed permutation (Pixar TM 13-01, "Correlated Multi-Jittered Sampling",
    ``permute``): index ``i`` < ``n`` to its place in a pseudo-random permutation of [0, n)
    chosen by ``key`` (UInt32 arrays; a bijection on the next power of two, cycle-walked into
    [0, n))."""
    w = n - 1
    for shift in (1, 2, 4, 8, 16):
        w |= w >> shift
    i = mi.UInt32(i)
    go = mi.Bool(True)
    while dr.hint(go, label="permute"):
        i ^= key
        i *= 0xE170893D
        i ^= key >> 16
        i ^= (i & w) >> 4
        i ^= key >> 8
        i *= 0x0929EB3F
        i ^= key >> 23
        i ^= (i & w) >> 1
        i *= 1 | key >> 27
        i *= 0x6935FA69
        i ^= (i & w) >> 11
        i *= 0x74DCB303
        i ^= (i & w) >> 2
        i *= 0x9E501CC3
        i ^= (i & w) >> 2
        i *= 0xC860A3DF
        i &= w
        i ^= i >> 5
        go = i >= n
    return (i + key) % n


def empty_records() -> dict:
    """Photon records (rex, u, v, Φ, depth of the hit), none of them."""
    return {"rex": np.zeros(0, np.uint32), "u": np.zeros(0, np.float32),
            "v": np.zeros(0, np.float32), "flux": np.zeros((0, 3), np.float32),
            "depth": np.zeros(0, np.uint16)}


def emitter_budgets(power, photons: int):
    """Photons per emitter, shared by power (at least 16 for every emitter that emits)."""
    total = float(power.sum()) if len(power) else 0.0
    if total <= 0 or not np.isfinite(total):
        return None
    share = np.where(np.isfinite(power) & (power > 0), power, 0.0) / total
    return np.where(share > 0, np.maximum(np.round(photons * share), 16), 0).astype(np.int64)


def record_capacity(size: int, rate=None) -> int:
    """Record slots for a batch of ``size`` photons that deposit about ``rate`` records each
    (``None``: not known): the rate times :data:`RECORD_MARGIN`, and at least
    :data:`RECORDS_PER_PHOTON` per photon. A batch whose
    records overflow it is traced again with room for all of them (the records do not depend
    on the capacity), so a low guess costs a second trace of the batch."""
    per_photon = RECORDS_PER_PHOTON if rate is None or not math.isfinite(rate) \
        else max(RECORDS_PER_PHOTON, RECORD_MARGIN * float(rate))
    return int(math.ceil(size * per_photon)) + 64


def shoot_photons(scene, tables, shoot, settings, seed, salt, keep_direct, seen_rex, bar=None,
                  rate=None, keep_lanes=False):
    """Trace the photons of ``shoot`` (a :class:`FinalShoot`), :data:`PHOTON_BATCH` per Dr.Jit
    launch; returns (records, rays traced, photons whose first ray hit the scene, each photon's
    deposits on the rexes ``seen_rex`` flags, in lane order, batches traced twice). A batch's
    record buffer holds what the probe measured in its leaves
    (:meth:`FinalShoot.expected_records`, × :data:`EXPECTED_MARGIN` + :data:`EXPECTED_SLACK`
    per photon); where the shoot has no such figures, ``rate`` (records per photon expected)
    sizes the first batch's (:func:`record_capacity`) and each later batch's follows the one
    before it. ``keep_lanes``: the records also hold ``lane``, the photon's lane (its top bit
    :data:`SHARP_BIT`: sharp light)."""
    max_depth = 0xFFFFFFFF if settings.max_depth < 0 else settings.max_depth
    parts = {k: [] for k in empty_records()}
    if keep_lanes:
        parts["lane"] = []
    rays = hits = retraced = 0
    yields = []
    # one entry past the rexes: a gather from an empty array is refused even when masked
    seen = jit(mi.Bool, np.append(np.asarray(seen_rex, bool), False))
    for b, start in enumerate(range(0, shoot.lanes, PHOTON_BATCH)):
        size = min(PHOTON_BATCH, shoot.lanes - start)
        expected = shoot.expected_records(start, size)
        capacity = record_capacity(size, rate) if expected is None else \
            int(math.ceil(EXPECTED_MARGIN * expected + EXPECTED_SLACK * size)) + 64
        while True:
            sampler = _sampler(hash31(seed, salt, b), size)
            em, s2, s3, scale = shoot.samples(start, size, sampler)
            ray, w = emitter_rays(scene, tables.bounds, em, s2, s3)
            flux = dr.select(dr.isfinite(w), w, 0.0) * scale
            recs = (dr.zeros(mi.UInt32, capacity), dr.zeros(mi.Float, capacity),
                    dr.zeros(mi.Float, capacity), dr.zeros(mi.Float, 3 * capacity),
                    dr.zeros(mi.UInt32, capacity),
                    dr.zeros(mi.UInt32, capacity if keep_lanes else 1))
            counter = dr.zeros(mi.UInt32, 1)
            n_rays, first_hit, n_seen = _photon_trace(
                scene, tables, ray, flux, sampler, recs, counter,
                dr.opaque(mi.UInt32, capacity),  # a literal compiled a kernel per batch size
                mi.Bool(keep_direct), mi.UInt32(max_depth), mi.UInt32(settings.rr_depth), seen,
                dr.opaque(mi.Bool, keep_lanes))
            dr.eval(n_rays, first_hit, n_seen, *recs)
            count = int(counter[0])
            if count <= capacity:
                break
            retraced += 1
            capacity = count  # deterministic: the same seed gives the same records
        rate = count / size
        rays += int(dr.sum(n_rays)[0])
        hits += int(dr.count(first_hit)[0])
        yields.append(np.asarray(n_seen, np.uint32))
        # compact records, 26 bytes each (copies: a view would keep the whole capacity alive)
        parts["rex"].append(np.asarray(recs[0], np.uint32)[:count].copy())
        parts["u"].append(np.asarray(recs[1], np.float32)[:count].copy())
        parts["v"].append(np.asarray(recs[2], np.float32)[:count].copy())
        parts["flux"].append(np.asarray(recs[3], np.float32)[:3 * count].reshape(-1, 3).copy())
        parts["depth"].append(np.minimum(np.asarray(recs[4], np.uint32)[:count],
                                         np.iinfo(np.uint16).max).astype(np.uint16))
        if keep_lanes:
            parts["lane"].append(np.asarray(recs[5], np.int64)[:count] + start)
        if bar is not None:
            bar.update(size)
    records = {k: np.concatenate(v) if v else (empty_records().get(k) if k != "lane"
                                                else np.zeros(0, np.int64))
               for k, v in parts.items()}
    return records, rays, hits, (np.concatenate(yields) if yields else np.zeros(0, np.uint32)), \
        retraced


def probe_shoot(scene, tables, seen_rex, settings, seed, power, adapt_dim, keep_direct):
    """The probe shoot: :data:`PROBE_PHOTONS` stratified photons over a uniform light quadtree
    (no adaptation). Returns (the light guide it measures, deposits per photon on rexes the eye
    sees (``seen_rex``), all deposits per photon, the records), or (None, 0, 0, no records)
    when no light emits."""
    budgets = emitter_budgets(power, PROBE_PHOTONS)
    if budgets is None:
        return None, 0.0, 0.0, empty_records()
    tree, _ = build_light_tree(scene, tables, seen_rex, replace(settings, light_levels=0), seed,
                               np.where(budgets > 0, np.maximum(budgets // LEAF_PHOTONS, 1), 0),
                               adapt_dim, tables.bounds)
    shoot = FinalShoot(tree, budgets, adapt_dim, hash31(seed, _SALT_NUMPY, 4))
    records, _, _, yields, _ = shoot_photons(scene, tables, shoot, settings, seed,
                                             _SALT_PROBE_PHOTON, keep_direct, seen_rex,
                                             rate=PROBE_RECORDS, keep_lanes=True)
    n = max(shoot.lanes, 1)
    leaves = shoot.leaves
    lanes = records.pop("lane")
    records["sharp"] = (lanes & SHARP_BIT) != 0
    lanes = lanes & (SHARP_BIT - 1)
    guide = LightGuide.from_probe(len(power), tree.em[leaves], tree.lev[leaves], tree.ix[leaves],
                                  tree.iy[leaves], shoot.leaf_lanes, yields, power,
                                  np.bincount(lanes, minlength=shoot.lanes))
    # each record's leaf: its photon's lane among the leaves' consecutive lanes
    leaf = np.searchsorted(np.cumsum(shoot.leaf_lanes), lanes, side="right")
    leaf = leaves[np.minimum(leaf, len(leaves) - 1)]
    records["weight_scale"] = guide.weight_scale(tree.em[leaf], tree.lev[leaf], tree.ix[leaf],
                                                 tree.iy[leaf], power) \
        if settings.light_guide and guide.active else np.ones(len(leaf))
    records["photons"] = n
    records["emitter"] = tree.em[leaf]  # index into scene.emitters()
    return guide, float(yields.sum()) / n, float(len(records["rex"])) / n, records


def size_cells(tables, rex, u, v):
    """``(cell, ix, iy)``: the size cell (index into the size pass's cells) of points ``(u, v)``
    on rexes ``rex`` (numpy), and their cell coordinates within their rex's size grid."""
    sizes = tables.rex_size_level.astype(np.int64)
    res = np.left_shift(1, sizes[rex])
    ix = np.minimum((np.asarray(u, np.float64) * res).astype(np.int64), res - 1)
    iy = np.minimum((np.asarray(v, np.float64) * res).astype(np.int64), res - 1)
    return tables.rex_size_offset[rex] + iy * res + ix, ix, iy


def probe_cell_sums(tables, records):
    """``(Σw, Σw², Σw of sharp light)`` per size cell of the probe shoot's ``records`` (w: a
    record's channel-mean flux; Σw² with each record's ``weight_scale``, as the light guide
    will shoot; sharp: ``records["sharp"]``, zeros without it)."""
    w = np.asarray(records["flux"], np.float64).mean(axis=1)
    rc, _, _ = size_cells(tables, np.asarray(records["rex"], np.int64), records["u"],
                          records["v"])
    s1 = np.bincount(rc, weights=w, minlength=tables.size_cells)
    s2 = np.bincount(rc, weights=w * w * records.get("weight_scale", 1.0),
                     minlength=tables.size_cells)
    sharp = records.get("sharp")
    s1_sharp = np.bincount(rc, weights=w * sharp, minlength=tables.size_cells) \
        if sharp is not None else np.zeros(tables.size_cells)
    return s1, s2, s1_sharp


def hit_cells(tables, hits):
    """``(cell, area)``: the size cell of each of the size pass's ``hits`` and its world area
    (∞ where it has none, so that Σw / area reads 0)."""
    rex = hits["rex"]
    cell, ix, iy = size_cells(tables, rex, hits["u"], hits["v"])
    area = tables.bucket_area(rex, tables.rex_size_level.astype(np.int64)[rex], ix, iy)
    return cell, np.where(area > 0, area, np.inf)


def predicted_noise(hits, known, records, tables, film, n_probe: int, model_pixels=None):
    """``(relmse, whole, sharp)``: the block relMSE the rexes' photon noise adds to the image,
    times the photon count; the share of the image's radiance that pixels read from rexes at
    level 0 (one bucket per rex: a rex no larger than its pixel, read past the cap); and the
    share they read from sharp light, deposits of photons that came from the light through
    delta bounces only (``records["sharp"]``: caustics, a sun patch through glass).

    ``relmse``:
    ``check``'s 8×8-block relMSE (:func:`mi_twopass.evaluation.metrics.block_relmse`, its ε)
    of the part two renders of one prepass share, predicted from the size pass's ``hits``
    and ``known`` (:func:`size_pass`) and the probe shoot's ``records`` (``n_probe``
    photons).

    A bucket b of world area A_b in the probe's size cell c (area A_c; Σw and Σw² the
    probe's deposits there) reads E_b with E[E_b] = Σw / A_c and, from N photons shot as the
    probe's were, Var(E_b) = Σw² · n_probe / (N · A_c · A_b): each photon's weight is
    n_probe / N of a probe photon's, and N / n_probe as many land. The bucket is the one at the
    size pass's cap, where every bucket is split down to once photons fill it (a coarser
    bucket averages over more photons: less noise, which is why the estimate is an upper
    bound, as is ignoring the bilinear read's mix of four buckets). A pixel reads
    a·E_b, a = β·ρ/π (β: the throughput of the specular chain the eye ray followed), plus
    what the eye pass takes from elsewhere (``known``: emitted light, and the direct light
    where shadow rays compute it; a pixel that meets no rex has only that, its indirect light
    left out: an upper bound again); pixels sharing a bucket share its error. Per 8×8 block
    k: Var(k) = Σ_b (Σ_{p∈b} a_p)² Var(E_b) / n_k², over (mean L)² + ε, averaged over the
    blocks of ``model_pixels`` (:func:`noise_model_pixels`, the pixels ``known`` holds;
    ``None``: every pixel of the film). Channel means throughout."""
    if not len(hits.get("rex", ())) or not len(records["rex"]):
        return 0.0, 0.0, 0.0
    s1, s2, s1_sharp = probe_cell_sums(tables, records)
    rex = hits["rex"]
    hc, area_c = hit_cells(tables, hits)
    level = hits["level"]
    area_b = hits["jac"] * np.ldexp(1.0, -2 * level)
    var = np.where(area_b > 0, s2[hc] * n_probe / (area_c * np.maximum(area_b, 1e-300)), 0.0)
    a = hits["beta"] * hits["albedo"] * units.INV_PI
    width, height = film
    bw, bh, block_of = _blocks(width, height)
    block = block_of[hits["pixel"]]
    scale = np.left_shift(1, level)
    bx = np.minimum((hits["u"] * scale).astype(np.int64), scale - 1)
    by = np.minimum((hits["v"] * scale).astype(np.int64), scale - 1)
    node = np.left_shift(1, 2 * level) + by * scale + bx  # the bucket within its rex
    order = np.lexsort((node, rex, block))
    kb, kr, kn = block[order], rex[order], node[order]
    starts = np.flatnonzero(np.r_[True, (kb[1:] != kb[:-1]) | (kr[1:] != kr[:-1])
                                  | (kn[1:] != kn[:-1])])
    share = np.add.reduceat(a[order], starts)
    count = np.diff(np.r_[starts, len(order)])
    var_run = np.add.reduceat(var[order], starts) / count
    n_blocks = bw * bh
    num = np.bincount(kb[starts], weights=share * share * var_run, minlength=n_blocks)
    read = s1[hc] / area_c
    model = np.arange(width * height) if model_pixels is None else model_pixels
    total = np.bincount(block_of[model], weights=known, minlength=n_blocks) \
        + np.bincount(block, weights=a * read, minlength=n_blocks)
    used = np.bincount(block_of[model], minlength=n_blocks) > 0
    pixels = np.bincount(block_of, minlength=n_blocks).astype(np.float64)  # edge blocks: fewer
    relmse = float(np.sum((num / pixels**2 / ((total / pixels) ** 2 + RELMSE_EPS))[used])
                   / max(np.count_nonzero(used), 1))
    # the image's radiance read from rexes at level 0 (a whole rex per bucket), and from
    # sharp light
    whole = float(np.sum((a * read)[level == 0]) / max(total.sum(), 1e-300))
    sharp_share = float(np.sum(a * s1_sharp[hc] / area_c) / max(total.sum(), 1e-300))
    return relmse, whole, sharp_share


def photon_need(need, settings, power, guide, visible_rate, all_rate, records=None,
                tables=None):
    """The automatic photon budget: the photons the image needs, the larger of two counts.

    - **Noise.** :func:`predicted_noise` predicts, from the size pass's pixels and the probe
      shoot's deposits, the block relMSE the rexes' photon noise leaves in the image for each
      photon count; the budget brings it to :data:`NOISE_SHARE` of ``check``'s bound on the
      block relMSE (:data:`~mi_twopass.evaluation.metrics.BLOCK_RELMSE_MAX`).
    - **Resolution.** Where the rexes hold sharp light (caustics, and direct light kept in
      them), every rex bucket the image needs (the size pass's ``visible_buckets``, at the cap
      it sets from the pixel footprints) gets :data:`CAP_FILL` × ``split_limit`` photons on
      average, so that buckets split down to the cap (§3.4.1, §4.1): with fewer, they stay
      coarse and blur what the noise model does not see. In proportion to the image's share
      of sharp light (:func:`predicted_noise`) up to :data:`SHARP_FULL`; none where the light
      is smooth, whose error is the noise; CAP_FILL × where whole-rex reads carry more than
      :data:`WHOLE_REX_SHARE` of it.

    Both divide by the deposits a photon leaves on rexes the eye sees, measured by the probe
    shoot (:func:`probe_shoot`) and, with the light guide on (``settings.light_guide``), the
    rate its allocation is expected to reach
    (:meth:`~mi_twopass.prepass.light_guide.LightGuide.guided_rate`); the noise model also
    weighs each probe deposit as the guide will. Without the size pass's pixels or the probe's
    records, the budget is session 12–28's rule: :data:`CAP_FILL` × ``split_limit`` photons
    per bucket. The budget lies within [:data:`MIN_PHOTONS`, :data:`MAX_AUTO_PHOTONS`] and
    keeps the records below :data:`MAX_RECORDS` (memory). Returns (photons, stats)."""
    stats = {"visible_pixels": float(need["visible_pixels"]),
             "visible_buckets": float(need["visible_buckets"])}
    if guide is None:
        return MIN_PHOTONS, stats
    rate = visible_rate
    if settings.light_guide and guide.active:
        # within 1-5 % of what the final shoot then deposits (window_interior, caustic, the
        # zoo, the Cornell box, mixed_room, the office at 256²: the leaves' counts follow their
        # area, so the probe's cells predict them)
        rate = guide.guided_rate(power)
        # the guide moves photons towards seen rexes: their other deposits may grow with them
        all_rate = all_rate * max(rate / max(visible_rate, 1e-300), 1.0)
    split = settings.split_limit * stats["visible_buckets"] / rate if rate > 0 else 0.0
    if records is not None and tables is not None and "hits" in need:
        per_photon, whole, sharp = predicted_noise(need["hits"], need["known"], records,
                                                   tables, need["film"], records["photons"],
                                                   need.get("model_pixels"))
        noise = per_photon / (NOISE_SHARE * BLOCK_RELMSE_MAX)
        # sharp light wants the buckets at the cap: up to CAP_FILL × split, in proportion to
        # its share; smooth light only what its noise needs
        fill = CAP_FILL if whole > WHOLE_REX_SHARE else CAP_FILL * min(sharp / SHARP_FULL, 1.0)
        split *= fill
        want = max(split, noise)
        stats.update(predicted_relmse_per_photon=per_photon, noise_photon_need=noise,
                     split_photon_need=split, whole_rex_share=whole, sharp_share=sharp)
    else:
        want = CAP_FILL * split
    photons = min(max(want, MIN_PHOTONS), MAX_AUTO_PHOTONS)
    if all_rate > 0:
        photons = max(min(photons, MAX_RECORDS / all_rate), MIN_PHOTONS)
    if "predicted_relmse_per_photon" in stats:
        stats["predicted_relmse"] = stats["predicted_relmse_per_photon"] / photons
    stats.update(photon_need=want, deposits_per_photon=all_rate,
                 visible_deposits_per_photon=rate, probe_visible_deposits_per_photon=visible_rate)
    return int(photons), stats


def photon_budget(scene, settings, seed: int = 0, sensor=None) -> int:
    """The photons :func:`build` shoots with ``settings``: ``settings.photons``, or where
    that is ≤ 0 the image's need (:func:`photon_need`; this runs the size pass and the probe
    shoot, a small part of the prepass)."""
    if settings.photons > 0:
        return int(settings.photons)
    m = measure_probe(scene, settings, seed, sensor)
    return photon_need(m.need, settings, m.power, *m.probe, tables=m.tables)[0]


@dataclass
class ProbeMeasure:
    """What the size pass and the probe shoot measure before any photon is shot for good:
    the rex tables, the size pass's ``cap``, ``seen``, ``size_rays`` and ``need``
    (:func:`size_pass`), the emitters' ``power`` and ``adapt_dim`` (:func:`probe_emitters`)
    and the probe's ``(guide, visible rate, all rate, records)`` (:func:`probe_shoot`): the
    plan of a build's light pass, which its photon count does not change."""

    tables: "RexTables"
    need: dict
    power: np.ndarray
    probe: tuple
    cap: np.ndarray = None
    seen: np.ndarray = None
    size_rays: int = 0
    adapt_dim: np.ndarray = None


class ProbeMemo:
    """The size pass and probe shoot (:class:`ProbeMeasure`) that the rex prepasses of one
    scene and camera share (``twopass``'s candidates: the photon need it reads, a cut build,
    its twin and its rebuild; cleared with each of its prepasses). Keyed by the settings but
    their photon count, which the plan does not read, and the sensor: a build that finds its
    plan here shoots only its own photons, with its own seed. Sharing the plan is sound: given
    the plan, each build's photons are an estimate of the same light (the plan shares them out
    and weights them, :mod:`mi_twopass.prepass.light_guide`), and the buckets' cap is the
    image's, which a twin of another seed reads alike. A plain class, not a dict, as
    :class:`~mi_twopass.prepass.radiosity.SolveMemo` (Dr.Jit traverses an integrator's
    dicts)."""

    def __init__(self):
        self._plans = {}

    @staticmethod
    def key(settings, sensor) -> tuple:
        return replace(settings, photons=0), id(sensor)

    def get(self, settings, sensor):
        return self._plans.get(self.key(settings, sensor))

    def put(self, settings, sensor, measure: ProbeMeasure) -> None:
        self._plans[self.key(settings, sensor)] = measure

    def clear(self) -> None:
        self._plans.clear()

    def __len__(self) -> int:
        return len(self._plans)


def measure_probe(scene, settings, seed: int = 0, sensor=None,
                  memo: ProbeMemo | None = None) -> ProbeMeasure:
    """The size pass and the probe shoot of :func:`photon_budget` (a small part of the
    prepass: 0.1-0.2 s at 256² on the corpus once its kernels are compiled); ``memo``: taken
    from it where a build of the same scene and camera measured it (:class:`ProbeMemo`), else
    measured and put there."""
    if memo is not None:
        found = memo.get(settings, sensor)
        if found is not None:
            return found
    tables = RexTables(scene)
    cap, seen, size_rays, need = size_pass(scene, tables, settings, seed, sensor)
    power, adapt_dim = probe_emitters(scene, seed, tables.bounds)
    probe = probe_shoot(scene, tables, seen, settings, seed, power, adapt_dim,
                        settings.direct == "rex")
    found = ProbeMeasure(tables, need, power, probe, cap, seen, size_rays, adapt_dim)
    if memo is not None:
        memo.put(settings, sensor, found)
    return found


def plan_shoot(scene, tables, seen_rex, settings, seed, bounds, keep_direct, need=None,
               measured: ProbeMeasure | None = None):
    """Everything of the light pass but the final photons: the probe shoot, the budget, the
    light quadtrees and the final shoot's allocation. Returns (the :class:`FinalShoot`, or None
    when no light emits; pilot rays; stats).

    ``settings.photons`` ≤ 0: the budget the image needs (:func:`photon_need`, from the size
    pass's ``need``). ``settings.light_guide``: the photons are shared out among the lights
    and the leaves of their quadtrees by the yield the probe shoot measured
    (:mod:`mi_twopass.prepass.light_guide`). ``measured``: the emitters' power and the probe
    shoot taken from there (:class:`ProbeMemo`), not measured again."""
    if measured is not None:
        power, adapt_dim = measured.power, measured.adapt_dim
    else:
        power, adapt_dim = probe_emitters(scene, seed, bounds)
    stats = {"emitters": len(power)}
    photons = settings.photons
    guide = None
    if measured is not None:
        guide, visible_rate, all_rate, probe_records = measured.probe
    elif photons <= 0 or settings.light_guide:
        guide, visible_rate, all_rate, probe_records = probe_shoot(
            scene, tables, seen_rex, settings, seed, power, adapt_dim, keep_direct)
    if photons <= 0:
        photons, need_stats = photon_need(need or {"visible_pixels": 0.0,
                                                   "visible_buckets": 0.0},
                                          settings, power, guide, visible_rate, all_rate,
                                          probe_records, tables)
        stats.update(need_stats)
    elif guide is not None:
        stats["deposits_per_photon"] = all_rate
    probe_guide = guide  # its cells' records per photon size the final batches' buffers
    if not (settings.light_guide and guide is not None and guide.active):
        guide = None
    stats["light_guide"] = guide is not None
    # photons per light: by power, times the light's mean importance with the guide
    share = power if guide is None else power * guide.emitter_importance()
    budgets = emitter_budgets(share, photons)
    if budgets is None:
        return None, 0, stats
    # the light quadtree's leaves each shoot LEAF_PHOTONS photons (reps per quadrant), more
    # where the tree would pass MAX_LIGHT_LEAVES
    per_leaf = max(LEAF_PHOTONS, -(-int(budgets.sum()) // MAX_LIGHT_LEAVES))
    tree, pilot_rays = build_light_tree(
        scene, tables, seen_rex, settings, seed,
        np.where(budgets > 0, np.maximum(budgets // per_leaf, 1), 0), adapt_dim, bounds)

    # final shoot: every leaf afresh, one jittered photon per quadrant, `reps` times so that
    # each emitter uses its budget (reps by the leaf's importance with the guide)
    importance = None if guide is None else guide.importance(tree.em, tree.lev, tree.ix,
                                                             tree.iy)
    shoot = FinalShoot(tree, budgets, adapt_dim, hash31(seed, _SALT_NUMPY, 2), importance,
                       None if probe_guide is None else
                       probe_guide.node_deposits(tree.em, tree.lev, tree.ix, tree.iy))
    stats.update(light_tree_leaves=int(np.count_nonzero(tree.leaf)),
                 light_tree_max_level=int(tree.lev.max()) if len(tree.lev) else 0,
                 light_tree_min_level=int(tree.lev.min()) if len(tree.lev) else 0,
                 light_tree_nodes=int(len(tree.lev)))
    return shoot, pilot_rays, stats


def light_pass(scene, tables, seen_rex, settings, seed, bounds, keep_direct, need=None,
               show_progress=True, measured: ProbeMeasure | None = None):
    """Plan the shoot (:func:`plan_shoot`; ``measured``: its probe shoot), then shoot the
    final photons; returns records and stats."""
    t0 = time.perf_counter()
    shoot, pilot_rays, plan = plan_shoot(scene, tables, seen_rex, settings, seed, bounds,
                                         keep_direct, need, measured)
    stats = {"light_rays": 0, "pilot_rays": 0, "photons": 0, "light_hit_percent": 0.0,
             "retraced_batches": 0,
             "light_tree_leaves": 0, "light_tree_max_level": 0, **plan}
    if shoot is None:
        stats["light_seconds"] = time.perf_counter() - t0
        return empty_records(), stats
    with progress(total=shoot.lanes, desc="rex light pass", unit="photon",
                  show=show_progress) as bar:
        records, rays, hits, yields, retraced = shoot_photons(
            scene, tables, shoot, settings, seed, _SALT_PHOTON, keep_direct, seen_rex, bar,
            rate=plan.get("deposits_per_photon"))
    stats.update(light_rays=rays + pilot_rays, pilot_rays=pilot_rays, photons=shoot.lanes,
                 retraced_batches=retraced,
                 light_hit_percent=100.0 * hits / max(shoot.lanes, 1),
                 final_visible_deposits_per_photon=float(yields.sum()) / max(shoot.lanes, 1),
                 light_seconds=time.perf_counter() - t0)
    return records, stats


# ---------------------------------------------------------------------------------------------
# Rex quadtrees (§3.3, §4.0.5, Fig. 5) built from the photon records
# ---------------------------------------------------------------------------------------------
class Rexes:
    """All rex quadtrees of a scene as flat node arrays (roots first: node r is rex r's root).

    ``child[node]`` is the index of the first of its four children (quadrant qx + 2·qy) or LEAF.
    Every node stores its bucket's world ``area``, photon ``count`` and irradiances ``E_direct``
    (photons that came straight from a light) and ``E_indirect`` (all others) in W/m², per depth
    class (:func:`depth_classes`; the (n, 3) attributes are class 0, ``*_classes`` all)."""

    def __init__(self, tables, node_rex, level, ix, iy, child, count, flux_d, flux_i,
                 exposure=None, exposure_rays=0):
        self.tables = tables
        self.exposure_rays = int(exposure_rays)
        self.node_rex, self.level, self.ix, self.iy = node_rex, level, ix, iy
        self.child = child
        self.count = count
        self.param_area = tables.bucket_area(node_rex, level, ix, iy) if len(node_rex) else \
            np.zeros(0)
        self.exposure = np.ones(len(child)) if exposure is None else exposure
        self.area = self.param_area * self.exposure
        flux_d = np.asarray(flux_d, np.float64)
        flux_i = np.asarray(flux_i, np.float64)
        if flux_d.ndim == 2:  # one depth class
            flux_d, flux_i = flux_d[:, None, :], flux_i[:, None, :]
        self.classes = int(flux_d.shape[1]) if flux_d.ndim == 3 else 1
        self.E_direct_classes = units.irradiance_from_flux(flux_d, self.area)
        self.E_indirect_classes = units.irradiance_from_flux(flux_i, self.area)
        self.flux_direct, self.flux_indirect = flux_d[:, 0], flux_i[:, 0]
        self.E_direct = self.E_direct_classes[:, 0]
        self.E_indirect = self.E_indirect_classes[:, 0]
        pad = np.zeros(1)
        self.d_child = jit(mi.UInt32, np.append(child, LEAF).astype(np.uint32))
        self.d_area = jit(mi.Float, np.append(self.area, pad).astype(np.float32))
        self.d_E_direct = jit(
            mi.Float, np.append(self.E_direct_classes.ravel(), np.zeros(3)).astype(np.float32))
        self.d_E_indirect = jit(
            mi.Float, np.append(self.E_indirect_classes.ravel(), np.zeros(3)).astype(np.float32))

    # -- numpy views ----------------------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return int(len(self.child))

    @property
    def is_leaf(self):
        return self.child == LEAF

    @property
    def n_leaves(self) -> int:
        return int(np.count_nonzero(self.is_leaf))

    @property
    def max_depth(self) -> int:
        return int(self.level.max()) if len(self.level) else 0

    @property
    def nbytes(self) -> int:
        # per node on the device: child (4), area (4), two RGB irradiances per class (24)
        return int(self.n_nodes * (8 + 24 * self.classes))

    def leaves(self, rex=None) -> dict:
        """The leaves (of one rex, or all) as numpy arrays: rex, level, u0, v0, size, area,
        count, flux and irradiance (direct + indirect)."""
        sel = self.is_leaf if rex is None else self.is_leaf & (self.node_rex == rex)
        h = np.ldexp(1.0, -self.level[sel].astype(np.int64))
        return {"node": np.nonzero(sel)[0], "rex": self.node_rex[sel], "level": self.level[sel],
                "u0": self.ix[sel] * h, "v0": self.iy[sel] * h, "size": h,
                "area": self.area[sel], "count": self.count[sel],
                "flux": self.flux_direct[sel] + self.flux_indirect[sel],
                "E": self.E_direct[sel] + self.E_indirect[sel],
                "E_direct": self.E_direct[sel], "E_indirect": self.E_indirect[sel]}

    # -- Dr.Jit lookups -------------------------------------------------------------------------
    @dr.syntax
    def descend(self, rex, u, v, active=True):
        """(leaf node, level) of the bucket holding (u, v) in ``rex``."""
        active = mi.Bool(active)
        node = mi.UInt32(dr.select(active, rex, 0))
        level = mi.UInt32(0)
        c = dr.gather(mi.UInt32, self.d_child, node, active)
        go = active & (c != LEAF)
        while dr.hint(go, label="rex_descend"):
            level = dr.select(go, level + 1, level)
            scale = mi.Float(mi.UInt32(1) << level)
            qx = mi.UInt32(u * scale) & 1
            qy = mi.UInt32(v * scale) & 1
            node = dr.select(go, c + qx + 2 * qy, node)
            c = dr.gather(mi.UInt32, self.d_child, node, go)
            go = go & (c != LEAF)
        return node, level

    def _value(self, node, active, w_direct, w_indirect, cls=0):
        """w_direct · E_direct + w_indirect · E_indirect of a node in depth class ``cls``
        (weights: floats or lanes)."""
        E = mi.Color3f(0.0)
        slot = node * self.classes + cls if self.classes > 1 else node
        if not (isinstance(w_direct, (int, float)) and w_direct == 0):
            E += w_direct * dr.gather(mi.Color3f, self.d_E_direct, slot, active)
        if not (isinstance(w_indirect, (int, float)) and w_indirect == 0):
            E += w_indirect * dr.gather(mi.Color3f, self.d_E_indirect, slot, active)
        return E

    def irradiance(self, rex, uv, active=True, w_direct=1.0, w_indirect=1.0, smooth=True, cls=0):
        """Irradiance E [W/m²] at (rex, uv) and its leaf (node, level).

        E = w_direct·E_direct + w_indirect·E_indirect in depth class ``cls`` (an eye vertex's
        depth under a finite max_depth), of the leaf bucket (``smooth=False``) or interpolated
        bilinearly between the centres of the leaf and its neighbours."""
        active = mi.Bool(active)
        u, v = uv.x, uv.y
        if self.classes > 1:
            cls = dr.minimum(mi.UInt32(cls), self.classes - 1)
        node, level = self.descend(rex, u, v, active)
        E0 = self._value(node, active, w_direct, w_indirect, cls)
        if not smooth:
            return E0, node, level
        h = dr.rcp(mi.Float(mi.UInt32(1) << level))
        cu = (dr.floor(u / h) + 0.5) * h
        cv = (dr.floor(v / h) + 0.5) * h
        su = dr.select(u >= cu, h, -h)
        sv = dr.select(v >= cv, h, -h)
        wu = dr.minimum(dr.abs(u - cu) / h, 0.5)
        wv = dr.minimum(dr.abs(v - cv) / h, 0.5)
        wrap = dr.gather(mi.UInt32, self.tables.d_wrap, rex, active)

        def neighbour(du, dv):
            nu, nv = cu + du, cv + dv
            nu = dr.select((wrap & WRAP_U) != 0, nu - dr.floor(nu), nu)
            nv = dr.select((wrap & WRAP_V) != 0, nv - dr.floor(nv), nv)
            inside = active & (nu >= 0) & (nu < 1) & (nv >= 0) & (nv < 1)
            n_node, _ = self.descend(rex, nu, nv, inside)
            ok = inside & (dr.gather(mi.Float, self.d_area, n_node, inside) > 0)
            return dr.select(ok, self._value(n_node, ok, w_direct, w_indirect, cls), E0)

        E = (1 - wu) * (1 - wv) * E0 + wu * (1 - wv) * neighbour(su, 0.0) \
            + (1 - wu) * wv * neighbour(0.0, sv) + wu * wv * neighbour(su, sv)
        return E, node, level


def probe_exposure(scene, tables, node_rex, level, ix, iy, nodes, seed, m=16):
    """Fraction of each bucket's area that is not buried inside closed geometry.

    A box standing on a floor covers part of the floor's buckets; no photon lands there, so
    E = ΣΦ / area would be too dark next to the box (the light leak of radiosity textures,
    inverted). ``m`` stratified points per bucket are lifted off the surface by a hair and tested
    with three rays (along the normal and both ways along a random tangent): a point all of whose
    rays first hit the back face of a one-sided surface (no BackSide BSDF flag) is inside a
    closed object. Two-sided and transmissive surfaces never bury a point: their normals may
    point anywhere (a room of two-sided walls with outward normals is not "inside"). Returns
    the open fraction per node in ``nodes`` (1 where nothing covers the bucket), and the rays
    traced. The buckets are probed :data:`EXPOSURE_BATCH` at a time (bounded memory)."""
    out = np.ones(len(nodes))
    rng = np.random.default_rng(hash31(seed, _SALT_NUMPY, 3))
    rays = 0
    for start in range(0, len(nodes), EXPOSURE_BATCH):
        part = nodes[start:start + EXPOSURE_BATCH]
        out[start:start + len(part)], r = _probe_open(scene, tables, node_rex, level, ix, iy,
                                                      part, rng, m)
        rays += r
    return out, rays


def _probe_open(scene, tables, node_rex, level, ix, iy, nodes, rng, m):
    """:func:`probe_exposure` for one batch of buckets. The lanes' parameters come from numpy
    (``rng``); their points, frames and the three rays run as one Dr.Jit kernel. Until session
    34 the points and frames were numpy float64 and each ray direction a kernel of its own:
    0.57 s of the 2.26 s rex prepass of mixed_room at 256², 0.48 s of veach-bidir's 2.05 s
    (``tools/prepass_profile.py``)."""
    k = int(round(math.sqrt(m)))
    lane_node = np.repeat(np.arange(len(nodes)), k * k)
    sub = np.tile(np.arange(k * k), len(nodes))
    h = np.ldexp(1.0, -level[nodes].astype(np.int64))[lane_node]
    u = (ix[nodes][lane_node] + (sub % k + rng.random(len(sub))) / k) * h
    v = (iy[nodes][lane_node] + (sub // k + rng.random(len(sub))) / k) * h
    rex = node_rex[nodes][lane_node].astype(np.int64)
    tri = tables.rex_tri[rex]
    is_tri = tri >= 0
    U, V = jit(mi.Float, u.astype(np.float32)), jit(mi.Float, v.astype(np.float32))
    on_tri = jit(mi.Bool, is_tri)
    tid = jit(mi.UInt32, np.where(is_tri, tri, 0).astype(np.uint32))
    e1 = dr.gather(mi.Vector3f, tables.d_tri_e1, tid, on_tri)
    e2 = dr.gather(mi.Vector3f, tables.d_tri_e2, tid, on_tri)
    p = dr.gather(mi.Point3f, tables.d_tri_p0, tid, on_tri) + U * e1 + V * e2
    n = dr.cross(e1, e2)
    ln = dr.norm(n)
    n = dr.select(ln > 0, n / dr.select(ln > 0, ln, 1.0), 0.0)
    valid = on_tri & (U + V <= 1) & (ln > 0)
    shapes = tables.rex_shape[rex]
    if not is_tri.all():  # analytic shapes, one vectorised call each
        p_a, n_a = np.zeros((len(sub), 3), np.float32), np.zeros((len(sub), 3), np.float32)
        valid_a = np.zeros(len(sub), bool)
        for s_idx in np.unique(shapes[~is_tri]):
            sel = np.nonzero((shapes == s_idx) & ~is_tri)[0]
            try:
                si = tables.shapes[int(s_idx)].eval_parameterization(
                    mi.Point2f(jit(mi.Float, u[sel].astype(np.float32)),
                               jit(mi.Float, v[sel].astype(np.float32))))
                dr.eval(si.p, si.n, si.t)
            except Exception:  # a shape without a parameterisation: leave its buckets open
                continue
            p_a[sel] = np.stack([np.asarray(si.p[c], np.float32) for c in range(3)], 1)
            n_a[sel] = np.stack([np.asarray(si.n[c], np.float32) for c in range(3)], 1)
            valid_a[sel] = np.asarray(si.is_valid(), bool)
        p = dr.select(on_tri, p, vectors(p_a, mi.Point3f))
        n = dr.select(on_tri, n, vectors(n_a, mi.Vector3f))
        valid |= ~on_tri & jit(mi.Bool, valid_a)
    n = dr.select(jit(mi.Bool, tables.rex_side[rex] == 1), -n, n)
    # a random tangent per point
    t1, t2 = mi.coordinate_system(n)
    phi = jit(mi.Float, (rng.random(len(sub)) * 2 * math.pi).astype(np.float32))
    tan = dr.cos(phi) * t1 + dr.sin(phi) * t2
    # the scene's size as an input, not a literal: one kernel for every scene
    eps = 1e-5 * (dr.opaque(mi.Float, tables.bounds.diagonal) + dr.max(dr.abs(p)))
    origin = p + n * eps
    enclosed = mi.Bool(valid)
    tried = []
    for d in (n, tan, -tan):
        tried.append(mi.Bool(enclosed))
        ray = mi.Ray3f(origin, d)
        si = scene.ray_intersect(ray, enclosed)
        # only the back of a one-sided surface walls a point in: a two-sided or transmissive
        # BSDF's normal says nothing about inside and outside (a room of two-sided walls whose
        # normals point out would otherwise count as the inside of a closed object)
        one_sided = ~mi.has_flag(si.bsdf().flags(), mi.BSDFFlags.BackSide)
        enclosed &= si.is_valid() & (dr.dot(si.n, ray.d) > 0) & one_sided
    is_open = valid & ~enclosed
    dr.eval(is_open, valid, *tried)
    rays = sum(int(np.count_nonzero(np.asarray(t, bool))) for t in tried)
    is_open, valid = np.asarray(is_open, bool), np.asarray(valid, bool)
    open_count = np.bincount(lane_node, weights=is_open.astype(np.float64), minlength=len(nodes))
    total = np.bincount(lane_node, weights=valid.astype(np.float64), minlength=len(nodes))
    return np.where(total > 0, open_count / np.maximum(total, 1), 1.0), rays


def _spread_bits(x):
    """Bits b of ``x`` (mi.UInt64, < 2^32) moved to bit 2b: one axis of a Morton (Z-order)
    code."""
    x = x & mi.UInt64(0x00000000FFFFFFFF)
    for shift, mask in ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF),
                        (4, 0x0F0F0F0F0F0F0F0F), (2, 0x3333333333333333),
                        (1, 0x5555555555555555)):
        x = (x | (x << shift)) & mi.UInt64(mask)
    return x


def key_bits(n_rexes: int) -> int:
    """Bits per axis of a record's quadtree key: 20 (:data:`MAX_LEVEL` levels) while the rex
    index fits the other 24 bits of a 64-bit key, fewer (a shallower deepest level) beyond."""
    return int(min(MAX_LEVEL, (64 - max(int(n_rexes), 1).bit_length()) // 2))


def quadtree_cells(rex, u, v, bits: int):
    """Integer cell coordinates ``(qx, qy) = (⌊u·2^bits⌋, ⌊v·2^bits⌋)`` (mi.UInt64, clipped to
    the square) and 64-bit keys ``rex · 4^bits + Morton(qx, qy)``, qx on the even bits, of the
    records ``rex`` (uint32), ``u``, ``v`` (float32; numpy or Dr.Jit arrays).

    Sorted, the records of every quadtree node at every level form one contiguous run (the
    node's key prefix), and the two bits at level l (counted from the root's children) are the
    quadrant qx + 2·qy that :meth:`Rexes.descend` takes there. Computed by Dr.Jit: millions of
    records (6.8 M on the Cornell box at 128²) are a vectorised kernel's work, not numpy's."""
    n = 1 << bits
    qx = mi.UInt64(dr.clip(dr.floor(mi.Float64(jit(mi.Float, u)) * n), 0, n - 1))
    qy = mi.UInt64(dr.clip(dr.floor(mi.Float64(jit(mi.Float, v)) * n), 0, n - 1))
    morton = _spread_bits(qx) | (_spread_bits(qy) << 1)
    return qx, qy, (mi.UInt64(jit(mi.UInt32, rex)) << (2 * bits)) | morton


def record_caps(tables, cap, rex, qx, qy, bits: int, max_level: int):
    """Every record's size-pass cap (at most ``max_level``), from its size cell: the top
    ``rex_size_level`` bits of its cell coordinates ``qx``, ``qy`` (:func:`quadtree_cells`)
    in its rex's block of ``cap``. Dr.Jit arrays in, an mi.Int32 array out."""
    r = mi.UInt32(rex)
    size_level = mi.UInt64(dr.gather(mi.UInt32, tables.d_size_level, r))
    drop = bits - size_level
    cell = mi.UInt32(dr.gather(mi.UInt32, tables.d_size_offset, r)) + mi.UInt32(
        ((qy >> drop) << size_level) | (qx >> drop))
    return dr.minimum(dr.gather(mi.Int32, jit(mi.Int32, np.asarray(cap, np.int32)), cell), max_level)


def _run_max(values, lo, hi):
    """max(values[lo:hi]) per run (runs non-empty)."""
    if len(lo) == 0:
        return np.zeros(0, values.dtype)
    padded = np.append(values, values[:1])  # reduceat's indices must stay inside the array
    idx = np.empty(2 * len(lo), np.int64)
    idx[0::2], idx[1::2] = lo, hi
    return np.maximum.reduceat(padded, idx)[0::2]


def sort_records(tables, records, cap, bits: int, max_level: int):
    """``(order, keys, rec_cap)``: the records' order by quadtree key (an mi.UInt32 array of
    record indices), their keys in that order and their size-pass caps (numpy uint64 and
    int16 arrays; :func:`quadtree_cells`, :func:`record_caps`).

    The keys and caps are computed, sorted (Dr.Jit's radix sort) and gathered by Dr.Jit, as is
    the deposit (:func:`deposit`); with numpy the build took 1.68 and 1.76 s on the Cornell box
    at 128², now 1.00 and 0.95 s, the same rexes bit for bit (``rex_build_seconds`` of
    ``bench --prepass --quick --integrators rex``, two runs each,
    docs/results/rex-build-2026-11-27). Ties (equal keys) may come in any order: nothing built
    from them depends on it."""
    if len(records["rex"]) == 0:
        return mi.UInt32(), np.zeros(0, np.uint64), np.zeros(0, np.int16)
    rex = jit(mi.UInt32, records["rex"])
    qx, qy, d_keys = quadtree_cells(rex, records["u"], records["v"], bits)
    d_cap = record_caps(tables, cap, rex, qx, qy, bits, max_level)
    dr.eval(d_keys, d_cap)
    order = dr.argsort(d_keys)
    keys = np.asarray(dr.gather(mi.UInt64, d_keys, order))
    rec_cap = np.asarray(dr.gather(mi.Int32, d_cap, order)).astype(np.int16)
    return order, keys, rec_cap


def deposit(records, order, sorted_leaf, n_nodes: int, classes: int, max_depth: int):
    """§4.1's deposit: every record's flux Φ into its leaf, per depth class and direct or not:
    sums of shape (n_nodes · classes · 2, 3). ``order``: the records in key order
    (:func:`sort_records`), ``sorted_leaf``: the leaf of each, in that order.

    In fixed point: quanta of the largest flux / 2^k, summed as float64 integers below 2^53,
    hence exactly, so the sums do not depend on the order of the records, which the light
    pass's atomic slot counter leaves random (and the sort's ties): the rexes, hence the image,
    are the same bit for bit for the same seed. Depth classes (finite ``max_depth``): a record
    of depth k goes to the deepest class it belongs to, c0 = min(C − 1, max_depth − 2 − k).
    The records are read in key order, a leaf's deposits neighbours, in one Dr.Jit kernel."""
    sums = np.zeros((n_nodes * classes * 2, 3))
    n_rec = len(records["rex"])
    if n_rec == 0:
        return sums
    flux_in = records["flux"]
    fmax = float(flux_in.max())
    k = min(32, 52 - int(n_rec).bit_length())
    quantum = fmax / 2.0**k if fmax > 0 and np.isfinite(fmax) else 1.0
    depth = dr.gather(mi.UInt32, jit(mi.UInt32, records["depth"].astype(np.uint32)), order)
    bins = jit(mi.UInt32, np.asarray(sorted_leaf, np.uint32)) * (2 * classes)
    if max_depth >= 0:
        c0 = dr.clip(mi.Int32(max_depth - 2) - mi.Int32(depth), 0, classes - 1)
        bins += 2 * mi.UInt32(c0)
    bins += dr.select(depth > 0, 1, 0)
    flat = jit(mi.Float, np.ascontiguousarray(flux_in, np.float32).ravel())
    totals = [dr.zeros(mi.Float64, len(sums)) for _ in range(3)]
    # the quantum follows the photons and the bins' count the tree: as literals they made
    # the kernel new for every seed (the LLVM default for a small target, ReduceMode.Expand,
    # bakes its size in); the records come in key order, so a packet's lanes mostly share a
    # bin, which Local pre-reduces
    quantum_d = dr.opaque(mi.Float64, quantum)
    for c in range(3):
        quanta = dr.round(mi.Float64(dr.gather(mi.Float, flat, order * 3 + c)) / quantum_d)
        dr.scatter_reduce(dr.ReduceOp.Add, totals[c], quanta, bins, mode=_DEPOSIT_MODE)
    dr.eval(totals)  # the three channels in one kernel
    for c in range(3):
        sums[:, c] = np.asarray(totals[c]) * quantum
    return sums


def build_rex_tree(tables, records, cap, settings, scene=None, seed=0) -> Rexes:
    """Split every rex bucket holding more than ``split_limit`` photons (past its size-pass cap,
    more than split_limit·4^(levels past it); §4.1 "rex subdivision"), all rexes at once, level
    by level; then deposit the records and, given the scene, measure how much of each leaf is
    buried under closed objects.

    The records are sorted once by their quadtree key (:func:`quadtree_keys`): a node's records
    are then one run of the sorted array, its photon count and largest cap come from the run's
    ends, and its children's runs from a binary search of their key prefixes, so each level
    costs the nodes it holds, not the photons (a Cornell box at 1M photons: 2.8M records)."""
    R = tables.count
    n_rec = len(records["rex"])
    bits = key_bits(R)
    max_level = min(int(settings.max_level), bits)
    order, keys, rec_cap = sort_records(tables, records, cap, bits, max_level)

    roots = np.arange(R, dtype=np.int64)
    root_keys = roots.astype(np.uint64) << np.uint64(2 * bits)
    node_rex, level, ix, iy, child = [roots], [np.zeros(R, np.int64)], \
        [np.zeros(R, np.int64)], [np.zeros(R, np.int64)], [np.full(R, LEAF, np.int64)]
    lo = [np.searchsorted(keys, root_keys, "left")]
    hi = [np.append(lo[0][1:], n_rec)]
    prefix = [root_keys]  # every node's smallest key
    n_total = R
    for lev in range(MAX_LEVEL):
        l_lo, l_hi = lo[-1], hi[-1]
        cnt = l_hi - l_lo
        if len(cnt) == 0 or lev >= max_level:
            break
        # the size-pass cap is soft: past it, a bucket splits only with 4× more photons per
        # level (threshold split_limit·4^(level − cap + 1)), so buckets still shrink as the
        # photon count grows. A hard cap left the sub-pixel triangles of a lamp shade (seen
        # only along their rims, or missed by the size pass) one bucket each, whose average
        # irradiance is not that of the visible part, a bias no photon count removed.
        limit = np.full(len(cnt), np.inf)
        busy = np.nonzero(cnt > settings.split_limit)[0]
        bucket_cap = _run_max(rec_cap, l_lo[busy], l_hi[busy]).astype(np.int64)
        past = np.maximum(lev - bucket_cap + 1, 0)
        limit[busy] = settings.split_limit * np.power(4.0, np.minimum(past, 30))
        split = np.nonzero(cnt > limit)[0]
        if len(split) == 0:
            break
        # the nodes of level `lev` are the last block appended: give split ones four children
        child[-1][split] = n_total + 4 * np.arange(len(split))
        q = np.tile(np.arange(4), len(split))
        node_rex.append(np.repeat(node_rex[-1][split], 4))
        level.append(np.full(4 * len(split), lev + 1, np.int64))
        ix.append(np.repeat(ix[-1][split] * 2, 4) + (q & 1))
        iy.append(np.repeat(iy[-1][split] * 2, 4) + (q >> 1))
        child.append(np.full(4 * len(split), LEAF, np.int64))
        step = np.uint64(1) << np.uint64(2 * (bits - lev - 1))
        kids = np.repeat(prefix[-1][split], 4) + q.astype(np.uint64) * step
        bounds = np.searchsorted(keys, kids, "left").reshape(-1, 4)
        prefix.append(kids)
        lo.append(bounds.ravel())
        hi.append(np.concatenate([bounds[:, 1:], l_hi[split, None]], 1).ravel())
        n_total += 4 * len(split)
    node_rex = np.concatenate(node_rex)
    level = np.concatenate(level)
    ix, iy = np.concatenate(ix), np.concatenate(iy)
    child = np.concatenate(child)
    lo, hi = np.concatenate(lo), np.concatenate(hi)

    # every record's leaf: the leaves' runs tile the sorted records
    n = len(child)
    is_leaf = child == LEAF
    count = np.where(is_leaf, hi - lo, 0).astype(np.int64)
    leaves = np.nonzero(is_leaf & (count > 0))[0]
    leaves = leaves[np.argsort(lo[leaves], kind="stable")]
    del keys, rec_cap
    # deposit (§4.1): every record's flux into its leaf
    C = depth_classes(settings.max_depth)
    sums = deposit(records, order, np.repeat(leaves, count[leaves]), n, C, settings.max_depth)
    del order
    sums = sums.reshape(n, C, 2, 3)
    flux = {name: np.cumsum(sums[:, ::-1, i], axis=1)[:, ::-1] for i, name in enumerate("di")}
    exposure = np.ones(n)
    exposure_rays = 0
    if scene is not None:
        leaves = np.nonzero(is_leaf)[0]
        f, exposure_rays = probe_exposure(scene, tables, node_rex, level, ix, iy, leaves, seed,
                                          EXPOSURE_PROBES)
        # a leaf that caught photons is open somewhere, however few probes found it open
        exposure[leaves] = np.where(count[leaves] > 0, np.maximum(f, 0.5 / EXPOSURE_PROBES), f)
    return Rexes(tables, node_rex.astype(np.uint32), level.astype(np.uint8), ix.astype(np.uint32),
                 iy.astype(np.uint32), child.astype(np.uint32), count, flux["d"], flux["i"],
                 exposure, exposure_rays)


# ---------------------------------------------------------------------------------------------
# The whole prepass
# ---------------------------------------------------------------------------------------------
@dataclass
class RexPrepass:
    """What the rex integrator renders from: the tables, the rexes and the passes' statistics."""

    tables: RexTables
    rexes: Rexes
    cap: np.ndarray
    seen: np.ndarray
    settings: RexSettings
    stats: dict

    @property
    def nbytes(self) -> int:
        return int(self.tables.nbytes + self.rexes.nbytes + self.cap.size)


def warn_short_bbox(scene, bounds):
    """Warn when ``scene.bbox()`` misses part of the geometry and an infinite emitter is present
    (:func:`mi_twopass.scene.bounds.infinite_light_leaks`): Mitsuba's ``path`` leaks light
    there (our shadow rays go on to infinity, :func:`mi_twopass.rays.shadow_ray`), so compare
    with a ``path`` render of the scene loaded with ``optimize=False``, which avoids the merge
    (``python -m mi_twopass check`` does)."""
    if infinite_light_leaks(scene, bounds):
        warnings.warn("scene.bbox() misses part of the geometry (Mitsuba merges rectangles that "
                      "share a BSDF into a mesh whose bbox leaves them out): infinite emitters' "
                      "shadow rays can leak through walls in Mitsuba's path (not in rex's); "
                      "compare with path on the scene loaded with optimize=False",
                      stacklevel=3)


def scene_media(scene) -> list:
    """``(where, medium)`` of every participating medium the scene attaches to its sensors,
    emitters and shapes."""
    found = []
    for i, sensor in enumerate(scene.sensors()):
        found.append((f"sensor {sensor.id() or i!r}", sensor.get_medium()))
    for i, emitter in enumerate(scene.emitters()):
        found.append((f"emitter {emitter.id() or i!r}", emitter.get_medium()))
    for i, shape in enumerate(scene.shapes()):
        name = shape.id() or f"{shape.class_name()} #{i}"
        found.append((f"interior of shape {name!r}", shape.interior_medium()))
        found.append((f"exterior of shape {name!r}", shape.exterior_medium()))
    return [(where, m) for where, m in found if m is not None]


def check_no_media(scene):
    """rex has no volumetric transport (no photon scatters or is absorbed in a medium, no eye
    path attenuates): refuse a scene with media rather than render it silently wrong."""
    media = scene_media(scene)
    if media:
        names = "; ".join(f"{m.class_name()} {m.id()!r} ({where})" if m.id() else
                          f"{m.class_name()} ({where})" for where, m in media[:4])
        more = f" and {len(media) - 4} more" if len(media) > 4 else ""
        raise ValueError(f"rex cannot render participating media, and this scene has: "
                         f"{names}{more}. Use Mitsuba's 'volpath' integrator for it.")


def build(scene, settings: RexSettings, seed: int = 0, progress: bool = True,
          sensor=None, memo: ProbeMemo | None = None) -> RexPrepass:
    """Size pass, light pass and rex build for ``scene`` (all random numbers from ``seed``);
    ``progress``: a bar over the light pass's photons (on a terminal); ``sensor``: the camera
    the size pass sizes the rexes for (default: the scene's first); ``memo``: the size pass
    and probe shoot taken from there where a build of the same scene and camera measured them
    (:class:`ProbeMemo`: ``plan_reused`` in the stats), else measured and put there; only
    the final photons are then this build's (from ``seed``)."""
    if settings.direct not in ("rex", "shadow"):
        raise ValueError(f"direct={settings.direct!r}: expected 'rex' or 'shadow'")
    check_no_media(scene)
    t0 = time.perf_counter()
    measured = None
    if memo is not None:
        reused = memo.get(settings, sensor) is not None
        measured = measure_probe(scene, settings, seed, sensor, memo)
        tables, cap, seen, need = measured.tables, measured.cap, measured.seen, measured.need
        size_rays = 0 if reused else measured.size_rays
    else:
        reused = False
        tables = RexTables(scene)
        cap, seen, size_rays, need = size_pass(scene, tables, settings, seed, sensor)
    warn_short_bbox(scene, tables.bounds)
    dr.sync_thread()
    t1 = time.perf_counter()
    records, light_stats = light_pass(scene, tables, seen, settings, seed, tables.bounds,
                                      settings.direct == "rex", need, progress, measured)
    t2 = time.perf_counter()
    rexes = build_rex_tree(tables, records, cap, settings, scene, seed)
    dr.sync_thread()
    t3 = time.perf_counter()
    stats = dict(light_stats)
    stats.update(size_rays=size_rays, size_seconds=t1 - t0, light_seconds=t2 - t1,
                 rex_build_seconds=t3 - t2, rexes=tables.count, rex_nodes=rexes.n_nodes,
                 rex_leaves=rexes.n_leaves, rex_max_depth=rexes.max_depth,
                 photon_records=int(len(records["rex"])), exposure_rays=rexes.exposure_rays,
                 prepass_rays=size_rays + light_stats["light_rays"] + rexes.exposure_rays,
                 plan_reused=reused)
    return RexPrepass(tables, rexes, cap, seen, settings, stats)
