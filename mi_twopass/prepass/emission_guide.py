"""Where the radiosity prepass's particles start: importance-driven emission.

A sun or a sky lights a room through a window. Mitsuba's ``sample_ray`` starts their particles
uniformly on a disk (a sphere) around the whole scene, so a few per cent of them enter, each
carrying a large share of the flux; the room's solution is then the sum of a few hundred heavy
deposits and differs from one prepass seed to the next by more than the bias bounds allow
(scenes_xml/mixed_room.xml: far reads 0.98–1.03 of a path-traced estimate over five seeds with
the sun and sky, ±0.3 % without them; ``tools/far_gather_hits.py --seed``). The noise does not
average away with samples per pixel: every pixel reads the same solution.

The remedy is Jensen's projection maps (Jensen 1996, "Global illumination using photon maps",
§3: photons are shot only where the map says they meet something) made importance-driven as
in Peter & Pietrek (1998, "Importance driven construction of photon maps"): particles are sent
where the *camera's* reads will meet them.

1. **Cells.** Each emitter's primary sample space, the (u2, u3) ∈ [0,1)⁴ from which
   :func:`mi_twopass.scene.emission.emitter_rays` builds its rays, is cut into cells over the
   dimensions the ray depends on (:func:`moving_dims`): ``GRID_2D``² cells where one pair
   matters (a sun's disk position, a point light's direction), ``GRID_4D``⁴ where both do (a
   sky's direction and disk position). An area emitter is one cell: its share of the
   particles is what is guided.
2. **Importance** W per receiver (:func:`camera_importance`): camera paths of
   ``CAMERA_BOUNCES`` BSDF-sampled bounces count the receivers they hit — where the far
   gather, its continuation and the spike lists will read the solution.
3. **Pilot**, in two stages: ``PILOT_PER_CELL`` particles per cell on average, the cells
   chosen uniformly; then ``PILOT_FOCUS`` per cell on the cells that scored and their
   neighbours, of emitters where those are not most of the grid (:func:`focus_cells`; a lit
   window is a few per cent of a sun's disk: a uniform pilot of a few particles per cell
   misses the cells it only partly covers). A
   particle's score is the W-weighted flux of all its deposits, brought to a common scale
   (× the pilot's probability of its cell × its particle count: the contribution density f
   times the cell volume V_c).
4. **The guide** (:func:`fitted`): cell c is drawn with probability
   P_c = (1 − α) · r_c / Σ r + α · P_default(c),   r_c = max(rms_c, γ · max of its
   neighbours' rms_c),
   rms_c of its scores: P_c ∝ V_c · sqrt(mean_c f²) is the variance-optimal piecewise-constant
   density; γ = ``NEIGHBOURS`` keeps a share for cells beside lit ones that the pilot missed,
   and the mixture with Mitsuba's own choice (its emitter selection × uniform cells; α =
   ``DEFENSIVE``) one for every cell: the estimate stays unbiased wherever the pilot saw
   nothing. A particle drawn in cell c, uniformly within it, carries the emitter's ray
   weight / (P_c / V_c).
5. **The particle count** (:func:`image_noise`): the same pilot particles, scored by the
   radiance their deposits send along the camera's paths (:class:`CameraImportance`), predict
   how much the solution's noise moves the image's mean: the noise of the light read from the
   solution (at the paths' second and later vertices) times its share of the image beside
   the first vertex's direct light (a particle's first deposit there), which emitter sampling
   renders without the solution. The solve gets the particles that bring it to
   ``radiosity.FLUX_NOISE``.

On scenes_xml/mixed_room.xml the predicted relative standard deviation of the camera-weighted
flux of 2^18 particles (:func:`predicted_noise`, against a 64-per-cell pilot) is 2.6 % with
Mitsuba's emission, 0.24 % with the best guide a cell grid allows, 1.4 % with a one-stage
pilot of 8 per cell, 0.7 % with the neighbours' share and 0.4 % with the second stage.

Only scenes with an emitter that is not an area light get a guide (its cost: a camera pass of
``CAMERA_LANES`` paths and the pilot); area lights alone are sampled as before. A guide the
pilot predicts to gain less than ``MIN_GAIN`` in variance is dropped (scenes_xml/caustic.xml's
sky: 1.8×; mixed_room 79×, window_interior 17×, many_lights' four point lights 6×).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..host_arrays import jit
from ..scene.emission import emitter_kinds
from ..units import channel_mean

#: cells per dimension where one (u2 or u3) pair of an emitter's samples moves its rays
GRID_2D = 32
#: cells per dimension where both pairs do
GRID_4D = 6
#: cells of all emitters' grids together at most (grid_resolution)
MAX_CELLS = 16384
#: pilot particles per cell (mean), first stage, and per cell of the second stage's cells.
#: A lit cell the first stage misses, and whose neighbours it misses too, keeps only the
#: ``DEFENSIVE`` share: the particles drawn there carry up to 1/``DEFENSIVE`` times Mitsuba's
#: own weight, and about one prepass in eight rendered heavy. With 4, scenes_xml/mixed_room.xml
#: (a sky seen through a window: clusters of its 6⁴ cells lit with probability ~1/30) drew
#: it in 5 prepass seeds of 40: the true noise per particle of the fitted guide 3.9–4.1
#: against a median of 2.3 (the pilot's own prediction 1.0–1.4 throughout), and seed 24301
#: at max_patches=1010 rendered 2.7 % bright (radiosity_gather, ``check``: 1.027, the 1 %
#: bound broken). With 16: median 2.20, largest 2.98; many_lights 0.72 → 0.59, window_interior
#: unchanged (4.9); the pilot's cost is the same within noise (0.08 s, 0.04–0.05 s at 256²;
#: many_lights' 4 point lights 0.12 → 0.15 s) (``tools/guide_noise.py --per-cell 4 16``,
#: docs/results/guide-pilot-2026-11-28)
PILOT_PER_CELL = 16
PILOT_FOCUS = 32
#: γ: a cell's share is at least this fraction of its most important neighbour's
NEIGHBOURS = 0.25
#: the second stage samples an emitter's lit cells again only where they are at most this
#: fraction of its grid: with a fraction f lit, a focused stage puts at most 1/f times the
#: first stage's density there (a sun through a window: 0.25–0.28 lit, a sky: 0.53; a point
#: light among walls, 0.79: its 1024 cells would cost 100k pilot particles for < 1.3×)
FOCUS_MAX_LIT = 0.6
#: a guide is used only where the pilot predicts it divides the camera-weighted flux's
#: variance by this much (else Mitsuba's emission: the pilot's cost bought nothing)
MIN_GAIN = 2.0
#: share of the particles drawn as Mitsuba would (emitter selection × uniform cells)
DEFENSIVE = 0.25
#: camera paths of the importance pass, and the bounces each follows
CAMERA_LANES = 1 << 16
CAMERA_BOUNCES = 3


def moving_dims(scene, index: int, probes: int = 16, kind: str | None = None
                ) -> tuple[bool, bool]:
    """Whether the rays :func:`mi_twopass.scene.emission.emitter_rays` builds for emitter
    ``index`` move with its first sample pair u2 and with its second u3. An infinite emitter's
    u2 picks a direction (fixed for a delta direction: a sun) and u3 a point of the disk facing
    it; a point, spot or projector light's rays are Mitsuba's ``sample_ray``, probed here: each
    pair changed at ``probes`` random points with the other held (on the emitter object itself:
    a virtual call over all of a scene's emitters is recorded anew at every call, ~0.1 s with
    116 of them). ``kind``: the emitter's :func:`~mi_twopass.scene.emission.emitter_kinds`
    entry, where the caller has them."""
    emitter = scene.emitters()[index]
    kind = kind if kind is not None else emitter_kinds(scene)[index]
    if kind == "surface":
        return (False, False)
    if kind == "infinite":
        return (not mi.has_flag(emitter.flags(), mi.EmitterFlags.DeltaDirection), True)
    rng = np.random.default_rng(1)
    a, b, c = (mi.Point2f(*rng.random((2, probes)).astype(np.float32)) for _ in range(3))

    def ray(u2, u3):
        r, _ = emitter.sample_ray(0.0, 0.5, u2, u3)
        return np.concatenate([np.broadcast_to(np.asarray(v), (3, probes))
                               for v in (r.o, r.d)])

    base = ray(a, b)
    scale = max(float(np.abs(base).max()), 1e-30)
    return (bool(np.abs(ray(c, b) - base).max() > 1e-6 * scale),
            bool(np.abs(ray(a, c) - base).max() > 1e-6 * scale))


class EmissionCells:
    """The cells of every emitter's primary sample space: per cell its emitter, its lower
    corner ``lo`` and extent ``size`` in (u2.x, u2.y, u3.x, u3.y), and the probability
    ``default`` Mitsuba's own emission gives it (emitter selection × volume); ``blocks``:
    per emitter (first cell, grid shape over the dimensions it is cut along)."""

    def __init__(self, emitter, lo, size, default, blocks=()):
        self.emitter = np.asarray(emitter, np.uint32)
        self.lo = np.asarray(lo, np.float64).reshape(-1, 4)
        self.size = np.asarray(size, np.float64).reshape(-1, 4)
        self.default = np.asarray(default, np.float64)
        self.blocks = list(blocks)

    @property
    def count(self) -> int:
        return int(self.emitter.size)

    @property
    def volume(self) -> np.ndarray:
        return self.size.prod(axis=1)


def grid_resolution(moves, gridded: int) -> int:
    """Cells per cut dimension of an emitter whose sample pairs move its rays as ``moves``
    says, when ``gridded`` emitters are cut: ``GRID_2D`` (one pair) or ``GRID_4D`` (both), less
    where the scene's grids would pass ``MAX_CELLS`` in all (a street of 200 point lights
    would otherwise take 200 × 1024 cells and a pilot of 800k particles); 1 below 2."""
    dims = 2 * sum(bool(m) for m in moves)
    if dims == 0:
        return 1
    res = min(GRID_4D if dims == 4 else GRID_2D,
              int((MAX_CELLS / max(gridded, 1)) ** (1.0 / dims) + 1e-9))
    return res if res >= 2 else 1


def cells(scene) -> EmissionCells:
    """:class:`EmissionCells` of ``scene``'s emitters (module docstring, step 1)."""
    n = len(scene.emitters())
    select = np.broadcast_to(np.asarray(
        scene.pdf_emitter(jit(mi.UInt32, np.arange(n, dtype=np.uint32))), np.float64).ravel(),
        (n,)) if n else np.zeros(0)
    kinds = emitter_kinds(scene)
    moves = [moving_dims(scene, i, kind=kinds[i]) for i in range(n)]
    gridded = sum(any(m) for m in moves)
    em, lo, size, default, blocks = [], [], [], [], []
    start = 0
    for i in range(n):
        res = grid_resolution(moves[i], gridded)
        axes = np.array([res if m else 1 for m in moves[i] for _ in range(2)])
        count = int(axes.prod())
        idx = np.indices(axes).reshape(4, -1).T  # row-major, as neighbour_max reshapes
        em.append(np.full(count, i))
        lo.append(idx / axes)
        size.append(np.broadcast_to(1.0 / axes, (count, 4)))
        default.append(np.full(count, select[i] / count))
        blocks.append((start, tuple(int(k) for k in axes if k > 1)))
        start += count
    if n == 0:
        return EmissionCells([], np.zeros((0, 4)), np.zeros((0, 4)), [], [])
    return EmissionCells(np.concatenate(em), np.concatenate(lo), np.concatenate(size),
                         np.concatenate(default), blocks)


