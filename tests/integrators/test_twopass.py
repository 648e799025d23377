"""``twopass`` (mi_twopass.integrators.twopass) and its pilot estimator ``ComponentPathIntegrator``:
parameters, each forced choice renders exactly what the integrator it names renders, the
consistency of the component split with Mitsuba's ``path``, the furnace, what is built (no rex
without caustics), stats, the debug view.

Statistical tests compare block means of K independent renders with a z-test (as
tests/test_hard_cases.py), never with a loose tolerance."""
import os
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_twopass  # noqa: F401
from mi_twopass.compose import cost
from mi_twopass.evaluation.statistics import block_z_scores
from mi_twopass.integrators.component_path import ComponentPathIntegrator

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import hard_scenes as hs  # noqa: E402

#: a pilot budget so large that every candidate the best case admits is built and piloted
TRY_ALL = {"pilot_budget": 1e6}


def render(scene, integrator, spp, seed=0):
    return np.asarray(mi.render(scene, integrator=integrator, spp=spp, seed=seed))


def component_path(**props):
    p = mi.Properties()
    for k, v in props.items():
        p[k] = v
    return ComponentPathIntegrator(p)


# -- parameters ----------------------------------------------------------------------------
def test_registered_and_loadable():
    assert "twopass" in mi_twopass.integrators.registered_names()
    integ = mi.load_dict({"type": "twopass"})
    assert integ.forced == {"direct": None, "indirect": None, "caustics": None}


@pytest.mark.parametrize("props, message", [
    ({"direct": "spike", "indirect": "rex"},
     "no composition has direct='spike', indirect='rex'"),
    ({"caustics": "rex", "direct": "spike"}, "no composition has direct='spike', caustics='rex'"),
    ({"direct": "lists"}, "direct='lists': expected one of auto, emitter, spike"),
    ({"pilot_pixels": 2}, "pilot_pixels=2: must be >= 16"),
    ({"pilot_budget": -1.0}, "pilot_budget=-1: must be >= 0")])
def test_bad_parameters_fail_at_load_time(props, message):
    with pytest.raises(RuntimeError, match=message):
        mi.load_dict({"type": "twopass", **props})


# -- forced choices ------------------------------------------------------------------------
@pytest.mark.parametrize("row", cost.COMPOSITIONS, ids=lambda c: c.name)
def test_each_forced_choice_renders_what_its_integrator_renders(row):
    """Every choice forced from XML: no pilot, the stats name the composition, and the image is
    the named integrator's, sample for sample (same seeds, same prepass)."""
    scene = mi.load_dict(hs.box())
    tp = mi.load_dict({"type": "twopass", "direct": row.direct, "indirect": row.indirect,
                       "caustics": row.caustics})
    img = render(scene, tp, spp=4, seed=3)
    assert tp.stats["twopass_choice"] == row.name
    assert tp.stats["twopass_skipped"] == {"pilot": "every choice forced from XML"}
    if row.plugin == "path":
        direct = component_path()
    else:
        direct = mi.load_dict({"type": row.plugin, **dict(row.props)})
    ref = render(scene, direct, spp=4, seed=3)
    assert np.isfinite(img).all()
    np.testing.assert_allclose(img, ref, rtol=1e-5, atol=1e-6)


