"""twopass's pilot (mi_twopass.compose.pilot): pixels, samples, variance and cost per sample."""
import os
import sys

import mitsuba as mi
import numpy as np
import pytest

import mi_twopass  # noqa: F401
from mi_twopass.compose import pilot as pl

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
import hard_scenes as hs  # noqa: E402


def test_pixels_are_distinct_and_the_whole_film_when_it_is_small(tiny_scene_file):
    scene = mi.load_file(tiny_scene_file)
    sensor = scene.sensors()[0]
    all_px = pl.choose_pixels(sensor, 4096, seed=0)
    assert all_px.film_pixels == 256 and np.array_equal(all_px.index, np.arange(256))
    some = pl.choose_pixels(sensor, 100, seed=0)
    assert len(np.unique(some.index)) == 100 and some.index.max() < 256


def test_pilot_of_a_constant_estimator_has_zero_variance_and_positive_cost(tiny_scene_file):
    scene = mi.load_file(tiny_scene_file)
    sensor = scene.sensors()[0]
    px = pl.choose_pixels(sensor, 64, seed=1)
    run = pl.pilot(scene, sensor, px, pl.PilotSettings(pixels=64, samples=36),
                   lambda s, sampler, ray, active: mi.Spectrum(0.25), seed=0)
    assert run.values.shape == (64, 36, 3)
    assert np.allclose(run.values, 0.25)  # box filter, unit importance weights
    assert pl.relative_variance(run.values, pl.pixel_means(run.values)) == pytest.approx(0.0)
    assert run.seconds_per_lane > 0
    assert run.lanes == pl.pilot_samples(pl.PilotSettings(pixels=64, samples=36), px) == 64 * 36


def test_cost_per_sample_leaves_the_fixed_part_of_a_call_out(tiny_scene_file):
    """An estimator whose every call costs 50 ms of tracing, whatever its lanes (many_lights'
    path pilot: 60 % of a 4M run), and next to nothing per lane: the pilot's cost per lane
    must not charge the 50 ms to the lanes (it put path at 3.4x its render's cost there)."""
    import time

    scene = mi.load_file(tiny_scene_file)
    sensor = scene.sensors()[0]
    px = pl.choose_pixels(sensor, 64, seed=1)
    settings = pl.PilotSettings(pixels=64, samples=36)

    def slow_to_trace(s, sampler, ray, active):
        time.sleep(0.05)
        return mi.Spectrum(0.25)

    run = pl.pilot(scene, sensor, px, settings, slow_to_trace, seed=0)
    lanes = 64 * 36
    assert run.seconds_per_lane * lanes < 0.3 * 0.05
    assert run.seconds_per_lane > 0


def test_relative_variance_is_the_relmse_of_one_sample():
    rng = np.random.default_rng(0)
    ref = np.full((500, 3), 2.0)
    values = ref[:, None, :] + rng.normal(0.0, 0.5, size=(500, 200, 3))
    # s² / (R² + ε) = 0.25 / 4.01
    assert pl.relative_variance(values, ref) == pytest.approx(0.25 / 4.01, rel=0.03)


def test_path_is_measured_against_the_other_pilots_so_its_fireflies_are_not_normalised_away():
    """Path: value 1 with probability 1 - 1/1000, else a firefly of 1001 (mean 2), 144 samples
    a pixel; a smooth candidate: N(2, 0.1²). Against its own means, or the average of its and
    the candidate's, path's relative variance is capped near n per firefly pixel; against the
    candidate's means it is near the truth."""
    rng = np.random.default_rng(3)
    pixels, n = 2000, 144
    fire = rng.random((pixels, n, 1)) < 1e-3
    path = np.repeat(np.where(fire, 1001.0, 1.0), 3, axis=2)
    cand = rng.normal(2.0, 0.1, (pixels, n, 3))
    true_v = (1e-3 * 999e-3 * 1000.0**2) / (2.0**2 + 0.01)  # Bernoulli variance / (R² + ε)
    own = pl.relative_variance(path, pl.pixel_means(path))
    plain = pl.relative_variance(path, 0.5 * (pl.pixel_means(path) + pl.pixel_means(cand)))
    against_others = pl.relative_variance(path, pl.path_reference(path, [cand]))
    assert own < 0.3 * true_v and plain < 0.5 * true_v
    assert against_others == pytest.approx(true_v, rel=0.2)
    assert np.array_equal(pl.path_reference(path, []), pl.pixel_means(path))  # no others