class EmissionGuide:
    """A distribution over :class:`EmissionCells` that particles are drawn from
    (:meth:`sample`). A plain class of Dr.Jit tables."""

    def __init__(self, cells_: EmissionCells, pmf):
        pmf = np.asarray(pmf, np.float64)
        pmf = pmf / pmf.sum()
        self.cells = cells_
        self.pmf = pmf
        self._distr = mi.DiscreteDistribution(jit(mi.Float, pmf.astype(np.float32)))
        self._emitter = jit(mi.UInt32, cells_.emitter)
        self._lo = [jit(mi.Float, cells_.lo[:, k].astype(np.float32)) for k in range(4)]
        self._size = [jit(mi.Float, cells_.size[:, k].astype(np.float32)) for k in range(4)]
        # 1 / density of u within the cell: V_c / P_c
        inv = np.where(pmf > 0, cells_.volume / np.where(pmf > 0, pmf, 1.0), 0.0)
        self._inv_density = jit(mi.Float, inv.astype(np.float32))

    def sample(self, u1, u2, u3, active=True):
        """(cell, emitter index, 1 / density of the drawn (u2, u3), the reused u1, u2 and u3
        moved into the cell) for uniform ``u1``, ``u2``, ``u3``."""
        cell, u1 = self._distr.sample_reuse(u1, active)
        g = lambda t: dr.gather(mi.Float, t, cell, active)  # noqa: E731
        lo, size = [g(t) for t in self._lo], [g(t) for t in self._size]
        v2 = mi.Point2f(lo[0] + size[0] * u2.x, lo[1] + size[1] * u2.y)
        v3 = mi.Point2f(lo[2] + size[2] * u3.x, lo[3] + size[3] * u3.y)
        return (cell, dr.gather(mi.UInt32, self._emitter, cell, active),
                g(self._inv_density), u1, v2, v3)


