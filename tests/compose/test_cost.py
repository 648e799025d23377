"""twopass's cost model (mi_twopass.compose.cost): the table, forced choices, the best case, the
bias estimate and the score."""
import dataclasses
import math

import numpy as np
import pytest

from mi_twopass.compose import cost


def test_every_forced_combination_either_names_rows_or_fails_naming_the_choices():
    assert [c.plugin for c in cost.matching(direct="spike")] == ["spike_gather", "spike_gather",
                                                                 "radiance_cache"]
    assert [c.props for c in cost.matching(direct="spike", indirect="cache")] == [
        (("direct", "spike"),) + cost.CACHE_RADIOSITY]
    assert [c.props for c in cost.matching(direct="emitter", indirect="cache")] == [
        (("direct", "emitter"),)]  # the cache's default direct light is spike lists
    assert [c.plugin for c in cost.matching(caustics="rex")] == ["rex"]
    assert len(cost.matching()) == len(cost.COMPOSITIONS)
    with pytest.raises(ValueError, match="no composition has direct='spike', indirect='rex'"):
        cost.matching(direct="spike", indirect="rex")


def test_best_case_removes_only_the_parts_a_technique_serves():
    parts = cost.VarianceParts(total=1.0, direct=0.6, caustic=0.1, indirect=0.3)
    rows = {(c.direct, c.indirect): c for c in cost.COMPOSITIONS}
    assert parts.best_case(rows["emitter", "path"]) == pytest.approx(1.0)
    assert parts.best_case(rows["spike", "path"]) == pytest.approx(0.4)
    assert parts.best_case(rows["emitter", "cache"]) == pytest.approx(0.7)
    assert parts.best_case(rows["spike", "radiosity"]) == pytest.approx(0.1)
    assert parts.best_case(rows["spike", "cache"]) == pytest.approx(0.1)
    assert parts.best_case(rows["emitter", "rex"]) == pytest.approx(0.0, abs=1e-12)


def test_a_predicted_caustic_part_raises_the_total_only_where_the_pilot_saw_less():
    parts = cost.VarianceParts(total=1.0, direct=0.6, caustic=0.1, indirect=0.3)
    raised = parts.with_caustic(5.0)
    assert (raised.total, raised.caustic) == pytest.approx((5.9, 5.0))
    assert (raised.direct, raised.indirect) == (0.6, 0.3)
    assert parts.with_caustic(0.05) == parts  # the pilot's own, where it saw more


def test_structural_reasons():
    rows = {(c.direct, c.indirect): c for c in cost.COMPOSITIONS}
    one = cost.SceneTraits(emitters=1, lambertian=True, max_depth=-1)
    assert "1 emitter" in cost.structural_reason(rows["spike", "path"], one)
    glossy = cost.SceneTraits(emitters=3, lambertian=False, max_depth=-1)
    assert "Lambertian" in cost.structural_reason(rows["emitter", "cache"], glossy)
    assert cost.structural_reason(rows["spike", "path"], glossy) is None
    bounded = cost.SceneTraits(emitters=3, lambertian=True, max_depth=3)
    assert "max_depth=3" in cost.structural_reason(rows["emitter", "radiosity"], bounded)
    assert cost.structural_reason(rows["emitter", "rex"], bounded) is None


def test_bias_is_zero_for_pilots_of_the_same_distribution_and_found_when_large():
    rng = np.random.default_rng(3)
    a = rng.exponential(1.0, size=(1024, 96, 3))
    b = rng.exponential(1.0, size=(1024, 96, 3))
    bias = cost.bias_squared(a, b)
    assert bias.b2 == 0.0 and bias.ratio == pytest.approx(1.0, abs=0.01)
    assert abs(bias.raw) < 4 * bias.se
    bias = cost.bias_squared(1.1 * a, b)
    assert bias.ratio == pytest.approx(1.1, abs=0.01)
    assert bias.b2 == pytest.approx(0.01, rel=0.2) and bias.b2 == bias.raw


