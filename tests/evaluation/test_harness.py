"""Harness bookkeeping (interpolation, time to target, equal-time ratio), its warm-up and image
I/O."""
import os
import sys

import numpy as np
import pytest

from mi_twopass.evaluation import harness, images
from mi_twopass.evaluation.harness import Curve, Point

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import hard_scenes as hs  # noqa: E402


def curve(label, times, errors):
    return Curve(label, [Point(2**i, t, e, 0.1, e) for i, (t, e) in enumerate(zip(times, errors))])


def test_time_to_error_loglog():
    # error ∝ 1/t: 0.04 at 1 s, 0.02 at 2 s, 0.005 at 8 s → 0.01 at exactly 4 s
    c = curve("path", [1, 2, 8], [0.04, 0.02, 0.005])
    assert harness.time_to_error(c.points, 0.01) == pytest.approx(4.0)
    assert harness.time_to_error(c.points, 1e-4) is None
    assert harness.time_to_error(c.points, 0.1) == 1  # already below at the first point


def test_equal_time_ratio_and_speedup():
    path = curve("path", [1, 2, 4, 8], [0.08, 0.04, 0.02, 0.01])
    fast = curve("x", [1, 2, 4], [0.02, 0.01, 0.005])  # 4× lower error at equal time
    curves = {"path": path, "x": fast}
    harness.summarise(curves)
    assert curves["x"].summary["equal_time_ratio"] == pytest.approx(4.0)
    assert curves["path"].summary["equal_time_ratio"] == pytest.approx(1.0)
    assert curves["x"].summary["time_to_target"] == pytest.approx(2.0)
    assert curves["x"].summary["speedup_to_target"] == pytest.approx(4.0)
    assert curves["x"].summary["final_relmse"] == 0.005
    # same spp (1, 2, 4): path 0.02 at 4 spp against 0.005 → 4× better per sample
    assert curves["x"].summary["equal_spp_ratio"] == pytest.approx(4.0)
    assert curves["x"].summary["equal_spp_at"] == 4
    table = harness.format_table(curves)
    assert "4.00" in table and "path" in table


def test_a_held_up_point_of_path_does_not_bend_the_equal_time_ratios():
    # path's 4-spp point held up (0.54 s between 0.011 s and 0.017 s, as on an H200): read
    # off the curve as measured, path's own ratio was 92 and x's came out of that segment
    spp_t = [0.009, 0.011, 0.54, 0.017, 0.025, 0.5]
    path = curve("path", spp_t, [1.4, 0.72, 0.34, 0.17, 0.09, 0.0037])
    x = curve("x", [0.5], [0.0037 / 2])
    curves = {"path": path, "x": x}
    harness.summarise(curves)
    assert harness.envelope_seconds(path.points) == [0.009, 0.011, 0.017, 0.017, 0.025, 0.5]
    assert curves["path"].summary["equal_time_ratio"] == pytest.approx(1.0)
    assert curves["x"].summary["equal_time_ratio"] == pytest.approx(2.0)


def _scripted_renders(monkeypatch, seconds):
    """``harness.timed_render`` replaced by renders whose times are ``seconds`` in turn and
    whose images are constant, run k's value k + 1; returns the calls' arguments."""
    calls = []

    def render(scene, spec, spp, seed):
        k = len(calls)
        calls.append((spec, spp, seed))
        return np.full((2, 2, 3), k + 1.0, np.float32), seconds[k], {"run": k}

    monkeypatch.setattr(harness, "timed_render", render)
    return calls


def test_a_short_point_is_the_run_of_median_time_with_its_own_image(monkeypatch):
    calls = _scripted_renders(monkeypatch, [0.5, 0.2, 0.4])
    ref = np.ones((2, 2, 3), np.float32)
    point, image = harness.timed_point(None, "twopass", 16, 7, ref, repeats=3,
                                       repeat_below=1.0)
    assert calls == [("twopass", 16, 7)] * 3  # the same seed every time
    assert point.seconds == 0.4 and point.stats["run"] == 2  # the median run, not the fastest
    assert np.all(image == 3.0)
    # its metrics are its own image's: (3 − 1)² / (1 + ε)
    assert point.relmse == pytest.approx(4.0 / 1.01)
    assert point.stats["repeat_seconds"] == [0.5, 0.2, 0.4]
    assert point.stats["repeat_relmse"] == pytest.approx([0.0, 1 / 1.01, 4 / 1.01])
    assert point.stats["repeat_kept"] == 2


def test_a_long_point_and_a_single_repeat_render_once(monkeypatch):
    ref = np.ones((2, 2, 3), np.float32)
    calls = _scripted_renders(monkeypatch, [1.5, 0.1, 0.1])
    point, _ = harness.timed_point(None, "path", 256, 0, ref, repeats=3, repeat_below=1.0)
    assert len(calls) == 1 and point.seconds == 1.5 and "repeat_seconds" not in point.stats
    calls = _scripted_renders(monkeypatch, [0.3, 0.1])
    point, _ = harness.timed_point(None, "path", 1, 0, ref, repeats=1)
    assert len(calls) == 1 and point.seconds == 0.3


def test_an_even_count_keeps_the_lower_of_the_middle_two(monkeypatch):
    _scripted_renders(monkeypatch, [0.3, 0.2])
    ref = np.ones((2, 2, 3), np.float32)
    point, _ = harness.timed_point(None, "path", 1, 0, ref, repeats=2, repeat_below=1.0)
    assert point.seconds == 0.2 and point.stats["repeat_kept"] == 1


def test_warm_up_builds_what_a_long_twopass_render_builds():
    """At 1 spp twopass renders path with no pilot; its warm-up plans for a long render, so
    the pilot and the structures it builds are compiled before the timed points (128² px:
    on a 16² film no prepass fits a quarter of even 4096 spp of path, and there is no
    pilot)."""
    import mitsuba as mi

    import mi_twopass  # noqa: F401
    d = hs.box()
    d["sensor"]["film"].update(width=128, height=128)
    scene = mi.load_dict(d)
    short = harness.make_integrator("twopass")
    mi.render(scene, integrator=short, spp=1)
    assert list(short.stats["twopass_candidates"]) == []  # no pilot at 1 spp
    warm = harness.warm_up(scene, "twopass", 7)
    assert warm.planned_spp == harness.WARM_UP_PLANNED_SPP
    assert len(warm.stats["twopass_candidates"]) >= 2  # path's pilot and a structure's
    assert not hasattr(harness.warm_up(scene, "path", 7), "planned_spp")


def test_spec_parsing():
    assert harness.parse_integrator_spec("path") == ("path", {})
    assert harness.parse_integrator_spec("a:r_thresh=0.5:max_depth=3:mode=x") == (
        "a", {"r_thresh": 0.5, "max_depth": 3, "mode": "x"})
    with pytest.raises(ValueError, match=r"^integrator spec 'a:oops': 'oops' is not key=value$"):
        harness.parse_integrator_spec("a:oops")


def test_exr_roundtrip_and_png(tmp_path):
    img = np.random.default_rng(0).uniform(0, 4, (5, 7, 3)).astype(np.float32)
    p = str(tmp_path / "x.exr")
    images.write_exr(p, img)
    assert np.array_equal(images.read_exr(p), img)
    images.write_png(str(tmp_path / "x.png"), img)
    assert (tmp_path / "x.png").stat().st_size > 0
    assert images.srgb_tonemap(np.array([0.0, 1.0, 10.0])).tolist() == [0, 255, 255]
