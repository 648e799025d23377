"""``twopass``'s choice: the pilot, the structures that may pay, and the composition that wins.

The cost model and the table of compositions are in :mod:`mi_twopass.compose.cost`, the pilot
estimates in :mod:`mi_twopass.compose.pilot`; :func:`choose` runs them on one scene and camera
and is the whole of ``twopass``'s prepass (:mod:`mi_twopass.integrators.twopass`).
"""
from __future__ import annotations

import dataclasses
import math
import time
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np

from ..evaluation.metrics import BLOCK, BLOCK_RELMSE_MAX
from ..scene.lambertian import is_lambertian
from . import cost
from .unsampled import WARN_SHARE, unsampled_radiance
from .pilot import (CALLS, PilotSettings, choose_blocks, choose_pixels, join_samples,
                    path_reference, pilot, pilot_samples, pixel_count, pixel_means, probe_render,
                    relative_variance, run_samples, samples_array)


class Choice:
    """What a ``twopass`` prepass leaves for the render: the decision and the chosen
    integrator (its structure built). A plain class: Dr.Jit would traverse a dataclass."""

    def __init__(self, decision, integrator, seconds):
        self.decision = decision
        self.integrator = integrator
        #: {"pilot": s, "prepasses": s}: where the twopass prepass spent its time
        self.seconds = seconds


#: seed offset of the candidates' pilots (path's use seed, seed + 1, seed + 2), of the bias
#: checks' further samples, of a cut prepass's twin and of the samples that compare the two
_CANDIDATE_SEEDS = 16
_CHECK_SEEDS = 64
_TWIN_SEED = 0x7717
_FROZEN_SEEDS = 96
#: seed offset of the render that times path before the pilot (:func:`probe_render`)
_PROBE_SEED = 128


def candidate_estimator(integ):
    """A candidate integrator's ``sample`` as a pilot estimator (its radiance alone)."""
    return lambda scene, sampler, ray, active: integ.sample(scene, sampler, ray, None, active)[0]


def check_bias(scene, sensor, pixels, seed, spp, runs, path_run, path_integ, decision,
               budget: float) -> str:
    """The name of the winner once no bias hidden in its pilot's noise can change the choice,
    as far as the budget can tell.

    While the best-scoring composition may be biased (:attr:`cost.Composition.biased`) and a
    bias below its pilot's detection limit could make it lose to the runner-up
    (:func:`cost.hidden_bias_may_decide`), both it and path are sampled further on the same
    pixels, to the samples per pixel :func:`cost.check_samples` asks for or as many as the
    tests' ``budget`` (seconds, all tests together) still pays for, and its bias is estimated
    again from all samples; it counts beyond :data:`cost.CHECK_SIGMAS` standard errors (the
    pilot's beyond :data:`cost.BIAS_SIGMAS`). The choice is then made again. A candidate is
    accepted on its estimate once :data:`cost.CHECK_ROUNDS` tests are done or the budget does
    not double its samples.
    Each test is recorded in ``decision.bias_checks``."""
    measured = decision.measured
    more = {name: [] for name in runs}  # name -> further sample arrays (pixels, n, 3)
    path_more = []
    estimate_path = path_sum_estimator(path_integ)
    settled = set()
    n_runs = 0
    t_start = time.perf_counter()
    while True:
        name = min(measured, key=lambda n: measured[n].score(spp))
        c, integ, run = runs[name]
        m = measured[name]
        runner_up = min((measured[n].score(spp) for n in measured if n != name),
                        default=math.inf)
        if name in settled or not c.biased or not cost.hidden_bias_may_decide(m, runner_up, spp):
            return name
        checks = decision.bias_checks.setdefault(name, [])
        have = run.values.shape[1] + sum(v.shape[1] for v in more[name])
        have_path = path_run.values.shape[1] + sum(v.shape[1] for v in path_more)
        per_sample = len(pixels.index) * (run.seconds_per_lane + path_run.seconds_per_lane)
        time_left = budget - (time.perf_counter() - t_start)
        affordable = have + int(max(time_left, 0.0) / per_sample)
        total = min(cost.check_samples(have, m, runner_up, spp), affordable)
        if len(checks) >= cost.CHECK_ROUNDS or total < 2 * have:
            why = "tests done" if len(checks) >= cost.CHECK_ROUNDS else "no budget for more"
            checks.append((have, None, m.bias_se,
                           f"accepted ({why}): a bias below {cost.BIAS_SIGMAS * m.bias_se:.3g} "
                           "cannot be told from noise"))
            settled.add(name)
            continue
        if total > have_path:
            path_more.append(run_samples(scene, sensor, pixels, total - have_path,
                                         estimate_path, seed + _CHECK_SEEDS + n_runs)[0])
            n_runs += 1
        more[name].append(run_samples(scene, sensor, pixels, total - have,
                                      candidate_estimator(integ),
                                      seed + _CHECK_SEEDS + n_runs)[0])
        n_runs += 1
        bias = cost.bias_squared(join_samples([run.values, *more[name]]),
                                 join_samples([path_run.values, *path_more]))
        found = bias.raw > cost.CHECK_SIGMAS * bias.se
        m.bias2, m.bias_se = (bias.raw if found else 0.0), bias.se
        checks.append((total, bias.raw, bias.se, "counted" if found else "below the limit"))


