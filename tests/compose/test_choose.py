"""mi_twopass.compose.choose: a prepass that refuses the scene leaves its rows out with the reason
(and the others compete); nothing allowed that can be built is a clear error; one allowed row is
built without a pilot."""
import os
import sys

import mitsuba as mi
import numpy as np
import pytest

import mi_twopass  # noqa: F401
from mi_twopass.compose import cost
from mi_twopass.compose.choose import (candidate_estimator, check_bias, choose,
                                       path_sum_estimator, predict_caustics, traits)
from mi_twopass.compose.pilot import PilotSettings, choose_pixels, pilot
from mi_twopass.evaluation.metrics import BLOCK_RELMSE_MAX

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import hard_scenes as hs  # noqa: E402

#: samples per pixel so many, with a budget so large, that no row is left out for its cost
SPP, BUDGET = 1 << 16, 1e6


def box_in_fog():
    """The lit box seen through a homogeneous medium on the camera: the radiance cache refuses
    it (it transports light between surfaces only), path tracing does not."""
    d = hs.box()
    d["sensor"]["medium"] = {"type": "homogeneous", "sigma_t": 0.05,
                             "albedo": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}
    return mi.load_dict(d)


def chooser(**forced):
    return mi.load_dict({"type": "twopass", **forced})


def run_choose(scene, tp, allowed):
    return choose(scene, scene.sensors()[0], 0, SPP, allowed, tp.candidate,
                  PilotSettings(pixels=64), BUDGET, tp.max_depth)


def test_a_refused_prepass_is_skipped_with_its_reason_and_path_still_wins():
    scene = box_in_fog()
    tp = chooser()
    allowed = [c for c in cost.COMPOSITIONS
               if c.plugin == "path" or c.plugin == "radiance_cache"]
    choice = run_choose(scene, tp, allowed)
    # one emitter: the spike-list row is left out for that before it is built
    plain = next(c.name for c in allowed if c.plugin == "radiance_cache" and c.direct == "emitter")
    assert choice.decision.skipped[plain].startswith("refused: radiance_cache: the scene has a "
                                                     "participating medium")
    assert all(c.name in choice.decision.skipped for c in allowed if c.plugin != "path")
    assert choice.decision.chosen == cost.COMPOSITIONS[0]
    assert set(choice.decision.measured) == {cost.COMPOSITIONS[0].name}


def test_nothing_buildable_among_the_allowed_rows_is_an_error_naming_why():
    scene = box_in_fog()
    tp = chooser(indirect="cache")
    assert len(tp.allowed) > 1 and all(c.indirect == "cache" for c in tp.allowed)
    with pytest.raises(ValueError, match=r"twopass: no composition allowed by the forced "
                                         r"choices can be built here: .*participating medium"):
        run_choose(scene, tp, tp.allowed)


def test_one_allowed_row_is_built_without_a_pilot():
    scene = mi.load_dict(hs.box())
    tp = chooser(direct="spike", indirect="radiosity", caustics="off")
    assert len(tp.allowed) == 1
    choice = run_choose(scene, tp, tp.allowed)
    assert choice.decision.chosen == tp.allowed[0]
    assert choice.decision.skipped == {"pilot": "every choice forced from XML"}
    assert choice.seconds["pilot"] == 0.0 and choice.seconds["prepasses"] > 0
    assert choice.integrator.structure is not None


def test_a_winner_that_may_be_biased_is_tested_again_before_a_long_render():
    """At 2^16 spp a bias far below the pilot's noise would dominate the render's error. The
    radiance cache is given a tenth of path's variance at path's cost (figures set here, so
    that timing does not decide whether it wins before the test): it is sampled again against
    path, with more samples per pixel than its pilot's, its bias is found, and path wins."""
    scene = mi.load_dict(hs.box())
    sensor = scene.sensors()[0]
    tp = chooser()
    path_row = cost.COMPOSITIONS[0]
    cache_row = next(c for c in cost.COMPOSITIONS
                     if c.plugin == "radiance_cache" and c.direct == "emitter")
    settings = PilotSettings(pixels=64)
    pixels = choose_pixels(sensor, settings.pixels, 0)
    path_integ, cache_integ = tp.candidate(path_row), tp.candidate(cache_row)
    cache_integ.ensure_prepass(scene, 0, sensor)
    path_run = pilot(scene, sensor, pixels, settings, path_sum_estimator(path_integ), 0)
    cache_run = pilot(scene, sensor, pixels, settings, candidate_estimator(cache_integ), 16)
    bias = cost.bias_squared(cache_run.values, path_run.values)
    decision = cost.Decision(chosen=path_row, spp=SPP, measured={
        path_row.name: cost.Measured(0.0, 0.01, 1.0, 0.0, 1.0),
        cache_row.name: cost.Measured(0.0, 0.01, 0.1, bias.b2, bias.ratio, bias_se=bias.se)})
    assert decision.measured[cache_row.name].score(SPP) < \
        decision.measured[path_row.name].score(SPP)  # the cache leads on its pilot
    runs = {path_row.name: (path_row, path_integ, path_run),
            cache_row.name: (cache_row, cache_integ, cache_run)}
    name = check_bias(scene, sensor, pixels, 0, SPP, runs, path_run, path_integ, decision,
                      budget=1e9)
    checks = decision.bias_checks[cache_row.name]
    assert checks[0][0] > cache_run.values.shape[1] and checks[0][1] is not None
    assert decision.measured[cache_row.name].bias2 > 0 and checks[-1][3] == "counted"
    assert name == path_row.name
    assert path_row.name not in decision.bias_checks  # path is the reference: never tested