def test_bias_that_changes_sign_over_the_image_is_found_though_the_mean_is_right():
    """+10 % on half the pixels, −10 % on the other half: the image mean is right, the relMSE
    floor is 0.01 (relative to the true pixel values 1)."""
    rng = np.random.default_rng(4)
    a = rng.exponential(1.0, size=(1024, 144, 3))
    b = rng.exponential(1.0, size=(1024, 144, 3))
    sign = np.where(np.arange(1024) % 2 == 0, 1.0, -1.0)[:, None, None]
    bias = cost.bias_squared(a * (1.0 + 0.1 * sign), b)
    assert bias.ratio == pytest.approx(1.0, abs=0.01)
    assert bias.b2 == pytest.approx(0.01, rel=0.25)


def test_score_is_predicted_error_times_seconds_and_prepass_amortises():
    m = cost.Measured(prepass_seconds=2.0, seconds_per_spp=0.01, variance=0.5, bias2=1e-4,
                      mean_ratio=1.0)
    assert m.score(100) == pytest.approx((0.5 / 100 + 1e-4) * (2.0 + 1.0))
    path = cost.Measured(prepass_seconds=0.0, seconds_per_spp=0.01, variance=2.0, bias2=0.0,
                         mean_ratio=1.0)
    assert path.score(16) < m.score(16)  # a short render: the prepass does not pay
    assert path.score(4096) > m.score(4096)  # a long one: it does


def test_a_built_prepass_is_spent_whichever_candidate_renders():
    """A structure whose prepass is most of a short render scores below path with that
    prepass counted, though it is built and has 15x less variance per sample. Once built,
    every candidate carries the same spent seconds."""
    path = cost.Measured(prepass_seconds=0.0, seconds_per_spp=0.04, variance=9.0, bias2=0.0,
                         mean_ratio=1.0)
    lists = cost.Measured(prepass_seconds=3.0, seconds_per_spp=0.08, variance=0.6, bias2=0.0,
                          mean_ratio=1.0)
    spp = 4
    assert path.score(spp) < lists.score(spp)  # whether to build: the prepass must pay
    cost.spend({"path": path, "lists": lists}, 3.5)  # pilot + prepass, spent
    assert path.predicted_seconds(spp) == pytest.approx(3.5 + spp * 0.04)
    assert lists.predicted_seconds(spp) == pytest.approx(3.5 + spp * 0.08)
    assert lists.score(spp) < path.score(spp)  # what to render with: the lists
    assert lists.prepass_seconds == 3.0  # its own prepass is still reported


def test_prepass_floor_counts_light_paths_at_path_cost():
    path = cost.Measured(prepass_seconds=0.0, seconds_per_spp=0.02, variance=1.0, bias2=0.0,
                         mean_ratio=1.0)
    # 1e6 light paths on a 100×100 film: 100 path samples per pixel's worth of paths
    assert cost.prepass_floor(10**6, path, 10**4) == pytest.approx(
        cost.PREPASS_FLOOR_FACTOR * 100 * 0.02)
    assert cost.light_paths_within(cost.PREPASS_FLOOR_FACTOR * 100 * 0.02, path, 10**4) == \
        pytest.approx(10**6, rel=1e-9, abs=1)


def test_a_prepass_costs_its_host_work_however_fast_the_device_traces():
    # a GPU: path at 256² costs 0.4 ms per spp, so 262,144 particles' floor in path samples'
    # time would be 3 ms; every prepass measured took at least 0.19 s there
    gpu_path = cost.Measured(prepass_seconds=0.0, seconds_per_spp=4e-4, variance=1.0,
                             bias2=0.0, mean_ratio=1.0)
    film = 256 * 256
    assert cost.PREPASS_FLOOR_FACTOR * 262_144 * 4e-4 / film < 0.01
    assert cost.prepass_floor(262_144, gpu_path, film) == cost.PREPASS_LEAST_SECONDS
    # below the least, no light paths fit; at it, as many as the floor in samples allows
    assert cost.light_paths_within(0.9 * cost.PREPASS_LEAST_SECONDS, gpu_path, film) == 0
    assert cost.light_paths_within(cost.PREPASS_LEAST_SECONDS, gpu_path, film) > 262_144