def fit_frozen(scene, sensor, c, integ, candidate, seed: int, decision, room: float,
               path_m, film_pixels: int, build_seconds: float = 0.0):
    """A candidate whose rexes twopass cut to fewer photons than the image needs
    (``decision.fitted``), checked for the noise of its own photons, which no number of
    samples per pixel removes and the path pilot, as noisy as path is where rexes pay, cannot
    resolve: a twin is built with another seed and both are sampled on the same blocks
    (:func:`cost.frozen_error`).

    The twin gets more photons where the ``room`` left in the candidate's budget pays for
    them at the first build's measured ``build_seconds`` (:func:`cost.twin_photons`: up to
    :data:`cost.FROZEN_TWIN_GROWTH` × or :func:`cost.least_cut`); it is then the build kept,
    its noise read from the pair (:func:`cost.frozen_of_larger`). Where the kept build has
    fewer photons than :func:`cost.least_cut` (their buckets blur the image beyond check's
    bound, :data:`cost.CUT_MAX`) or the block relMSE its noise leaves is above
    :func:`cost.frozen_limit`, the candidate is built again with the photons that do
    (:func:`cost.frozen_photons`) if the seconds left pay for them at the first build's rate
    (:func:`cost.affordable_photons`; :func:`cost.light_paths_within` where no build was
    timed). Where they do not, a build below the least cut is left out, and one at or above it
    is kept while its noise is within check's bound
    (:data:`~mi_twopass.evaluation.metrics.BLOCK_RELMSE_MAX`), the noise counted in its
    score. Until session 33 it was dropped there, and path rendered: on caustic.xml at 256²,
    render seed 1, twopass rendered path at 64 and 128 spp, relMSE 0.49 and 0.28 against a
    16384-spp reference, where the rexes it had built (noise read at 1.7-2.0e-3, the limit
    1.5e-3) reach 0.026 and 0.014 (docs/results/revalidate-2026-11-29-s33); those rexes had
    1/8-1/16 of the need and blurred the caustic to a bias part of 4.0-6.3e-3, which the
    twin, as blurred as they, did not see (docs/results/cut-blur-2026-11-29).

    Returns (integrator, Frozen as predicted for it, seconds the twin and any rebuild took),
    or (None, reason, seconds) where the photons that would do are not affordable and the
    blur or the noise is beyond the bound. Each measurement or prediction is recorded in
    ``decision.frozen``."""
    photons, need = decision.fitted[c.name]
    first = photons  # the photons build_seconds paid for
    t0 = time.perf_counter()
    more = cost.twin_photons(photons, need, build_seconds, room)
    if more > photons:  # kept: its own seed offset, so the render's seed finds it built
        twin = candidate(c, photons=more, seed_offset=_TWIN_SEED)
        twin.ensure_prepass(scene, seed, sensor)
    else:
        twin = candidate(c, photons=photons, twin=True)
        twin.ensure_prepass(scene, seed + _TWIN_SEED, sensor)
    blocks = choose_blocks(sensor, cost.FROZEN_BLOCKS, BLOCK, seed)
    a, _ = run_samples(scene, sensor, blocks, cost.FROZEN_SAMPLES, candidate_estimator(integ),
                       seed + _FROZEN_SEEDS)
    b, _ = run_samples(scene, sensor, blocks, cost.FROZEN_SAMPLES, candidate_estimator(twin),
                       seed + _FROZEN_SEEDS + 1)
    frozen = cost.frozen_error(a, b, min(BLOCK * BLOCK, len(blocks.index)))
    history = decision.frozen.setdefault(c.name, [])
    history.append((photons, frozen))
    if more > photons:
        integ, frozen = twin, cost.frozen_of_larger(frozen, more / photons)
        photons = more
        decision.fitted[c.name] = (photons, need)
        history.append((photons, frozen))
    del twin
    limit = cost.frozen_limit()
    want = cost.frozen_photons(photons, frozen, need)
    if want == photons:
        return integ, frozen, time.perf_counter() - t0
    room -= time.perf_counter() - t0
    affordable = (cost.affordable_photons(first, build_seconds, room)
                  if build_seconds > 0 else cost.light_paths_within(room, path_m, film_pixels))
    if want > affordable:
        if photons < cost.least_cut(need):
            return None, (f"its rexes at {photons} photons are cut more than "
                          f"{cost.CUT_MAX:g}-fold below the image's {need} (their buckets "
                          f"blur it); the {want} photons that would do do not fit the "
                          f"{max(room, 0.0):.3g} s left of its budget"), \
                time.perf_counter() - t0
        if frozen.block <= BLOCK_RELMSE_MAX:  # within check's bound: kept, counted
            return integ, frozen, time.perf_counter() - t0
        return None, (f"its rexes' own noise at {photons} photons leaves a block relMSE of "
                      f"{frozen.block:.3g} (> {limit:.3g}); the {want} photons that would bring "
                      f"it there do not fit the {max(room, 0.0):.3g} s left of its budget"), \
            time.perf_counter() - t0
    integ = candidate(c, photons=want)
    integ.ensure_prepass(scene, seed, sensor)
    decision.fitted[c.name] = (want, need)
    predicted = frozen.scaled(want / photons)
    history.append((want, predicted))
    return integ, predicted, time.perf_counter() - t0