def rex_case():
    """The lit box, its sensor, a twopass, the rex row and a path pilot's figures: what the
    tests of a cut rex's second build share."""
    scene = mi.load_dict(hs.box())
    return (scene, scene.sensors()[0], chooser(),
            next(c for c in cost.COMPOSITIONS if c.plugin == "rex"),
            cost.Measured(0.0, 0.01, 1.0, 0.0, 1.0))


def test_a_cut_rex_is_built_twice_and_its_own_noise_decides_its_photons(monkeypatch):
    """A rex candidate cut below the image's need is built again with another seed; the noise
    the two builds do not share is recorded. Below the limit the cut build is kept; above it,
    the candidate is built with the photons that bring it there (here the need: the noise is
    read far above the limit); where its budget has no room for them, it is kept while the
    noise is within check's bound (counted in its score) and left out, with the reason, beyond
    it."""
    from mi_twopass.compose.choose import fit_frozen

    scene, sensor, tp, rex_row, path_m = rex_case()
    cut = 1 << 16
    need = cut * cost.CUT_MAX  # the cut is the least allowed: only its noise decides
    film = 32 * 32

    def fit(room, need=need):
        decision = cost.Decision(chosen=rex_row, spp=SPP, fitted={rex_row.name: (cut, need)})
        integ = tp.candidate(rex_row, photons=cut)
        integ.ensure_prepass(scene, 0, sensor)
        return decision, integ, fit_frozen(scene, sensor, rex_row, integ, tp.candidate, 0,
                                           decision, room, path_m, film)

    monkeypatch.setattr(cost, "FROZEN_SHARE", 1e9)  # any noise is below the limit
    decision, integ, (kept, frozen, seconds) = fit(room=0.0)
    assert kept is integ and seconds > 0 and np.isfinite(frozen.block)
    assert decision.frozen[rex_row.name] == [(cut, frozen)]

    monkeypatch.undo()
    measure = cost.frozen_error  # the measurement, read as far above the limit
    monkeypatch.setattr(cost, "frozen_error",
                        lambda a, b, n: cost.Frozen(1.0, measure(a, b, n).block_se, 1.0))
    decision, integ, (kept, why, _) = fit(room=0.0)
    assert kept is None and f"its rexes' own noise at {cut} photons" in why
    between = 0.5 * (cost.frozen_limit() + BLOCK_RELMSE_MAX)  # over the limit, in the bound
    monkeypatch.setattr(cost, "frozen_error",
                        lambda a, b, n: cost.Frozen(between, measure(a, b, n).block_se, between))
    decision, integ, (kept, frozen, _) = fit(room=0.0)
    assert kept is integ and frozen.block == between
    assert decision.fitted[rex_row.name] == (cut, need)
    monkeypatch.setattr(cost, "frozen_error",
                        lambda a, b, n: cost.Frozen(1.0, measure(a, b, n).block_se, 1.0))
    decision, integ, (kept, predicted, _) = fit(room=1e9)
    assert kept is not integ and kept.photons == need
    assert decision.fitted[rex_row.name] == (need, need)
    assert [k for k, _ in decision.frozen[rex_row.name]] == [cut, need]
    assert predicted.block < decision.frozen[rex_row.name][0][1].block