def test_blocks_lie_on_checks_grid_inside_the_film_listed_block_by_block():
    def sensor(w, h):
        return mi.load_dict({"type": "perspective", "film": {"type": "hdrfilm", "width": w,
                                                             "height": h}})

    blocks = pl.choose_blocks(sensor(44, 20), 3, 8, seed=1)  # 5 x 2 whole blocks
    idx = blocks.index.astype(np.int64).reshape(3, 64)
    rows, cols = idx // 44, idx % 44
    for r, c in zip(rows, cols):  # each block: one 8 x 8 square on the grid, row-major
        assert r[0] % 8 == 0 and c[0] % 8 == 0 and r.max() < 16 and c.max() < 40
        assert np.array_equal(r - r[0], np.repeat(np.arange(8), 8))
        assert np.array_equal(c - c[0], np.tile(np.arange(8), 8))
    assert len({(r[0], c[0]) for r, c in zip(rows, cols)}) == 3
    assert len(pl.choose_blocks(sensor(44, 20), 100, 8, seed=1).index) == 10 * 64
    # a film smaller than a block: the whole film, one block
    assert np.array_equal(pl.choose_blocks(sensor(6, 5), 4, 8, 0).index, np.arange(30))


def test_the_render_probe_splits_paths_time_into_a_fixed_part_and_one_per_sample():
    """One timed 1-spp render, its kernels' compilation taken off: its prediction of a 16-spp
    render is the right size (within 4x either way on a loaded 2-core machine)."""
    import time

    d = hs.box()
    d["sensor"] = hs.sensor([0, 0, 3.5], [0, 0, 0], res=64)
    scene = mi.load_dict(d)
    integ = mi.load_dict({"type": "path", "max_depth": 6})
    probe = pl.probe_render(scene, scene.sensors()[0], integ, 3)
    assert probe.fixed >= 0.0 and probe.per_spp > 0.0
    t0 = time.perf_counter()
    np.asarray(integ.render(scene, spp=16, seed=5))
    seconds = time.perf_counter() - t0
    assert 0.25 * seconds < probe.seconds(16) < 4.0 * seconds


def test_a_short_render_gets_a_smaller_pilot_never_below_the_floor():
    """pixel_count: the settings' pixels where their 144 samples each are at most PIXEL_SHARE
    of the render's samples; fewer for a short render, down to MIN_PIXELS; never more than the
    settings ask for."""
    s = pl.PilotSettings(pixels=1024, samples=144)
    per_pixel = 144
    film = 256 * 256
    assert pl.pixel_count(s, 256, film) == 1024
    spp = 16
    assert pl.pixel_count(s, spp, film) == int(pl.PIXEL_SHARE * spp * film / per_pixel) < 1024
    assert pl.pixel_count(s, spp, film) * per_pixel <= pl.PIXEL_SHARE * spp * film
    assert pl.pixel_count(s, 1, film) == pl.MIN_PIXELS
    assert pl.pixel_count(pl.PilotSettings(pixels=64, samples=144), 1, film) == 64


def test_samples_are_stored_channel_major_and_joined_as_concatenated():
    """samples_array: lanes sample-minor, pixel-major → values[p, s, c], read through a view
    whose samples are contiguous per channel (the pilot's reductions run over them);
    join_samples: np.concatenate along the samples, same layout."""
    P, S = 5, 7
    lanes = np.arange(P * S, dtype=np.float32)
    spectrum = mi.Color3f(mi.Float(lanes), mi.Float(lanes + 1000), mi.Float(lanes + 2000))
    px = pl.PilotPixels(index=np.arange(P, dtype=np.uint32), width=P, height=1)
    v = pl.samples_array(spectrum, px, S)
    assert v.shape == (P, S, 3)
    assert v[3, 4, 0] == 3 * S + 4 and v[3, 4, 2] == 2000 + 3 * S + 4
    assert v.strides[1] == v.itemsize  # samples contiguous
    w = pl.samples_array(spectrum, px, S) + 0.5
    joined = pl.join_samples([v, w])
    assert np.array_equal(joined, np.concatenate([v, w], axis=1))
    assert joined.strides[1] == joined.itemsize