def _over_budget(spent: float, floor: float, budget: float, basis: str) -> str:
    """Why a candidate's prepass is not started: what was spent and its floor pass its budget
    (``basis``: what the budget is)."""
    return (f"budget: {spent:.3g} s spent + a prepass of at least {floor:.3g} s > {budget:.3g} s "
            f"({basis})")


def path_sum_estimator(path_integ, parts_out=None):
    """The path pilot's estimator: the sum of the component path tracer's parts; each call's
    ``(direct, caustic, indirect)`` appended to ``parts_out`` where one is given."""
    def estimate(scene, sampler, ray, active):
        direct, caustic, indirect, _ = path_integ.sample_components(scene, sampler, ray, active)
        if parts_out is not None:
            parts_out.append((direct, caustic, indirect))
        return direct + caustic + indirect
    return estimate


def path_pilot(scene, sensor, pixels, settings: PilotSettings, path_integ, seed: int):
    """path's pilot (:func:`~mi_twopass.compose.pilot.pilot` of :func:`path_sum_estimator`)
    and its samples split into parts: ``(PilotRun, [direct, caustic, indirect])``, each part
    an array (pixels, samples, 3) that sums to the run's values."""
    parts_out = []
    run = pilot(scene, sensor, pixels, settings, path_sum_estimator(path_integ, parts_out), seed)
    return run, [samples_array(parts_out[0][k], pixels, settings.samples) for k in range(3)]