def test_a_rex_cut_past_the_least_cut_is_rebuilt_or_left_out_whatever_its_noise(monkeypatch):
    """Below cost.least_cut (1/CUT_MAX of the need) a cut rex's buckets blur the image beyond
    check's bound, which its twin, as blurred, does not read: however quiet its own photons,
    it is built again with the least cut's photons where the room pays for them, and left out,
    with the reason, where it does not."""
    from mi_twopass.compose.choose import fit_frozen

    scene, sensor, tp, rex_row, path_m = rex_case()
    cut = 1 << 16
    need = cut * cost.PROBE_CUT
    assert cost.least_cut(need) > cut
    monkeypatch.setattr(cost, "FROZEN_SHARE", 1e9)  # any noise is below the limit

    def fit(room):
        decision = cost.Decision(chosen=rex_row, spp=SPP, fitted={rex_row.name: (cut, need)})
        integ = tp.candidate(rex_row, photons=cut)
        _, seconds = integ.ensure_prepass(scene, 0, sensor)
        return decision, fit_frozen(scene, sensor, rex_row, integ, tp.candidate, 0, decision,
                                    room, path_m, 32 * 32, seconds)

    decision, (kept, why, _) = fit(room=0.0)
    assert kept is None and f"cut more than {cost.CUT_MAX:g}-fold" in why
    assert str(cost.least_cut(need)) in why
    decision, (kept, _, _) = fit(room=1e9)
    assert kept.photons == cost.least_cut(need)  # the twin grows to it, and is kept
    assert decision.fitted[rex_row.name] == (cost.least_cut(need), need)


def test_a_cut_rexs_twin_gets_the_photons_its_budget_pays_for_and_is_the_build_kept(monkeypatch):
    """With room in its budget, the second build of a cut rex gets more photons (up to
    FROZEN_TWIN_GROWTH x, or the least cut where that is more, at the first build's seconds
    per photon) and renders: its prepass seed is offset, so the render's seed finds it built,
    and its noise is read from the pair as the larger build's (frozen_of_larger). With no room
    it has the cut's photons."""
    from mi_twopass.compose.choose import fit_frozen

    scene, sensor, tp, rex_row, path_m = rex_case()
    cut, need = 1 << 16, 1 << 18
    assert cost.least_cut(need) < cost.FROZEN_TWIN_GROWTH * cut
    monkeypatch.setattr(cost, "FROZEN_SHARE", 1e9)  # any noise is below the limit
    decision = cost.Decision(chosen=rex_row, spp=SPP, fitted={rex_row.name: (cut, need)})
    integ = tp.candidate(rex_row, photons=cut)
    _, seconds = integ.ensure_prepass(scene, 0, sensor)
    room = 2.5 * seconds  # pays for 2.5x the photons at the measured seconds per photon
    assert abs(cost.twin_photons(cut, need, seconds, room) - cut * 2.5) <= 1
    assert cost.twin_photons(cut, need, seconds, 1e9) == cost.FROZEN_TWIN_GROWTH * cut
    assert cost.twin_photons(cut, 2 * cut, seconds, 1e9) == 2 * cut  # at most the need
    big = cut * cost.PROBE_CUT  # the least cut is more than the growth: the twin reaches it
    assert cost.twin_photons(cut, big, seconds, 1e9) == cost.least_cut(big)
    kept, frozen, _ = fit_frozen(scene, sensor, rex_row, integ, tp.candidate, 0, decision,
                                 1e9, path_m, 32 * 32, seconds)
    more = cost.FROZEN_TWIN_GROWTH * cut
    assert kept is not integ and kept.photons == more
    assert decision.fitted[rex_row.name] == (more, need)
    (n0, pair), (n1, larger) = decision.frozen[rex_row.name]
    assert (n0, n1) == (cut, more) and larger is frozen
    assert frozen.pixel == pytest.approx(pair.pixel * 2 * 0.5 / 1.5)  # rho = 4^-0.5
    assert kept.ensure_prepass(scene, 0, sensor)[1] == 0.0  # the render's seed finds it
    # no room: the twin has the cut's photons and only measures (the cut is the least one)
    need = cut * cost.CUT_MAX
    decision = cost.Decision(chosen=rex_row, spp=SPP, fitted={rex_row.name: (cut, need)})
    kept, _, _ = fit_frozen(scene, sensor, rex_row, integ, tp.candidate, 0, decision, 0.0,
                            path_m, 32 * 32, seconds)
    assert kept is integ and decision.fitted[rex_row.name] == (cut, need)


def test_no_prepass_is_measured_or_built_where_not_even_the_least_one_fits(monkeypatch):
    # where the pilot leaves less than PREPASS_LEAST_SECONDS of the budget, a candidate is
    # skipped before its prepass's size is measured (rex's: a size pass and a probe shoot)
    scene = mi.load_dict(hs.box())
    tp = chooser()
    rex_row = next(c for c in cost.COMPOSITIONS if c.plugin == "rex")
    monkeypatch.setattr(cost, "CAUSTIC_SHARE", 0.0)  # the box has no caustics to speak of
    monkeypatch.setattr(cost, "PREPASS_LEAST_SECONDS", float("inf"))

    def never(*args, **kwargs):
        raise AssertionError("rex's photon need was measured")

    monkeypatch.setattr(cost, "light_paths", never)
    choice = run_choose(scene, tp, [cost.COMPOSITIONS[0], rex_row])
    assert choice.decision.skipped[rex_row.name].startswith("budget: ")
    assert "a prepass of at least inf s" in choice.decision.skipped[rex_row.name]
    assert choice.decision.chosen == cost.COMPOSITIONS[0]
    assert set(choice.decision.measured) == {cost.COMPOSITIONS[0].name}


