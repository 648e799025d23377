"""``twopass``'s compositions and the cost model that chooses one per scene and camera.

A *composition* names the technique that serves each part of path space (the parts of
:mod:`mi_twopass.integrators.component_path`):

======== ============ ========== ================================================================
direct   indirect     caustics   estimator
======== ============ ========== ================================================================
emitter  path         off        Mitsuba's ``path`` (emitter + BSDF sampling, MIS), no prepass
spike    path         off        ``spike_gather`` with no far gather (``r_thresh`` → ∞)
spike    radiosity    off        ``spike_gather`` (spike lists + radiosity far gather)
emitter  radiosity    off        ``radiosity_gather`` (GSII: virtual luminaires + far gather)
emitter  cache        off        ``radiance_cache`` (SH far field + near-field correction)
emitter  rex          rex        ``rex`` (photon quadtrees hold all of L(S|D)*D; direct light
                                 by emitter sampling at the rex vertex)
======== ============ ========== ================================================================

"off" caustics are path traced (BSDF sampling through the specular chain), never dropped. Each
row is one of the suite's estimators, each consistent (or within its stated bias bound) on its
own, so every part of path space is estimated once in every composition.

**The model.** For each candidate c the pilot (:mod:`mi_twopass.compose.pilot`) measures the
prepass seconds T_c, the seconds t_c of one sample of every pixel, the relative variance v_c of
one sample and its relative bias b_c against the path pilot, pixel by pixel (squared, less
both pilots' noise, counted where it stands out of that noise: :func:`bias_squared`). A render of N samples per pixel is predicted to take
T_c + N·t_c seconds and to reach relMSE v_c/N + b_c²; the candidate with the smallest product
(error × time: the inverse of the efficiency, prepass and bias included) is rendered.

**Only what pays is built.** Before a candidate's prepass is built, its *best case* is bounded
from the path pilot's variance split: a technique can at most remove the variance of the parts
it serves (spike lists: the direct part; a far field: the indirect part; rexes: everything, but
only where caustics carry at least :data:`CAUSTIC_SHARE` of the variance, the caustic part read
as the larger of the pilot's and the one rex's probe photons predict where the scene has a
specular surface: :mod:`mi_twopass.prepass.sharp_light`), it costs at least what
``path`` costs per sample (every one traces the camera ray, a shadow ray and a BSDF ray per
vertex) and its prepass at least 0 s. A candidate whose best case does not beat the best score
measured so far by :data:`MIN_GAIN` is not built; nor is any once the pilot and the prepasses
built so far have spent :data:`PILOT_BUDGET` of the time ``path`` is predicted to take for the
render (a prepass cannot pay in a render shorter than itself; at most one prepass overshoots,
as none is stopped once started, so one whose predicted floor, :data:`PREPASS_FLOOR_FACTOR` path
samples per light path it traces and at least :data:`PREPASS_LEAST_SECONDS`, would pass the
budget is not started); nor one the scene gives
nothing to (one
emitter for spike lists, no Lambertian surface for the far fields and rexes, a finite
``max_depth`` for the far fields, which hold every path length).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..evaluation.metrics import BLOCK, BLOCK_RELMSE_MAX, RELMSE_EPS

#: a candidate is built only if its best case beats the best score so far by this factor
MIN_GAIN = 1.25
#: rexes are tried only where the caustic part carries this share of path's pilot variance
CAUSTIC_SHARE = 0.2

#: a pilot pair's bias estimate counts beyond this many standard errors (bias_squared)
BIAS_SIGMAS = 3.0
#: a winner that may be biased is measured again against path while a bias below its pilot's
#: detection limit could still change the choice (:func:`hidden_bias_may_decide`): a round
#: takes the samples per pixel of both estimators to where the limit, which falls as 1/samples
#: while the bias is small, is CHECK_MARGIN below the bias the winner can afford (at least
#: twice, at most CHECK_MAX_GROWTH× the last test's, and what CHECK_BUDGET still pays for), at
#: most CHECK_ROUNDS rounds (mi_twopass.compose.choose.check_bias)
CHECK_MARGIN = 1.25
CHECK_MAX_GROWTH = 16
CHECK_ROUNDS = 2
#: the bias tests may take this share of the time ``path`` is predicted to need for the
#: render, besides the pilot budget (which the prepasses may have spent)
CHECK_BUDGET = 0.05
#: a bias test's estimate counts beyond this many standard errors: fewer than the pilot's
#: BIAS_SIGMAS, as the test is run only on a suspect (the winner whose bias could decide),
#: and the bias of a cache that varies over the image keeps the standard error high however
#: many samples a pixel gets (the Cornell box's cache: z = 2.8 to 3.8 at 785–1839 samples);
#: not 0, as the estimate of a noisy scene can be far above its bias by chance (caustic.xml at
#: 1024 spp: rex's raw b² 5.7e-3 at z = 1.1, counted, sent the render to path: relMSE 0.041
#: where rex reached 0.015)
CHECK_SIGMAS = 2.0
#: building stops once the pilot and the prepasses built have taken this share of the time
#: ``path`` is predicted to need for the render (``pilot_budget``)
PILOT_BUDGET = 0.25
#: a candidate whose best case beats path's score by g may have its prepass started while the
#: pilot and the prepasses so far leave room for BREAK_EVEN_SHARE of its break-even time,
#: (g − 1) × path's predicted render time (:func:`prepass_budget`), up to BREAK_EVEN_MAX of
#: that render time (and never less than ``pilot_budget``): the best case is an upper bound
#: of the gain and the prepass floor a lower bound of the cost, so both keep a margin
BREAK_EVEN_SHARE = 0.5
BREAK_EVEN_MAX = 1.0
#: the pilot starts only where its samples (every candidate's pilot runs as many as path's)
#: are at most this share of the render's path samples, at the default ``pilot_budget`` (in
#: proportion to it otherwise): it is all twopass loses where nothing pays. The office at
#: 256² reaches relMSE 0.01 near 16 spp with the spike lists, where the pilot's 147,456
#: samples are 14 % of the render's; the furnace reaches it with path at 4 spp (56 %)
PILOT_SHARE_MAX = 0.15
#: a prepass is predicted to cost at least this many path samples' time per light path it
#: traces (radiosity particles, rex photons); measured on the corpus at 128²: 2.4 (office,
#: window_interior) to 38 (furnace), docs/design.md "twopass"
PREPASS_FLOOR_FACTOR = 2.0
#: ... and at least this many seconds, whatever the device: a prepass's host work (patches,
#: Python, numpy, many small kernels) does not get faster with it. The least prepass measured
#: took 0.20 s on two CPU cores (radiosity_gather, Cornell box at 64², ``bench --prepass
#: --quick``) and 0.19 s on an H200 (the same at 256², docs/results/gpu-2026-11-27), where
#: the floor in path samples' time predicted about 0.002 s and twopass built 1.4 s of spike
#: lists and radiosity for a 0.07 s render; three quarters of the least, as a floor must not
#: pass what it bounds
PREPASS_LEAST_SECONDS = 0.15

#: the rexes twopass renders have at least 1/CUT_MAX of the photons the image needs. Their
#: buckets stop splitting at the pixel footprint with the image's need, and coarser with fewer
#: photons: cuts blur caustics and contact shadows into square leaves, a bias no number of
#: samples removes. On caustic.xml at 64 spp, check's bias part (the block relMSE two renders
#: of one build share: the blur and the build's own noise) read, at 1/16, 1/8, 1/4, 1/2 and
#: all of the need: 1.3e-2, 7.5e-3, 6.0e-3, 1.4e-3, 1.0e-3 at 128² (need 2.1 M; 1/4 and 1/2
#: over two more seeds: 5.5e-3 and 8.1e-3, 1.8e-3 and 1.2e-3) and 1.3e-2, 5.8e-3, 1.8e-3,
#: 1.6e-3, 1.1e-3 at 256² (need 8.0 M) against check's bound of 3e-3
#: (docs/results/cut-blur-2026-11-29). Until session 34 the cut was 16, from a measurement
#: made when the need was counted otherwise (17 M at 128²); at 256², 64 spp, twopass's cut
#: rexes then read 4.0-6.3e-3
CUT_MAX = 2
#: a cut rex's first build, which the pilot measures, may have 1/PROBE_CUT of the need: it is
#: built again with at least 1/CUT_MAX where its measured score pays for that
#: (:func:`measured_room`), and left out where it does not
PROBE_CUT = (BLOCK // 2) ** 2
#: a cut rex is built a second time with another seed and both are sampled on FROZEN_BLOCKS
#: blocks of check's grid (all of a 128² film), FROZEN_SAMPLES samples per pixel
#: (:func:`frozen_error`); the noise of its own photons, which no number of samples per pixel
#: removes, may fill at most FROZEN_SHARE of check's bound on the block relMSE (the rest is
#: left to the bias). Above it, the photons are raised by (measured / limit)^(1/FROZEN_DECAY)
#: (up to the image's need): the noise fell as photons^-0.25 to ^-1 where measured (office at
#: 128², need 0.77 M: 5.8e-3 at 2^16, 4.3e-3 at need/4, 1.8e-3 at need; caustic: 3.3e-3,
#: 1.2e-3, 1.7e-4 at 2^16, 2^18, 2^20), the buckets growing as the photons fall
FROZEN_BLOCKS = 256
FROZEN_SAMPLES = 8
FROZEN_SHARE = 0.5
FROZEN_DECAY = 0.5
#: the second build of a cut rex gets up to this many times its photons, where the rest of the
#: candidate's budget pays for them at the first build's measured seconds per photon
#: (:func:`twin_photons`); it is then the build that renders. The twin's comparison sees the
#: photons' noise and not the buckets' blur, which two builds of one photon count share: on
#: caustic.xml at 256² (256 spp, 1.8 M photons, budget 0.25 x path's render) it predicted a
#: persistent relMSE of 0.0036 where the harness read ~0.012 against a 16384-spp reference
#: (docs/results/bench-2026-11-27g), so the cut was kept where more photons would have paid
FROZEN_TWIN_GROWTH = 4

DIRECT = ("emitter", "spike")
INDIRECT = ("path", "radiosity", "cache", "rex")
CAUSTICS = ("off", "rex")


@dataclass(frozen=True)
class Composition:
    """One row of the module's table: the technique per part and the plugin that renders it
    (``"path"``: :class:`~mi_twopass.integrators.component_path.ComponentPathIntegrator`)."""

    direct: str
    indirect: str
    caustics: str
    plugin: str
    props: tuple = ()
    #: the variance parts (of the path pilot) the technique can remove
    serves: tuple = ()

    @property
    def name(self) -> str:
        return f"direct={self.direct},indirect={self.indirect},caustics={self.caustics}"

    @property
    def needs_prepass(self) -> bool:
        return self.plugin != "path"

    @property
    def biased(self) -> bool:
        """Whether the composition reads a cache (a far field or rexes), whose bias only the
        pilot's comparison with path can bound; spike lists alone are unbiased (defensive
        choice and MIS)."""
        return self.indirect != "path" or self.caustics != "off"


#: the radiosity budget of twopass's row of spike lists with the radiance cache: spike_gather's
#: own (``SpikeGatherIntegrator.RADIOSITY_DEFAULTS``), so that it reads the solve the other
#: spike-list rows built (radiosity.build's memo) instead of solving again with the cache's
#: default (2048 patches x 256 particles, 4 elements): mixed_room at 256², 256 spp, pilot and
#: prepasses 2.66-2.83 -> 2.08-2.16 s, the render 7.45-7.77 -> 6.93-7.06 s; window_interior
#: 1.85-1.88 -> 1.51-1.59 s (docs/results/twopass-shared-solve-2026-11-28). The row of the cache
#: alone keeps the cache's default: where it is built without spike lists (one emitter) there is
#: no solve to share, and with half the particles it won the Cornell box's 512-spp point on a
#: bias its test did not see (equal-time 0.98 against 2.09 with the radiosity gather)
CACHE_RADIOSITY = (("max_patches", 4096), ("particles_per_patch", 64),
                   ("elements_per_patch", 4))

COMPOSITIONS = (
    Composition("emitter", "path", "off", "path"),
    Composition("spike", "path", "off", "spike_gather", (("r_thresh_rel", 1e9),), ("direct",)),
    Composition("spike", "radiosity", "off", "spike_gather", (), ("direct", "indirect")),
    Composition("emitter", "radiosity", "off", "radiosity_gather", (), ("indirect",)),
    Composition("emitter", "cache", "off", "radiance_cache", (("direct", "emitter"),),
                ("indirect",)),
    Composition("spike", "cache", "off", "radiance_cache",
                (("direct", "spike"),) + CACHE_RADIOSITY, ("direct", "indirect")),
    Composition("emitter", "rex", "rex", "rex", (), ("direct", "indirect", "caustic")),
)


def matching(direct=None, indirect=None, caustics=None) -> list:
    """The compositions that agree with the choices forced from XML (``None``: free). Raises
    ValueError naming the forced choices when none does (e.g. spike lists with the cache)."""
    rows = [c for c in COMPOSITIONS
            if (direct is None or c.direct == direct)
            and (indirect is None or c.indirect == indirect)
            and (caustics is None or c.caustics == caustics)]
    if not rows:
        forced = ", ".join(f"{k}={v!r}" for k, v in
                           (("direct", direct), ("indirect", indirect), ("caustics", caustics))
                           if v is not None)
        raise ValueError(f"twopass: no composition has {forced}; the ones there are: "
                         + "; ".join(c.name for c in COMPOSITIONS))
    return rows


@dataclass(frozen=True)
class SceneTraits:
    """What the scene offers the techniques, read without building anything."""

    emitters: int
    lambertian: bool
    max_depth: int
    #: some surface has a delta (specular) lobe: light can reach a diffuse surface through it
    specular: bool = True


def structural_reason(c: Composition, traits: SceneTraits) -> str | None:
    """Why ``c`` cannot pay on this scene whatever its measurements (None: it may)."""
    if c.direct == "spike" and traits.emitters < 2:
        return f"{traits.emitters} emitter(s): a spike list of one source is emitter sampling"
    if c.plugin in ("radiosity_gather", "radiance_cache", "rex") or c.indirect == "radiosity":
        if not traits.lambertian:
            return "no Lambertian surface to hold radiosity, a cache or rexes"
    if c.indirect in ("radiosity", "cache") and traits.max_depth >= 0:
        return (f"max_depth={traits.max_depth}: the far field holds light of every path "
                "length, so a bounded path cannot end in it")
    return None


@dataclass
class VarianceParts:
    """The path pilot's relative variance in all and per part (:mod:`.pilot`)."""

    total: float
    direct: float
    caustic: float
    indirect: float

    def best_case(self, c: Composition) -> float:
        """The least relative variance ``c`` could reach: path's, less the parts it serves
        (0 at least; the parts' covariances are ignored)."""
        removed = sum(getattr(self, part) for part in c.serves)
        return max(self.total - removed, 0.0)

    def with_caustic(self, predicted: float) -> "VarianceParts":
        """The parts with the caustic part at least ``predicted`` and the total raised by as
        much: a pilot of a few hundred samples underestimates light that comes as rare bright
        samples, which photons predict (:mod:`mi_twopass.prepass.sharp_light`)."""
        extra = max(predicted - self.caustic, 0.0)
        return VarianceParts(total=self.total + extra, direct=self.direct,
                             caustic=self.caustic + extra, indirect=self.indirect)