def traits(scene, max_depth) -> cost.SceneTraits:
    """What :func:`cost.structural_reason` reads of ``scene``: emitter count, whether any
    surface is Lambertian, the depth bound; and whether any is specular (delta), which
    :func:`predict_caustics` reads."""
    lambertian = any(s.bsdf() is not None and is_lambertian(s.bsdf())
                     for s in scene.shapes())
    specular = any(s.bsdf() is not None and mi.has_flag(s.bsdf().flags(), mi.BSDFFlags.Delta)
                   for s in scene.shapes())
    return cost.SceneTraits(emitters=len(scene.emitters()), lambertian=lambertian,
                            max_depth=max_depth, specular=specular)


def predict_caustics(scene, sensor, variance: cost.VarianceParts, allowed, candidate,
                     scene_traits: cost.SceneTraits, decision: cost.Decision, seed: int = 0):
    """path's caustic variance as the larger of what its pilot measured and what rex's probe
    photons predict (:mod:`mi_twopass.prepass.sharp_light`): ``(variance parts, the variance
    added to path's total)``.

    Light through delta bounces comes to path as rare bright samples that a pilot of a few
    hundred catches now and then (veach-bidir at 256²: 0.0-1.4 % of path's pilot variance
    over three seeds, where rex renders 48× better than path at equal time); photons find it
    every time. Asked only where the pilot's caustic part is below :data:`cost.CAUSTIC_SHARE`
    (else rexes are tried anyway), a rex row is allowed and not ruled out by the scene's
    structure, and some surface is specular (without one no light is sharp). The
    measurement is the size pass and probe shoot rex's photon budget reads anyway
    (remembered by the candidate, :meth:`~mi_twopass.integrators.rex.RexIntegrator.
    sharp_light`, at the prepass ``seed`` its builds read it at); a scene rex refuses (media)
    has its rex rows skipped here."""
    rows = [c for c in allowed if c.caustics == "rex"
            and cost.structural_reason(c, scene_traits) is None]
    if not rows or not scene_traits.specular or \
            variance.caustic >= cost.CAUSTIC_SHARE * variance.total:
        return variance, 0.0
    try:
        sharp = candidate(rows[0]).sharp_light(scene, seed, sensor)
    except (ValueError, NotImplementedError) as err:  # refused: media, ...
        for c in rows:
            decision.skipped[c.name] = f"refused: {err}"
        return variance, 0.0
    decision.caustic_prediction = {"predicted": sharp.relative_variance,
                                   "pilot": variance.caustic, "sharp_share": sharp.share}
    raised = variance.with_caustic(sharp.relative_variance)
    return raised, raised.total - variance.total


def unsampled_share(scene, sensor, seed: int, path_values) -> float:
    """The share of the image's mean, at least, that no composition but rexes renders (nor
    path): :func:`~mi_twopass.compose.unsampled.unsampled_radiance` over itself plus the path
    pilot's mean (``path_values``: its samples, which lack that light)."""
    missing = unsampled_radiance(scene, sensor, seed)
    if missing <= 0.0:
        return 0.0
    return missing / (missing + max(float(np.mean(path_values)), 0.0))


def _no_pilot(prepassed, reason: str) -> dict:
    """{name: why} for every composition with a prepass, where a gate before the pilot said
    ``reason`` (rexes, which no gate counts where another prepass could be built, say so)."""
    return {c.name: reason for c in prepassed}


def sample_gates(spp: int, pixels, allowed, candidate, settings: PilotSettings,
                 budget_factor: float):
    """The gates before any pilot that count samples, not seconds (path's cost per sample is
    not known yet): ``{name: why}`` for every composition with a prepass where the render is
    path with no pilot, else None. No pilot where its samples would cost too large a share of
    the render's (:func:`cost.pilot_too_dear`: all that is lost where nothing pays), nor where
    no prepass can fit the largest budget a candidate may get (:func:`cost.none_fit`). Rexes,
    which can be cut to 2^16 photons, count only where nothing else could be built: alone they
    would start a pilot at 32 spp of a 128² film, where its 147,456 samples cost more than any
    rexes that small could save (the office's and window_interior's twopass fell to 0.93x and
    0.84x path at 128²). Cheap: nothing is traced, so ``twopass`` asks before it computes its
    prepass key."""
    prepassed = [c for c in allowed if c.needs_prepass]
    others = [c for c in prepassed if c.plugin != "rex"]
    path_samples = spp * pixels.film_pixels
    dear = cost.pilot_too_dear(pilot_samples(settings, pixels), path_samples, budget_factor)
    if dear is not None:
        return _no_pilot(prepassed, dear)
    too_big = cost.none_fit(
        {c.name: cost.least_light_paths(candidate(c)) for c in others or prepassed},
        path_samples, cost.largest_budget(budget_factor))
    if too_big is not None and others:
        for c in prepassed:
            too_big.setdefault(c.name, "no pilot: rexes cut to the budget do not start a "
                                       "pilot where no other prepass fits")
    return too_big