def test_where_the_probe_finds_paths_render_shorter_than_any_prepass_no_pilot_runs(monkeypatch):
    # the probe forced on, with made-up figures: a render of 0.018 s (a GPU's fixed 11 ms and
    # a tiny cost per sample) leaves no room for a pilot and a prepass: path, no pilot, the
    # probe in the decision; 0.5 s per spp leaves room, and the pilot runs. The spike row
    # (one emitter here) is skipped before it is built, so nothing else is built
    import mi_twopass.compose.choose as choose_module

    scene = mi.load_dict(hs.box())
    tp = chooser()
    spike = next(c for c in cost.COMPOSITIONS if c.plugin == "spike_gather")
    allowed = [cost.COMPOSITIONS[0], spike]
    calls = []

    def run(figures, probe="on"):
        def fake(scene, sensor, integ, seed):
            calls.append(seed)
            return figures
        monkeypatch.setattr(choose_module, "probe_render", fake)
        return choose(scene, scene.sensors()[0], 0, SPP, allowed, tp.candidate,
                      PilotSettings(pixels=64), cost.PILOT_BUDGET, tp.max_depth, probe=probe)

    short = cost.RenderProbe(fixed=0.011, per_spp=1e-7)
    d = run(short).decision
    assert len(calls) == 1 and d.probe == short and d.chosen == cost.COMPOSITIONS[0]
    assert not d.measured and all(v.startswith("no pilot: path's render is predicted")
                                  for v in d.skipped.values())
    d = run(cost.RenderProbe(fixed=0.001, per_spp=0.5)).decision
    assert cost.COMPOSITIONS[0].name in d.measured and d.probe is not None  # the pilot ran
    calls.clear()
    d = run(short, probe="off").decision  # "off" (and "auto" on the CPU): no probe
    assert not calls and d.probe is None and cost.COMPOSITIONS[0].name in d.measured


def test_caustics_a_pilot_missed_are_predicted_from_rexs_photons():
    """A light inside a glass sphere: read as if the pilot had caught none of its rare
    samples, the caustic part is raised to the photons' prediction and path's total with it;
    where no surface is specular the photons are not asked; a scene rex refuses (fog) has its
    rex rows skipped with the reason."""
    pilot_parts = cost.VarianceParts(total=0.5, direct=0.3, caustic=0.0, indirect=0.2)
    scene = mi.load_dict(hs.glass_light())
    tp = chooser()
    decision = cost.Decision(chosen=cost.COMPOSITIONS[0], spp=SPP)
    raised, added = predict_caustics(scene, scene.sensors()[0], pilot_parts, tp.allowed,
                                     tp.candidate, traits(scene, -1), decision)
    predicted = decision.caustic_prediction["predicted"]
    assert predicted > 1.0 and decision.caustic_prediction["pilot"] == 0.0
    assert raised.caustic == pytest.approx(predicted)
    assert added == pytest.approx(predicted) and raised.total == pytest.approx(0.5 + predicted)

    box = mi.load_dict(hs.box())
    decision = cost.Decision(chosen=cost.COMPOSITIONS[0], spp=SPP)
    assert not traits(box, -1).specular
    assert predict_caustics(box, box.sensors()[0], pilot_parts, tp.allowed, tp.candidate,
                            traits(box, -1), decision) == (pilot_parts, 0.0)
    assert decision.caustic_prediction is None

    d = hs.glass_light()
    d["sensor"]["medium"] = {"type": "homogeneous", "sigma_t": 0.05,
                             "albedo": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}
    fog = mi.load_dict(d)
    decision = cost.Decision(chosen=cost.COMPOSITIONS[0], spp=SPP)
    assert predict_caustics(fog, fog.sensors()[0], pilot_parts, tp.allowed, tp.candidate,
                            traits(fog, -1), decision) == (pilot_parts, 0.0)
    rex_rows = [c.name for c in tp.allowed if c.caustics == "rex"]
    assert rex_rows and all(decision.skipped[n].startswith("refused: rex cannot render "
                                                           "participating media")
                            for n in rex_rows)