@dataclass
class Measured:
    """A candidate's pilot figures (module docstring) and its predicted render."""

    prepass_seconds: float
    seconds_per_spp: float
    variance: float
    bias2: float
    mean_ratio: float
    #: the standard error of the bias estimate (:class:`Bias`); 0 for path, the reference
    bias_se: float = 0.0
    #: once building is over, the seconds the pilot and every prepass built have taken: spent
    #: whichever candidate renders, so the final choice counts them for every candidate
    #: instead of each one's own prepass (:func:`spend`); None while candidates are built
    sunk_seconds: float | None = None
    #: the pixel relMSE a cut prepass's own noise leaves (:class:`Frozen`, measured by two
    #: builds): an error of every pixel that no number of samples removes, as a bias's is. The
    #: bias estimate against path holds it too, so the larger of the two counts (a bias test
    #: that finds b² below the pilot's limit sets ``bias2`` to 0, not this)
    frozen: float = 0.0

    def predicted_error(self, spp: int) -> float:
        return self.variance / spp + max(self.bias2, self.frozen)

    def predicted_seconds(self, spp: int) -> float:
        spent = self.prepass_seconds if self.sunk_seconds is None else self.sunk_seconds
        return spent + spp * self.seconds_per_spp

    def score(self, spp: int) -> float:
        """Predicted relMSE × seconds of a render of ``spp`` samples per pixel."""
        return self.predicted_error(spp) * self.predicted_seconds(spp)