def path_without_pilot(sensor, seed: int, spp: int, allowed, candidate,
                       settings: PilotSettings, budget_factor: float):
    """The :class:`Choice` of path with no pilot where :func:`sample_gates` says so (path
    allowed, and some other composition too), else None. Traces nothing."""
    path_row = cost.COMPOSITIONS[0]
    if path_row not in allowed or len(allowed) < 2:
        return None
    pixels = choose_pixels(sensor, settings.pixels, seed)
    too_big = sample_gates(spp, pixels, allowed, candidate, settings, budget_factor)
    if too_big is None:
        return None
    decision = cost.Decision(chosen=path_row, spp=spp, skipped=too_big)
    return Choice(decision, candidate(path_row), {"pilot": 0.0, "prepasses": 0.0})


def probe_gate(scene, sensor, seed: int, spp: int, allowed, candidate,
               settings: PilotSettings, budget_factor: float, probe: str = "auto"):
    """Where the sample gates leave the pilot open and path's render is probed
    (:func:`cost.probe_wanted`): ``(Choice of path with no pilot, or None, the probe)`` from
    the gates in the probe's seconds (:func:`cost.too_dear_in_seconds`); ``(None, None)``
    where no probe is wanted. ``twopass`` asks before its prepass key (and hands the probe to
    :func:`choose`, which then does not probe again)."""
    path_row = cost.COMPOSITIONS[0]
    if path_row not in allowed or len(allowed) < 2 or not cost.probe_wanted(backend_name(),
                                                                             probe):
        return None, None
    pixels = choose_pixels(sensor, settings.pixels, seed)
    path_integ = candidate(path_row)
    probed = probe_render(scene, sensor, path_integ, seed + _PROBE_SEED)
    dear = cost.too_dear_in_seconds(probed, spp, pilot_samples(settings, pixels),
                                    pixels.film_pixels, CALLS, budget_factor)
    if dear is None:
        return None, probed
    decision = cost.Decision(chosen=path_row, spp=spp,
                             skipped=_no_pilot([c for c in allowed if c.needs_prepass], dear),
                             probe=probed)
    return Choice(decision, path_integ, {"pilot": 0.0, "prepasses": 0.0}), probed


def backend_name() -> str:
    """"cuda" or "llvm": the JIT backend of the variant set."""
    return "cuda" if dr.backend_v(mi.Float) == dr.JitBackend.CUDA else "llvm"