def test_prepass_budget_follows_the_best_case_break_even_within_its_bounds():
    # path's score 1.0; a best case of 0.2 (g = 5) breaks even with a prepass of 4 P
    assert cost.prepass_budget(0.2, 1.0, 0.25) == pytest.approx(cost.BREAK_EVEN_MAX)
    # g = 1.5: half of 0.5 P is 0.25 P, g = 1.2: 0.1 P, but never below the pilot budget
    assert cost.prepass_budget(1.0 / 1.5, 1.0, 0.1) == pytest.approx(
        cost.BREAK_EVEN_SHARE * 0.5)
    assert cost.prepass_budget(1.0 / 1.2, 1.0, 0.25) == pytest.approx(0.25)
    assert cost.prepass_budget(0.0, 1.0, 0.25) == pytest.approx(cost.BREAK_EVEN_MAX)
    assert cost.prepass_budget(0.0, 1.0, 2.0) == pytest.approx(2.0)  # a larger pilot budget
    assert cost.prepass_budget(0.01, 1.0, 0.0) == 0.0  # pilot_budget = 0: path only
    # the bound it halves: a candidate at its best case that spends (g - 1) P ties with path
    path = cost.Measured(prepass_seconds=0.0, seconds_per_spp=0.01, variance=2.0, bias2=0.0,
                         mean_ratio=1.0)
    spp, g = 64, 4.0
    tie = cost.Measured(prepass_seconds=(g - 1) * spp * 0.01, seconds_per_spp=0.01,
                        variance=2.0 / g, bias2=0.0, mean_ratio=1.0)
    assert tie.score(spp) == pytest.approx(path.score(spp))


def test_later_candidates_are_budgeted_on_the_leaders_render_not_paths():
    # path would render in 10 s; the first structure was measured after 1.5 s and renders in 2 s
    assert cost.later_budget(10.0, 1.5, 2.0, 0.25) == pytest.approx(1.5 + 0.25 * 2.0)
    # a leader no faster than path (or path itself) leaves path's budget
    assert cost.later_budget(10.0, 1.5, 10.0, 0.25) == pytest.approx(2.5)
    assert cost.later_budget(10.0, 2.4, 10.0, 0.25) == pytest.approx(2.5)
    assert cost.later_budget(10.0, 1.5, 2.0, 0.0) == 0.0  # pilot_budget = 0: path only


def test_none_fit_decides_without_a_pilot_only_when_every_floor_is_too_big():
    counts = {"a": 262144, "b": 4 * 10**6}
    # 16384 pixels x 16 spp: half of it over the factor 2 is 65536 light paths
    reasons = cost.none_fit(counts, 16384 * 16, 0.5)
    assert set(reasons) == {"a", "b"} and all("no pilot" in r for r in reasons.values())
    assert cost.none_fit(counts, 16384 * 256, 0.5) is None  # 1 M > 262144: a may fit


def test_the_pilot_gate_fits_the_largest_budget_and_weighs_the_pilots_own_samples():
    """Before the pilot, a prepass must fit the most any candidate may spend (the break-even
    cap, all of path's predicted time), not the quarter every candidate keeps: the office at
    256² reached relMSE 0.01 near 16 spp with spike lists, where twopass ran no pilot. The
    pilot itself (every candidate's as many samples as path's) starts only where its samples
    are at most PILOT_SHARE_MAX of the render's, in proportion to pilot_budget."""
    assert cost.largest_budget(cost.PILOT_BUDGET) == cost.BREAK_EVEN_MAX
    assert cost.largest_budget(4.0) == 4.0 and cost.largest_budget(0.0) == 0.0
    office_16 = 256 * 256 * 16
    spike = {"spike": 262144}  # its radiosity particles: floor 2 x 262144 samples
    assert cost.none_fit(spike, office_16, cost.PILOT_BUDGET) is not None  # the old gate
    assert cost.none_fit(spike, office_16, cost.largest_budget(cost.PILOT_BUDGET)) is None
    pilot = 1024 * 144
    assert pilot <= cost.PILOT_SHARE_MAX * office_16
    assert cost.pilot_too_dear(pilot, office_16) is None
    why = cost.pilot_too_dear(pilot, 256 * 256 * 8)  # 8 spp: 28 %
    assert why.startswith("no pilot") and "147456 samples" in why
    assert cost.pilot_too_dear(pilot, 256 * 256 * 8, 4 * cost.PILOT_BUDGET) is None
    assert cost.pilot_too_dear(pilot, 10**9, 0.0) is not None  # pilot_budget 0: path only