def spend(measured: dict, seconds: float) -> None:
    """Mark building as over: every candidate's predicted render time is ``seconds`` (the
    pilot and all prepasses, spent whichever renders) plus its own samples. A candidate is
    built on the promise that its prepass pays (its score with its own prepass); once it is
    built, that prepass is sunk, and scoring it again could throw away a structure already
    paid for (until session 9 twopass scored it so; in that session's bench at 256² no
    choice turned on it: where path won over a built structure, it won on variance or bias
    alone)."""
    for m in measured.values():
        m.sunk_seconds = seconds


def light_paths(integ, scene, sensor=None, seed: int = 0) -> tuple[int, int]:
    """``(least, need)``: the light paths a candidate's prepass traces. rex: the photons the
    image needs (:meth:`~mi_twopass.integrators.rex.RexIntegrator.photon_budget`, measured by a
    size pass and a probe shoot at the prepass ``seed``, which its builds then read), and as
    few as :func:`least_light_paths` where twopass cuts them to its budget
    (:func:`light_paths_within`); the others: their radiosity particles, not cut."""
    least = least_light_paths(integ)
    if hasattr(integ, "photon_budget"):
        return least, int(integ.photon_budget(scene, seed, sensor))
    return least, least


def least_light_paths(integ) -> int:
    """The fewest light paths a candidate's prepass can be built with: rex's floor of 2^16
    photons, or the radiosity particles (at least the radiosity prepass's floor). Cheap: nothing
    is traced (``none_fit`` decides on it before any pilot)."""
    from ..prepass.radiosity import MIN_PARTICLES
    from ..prepass.rex_textures import MIN_PHOTONS

    if hasattr(integ, "photon_budget"):
        return MIN_PHOTONS
    r = integ.radiosity
    return max(int(r.max_patches) * int(r.particles_per_patch), MIN_PARTICLES)