# -- the component split ---------------------------------------------------------------------
def test_components_add_up_to_all_sample_for_sample():
    scene = mi.load_dict(hs.glass_light())
    all_ = render(scene, component_path(), spp=4, seed=1)
    direct = render(scene, component_path(component="direct"), spp=4, seed=1)
    indirect = render(scene, component_path(component="indirect"), spp=4, seed=1)
    np.testing.assert_allclose(direct + indirect, all_, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("scene_name", ["glass_light", "objects"])
def test_component_path_converges_to_mitsubas_path(scene_name):
    """K = 4 independent renders of each; block z-scores of the difference, |z| < 4 (16
    blocks: a false alarm has probability ~1e-3)."""
    scene = hs.build(scene_name)
    ours = [render(scene, component_path(), spp=32, seed=10 + k) for k in range(4)]
    path = [render(scene, mi.load_dict({"type": "path"}), spp=32, seed=20 + k)
            for k in range(4)]
    z = block_z_scores(ours, path, block=4)
    assert np.abs(z).max() < 4.0, z


def test_caustic_part_is_found_behind_glass_and_zero_without_it():
    integ = component_path()
    for build, has_caustic in ((hs.glass_light, True), (hs.box, False)):
        scene = mi.load_dict(build())
        sensor = scene.sensors()[0]
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(0, 256 * 16)
        idx = dr.arange(mi.UInt32, 256 * 16) // 16
        pos = (mi.Point2f(mi.Float(idx % 16), mi.Float(idx // 16)) + sampler.next_2d()) / 16
        ray, _ = sensor.sample_ray(0.0, 0.5, pos, sampler.next_2d())
        _, caustic, _, _ = integ.sample_components(scene, sampler, ray, True)
        total = float(np.asarray(caustic.x).sum())
        assert (total > 0) == has_caustic, (build.__name__, total)


# -- what is built, and why -----------------------------------------------------------------
def test_no_rex_without_caustics_and_stats_say_why():
    """A diffuse box: the pilot finds no caustic variance, so no rex is built (the stats give
    the measured share), even with an unlimited pilot budget."""
    scene = mi.load_dict(hs.box())
    tp = mi.load_dict({"type": "twopass", **TRY_ALL})
    render(scene, tp, spp=16)
    rex_row = next(c for c in cost.COMPOSITIONS if c.plugin == "rex")
    assert rex_row.name not in tp.stats["twopass_candidates"]
    assert "caustics carry 0.0%" in tp.stats["twopass_skipped"][rex_row.name]
    # no specular surface: no light is sharp, so rex's photons were not asked
    assert tp.stats["twopass_caustic_prediction"] is None
    spikes = [c.name for c in cost.COMPOSITIONS if c.direct == "spike"]
    assert all("1 emitter" in tp.stats["twopass_skipped"][n] for n in spikes)
    chosen = tp.stats["twopass_choice"]
    cands = tp.stats["twopass_candidates"]
    assert chosen in cands and len(cands) >= 2
    assert min(cands, key=lambda n: cands[n]["score"]) == chosen
    assert tp.stats["twopass_reason"].startswith(chosen)
    # every composition with a prepass has its best case (the order they were considered in)
    best = tp.stats["twopass_best_case"]
    assert set(best) == {c.name for c in cost.COMPOSITIONS if c.needs_prepass}
    assert all(v >= 0.0 for v in best.values())
    assert tp.stats["prepass_seconds"] >= tp.stats["pilot_seconds"] > 0


def test_short_render_builds_nothing_and_runs_no_pilot():
    """1 spp of a 16×16 image: every prepass traces more light paths than half the render's
    256 path samples over the floor factor, so twopass is path without a pilot."""
    scene = mi.load_dict(hs.box())
    tp = mi.load_dict({"type": "twopass"})
    render(scene, tp, spp=1)
    assert tp.stats["twopass_choice"] == cost.COMPOSITIONS[0].name
    assert tp.stats["twopass_candidates"] == {}
    assert "no pilot" in tp.stats["twopass_reason"]
    assert all(r.startswith("no pilot") for r in tp.stats["twopass_skipped"].values())


def test_budget_stops_building_once_the_pilot_has_spent_it():
    """The budget is 1 × the render's path time, N·256 samples with N·256 = 2.2 × 262144 (the
    particles of the smallest prepass). That prepass's floor, 2 × 262144 samples' time, fits
    before the pilot (2 < 2.2) but leaves 0.2 × 262144 ≈ 52k samples' time, which the path
    pilot's 147456 samples alone exceed: nothing is built, path is chosen."""
    scene = mi.load_dict(hs.box())
    tp = mi.load_dict({"type": "twopass", "pilot_budget": 1.0})
    render(scene, tp, spp=int(2.2 * 262144 / 256))
    assert tp.stats["twopass_choice"] == cost.COMPOSITIONS[0].name
    assert list(tp.stats["twopass_candidates"]) == [cost.COMPOSITIONS[0].name]
    assert any(r.startswith("budget") for r in tp.stats["twopass_skipped"].values())


def test_finite_max_depth_skips_the_far_fields():
    scene = mi.load_dict(hs.box())
    tp = mi.load_dict({"type": "twopass", "max_depth": 3, **TRY_ALL})
    render(scene, tp, spp=16)
    for c in cost.COMPOSITIONS:
        if c.indirect in ("radiosity", "cache") and c.direct == "emitter":
            assert "max_depth=3" in tp.stats["twopass_skipped"][c.name]


def test_max_depth_zero_is_black_without_a_pilot():
    scene = mi.load_dict(hs.box())
    tp = mi.load_dict({"type": "twopass", "max_depth": 0})
    assert np.all(render(scene, tp, spp=2) == 0.0)
    assert tp.structure is None


def test_second_render_reuses_the_choice():
    scene = mi.load_dict(hs.box())
    tp = mi.load_dict({"type": "twopass"})
    render(scene, tp, spp=8)
    assert tp.stats["prepass_seconds"] > 0
    render(scene, tp, spp=8)  # same scene, seed, spp: the pilot and prepass are reused
    assert tp.stats["prepass_seconds"] == 0.0


def test_where_the_sample_gates_rule_out_the_pilot_no_prepass_key_is_computed(monkeypatch):
    """A render too short for any pilot (4 spp of the small box) is path's, decided before the
    prepass key, which would fingerprint every scene parameter for nothing to reuse; the
    decision is kept for the same film, spp and settings."""
    from mi_twopass.integrators import base

    def no_key(*args, **kwargs):
        raise AssertionError("the prepass key was computed")

    scene = mi.load_dict(hs.box())
    tp = mi.load_dict({"type": "twopass"})
    monkeypatch.setattr(base, "parameter_fingerprint", no_key)
    image = render(scene, tp, spp=4)
    assert np.isfinite(image).all()
    assert tp.stats["twopass_choice"] == cost.COMPOSITIONS[0].name
    assert all(v.startswith("no pilot") for v in tp.stats["twopass_skipped"].values())
    render(scene, tp, spp=4)
    assert tp.stats["prepass_seconds"] == 0.0  # the decision reused
    monkeypatch.undo()
    render(scene, tp, spp=1 << 14)  # long enough for a pilot: the key and the prepass
    assert tp.stats["twopass_candidates"]
    render(scene, tp, spp=4)  # back to the early decision, with its own stats
    assert not tp.stats["twopass_candidates"] and tp.stats["prepass_seconds"] == 0.0


def test_where_the_probe_rules_out_the_pilot_no_prepass_key_is_computed(monkeypatch):
    """path_probe="on" with made-up probe figures. A 0.018 s render leaves no room: path,
    with no prepass key and the probe in the stats. A long one (0.5 s per spp) leaves room:
    the pilot runs, on the probe made before the key (one probe per render)."""
    import mi_twopass.compose.choose as choose_module
    from mi_twopass.integrators import base

    scene = mi.load_dict(hs.box())
    calls = []

    def fake(figures):
        def probe(scene, sensor, integ, seed):
            calls.append(seed)
            return figures
        return probe

    def no_key(*args, **kwargs):
        raise AssertionError("the prepass key was computed")

    spp = 1 << 16  # the sample gates leave the pilot open
    monkeypatch.setattr(choose_module, "probe_render", fake(cost.RenderProbe(0.011, 1e-7)))
    with monkeypatch.context() as m:
        m.setattr(base, "parameter_fingerprint", no_key)
        tp = mi.load_dict({"type": "twopass", "path_probe": "on", "direct": "emitter"})
        tp.planned_spp = spp
        render(scene, tp, spp=1)
    assert len(calls) == 1 and tp.stats["twopass_probe"]["fixed_seconds"] == 0.011
    assert not tp.stats["twopass_candidates"]
    assert all(v.startswith("no pilot: path's render") for v in
               tp.stats["twopass_skipped"].values())
    calls.clear()
    monkeypatch.setattr(choose_module, "probe_render", fake(cost.RenderProbe(0.001, 0.5)))
    tp = mi.load_dict({"type": "twopass", "path_probe": "on", "direct": "emitter",
                       "caustics": "off"})  # path and the two far fields
    tp.planned_spp = spp
    render(scene, tp, spp=1)
    assert len(calls) == 1 and tp.stats["twopass_probe"]["seconds_per_spp"] == 0.5
    assert cost.COMPOSITIONS[0].name in tp.stats["twopass_candidates"]  # the pilot ran


def test_furnace_is_exact():
    """ρ = 0.5, Le = 1: L = 2 everywhere. K = 4 renders with every candidate tried; the image
    mean within 4 standard errors of 2 plus the chosen integrator's stated allowance (the
    radiance cache: 15 % of the indirect light, tests/test_hard_cases.py; others 1e-3)."""
    scene = mi.load_dict(hs.furnace(0.5))
    means, chosen = [], set()
    for k in range(4):
        tp = mi.load_dict({"type": "twopass", **TRY_ALL})
        means.append(render(scene, tp, spp=16, seed=k).mean())
        chosen.add(tp.stats["twopass_choice"])
    means = np.array(means)
    se = max(means.std(ddof=1) / 2.0, 1e-4)
    indirect = 2.0 - 1.0 * (1 + 0.5)
    allowance = 0.15 * indirect if any("cache" in c for c in chosen) else 2e-3
    assert abs(means.mean() - 2.0) < 4 * se + allowance, (means, chosen)


def assert_technique_view(scene, props, colour):
    """Render ``scene`` at 1 spp with twopass forced by ``props`` (a debug view among them):
    more than half the pixels are ``colour`` (the forced technique), all others grey (path
    traced) or black (no surface)."""
    tp = mi.load_dict({"type": "twopass", **props})
    img = render(scene, tp, spp=1)[..., :3].reshape(-1, 3)
    technique = np.all(np.isclose(img, colour), axis=1)
    grey = np.all(np.isclose(img, [0.5, 0.5, 0.5]), axis=1)
    black = np.all(img == 0, axis=1)
    assert technique.mean() > 0.5
    assert np.all(technique | grey | black)


def test_debug_view_colours_the_technique():
    """Forced to the radiosity gather on the box: walls the radiosity caches are blue, the
    rest grey (path traced), the background black."""
    assert_technique_view(mi.load_dict(hs.box()),
                          {"direct": "emitter", "indirect": "radiosity",
                           "debug": "indirect_technique"}, [0.0, 0.35, 0.9])


def test_debug_view_shows_what_the_radiance_cache_holds():
    """Forced to the radiance cache on the box: green where the cache holds the surface (its
    receiving element, since session 18, not its patch too), grey elsewhere."""
    assert_technique_view(mi.load_dict(hs.box()),
                          {"direct": "emitter", "indirect": "cache",
                           "debug": "indirect_technique"}, [0.0, 0.75, 0.2])


def test_direct_debug_view_shows_spike_lists_on_a_scene_with_many_lights():
    """Forced to spike lists on the mixed room (26 lamps, a sun and a sky): orange where a cell
    has a list, grey elsewhere, black where the camera sees no surface (the window)."""
    scene = mi.load_file(os.path.join(hs.__file__.rsplit("tests", 1)[0], "scenes_xml",
                                      "mixed_room.xml"), res=16)
    assert_technique_view(scene, {"direct": "spike", "indirect": "path",
                                  "debug": "direct_technique"}, [0.9, 0.45, 0.0])


def test_a_render_in_passes_is_chosen_for_its_whole_spp(tiny_scene_file, tmp_path, monkeypatch):
    """``python -m mi_twopass render`` splits a large render into passes: twopass must weigh
    the prepasses against the whole render's samples, not one pass's."""
    from mi_twopass import cli

    monkeypatch.setattr(cli, "LANES_PER_PASS", 16 * 16 * 4)
    res = cli.render_command(tiny_scene_file, str(tmp_path / "a.exr"), "twopass", spp=64,
                             out=lambda *_: None)
    assert res["passes"] == 16
    assert "at 64 spp" in res["stats"]["twopass_reason"]


def test_candidates_share_one_radiosity_solve():
    """The two spike_gather rows (spike lists with the far gather, and with paths) and the row
    of spike lists with the radiance cache (``cost.CACHE_RADIOSITY``) ask for the same
    radiosity budget: within one twopass prepass the first solves, the others take its solve
    (radiosity.build's memo); radiosity_gather and the cache alone, whose budgets differ, solve
    their own; the memo is emptied once the choice is made."""
    d = hs.box()
    d["light2"] = {"type": "rectangle", "emitter": {"type": "area",
                                                    "radiance": hs.rgb(4.0)},
                   "to_world": mi.ScalarTransform4f().translate([-0.6, 0.99, -0.5])
                   .rotate([1, 0, 0], 90).scale(0.15)}
    scene = mi.load_dict(d)
    tp = mi.load_dict({"type": "twopass", **TRY_ALL})
    render(scene, tp, spp=16)
    spikes = [c for c in cost.COMPOSITIONS if c.plugin == "spike_gather"]
    gather = next(c for c in cost.COMPOSITIONS if c.plugin == "radiosity_gather")
    assert all(c.name in tp.stats["twopass_candidates"] for c in spikes + [gather]), tp.stats
    a, b = (tp.candidate(c) for c in spikes)
    assert a.structure.solution is b.structure.solution
    assert sorted([a._prepass_stats["radiosity_reused"], b._prepass_stats["radiosity_reused"]]) \
        == [False, True]
    assert tp.candidate(gather).structure.solution is not a.structure.solution
    spike_cache, cache = (next(c for c in cost.COMPOSITIONS if c.plugin == "radiance_cache"
                               and c.direct == direct) for direct in ("spike", "emitter"))
    assert {spike_cache.name, cache.name} <= set(tp.stats["twopass_candidates"]), tp.stats
    assert tp.candidate(spike_cache).structure.solution is a.structure.solution
    assert tp.candidate(cache).structure.solution is not a.structure.solution
    assert len(tp._radiosity_memo) == 0


def test_a_plain_path_render_is_mitsubas_path_where_that_is_the_same_estimator():
    """Where twopass renders path, it renders with Mitsuba's own plugin when that is the same
    estimator (every component, Mitsuba's ray offsets, no infinite emitter): the same image as
    ``path`` with the same seed, at path's cost (the furnace at 256², 4 spp: 9 % slower through
    the component loop). A millimetre box keeps the loop and its scene-relative offsets."""
    scene = mi.load_dict(hs.box())
    tp = mi.load_dict({"type": "twopass", "max_depth": 6})
    img = render(scene, tp, spp=1, seed=3)
    assert tp.stats["twopass_choice"] == cost.COMPOSITIONS[0].name
    ref = np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 6}),
                               spp=1, seed=3))
    assert np.array_equal(img, ref)
    assert tp.stats["viewing_rays"] == 16 * 16 and "implicit_rays" not in tp.stats
    assert component_path().mitsuba_path_is_the_same(scene)
    assert not component_path(component="direct").mitsuba_path_is_the_same(scene)
    assert not component_path().mitsuba_path_is_the_same(mi.load_dict(hs.box(scale=1e-3)))