def test_a_hidden_bias_decides_only_where_the_affordable_bias_is_below_the_detection_limit():
    m = cost.Measured(prepass_seconds=1.0, seconds_per_spp=0.01, variance=0.1, bias2=0.0,
                      mean_ratio=1.0, bias_se=1e-4)
    # 100 spp: 2 s, relMSE 1e-3; the runner-up's 0.01 leaves 0.01 / 2 - 1e-3 = 4e-3 of bias²
    assert cost.bias_slack(m, 0.01, 100) == pytest.approx(4e-3)
    assert not cost.hidden_bias_may_decide(m, 0.01, 100)
    # 10^4 spp: 101 s, relMSE 1e-5; 0.01 / 101 - 1e-5 ≈ 8.9e-5 < 3 × 1e-4
    slack = 0.01 / 101 - 1e-5
    assert cost.hidden_bias_may_decide(m, 0.01, 10**4)
    # the next test's samples: where 3·se·(144 / n) is 1.25× below the slack
    assert cost.check_samples(144, m, 0.01, 10**4) == math.ceil(144 * 1.25 * 3e-4 / slack)
    # within [2, 16] × the last test's
    assert cost.check_samples(144, m, 1.0, 10**4) == 288
    assert cost.check_samples(144, m, 0.0011, 10**4) == 144 * cost.CHECK_MAX_GROWTH
    path = cost.Measured(prepass_seconds=0.0, seconds_per_spp=0.01, variance=1.0, bias2=0.0,
                         mean_ratio=1.0)
    # no standard error (path, the reference): nothing hidden, even at a tie
    assert not cost.hidden_bias_may_decide(path, path.score(10**6), 10**6)


def test_frozen_error_reads_the_noise_two_builds_do_not_share_and_drops_the_samples():
    """Two builds of a prepass, each with its own noise per block (σ = 5 % of the pixel
    value, shared by every sample of one build) and per-sample noise (30 %): the block
    estimate is σ² within its standard error, 0 where the builds agree."""
    rng = np.random.default_rng(3)
    blocks, per_block, samples = 256, 64, 8
    truth = rng.uniform(0.5, 2.0, (blocks, 1, 1, 3)) * np.ones((1, per_block, 1, 1))

    def build(sigma):
        shared = 1.0 + sigma * rng.standard_normal((blocks, 1, 1, 1))
        value = truth * shared * (1.0 + 0.3 * rng.standard_normal((blocks, per_block, samples,
                                                                    3)))
        return value.reshape(blocks * per_block, samples, 3)

    f = cost.frozen_error(build(0.05), build(0.05), per_block)
    want = np.mean(0.05**2 * truth[:, 0, 0] ** 2 / (truth[:, 0, 0] ** 2 + 0.01))
    assert abs(f.block - want) < 3 * f.block_se and f.block_se < 0.25 * want
    f0 = cost.frozen_error(build(0.0), build(0.0), per_block)
    assert abs(f0.block) < 3 * f0.block_se
    # the per-sample noise (0.3² / 8 per pixel mean) is subtracted, not read as frozen
    assert abs(f0.pixel) < 0.1 * 0.3**2 / samples


def test_cut_photons_stay_within_the_blur_limit_and_rise_with_measured_noise():
    need = 16_000_000
    assert cost.least_cut(need) == need // cost.CUT_MAX
    assert cost.least_probe(need) == need // cost.PROBE_CUT < cost.least_cut(need)
    limit = cost.frozen_limit()
    assert limit == cost.FROZEN_SHARE * cost.BLOCK_RELMSE_MAX
    quiet = cost.Frozen(block=0.5 * limit, block_se=1e-4, pixel=1e-3)
    assert cost.frozen_photons(10_000_000, quiet, need) == 10_000_000
    # however quiet, a build below the least cut needs the least cut (its blur)
    assert cost.frozen_photons(1_000_000, quiet, need) == cost.least_cut(need)
    noisy = cost.Frozen(block=1.2 * limit, block_se=1e-4, pixel=1e-2)
    more = cost.frozen_photons(6_000_000, noisy, need)
    # (1.2)^(1/FROZEN_DECAY) as many photons, and the noise predicted for them is the limit
    assert more == int(np.ceil(6_000_000 * 1.2 ** (1 / cost.FROZEN_DECAY))) > cost.least_cut(need)
    assert noisy.scaled(more / 6_000_000).block == pytest.approx(limit, rel=1e-6)
    assert cost.frozen_photons(1_000_000, cost.Frozen(1.0, 1e-4, 1.0), need) == need