def light_paths_within(seconds: float, path: Measured, film_pixels: int) -> int:
    """The most light paths whose :func:`prepass_floor` is ``seconds`` (none below
    :data:`PREPASS_LEAST_SECONDS`)."""
    per_path = PREPASS_FLOOR_FACTOR * path.seconds_per_spp / max(film_pixels, 1)
    if per_path <= 0 or seconds < PREPASS_LEAST_SECONDS:
        return 0
    return int(seconds / per_path)


def prepass_floor(light_path_count: int, path: Measured, film_pixels: int) -> float:
    """The least a prepass tracing ``light_path_count`` light paths is predicted to cost:
    :data:`PREPASS_FLOOR_FACTOR` × that many path samples at the path pilot's cost, and at
    least :data:`PREPASS_LEAST_SECONDS`."""
    return max(PREPASS_LEAST_SECONDS, PREPASS_FLOOR_FACTOR * light_path_count
               * path.seconds_per_spp / max(film_pixels, 1))


def largest_budget(pilot_share: float) -> float:
    """The largest share of path's predicted render time any candidate may spend
    (:func:`prepass_budget`'s cap): what a prepass's floor must fit for a pilot to be worth
    starting."""
    return 0.0 if pilot_share <= 0.0 else max(BREAK_EVEN_MAX, pilot_share)


def none_fit(light_path_counts: dict, path_samples: int, budget_share: float):
    """Before any pilot: the budget is ``budget_share`` (:func:`largest_budget`) × the
    render's ``path_samples`` (film pixels × spp) path samples' time and a prepass's floor is
    :data:`PREPASS_FLOOR_FACTOR` path samples per light path (:func:`prepass_floor`), so
    whether a composition's floor fits does not depend on path's cost per sample. Returns
    {name: reason} when none fits (the render is path, with no pilot), else None."""
    limit = budget_share * path_samples / PREPASS_FLOOR_FACTOR
    if any(n < limit for n in light_path_counts.values()):
        return None
    return {name: (f"no pilot: its prepass traces {n} light paths, at least "
                   f"{PREPASS_FLOOR_FACTOR:g} path samples' time each, more than "
                   f"{budget_share:g} x the render's {path_samples} path samples")
            for name, n in light_path_counts.items()}