def uniform(cells_: EmissionCells) -> EmissionGuide:
    """Every cell equally likely: the pilot's guide."""
    return EmissionGuide(cells_, np.ones(cells_.count))


def neighbour_max(cells_: EmissionCells, values) -> np.ndarray:
    """Per cell, the largest value among it and its neighbours in its emitter's grid (the
    3 × … × 3 box; an area emitter's one cell is its own)."""
    values = np.asarray(values, np.float64)
    out = values.copy()
    for start, shape in cells_.blocks:
        if not shape:
            continue
        stop = start + int(np.prod(shape))
        grid = values[start:stop].reshape(shape)
        for axis in range(grid.ndim):
            lo = np.concatenate([grid.take([0], axis), grid.take(range(grid.shape[axis] - 1),
                                                                 axis)], axis)
            hi = np.concatenate([grid.take(range(1, grid.shape[axis]), axis),
                                 grid.take([grid.shape[axis] - 1], axis)], axis)
            grid = np.maximum(grid, np.maximum(lo, hi))
        out[start:stop] = grid.ravel()
    return out


def focus_cells(cells_: EmissionCells, cell_of, score) -> np.ndarray:
    """The cells the second pilot stage samples (step 3): those that scored in the first and
    their neighbours, of the emitters cut into a grid where those are at most
    ``FOCUS_MAX_LIT`` of it."""
    lit = neighbour_max(cells_, cell_rms(cells_, cell_of, score)) > 0
    focus = np.zeros_like(lit)
    for start, shape in cells_.blocks:
        stop = start + int(np.prod(shape))
        if shape and lit[start:stop].mean() <= FOCUS_MAX_LIT:
            focus[start:stop] = lit[start:stop]
    return focus