def test_a_measured_candidates_room_is_a_share_of_its_break_even_prepass():
    """cost.measured_room: BREAK_EVEN_SHARE of the prepass T at which the candidate's score
    (T + N·t_c)·e_c equals path's; 0 where it loses even with no prepass."""
    path = cost.Measured(prepass_seconds=0.0, seconds_per_spp=0.01, variance=40.0, bias2=0.0,
                         mean_ratio=1.0)
    rex = cost.Measured(prepass_seconds=0.3, seconds_per_spp=0.008, variance=0.5, bias2=1e-3,
                        mean_ratio=1.0)
    spp = 64
    room = cost.measured_room(rex, path, spp)
    even = dataclasses.replace(rex, prepass_seconds=room / cost.BREAK_EVEN_SHARE)
    assert even.score(spp) == pytest.approx(path.score(spp), rel=1e-9)
    assert room > 10 * path.predicted_seconds(spp)  # far ahead: far past path's render time
    worse = dataclasses.replace(rex, variance=80.0)
    assert cost.measured_room(worse, path, spp) == 0.0


def test_a_prepass_own_noise_counts_as_an_error_no_sample_removes():
    m = cost.Measured(prepass_seconds=1.0, seconds_per_spp=0.01, variance=0.5, bias2=0.0,
                      mean_ratio=1.0, frozen=0.002)
    assert m.predicted_error(100) == pytest.approx(0.005 + 0.002)
    assert m.predicted_error(10**9) == pytest.approx(0.002, rel=1e-6)
    m.bias2 = 0.003  # a bias found against path holds the frozen noise too: the larger counts
    assert m.predicted_error(10**9) == pytest.approx(0.003, rel=1e-6)


def test_the_probe_is_wanted_on_a_gpu_only_unless_forced():
    assert cost.probe_wanted("cuda") and not cost.probe_wanted("llvm")
    assert cost.probe_wanted("llvm", "on") and not cost.probe_wanted("cuda", "off")


def test_the_seconds_gate_skips_the_pilot_where_paths_render_is_shorter_than_any_prepass():
    """The office at 256² on an H200 (session 13's bench): path took 11.5 ms at 1 spp and
    16.2 ms at 8, about 11 ms fixed and 0.7 ms per spp. Its 32-spp render, ~0.03 s, is
    shorter than the least prepass (PREPASS_LEAST_SECONDS) alone: no pilot. On two CPU cores
    the same render takes ~0.17 s per spp and both fit."""
    gpu = cost.RenderProbe(fixed=0.011, per_spp=0.0007)
    assert gpu.seconds(32) == pytest.approx(0.011 + 32 * 0.0007)
    pilot_lanes, film = 1024 * 144, 256 * 256
    why = cost.too_dear_in_seconds(gpu, 32, pilot_lanes, film, 4)
    assert why is not None and why.startswith("no pilot")
    cpu = cost.RenderProbe(fixed=0.002, per_spp=0.17)
    assert cost.too_dear_in_seconds(cpu, 32, pilot_lanes, film, 4) is None
    # the pilot's own floor: 4 calls of the fixed part plus its lanes at the render's cost
    # per lane; a fixed part of 0.5 s makes even a 1000-spp render too short for it
    slow_calls = cost.RenderProbe(fixed=0.5, per_spp=0.001)
    why = cost.too_dear_in_seconds(slow_calls, 1000, pilot_lanes, film, 4)
    assert "the pilot at least 2" in why
    # pilot_budget 0: path only; a larger pilot_budget lets the pilot start sooner
    assert cost.too_dear_in_seconds(cpu, 32, pilot_lanes, film, 4, 0.0) is not None
    long_gpu = 20000  # spp: 14 s of path on the GPU, room for pilot and prepasses
    assert cost.too_dear_in_seconds(gpu, long_gpu, pilot_lanes, film, 4) is None