def pilot_too_dear(pilot_samples: int, path_samples: int, pilot_share: float = PILOT_BUDGET):
    """Before any pilot: a reason not to start it where its ``pilot_samples`` are more than
    :data:`PILOT_SHARE_MAX` × ``pilot_share`` / :data:`PILOT_BUDGET` of the render's
    ``path_samples``, else None."""
    share = PILOT_SHARE_MAX * pilot_share / PILOT_BUDGET
    if pilot_samples <= share * path_samples:
        return None
    return (f"no pilot: its {pilot_samples} samples per candidate would cost more than "
            f"{share:.3g} x the render's {path_samples} path samples")


@dataclass(frozen=True)
class RenderProbe:
    """``path``'s render time on this device, from one timed render of the whole film at one
    sample per pixel (:func:`mi_twopass.compose.pilot.probe_render`): ``per_spp``, its kernels'
    own execution time, grows with the samples; ``fixed``, the rest of the call (recording
    the loop, launching, developing the film, copying the image back), does not."""

    fixed: float
    per_spp: float

    def seconds(self, spp: int) -> float:
        """Predicted seconds of a render of ``spp`` samples per pixel."""
        return self.fixed + spp * self.per_spp


def probe_wanted(backend: str, setting: str = "auto") -> bool:
    """Whether ``twopass`` times ``path``'s render (:class:`RenderProbe`) before its pilot:
    ``setting`` "on" / "off", or "auto": on the CUDA backend only.

    On two CPU cores (LLVM) the pilot's samples and the prepasses' light paths cost about
    what path samples cost (:data:`PREPASS_FLOOR_FACTOR`, measured there), so the gates before
    the pilot read sample counts (:func:`pilot_too_dear`, :func:`none_fit`) and a probe would
    only add 1/spp of path's render to every twopass render (the office at 256²: 0.17 s, a
    sixth of twopass's time to relMSE 0.01). On a GPU they do not: an H200 rendered path
    19–61× faster than two CPU cores where the prepasses ran 1–2× faster and the pilot took
    0.2–0.35 s of host time for a 0.055 s render (docs/results/gpu-2026-11-27), and path's
    render there is mostly a fixed part (the office at 256²: 11.5 ms at 1 spp, 16.2 ms at 8)."""
    if setting != "auto":
        return setting == "on"
    return backend == "cuda"


def too_dear_in_seconds(probe: RenderProbe, spp: int, pilot_lanes: int, film_pixels: int,
                        pilot_calls: int, pilot_share: float = PILOT_BUDGET):
    """Before any pilot, from path's measured render time P = ``probe.seconds(spp)``: a reason
    to render path with no pilot, else None. The path pilot costs at least ``pilot_calls`` ×
    the render's fixed part plus its ``pilot_lanes`` samples at the render's cost per sample
    (pilot_lanes / film_pixels × per_spp). No pilot where that floor is more than
    :data:`PILOT_SHARE_MAX` × P (in proportion to ``pilot_share``, as :func:`pilot_too_dear`),
    nor where it and the least prepass, :data:`PREPASS_LEAST_SECONDS`, do not fit the largest
    budget a candidate may get (:func:`largest_budget`) × P, as :func:`none_fit` in samples."""
    render = probe.seconds(spp)
    floor = pilot_calls * probe.fixed + pilot_lanes / max(film_pixels, 1) * probe.per_spp
    share = PILOT_SHARE_MAX * pilot_share / PILOT_BUDGET
    if floor > share * render:
        return (f"no pilot: path's render is predicted to take {render:.3g} s (probe: "
                f"{probe.fixed:.3g} s + {spp} x {probe.per_spp:.3g} s), and the pilot at least "
                f"{floor:.3g} s, more than {share:.3g} x that")
    room = largest_budget(pilot_share) * render
    if floor + PREPASS_LEAST_SECONDS > room:
        return (f"no pilot: path's render is predicted to take {render:.3g} s (probe: "
                f"{probe.fixed:.3g} s + {spp} x {probe.per_spp:.3g} s); the pilot's "
                f"{floor:.3g} s and the least prepass, {PREPASS_LEAST_SECONDS:g} s, do not fit "
                f"the largest budget, {room:.3g} s")
    return None