def choose(scene, sensor, seed: int, render_spp: int, allowed, candidate,
           settings: PilotSettings, budget_factor: float, max_depth: int,
           probe: str = "auto", probed=None) -> Choice:
    """``twopass``'s prepass: the pilot, then the structures that may pay, and the composition
    with the lowest predicted relMSE × seconds (:mod:`mi_twopass.compose.cost`).

    ``allowed``: the rows of :data:`cost.COMPOSITIONS` the XML leaves open; ``candidate(c,
    photons=0)``: the integrator of row ``c`` (kept by the caller so that prepasses are reused;
    ``photons`` > 0: rexes cut to that many photons); ``render_spp``: the samples per pixel the
    image will get (0: the sensor's); ``budget_factor``: the pilot and prepasses may cost that
    many times path's predicted render time. Order of work:

    1. nothing to measure when one row is allowed: build it;
    2. no pilot where it would cost more than :data:`cost.PILOT_SHARE_MAX` of the render
       (:func:`cost.pilot_too_dear`) or no prepass can fit the largest budget a candidate may
       get (:func:`cost.none_fit`, :func:`cost.largest_budget`); where path's render is
       probed first (``probe``: :func:`cost.probe_wanted`), the same two gates in its
       measured seconds (:func:`cost.too_dear_in_seconds`, :func:`probe_gate`; ``probed``:
       a probe already made), whose render time then sets the budgets;
    3. the pilot path trace, split into direct, caustic and indirect variance; the caustic
       part raised to what rex's probe photons predict where the pilot may have missed it
       (:func:`predict_caustics`);
    4. per row, cheapest best case first: skipped for a structural reason, a best case that
       cannot beat the best measured score by ``cost.MIN_GAIN``, or the budget (rexes cut to
       the photons the budget pays for first, down to :func:`cost.least_probe`); else built
       and piloted on the same pixels; a cut rex is then built again (:func:`fit_frozen`),
       within the larger of its budget and what its measured score pays for
       (:func:`cost.measured_room`), with the photons its blur and its own noise need, or
       left out;
    5. variances again against the pilots' pooled pixel means (path's against the other
       pilots' means: :func:`~mi_twopass.compose.pilot.path_reference`); the lowest score,
       with the pilot and the prepasses built counted as spent for every candidate
       (:func:`cost.spend`), wins, once a winner that may be biased has passed the bias test
       of :func:`check_bias`."""
    spp = max(int(render_spp or sensor.sampler().sample_count()), 1)
    t_start = time.perf_counter()
    build_seconds = 0.0
    if len(allowed) == 1:  # everything forced: nothing to measure
        c = allowed[0]
        integ = candidate(c)
        if c.needs_prepass:
            _, build_seconds = integ.ensure_prepass(scene, seed, sensor)
        decision = cost.Decision(chosen=c, spp=spp)
        decision.skipped = {"pilot": "every choice forced from XML"}
        return Choice(decision, integ, {"pilot": 0.0, "prepasses": build_seconds})

    early = path_without_pilot(sensor, seed, spp, allowed, candidate, settings, budget_factor)
    if early is None and probed is None:
        early, probed = probe_gate(scene, sensor, seed, spp, allowed, candidate, settings,
                                   budget_factor, probe)
    if early is not None:
        early.seconds["pilot"] = time.perf_counter() - t_start
        return early
    width, height = (int(v) for v in sensor.film().crop_size())
    pixels = choose_pixels(sensor, pixel_count(settings, spp, width * height), seed)
    film_pixels = pixels.film_pixels
    path_row = cost.COMPOSITIONS[0]
    path_integ = candidate(path_row)
    path_run, parts = path_pilot(scene, sensor, pixels, settings, path_integ, seed)
    ref = pixel_means(path_run.values)
    variance = cost.VarianceParts(
        total=relative_variance(path_run.values, ref),
        direct=relative_variance(parts[0], ref), caustic=relative_variance(parts[1], ref),
        indirect=relative_variance(parts[2], ref))
    runs = {}
    measured = {}
    decision = cost.Decision(chosen=path_row, spp=spp, probe=probed)
    scene_traits = traits(scene, max_depth)
    variance, unseen = predict_caustics(scene, sensor, variance, allowed, candidate,
                                        scene_traits, decision, seed)
    path_m = cost.Measured(prepass_seconds=0.0,  # bias 0 exactly: path is the reference
                           seconds_per_spp=path_run.seconds_per_spp(film_pixels),
                           variance=variance.total, bias2=0.0, mean_ratio=1.0)
    if path_row in allowed:
        measured[path_row.name] = path_m
        runs[path_row.name] = (path_row, path_integ, path_run)

    others = [c for c in allowed if c.needs_prepass and c.name not in decision.skipped]
    for c in others:
        decision.best_case[c.name] = cost.best_case_score(variance, path_m, c, spp)
    best = min((m.score(spp) for m in measured.values()), default=float("inf"))
    # the render as probed where it was (fixed part included), else as the pilot predicts it
    path_seconds = probed.seconds(spp) if probed is not None else spp * path_m.seconds_per_spp
    first_done = None  # seconds spent when the first structure was measured
    for c in sorted(others, key=lambda c: decision.best_case[c.name]):
        # the break-even budget for the first structure only: once one is measured, the
        # others' best cases (near 0 for a composition that serves every part) promise
        # nothing the measured one has not (with it for every candidate, many_lights at
        # 256², 64 spp, built the radiance cache beside the spike lists it then rendered)
        first = first_done is None
        share = (cost.prepass_budget(decision.best_case[c.name], path_m.score(spp),
                                     budget_factor) if first else budget_factor)
        budget = share * path_seconds
        basis = f"{share:.3g} x path's predicted {path_seconds:.3g} s"
        if not first:
            leader = min(measured.values(), key=lambda m: m.score(spp))
            leader_seconds = path_seconds if leader is path_m else \
                spp * leader.seconds_per_spp
            later = cost.later_budget(path_seconds, first_done, leader_seconds, budget_factor)
            if later < budget:
                budget = later
                basis = (f"{first_done:.3g} s when the first structure was measured + "
                         f"{budget_factor:.3g} x the best one's predicted render "
                         f"{leader_seconds:.3g} s")
        why = cost.structural_reason(c, scene_traits)
        if why is None and c.caustics == "rex" and \
                variance.caustic < cost.CAUSTIC_SHARE * variance.total:
            why = (f"caustics carry {variance.caustic / max(variance.total, 1e-30):.1%} "
                   f"of path's variance (< {cost.CAUSTIC_SHARE:.0%})")
        if why is None and decision.best_case[c.name] * cost.MIN_GAIN >= best:
            why = (f"best case {decision.best_case[c.name]:.3g} (relMSE x s) cannot beat "
                   f"{best:.3g} by {cost.MIN_GAIN}x")
        if why is not None:  # before light_paths: rex's photon need is a size pass and a
            decision.skipped[c.name] = why  # probe shoot (1.3 s on many_lights at 256²)
            continue
        spent = time.perf_counter() - t_start
        if measured and spent + cost.PREPASS_LEAST_SECONDS > budget:
            # no prepass fits: said before rex's photon need is measured (a size pass and a
            # probe shoot), as the floor below would say after it
            decision.skipped[c.name] = _over_budget(spent, cost.PREPASS_LEAST_SECONDS, budget,
                                                    basis)
            continue
        integ = candidate(c)
        try:  # rex's photon need: a size pass and a probe shoot
            least, need = cost.light_paths(integ, scene, sensor, seed)
        except (ValueError, NotImplementedError) as err:  # refused: media, ...
            decision.skipped[c.name] = f"refused: {err}"
            continue
        least = max(least, cost.least_probe(need))
        floor = cost.prepass_floor(need, path_m, film_pixels)
        pilot_room = budget_factor * path_seconds - spent
        if measured and least < need and floor > pilot_room:
            # rexes coarser than the image asks for: the photons pilot_budget pays for, at
            # least rex's floor where the candidate's own budget pays for that. Not the
            # photons of the whole break-even budget: they trade bias for time in a way the
            # floor does not predict (tut-cbox at 256²: the 4.1 M photons the image needs took
            # 5.8 s at 128 spp, 2.7x their floor; 64 spp with 2.0 M: 2.85 s for half the
            # error of 0.41 M in 0.92 s)
            fits = cost.light_paths_within(pilot_room, path_m, film_pixels)
            if cost.light_paths_within(budget - spent, path_m, film_pixels) >= least:
                fits = max(fits, least)
            if fits >= least:
                integ = candidate(c, photons=fits)
                decision.fitted[c.name] = (fits, need)
                floor = cost.prepass_floor(fits, path_m, film_pixels)
        if spent + floor > budget and measured:
            decision.skipped[c.name] = _over_budget(spent, floor, budget, basis)
            if least < need and c.name not in decision.fitted:
                decision.skipped[c.name] += (
                    f"; cut to the fewest photons allowed, {least} (1/{cost.PROBE_CUT} of the "
                    f"image's {need}), at least "
                    f"{cost.prepass_floor(least, path_m, film_pixels):.3g} s")
            continue
        try:
            _, seconds = integ.ensure_prepass(scene, seed, sensor)
        except (ValueError, NotImplementedError) as err:  # refused: media, ...
            decision.skipped[c.name] = f"refused: {err}"
            continue
        build_seconds += seconds
        # seeds apart from path's: the bias test takes the two pilots to be independent
        run = pilot(scene, sensor, pixels, settings, candidate_estimator(integ), seed + _CANDIDATE_SEEDS)
        bias = cost.bias_squared(run.values, path_run.values)
        m = cost.Measured(
            prepass_seconds=seconds,
            seconds_per_spp=run.seconds_per_spp(film_pixels),
            variance=relative_variance(run.values, ref), bias2=bias.b2,
            mean_ratio=bias.ratio, bias_se=bias.se)
        if c.name in decision.fitted:
            # measured now, its room is at least what its own score pays for
            # (cost.measured_room), as its best case could not bound it. path's variance there
            # is read as the final choice reads it: against this pilot's means (path
            # normalises its own rare caustic samples away), plus what its pilot missed. The
            # pilot's figures stay the first build's, its bias an upper bound for a rebuild
            # with more photons
            path_now = dataclasses.replace(path_m, variance=unseen + relative_variance(
                path_run.values, path_reference(path_run.values, [run.values])))
            room = max(budget - (time.perf_counter() - t_start),
                       cost.measured_room(m, path_now, spp) - seconds)
            integ, frozen, more = fit_frozen(scene, sensor, c, integ, candidate, seed, decision,
                                             room, path_m, film_pixels, seconds)
            build_seconds += more
            if integ is None:
                decision.skipped[c.name] = frozen
                continue
            m.prepass_seconds += more
            m.frozen = max(frozen.pixel, 0.0)
        measured[c.name] = m
        runs[c.name] = (c, integ, run)
        best = min(best, measured[c.name].score(spp))
        if first_done is None:
            first_done = time.perf_counter() - t_start

    if not measured:  # nothing allowed could be built: say why
        raise ValueError("twopass: no composition allowed by the forced choices can be "
                         "built here: " + "; ".join(f"{k}: {v}" for k, v in
                                                   decision.skipped.items()))
    # the variances again against every pilot's pixel means (less noise in R)
    pooled = np.mean([pixel_means(r[2].values) for r in runs.values()], axis=0)
    for name, (_, _, run) in runs.items():
        ref = pooled if name != path_row.name else path_reference(
            run.values, [r[2].values for n, r in runs.items() if n != name])
        # path's: plus the caustic variance its pilot missed, as predicted against its own
        # means (a pooled reference that already shows some of it counts it twice: an
        # overestimate of path's variance where rexes were measured anyway)
        measured[name].variance = relative_variance(run.values, ref) + \
            (unseen if name == path_row.name else 0.0)
    decision.measured = measured
    cost.spend(measured, time.perf_counter() - t_start)
    name = check_bias(scene, sensor, pixels, seed, spp, runs, path_run, path_integ, decision,
                      cost.CHECK_BUDGET * path_seconds)
    decision.chosen = runs[name][0]
    decision.unsampled = unsampled_share(scene, sensor, seed, path_run.values)
    if decision.unsampled >= WARN_SHARE and decision.chosen.caustics != "rex":
        warnings.warn(
            f"twopass: at least {decision.unsampled:.1%} of this image is light that delta "
            "emitters send through specular surfaces onto diffuse ones, which path (and so the "
            f"composition chosen, {decision.chosen.name}) cannot sample: set caustics=\"rex\" "
            "to render it (mi_twopass.compose.unsampled)", stacklevel=2)
    pilot_seconds = time.perf_counter() - t_start - build_seconds
    return Choice(decision, runs[name][1], {"pilot": pilot_seconds,
                                             "prepasses": build_seconds})


__all__ = ["Choice", "backend_name", "candidate_estimator", "check_bias", "choose", "fit_frozen",
           "path_pilot", "path_sum_estimator", "path_without_pilot", "predict_caustics",
           "probe_gate", "sample_gates", "traits", "unsampled_share"]