def test_a_cut_rex_and_its_twin_read_the_plan_the_photon_need_measured():
    """Within one twopass prepass the rex size pass and probe shoot are made once, for the
    photon need (``cost.light_paths``), and every rex build of the scene and camera reads
    them (``rex_textures.ProbeMemo``): the cut build the pilot measures, its twin, any
    rebuild. The memo is emptied once the choice is made."""
    scene = mi.load_dict(hs.box())
    tp = mi.load_dict({"type": "twopass", "direct": "emitter", "indirect": "rex",
                       "caustics": "rex", "pilot_budget": 1e6})
    rex_row = next(c for c in cost.COMPOSITIONS if c.plugin == "rex")
    need = tp.candidate(rex_row).photon_budget(scene, 0, scene.sensors()[0])
    assert len(tp._probe_memo) == 1
    builds = []
    for photons, offset in ((1 << 16, 0), (1 << 17, 0x7717)):
        integ = tp.candidate(rex_row, photons=photons, seed_offset=offset)
        integ.ensure_prepass(scene, 0, scene.sensors()[0])
        builds.append(integ)
    assert need > 0 and all(b._prepass_stats["plan_reused"] for b in builds)
    assert all(b._prepass_stats["size_rays"] == 0 for b in builds)
    assert builds[0].structure.cap is builds[1].structure.cap
    render(scene, tp, spp=16)
    assert len(tp._probe_memo) == 0