def prepass_budget(best_case: float, path_score: float, pilot_share: float) -> float:
    """The share of path's predicted render time P = N·t_p that the pilot and the prepasses
    may have spent, a candidate's own included, when its prepass is started.

    A candidate of prepass T, cost t_c and variance v_c per sample scores below path at N
    samples per pixel only if (T + N·t_c)·v_c < N·t_p·v_p, i.e. T < P·(v_p/v_c − t_c/t_p)
    ≤ P·(g − 1), g = path's score over the candidate's best case (:func:`best_case_score`:
    t_c ≥ t_p and v_c at least the best case's). The share is :data:`BREAK_EVEN_SHARE` of
    that bound, at least ``pilot_share`` (``pilot_budget``, the share every candidate had
    until session 9) and at most :data:`BREAK_EVEN_MAX`, or ``pilot_share`` where that is
    larger (0 stays 0: path only). A candidate with little to gain gets no more than
    before; one whose best case is far ahead of path may spend up to P. Only the first
    candidate built gets it (:func:`mi_twopass.compose.choose.choose`): the best case of a
    composition that serves every part is near 0 whatever was measured before it."""
    if pilot_share <= 0.0:  # pilot_budget = 0: path only
        return 0.0
    gain = path_score / best_case if best_case > 0 else math.inf
    share = min(BREAK_EVEN_SHARE * (gain - 1.0), BREAK_EVEN_MAX)
    return max(share, pilot_share)


def later_budget(path_seconds: float, first_done: float, leader_seconds: float,
                 pilot_share: float) -> float:
    """The seconds the pilot and the prepasses may have spent when a candidate after the first
    structure measured is started: what had been spent when that one was measured, plus
    ``pilot_share`` of the predicted render time of the best-scoring candidate so far
    (``leader_seconds``), never more than ``pilot_share`` of path's (``path_seconds``, the
    budget every candidate had before session 18).

    Once a structure is measured, the render the user is waiting for is the leader's, not
    path's: a further prepass is an overhead on that. With path's budget, on window_interior
    at 256² and 256 spp twopass built spike lists with radiosity (0.87 s), then the radiance
    cache with spike lists (1.22 s) and radiosity_gather's solve (0.84 s), with a pilot each:
    3.6 s of a 8.2 s run (ad hoc, beside another job), to choose radiosity_gather's composition
    at a score 16 % below the first one's."""
    return min(pilot_share * path_seconds, first_done + pilot_share * leader_seconds)


def best_case_score(parts: VarianceParts, path: Measured, c: Composition, spp: int) -> float:
    """The score ``c`` could at best reach: no prepass, path's cost per sample, no bias, the
    variance of :meth:`VarianceParts.best_case`."""
    return parts.best_case(c) * path.seconds_per_spp  # (v/N)·(N·t)


@dataclass
class Bias:
    """A pilot pair's bias estimate (:func:`bias_squared`): ``b2`` the squared relative bias
    counted (0 unless it stands :data:`BIAS_SIGMAS` standard errors above 0), ``raw`` the
    estimate itself, ``se`` its standard error, ``ratio`` the ratio of the image means."""

    b2: float
    raw: float
    se: float
    ratio: float


def bias_squared(values: np.ndarray, path_values: np.ndarray) -> Bias:
    """The squared relative bias of a candidate's pilot against path's on the same pixels.

    b² is the relMSE floor the candidate's bias sets, per pixel as relMSE counts error:
    b² = mean over pixels p and channels of [(m̄_p − m̄'_p)² − s²_p/n − s'²_p/n'] / (R_p² + ε),
    m̄, s² the pilots' sample means and variances (of the second half of their samples) and
    R_p their pooled mean (of the first half); each pixel's term is an unbiased estimate of
    its squared bias over R² when the two pilots are independent (they are drawn with
    different seeds). The difference of the image means alone (this function until session
    6) misses a bias that changes sign over the image or sits in a few pixels: on the Cornell
    box at 128² twopass chose the radiance cache for 2048 spp and reached relMSE 1.2e-3 where
    path reached 2.3e-4 (bench, docs/results/bench-2026-11-25c). Counted only where it stands
    :data:`BIAS_SIGMAS` standard errors (of the pixel terms' mean) above 0. ``values``:
    (pixels, samples, 3)."""
    n_c, n_p = values.shape[1], path_values.shape[1]
    m_c, m_p = values.mean(axis=1), path_values.mean(axis=1)
    ratio = float(m_c.mean() / m_p.mean()) if m_p.mean() > 0 else 1.0
    if n_c < 4 or n_p < 4:
        return Bias(0.0, 0.0, float("inf"), ratio)
    # R_p from the first half of each pilot's samples, the difference from the second: a
    # difference and a denominator from the same samples are correlated (a pixel drawn high
    # has a larger difference and a larger R), which biased b² low
    h_c, h_p = n_c // 2, n_p // 2
    R = 0.5 * (values[:, :h_c].mean(axis=1) + path_values[:, :h_p].mean(axis=1))
    a, b = values[:, h_c:], path_values[:, h_p:]
    noise = a.var(axis=1, ddof=1) / a.shape[1] + b.var(axis=1, ddof=1) / b.shape[1]
    d2 = (a.mean(axis=1) - b.mean(axis=1)) ** 2
    terms = ((d2 - noise) / (R**2 + RELMSE_EPS)).mean(axis=1)  # per pixel
    raw = float(terms.mean())
    se = float(terms.std(ddof=1) / np.sqrt(terms.size)) if terms.size > 1 else float("inf")
    return Bias(raw if raw > BIAS_SIGMAS * se else 0.0, raw, se, ratio)