def cell_rms(cells_: EmissionCells, cell_of, score) -> np.ndarray:
    """Per cell, the root mean square of the scores of the pilot particles drawn in it."""
    cell_of = np.asarray(cell_of, np.int64)
    score = np.asarray(score, np.float64)
    n = np.bincount(cell_of, minlength=cells_.count)
    s2 = np.bincount(cell_of, weights=score ** 2, minlength=cells_.count)
    return np.sqrt(s2 / np.maximum(n, 1))


def fitted(cells_: EmissionCells, cell_of, score) -> EmissionGuide | None:
    """The guide from pilot particles (module docstring, step 4): per cell the root mean
    square of its particles' scores (on the common scale of step 3), at least ``NEIGHBOURS``
    × its neighbours', mixed with Mitsuba's choice. ``None`` where no pilot particle scored
    (the camera reads nothing the emitters reach)."""
    rms = cell_rms(cells_, cell_of, score)
    if not (rms.sum() > 0 and np.isfinite(rms.sum())):
        return None
    r = np.maximum(rms, NEIGHBOURS * neighbour_max(cells_, rms))
    default = cells_.default / cells_.default.sum()
    return EmissionGuide(cells_, (1.0 - DEFENSIVE) * r / r.sum() + DEFENSIVE * default)


def predicted_noise(cells_: EmissionCells, pmf, cell_of, score, particles: int) -> float:
    """The relative standard deviation of the camera-weighted flux of ``particles`` particles
    drawn with cell probabilities ``pmf``, from pilot scores s = f·V_c (step 3's common scale)
    of particles drawn uniformly within their cells: the total is I = Σ_c mean_c(s), a
    particle's estimate s / P_c has variance Σ_c mean_c(s²) / P_c − I² (cells without pilot
    particles count as dark)."""
    cell_of = np.asarray(cell_of, np.int64)
    score = np.asarray(score, np.float64)
    C = cells_.count
    n = np.maximum(np.bincount(cell_of, minlength=C), 1)
    total = cell_total(cells_, cell_of, score)
    ms2 = np.bincount(cell_of, weights=score ** 2, minlength=C) / n
    pmf = np.asarray(pmf, np.float64)
    second = np.sum(np.where(ms2 > 0, ms2 / np.where(pmf > 0, pmf, 1e-300), 0.0))
    var = max(second - total ** 2, 0.0)
    return float(np.sqrt(var / particles) / max(abs(total), 1e-300))


class CameraImportance:
    """What the camera's paths say of each receiver (+1 sentinel), :func:`camera_importance`:

    * ``hits``: how many paths hit it, at any of their ``CAMERA_BOUNCES`` vertices (the guide's
      W, module docstring step 2);
    * ``first``, ``read``: per unit flux Φ received, the mean over the paths of the radiance
      ρΦ / (πA) it sends along them (× their throughput, the BSDF weights before the hit), at
      the first vertex and at the later ones. The light the first vertex receives straight from
      the emitters is rendered by emitter sampling; what the later vertices send is read from
      the solution (the far gather, the spike lists' virtual luminaires, the radiance cache).
      So, with the particles' deposits, ``read`` gives the part of the image the solution's
      noise is in and ``first`` the direct part beside it (:func:`image_noise`)."""

    def __init__(self, hits, first, read):
        self.hits = hits
        self.first = first
        self.read = read