@dataclass
class Frozen:
    """What a prepass's own noise leaves in an image (:func:`frozen_error`): the relative
    variance of the block means (``block``, with its standard error) and of the pixels."""

    block: float
    block_se: float
    pixel: float

    def scaled(self, factor: float) -> "Frozen":
        """The noise predicted with ``factor`` times the light paths (:data:`FROZEN_DECAY`)."""
        k = factor ** FROZEN_DECAY
        return Frozen(self.block / k, self.block_se / k, self.pixel / k)


def frozen_error(a: np.ndarray, b: np.ndarray, block_pixels: int) -> Frozen:
    """The relative variance that a prepass's own noise (its photons) leaves in an image, from
    two builds with independent seeds sampled on the same pixels: ``a``, ``b`` of shape
    (pixels, samples, 3), the pixels listed block by block, ``block_pixels`` to a block
    (:func:`mi_twopass.compose.pilot.choose_blocks`).

    For a pixel (or a block mean) m_a, m_b of the two builds, E[(m_a − m_b)²] = 2σ² + s_a²/n_a +
    s_b²/n_b: σ² the frozen variance, shared by every sample of one build, and the samples'
    variance of the two means, which is subtracted (s² the sample variance; a block mean's is
    the mean of its pixels' over its pixel count). Divided by R² + ε, R the two builds' mean,
    and averaged over blocks (or pixels) and channels; each estimate may be below 0 by noise."""
    n = a.shape[1]
    per_block = a.shape[0] // block_pixels
    if per_block < 1 or n < 2:
        return Frozen(0.0, math.inf, 0.0)

    def relative(ma, mb, noise):
        R = 0.5 * (ma + mb)
        return (0.5 * ((ma - mb) ** 2 - noise) / (R**2 + RELMSE_EPS)).mean(axis=-1)

    va, vb = a.var(axis=1, ddof=1), b.var(axis=1, ddof=1)  # (pixels, 3)
    pixel = relative(a.mean(axis=1), b.mean(axis=1), (va + vb) / n)
    shape = (per_block, block_pixels, 3)
    k = per_block * block_pixels

    def block_mean(x):
        return x[:k].reshape(shape).mean(axis=1)

    block = relative(block_mean(a.mean(axis=1)), block_mean(b.mean(axis=1)),
                     block_mean(va + vb) / (n * block_pixels))
    se = float(block.std(ddof=1) / math.sqrt(block.size)) if block.size > 1 else math.inf
    return Frozen(float(block.mean()), se, float(pixel.mean()))


def affordable_photons(photons: int, build_seconds: float, room: float) -> int:
    """The photons ``room`` seconds pay for at a build's measured ``build_seconds`` per
    ``photons`` (its fixed part counted per photon too: an upper bound of the cost)."""
    return int(photons * max(room, 0.0) / build_seconds)


def twin_photons(photons: int, need: int, build_seconds: float, room: float) -> int:
    """The photons of a cut rex's second build (:func:`mi_twopass.compose.choose.fit_frozen`):
    up to :data:`FROZEN_TWIN_GROWTH` × ``photons`` or :func:`least_cut` where that is more,
    and the image's ``need``, as many as the ``room`` left in the candidate's budget pays for
    (:func:`affordable_photons`); at least ``photons`` (the twin then only measures the
    noise)."""
    if photons <= 0 or build_seconds <= 0:
        return int(photons)
    grown = max(FROZEN_TWIN_GROWTH * photons, least_cut(need))
    return int(max(photons, min(need, grown,
                                affordable_photons(photons, build_seconds, room))))


def frozen_of_larger(measured: Frozen, factor: float) -> Frozen:
    """The noise of the larger of two builds, ``factor`` times the other's light paths, from
    :func:`frozen_error` of the pair, which reads E[Δ²]/2 as if both were alike: with
    σ_large² = ρ·σ_small², ρ = factor^−:data:`FROZEN_DECAY`, E[Δ²] = (1 + ρ)·σ_small², so
    σ_large² = 2ρ / (1 + ρ) × the reading (1 for equal builds)."""
    rho = max(factor, 1.0) ** -FROZEN_DECAY
    k = 2.0 * rho / (1.0 + rho)
    return Frozen(measured.block * k, measured.block_se * k, measured.pixel * k)


def least_cut(need: int) -> int:
    """The fewest photons a rex twopass renders may have where the image needs ``need``:
    need / :data:`CUT_MAX`."""
    return int(math.ceil(need / CUT_MAX))


def least_probe(need: int) -> int:
    """The fewest photons of a cut rex's first build, the one the pilot measures: need /
    :data:`PROBE_CUT`."""
    return int(math.ceil(need / PROBE_CUT))


def measured_room(m: "Measured", path: "Measured", spp: int) -> float:
    """The seconds a candidate measured by the pilot may spend on its prepasses in all:
    :data:`BREAK_EVEN_SHARE` of its break-even prepass at ``spp`` samples per pixel, the T at
    which (T + N·t_c)·e_c = path's score, e_c = v_c/N + b² its predicted error
    (:meth:`Measured.predicted_error`); 0 where it does not beat path even with no prepass.

    :func:`prepass_budget` bounds a candidate's first build by its best case, which is an
    upper bound of the gain and loose for rexes (0 where the pilot reads the caustics as
    path's), so it is capped at path's render time; once the pilot has measured the build,
    the gain is known and a cut rex may be built again with the photons its blur and noise
    need (:func:`mi_twopass.compose.choose.fit_frozen`). On caustic.xml at 256², 64 spp,
    render seed 1, this room was 51 s, where the cap, path's predicted render, was 0.79 s
    (0.0123 s per spp)."""
    error = m.predicted_error(spp)
    if error <= 0:
        return math.inf
    return BREAK_EVEN_SHARE * max(path.score(spp) / error - spp * m.seconds_per_spp, 0.0)


def frozen_photons(photons: int, frozen: Frozen, need: int) -> int:
    """The photons a cut rex kept for the render needs: those that bring its measured
    ``frozen`` block noise at ``photons`` to :func:`frozen_limit`, as :data:`FROZEN_DECAY`
    predicts, and at least :func:`least_cut` (its blur); at most ``need``. ``photons`` where
    it is there already."""
    limit = frozen_limit()
    more = least_cut(need)
    if frozen.block > limit:
        more = max(more, math.ceil(photons * (frozen.block / limit) ** (1.0 / FROZEN_DECAY)))
    return int(max(photons, min(need, more)))


def frozen_limit() -> float:
    """The block relMSE a prepass's own noise may leave: :data:`FROZEN_SHARE` of check's
    bound."""
    return FROZEN_SHARE * BLOCK_RELMSE_MAX


def bias_slack(m: Measured, runner_up: float, spp: int) -> float:
    """The squared relative bias candidate ``m`` could carry and still score below the
    runner-up's score at ``spp``: runner_up / T(spp) − (v/spp + b²)."""
    return runner_up / m.predicted_seconds(spp) - m.predicted_error(spp)


def hidden_bias_may_decide(m: Measured, runner_up: float, spp: int) -> bool:
    """Whether a bias the pilot could not tell from 0 (up to :data:`BIAS_SIGMAS` standard
    errors of its estimate) could make candidate ``m`` lose to the runner-up's score at
    ``spp``: BIAS_SIGMAS·se > :func:`bias_slack`."""
    return BIAS_SIGMAS * m.bias_se > bias_slack(m, runner_up, spp)


def check_samples(have: int, m: Measured, runner_up: float, spp: int) -> int:
    """Samples per pixel (of each estimator) for the next bias test of ``m``, whose last test
    had ``have``: where its detection limit BIAS_SIGMAS·se, falling as 1/samples, is
    :data:`CHECK_MARGIN` below :func:`bias_slack`; within [2, :data:`CHECK_MAX_GROWTH`] ×
    ``have``."""
    slack = bias_slack(m, runner_up, spp)
    limit = BIAS_SIGMAS * m.bias_se
    growth = CHECK_MARGIN * limit / slack if slack > 0 else math.inf
    return int(math.ceil(have * min(max(growth, 2.0), CHECK_MAX_GROWTH)))


@dataclass
class Decision:
    """What ``twopass`` chose and why: the composition, every candidate's figures and every
    skipped one's reason (these go into ``integrator.stats``)."""

    chosen: Composition
    spp: int
    measured: dict = field(default_factory=dict)   # name -> Measured
    skipped: dict = field(default_factory=dict)    # name -> reason
    best_case: dict = field(default_factory=dict)  # name -> best-case score
    #: name -> (light paths built, light paths the image needs) where the budget cut them
    fitted: dict = field(default_factory=dict)
    #: name -> [(samples per pixel of each pilot, raw b², its standard error, outcome)]: the
    #: bias checks of a winner that may be biased (:func:`hidden_bias_may_decide`)
    bias_checks: dict = field(default_factory=dict)
    #: name -> [(light paths, Frozen)]: the noise of a cut prepass's own light paths, as
    #: measured and, where it was above :func:`frozen_limit`, as predicted for the light paths
    #: built in its place (:func:`frozen_error`)
    frozen: dict = field(default_factory=dict)
    #: path's render time as probed before the pilot (:class:`RenderProbe`); None: no probe
    probe: RenderProbe | None = None
    #: the share of the image's mean, at least, of light path cannot sample (delta emitters
    #: through specular surfaces, :mod:`mi_twopass.compose.unsampled`); 0.0 where none was
    #: found or no pilot ran
    unsampled: float = 0.0
    #: path's relative variance per sample on sharp light as the photons predict it and as
    #: the pilot measured it, where the photons were asked
    #: (:func:`mi_twopass.compose.choose.predict_caustics`); None where they were not
    caustic_prediction: dict | None = None

    def reason(self) -> str:
        if self.chosen.name not in self.measured:  # forced, or no prepass could fit
            why = self.skipped.get("pilot") or "the pilot would not pay (twopass_skipped)"
            return f"{self.chosen.name} at {self.spp} spp, no pilot: {why}"
        m = self.measured[self.chosen.name]
        others = [f"{n}: {self.measured[n].score(self.spp):.3g}" for n in self.measured
                  if n != self.chosen.name]
        text = (f"{self.chosen.name}: predicted relMSE x seconds {m.score(self.spp):.3g} at "
                f"{self.spp} spp (relMSE {m.predicted_error(self.spp):.3g} in "
                f"{m.predicted_seconds(self.spp):.3g} s)")
        if others:
            text += "; others " + ", ".join(others)
        return text