def radiance_per_flux(receivers) -> np.ndarray:
    """Per receiver (+1 sentinel, 0): ρ̄ / (π A), the radiance a Lambertian receiver of area A
    and mean albedo ρ̄ sends per unit flux it receives (0 where it has no area or does not
    reflect diffusely)."""
    area = np.asarray(receivers.area, np.float64)
    albedo = np.asarray(receivers.albedo, np.float64).mean(axis=1)
    k = np.where(area > 0, albedo / (np.pi * np.where(area > 0, area, 1.0)), 0.0)
    return np.append(k, 0.0)


def camera_importance(scene, sensor, receivers, seed: int, lanes: int = CAMERA_LANES
                      ) -> CameraImportance:
    """:class:`CameraImportance` of each receiver from ``lanes`` camera paths, each of
    ``CAMERA_BOUNCES`` BSDF-sampled bounces from a uniform film position. ``receivers``: the
    elements, else the patches (``lookup``)."""
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, seed), lanes)  # a literal seed: kernels per seed
    ray, _ = sensor.sample_ray(0.0, 0.5, sampler.next_2d(), sampler.next_2d())
    ray = mi.Ray3f(ray)
    W = dr.zeros(mi.Float, receivers.count + 1)
    first = dr.zeros(mi.Float, receivers.count + 1)
    read = dr.zeros(mi.Float, receivers.count + 1)
    throughput = dr.full(mi.Float, 1.0, lanes)
    ctx = mi.BSDFContext()
    active = dr.full(mi.Bool, True, lanes)
    for bounce in range(CAMERA_BOUNCES):
        si = scene.ray_intersect(ray, active)
        active &= si.is_valid()
        rid = receivers.lookup(si, active)
        at = active & (rid < receivers.count)
        dr.scatter_reduce(dr.ReduceOp.Add, W, 1.0, rid, at)
        dr.scatter_reduce(dr.ReduceOp.Add, first if bounce == 0 else read, throughput, rid, at)
        bs, w = si.bsdf(ray).sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active)
        active &= (bs.pdf > 0) & dr.any(w > 0)
        throughput = dr.select(active, throughput * channel_mean(w), 0.0)
        ray = si.spawn_ray(si.to_world(bs.wo))
        dr.eval(W, first, read, ray, active, throughput)
    k = radiance_per_flux(receivers) / lanes
    W = np.asarray(W, np.float64)
    W[-1] = 0.0
    return CameraImportance(W, np.asarray(first, np.float64) * k, np.asarray(read, np.float64) * k)


def cell_total(cells_: EmissionCells, cell_of, score) -> float:
    """I = Σ_c mean_c(s): the total a score on step 3's common scale estimates."""
    cell_of = np.asarray(cell_of, np.int64)
    n = np.maximum(np.bincount(cell_of, minlength=cells_.count), 1)
    return float(np.sum(np.bincount(cell_of, weights=np.asarray(score, np.float64),
                                    minlength=cells_.count) / n))


def image_noise(cells_: EmissionCells, pmf, cell_of, read, first, particles: int) -> float:
    """The relative standard deviation of the image's mean that the noise of a solution of
    ``particles`` particles drawn with ``pmf`` leaves, from the pilot's ``read`` and ``first``
    scores (the particles' deposits weighted by :class:`CameraImportance`'s ``read`` and, for
    their first deposit alone, ``first``): sd(Σ read) / (I_read + I_first), i.e. the relative
    noise of the light read from the solution (:func:`predicted_noise`) times its share of the
    image, the rest being the first vertex's direct light, which emitter sampling renders
    without the solution. Light the camera sees straight from an emitter is not counted, so the
    share is an upper bound. 0 where the camera reads nothing of the solution."""
    i_read = cell_total(cells_, cell_of, read)
    if not i_read > 0:
        return 0.0
    share = i_read / (i_read + max(cell_total(cells_, cell_of, first), 0.0))
    return predicted_noise(cells_, pmf, cell_of, read, particles) * share


__all__ = ["CameraImportance", "EmissionCells", "EmissionGuide", "camera_importance", "cell_rms",
           "cell_total", "cells", "fitted", "focus_cells", "image_noise", "moving_dims",
           "neighbour_max", "predicted_noise", "radiance_per_flux", "uniform"]
