"""The ``spike_gather`` integrator (Zimmerman & Shirley 1995): parameters, the consistency limit
against Mitsuba's ``path`` (r_thresh → ∞, complete lists or truncated ones), the paper's
truncation with ``complete = false``, the window's sun, hard cases, stats and debug views.

Statistical tests compare per-block means of independent renders (a fresh prepass each) with a
z-test that accounts for the noise of both images, never with a loose tolerance."""
import os
import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_twopass  # noqa: F401
import mi_twopass.integrators.spike_gather  # noqa: F401  (registers the plugin)
from mi_twopass.prepass.spike_grid import BAND_IMPLICIT

T = mi.ScalarTransform4f
SCENES = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))), "scenes_xml")
#: a small prepass: tests run on 16×16 images
FAST = {"max_patches": 128, "particles_per_patch": 32, "grid_res": 8, "camera_res": 16}
INFINITE = 1e4  # an r_thresh larger than every scene here: the path-tracing limit


def rgb(v):
    return {"type": "rgb", "value": [v, v, v] if np.isscalar(v) else list(v)}


def sensor(res, origin=(0.0, -3.6, 4.6), target=(0, 0.3, 0), fov=68):
    return {"type": "perspective", "fov": fov,
            "to_world": T().look_at(list(origin), list(target), [0, 0, 1]),
            "sampler": {"type": "independent", "sample_count": 4},
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}}


def rooms_scene(res=16, n_rooms=3, lights_per_room=8, seed=1):
    """``n_rooms`` roofless boxes side by side, each with its own lights (a point light, a
    down-facing square lamp, small and tiny bright spheres): most lights are occluded from
    most points, as in the paper's office building."""
    rng = np.random.default_rng(seed)
    d = {"type": "scene", "sensor": sensor(res),
         "floor": {"type": "rectangle", "to_world": T().scale([1 + n_rooms, 2.0, 1]),
                   "bsdf": {"type": "diffuse", "reflectance": rgb([0.5, 0.45, 0.4])}}}
    wall = {"type": "diffuse", "reflectance": rgb(0.7)}
    x0 = -n_rooms
    for k in range(n_rooms + 1):
        d[f"wall_x{k}"] = {"type": "cube", "bsdf": wall, "to_world":
                           T().translate([x0 + 2 * k, 0, 0.5]).scale([0.04, 1.5, 0.5])}
    for side in (-1, 1):
        d[f"wall_y{side}"] = {"type": "cube", "bsdf": wall, "to_world":
                              T().translate([0, side * 1.5, 0.5]).scale([n_rooms, 0.04, 0.5])}
    i = 0
    for k in range(n_rooms):
        cx = x0 + 2 * k + 1
        for j in range(lights_per_room):
            p = [cx + rng.uniform(-0.8, 0.8), rng.uniform(-1.3, 1.3), rng.uniform(0.25, 0.8)]
            if j == 0:
                d[f"point{i}"] = {"type": "point", "position": p,
                                  "intensity": rgb(rng.uniform(0.2, 0.5))}
            elif j == 1:
                d[f"lamp{i}"] = {"type": "rectangle", "to_world": T().translate(
                    [cx, p[1], 0.9]).scale(0.12).rotate([1, 0, 0], 180),
                    "emitter": {"type": "area", "radiance": rgb(rng.uniform(2, 6))}}
            else:
                tiny = j % 3 == 0
                d[f"light{i}"] = {"type": "sphere", "center": p, "radius": 0.02 if tiny else 0.06,
                                  "emitter": {"type": "area", "radiance": rgb(
                                      rng.uniform(40, 80) if tiny else rng.uniform(2, 8))}}
            i += 1
    return d


def render(scene, spp=4, seed=0, **props):
    integrator = mi.load_dict({"type": "spike_gather", **FAST, **props})
    img = np.asarray(mi.render(scene, integrator=integrator, spp=spp, seed=seed))
    return img, integrator


def render_path(scene, spp, seed, max_depth=-1):
    return np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "path", "max_depth": max_depth}), spp=spp, seed=seed))


def blocks(img, b=4, mask=None):
    """Luminance means of b×b blocks (over the pixels of ``mask`` where given)."""
    h, w = img.shape[:2]
    lum = img[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
    m = np.ones((h, w)) if mask is None else mask.astype(np.float64)
    num = (lum * m).reshape(h // b, b, w // b, b).sum(axis=(1, 3))
    den = m.reshape(h // b, b, w // b, b).sum(axis=(1, 3))
    return (num / np.maximum(den, 1)).ravel()


def emitter_free_pixels(scene, n=16):
    """Pixels where none of n×n camera rays sees an emitter directly: the pixel-coverage noise
    of tiny lights seen by the camera is the same for every integrator, and would hide the
    differences the tests look for."""
    cam = scene.sensors()[0]
    w, h = (int(v) for v in cam.film().crop_size())
    k = dr.arange(mi.UInt32, w * h * n * n)
    pix, sub = k // (n * n), k % (n * n)
    x = (mi.Float(pix % w) + (mi.Float(sub % n) + 0.5) / n) / w
    y = (mi.Float(pix // w) + (mi.Float(sub // n) + 0.5) / n) / h
    ray, _ = cam.sample_ray(0.0, 0.5, mi.Point2f(x, y), mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    seen = np.array(dr.reinterpret_array(mi.UInt32, si.emitter(scene)) != 0)
    return ~seen.reshape(h, w, n * n).any(axis=2)


def z_scores(a, b):
    """Per-block z of the difference of two sets of independent renders (K each)."""
    a, b = np.asarray(a), np.asarray(b)
    se = np.sqrt(a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b))
    return (a.mean(axis=0) - b.mean(axis=0)) / np.maximum(se, 1e-12)


# ---------------------------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------------------------
# mi.load_dict wraps the constructor's ValueError in a RuntimeError that ends with its message
@pytest.mark.parametrize("bad", [0, -3])
def test_non_positive_grid_res_fails_at_load_time(bad):
    with pytest.raises(RuntimeError, match=rf"ValueError: grid_res={bad}: must be >= 1$"):
        mi.load_dict({"type": "spike_gather", "grid_res": bad})


@pytest.mark.parametrize("props, message", [
    ({"defensive": 1.0}, "defensive=1.0: must be < 1"),
    ({"e_low": 5.0, "e_high": 1.0}, "e_low=5.0: must be <= e_high=1.0"),
    ({"debug": "cells"}, "debug='cells': expected one of none, list_length, radiosity"),
    ({"visibility_max_rays": 5}, "visibility_max_rays=5: must be >= 10"),
    ({"camera_res": 0}, "camera_res=0: must be >= 1"),
    ({"complete": "maybe"}, "complete='maybe': expected true or false"),
    ({"r_thresh": -1.0}, "r_thresh=-1: must be >= 0"),
    ({"jitter": -0.5}, "jitter=-0.5: must be >= 0"),
    ({"gather_cells": "sometimes"}, "gather_cells='sometimes': expected true or false"),
    ({"elements_per_patch": 0}, "elements_per_patch=0: must be >= 1")])
def test_bad_parameters_fail_at_load_time(props, message):
    with pytest.raises(RuntimeError, match="ValueError: " + re.escape(message) + "$"):
        mi.load_dict({"type": "spike_gather", **props})


# ---------------------------------------------------------------------------------------------
# The consistency limit: r_thresh → ∞ is path tracing with many-light sampling
# ---------------------------------------------------------------------------------------------
#: lists as built by default, and lists truncated on purpose: one visibility sample point per
#: cell, 10 rays per pair, most area lights below E_low, no influence regions
TRUNCATED = {"visibility_max_rays": 10, "cell_points": 1, "e_low_rel": 1.0, "influence": 1e9}


@pytest.fixture(scope="module")
def rooms():
    scene = mi.load_dict(rooms_scene(16))
    mask = emitter_free_pixels(scene)
    K = 8
    path = np.array([blocks(render_path(scene, 4096, 100 + k), mask=mask) for k in range(K)])
    return scene, mask, path


@pytest.mark.parametrize("lists", ["default", "truncated", "partition"])
def test_agrees_with_path_when_r_thresh_is_infinite(rooms, lists):
    """24 lights in 3 boxes, 16×16: per-block means (4×4 pixels, those that see no emitter
    directly) of 8 spike_gather renders (32 spp, a fresh prepass each) against 8 path renders
    (4096 spp). With ``complete`` (default) the estimator is unbiased however the lists were
    truncated, with MIS and the defensive mixture over every emitter (default) or with the
    paper's partition (``mis = false``). (This test catches a 5 % error in the explicit
    estimator through ``z_all``.)"""
    scene, mask, path = rooms
    props = {"r_thresh": INFINITE, **({} if lists == "default" else TRUNCATED),
             **({"mis": False} if lists == "partition" else {})}
    spike = []
    for k in range(len(path)):
        img, integrator = render(scene, spp=32, seed=k, **props)
        assert np.isfinite(img).all()
        spike.append(blocks(img, mask=mask))
    spike = np.array(spike)
    st = integrator.stats
    assert st["cells_with_lists"] > 5 and st["spike_list_max"] >= 1
    if lists != "default":
        assert st["bands"]["implicit"] > 5  # the knobs did truncate
    used = path.mean(axis=0) > 0  # blocks that show the scene
    z = z_scores(spike[:, used], path[:, used])
    # Welch z of 8 + 8 renders (t-like, ~10 degrees of freedom): E[z²] ≈ 1.25
    assert np.mean(z**2) < 4.0, z
    assert np.max(np.abs(z)) < 5.0, z
    z_all = z_scores(spike[:, used].mean(axis=1, keepdims=True),
                     path[:, used].mean(axis=1, keepdims=True))[0]
    assert abs(z_all) < 3.5, z_all


def test_paper_mode_truncates_near_unlisted_sources(rooms):
    """``complete = false`` (the paper) loses the emission of unlisted sources met by near
    implicit rays (§5.3); with truncated lists that is a significant darkening. Paired renders
    (same seed, same prepass): the difference is the truncation alone."""
    scene, _, _ = rooms
    props = {"r_thresh": INFINITE, **TRUNCATED}
    K = 4
    paper = np.array([render(scene, spp=32, seed=k, complete=False, **props)[0].mean()
                      for k in range(K)])
    full = np.array([render(scene, spp=32, seed=k, **props)[0].mean() for k in range(K)])
    d = paper - full
    z = d.mean() / (d.std(ddof=1) / np.sqrt(K))
    truncation = -d.mean() / full.mean()
    assert z < -5 and truncation > 0.05, (z, truncation)


# ---------------------------------------------------------------------------------------------
# Infinite emitters: the window's sun
# ---------------------------------------------------------------------------------------------
def test_window_sun_lights_the_room():
    """window_interior.xml: the directional sun (and the sky) are global sources: the sun is in
    the lists of the cells it reaches, and the direct light agrees with path's (max_depth 2)."""
    scene = mi.load_file(os.path.join(SCENES, "window_interior.xml"), res=16)
    K = 3
    spike, integrator = [], None
    for k in range(K):
        img, integrator = render(scene, spp=16, seed=k, component="direct")
        spike.append(blocks(img))
    pre = integrator.structure
    names = [e.class_name() for e in scene.emitters()]
    sun = names.index("DirectionalEmitter")
    lists_with_sun = np.count_nonzero(pre.grid.source == sun)
    assert lists_with_sun > 0
    assert sun in pre.sources.delta_ids.tolist()
    path = [blocks(render_path(scene, 64, 100 + k, max_depth=2)) for k in range(K)]
    ratio = np.mean(spike) / np.mean(path)
    se = np.hypot(np.std(np.mean(spike, 1), ddof=1), np.std(np.mean(path, 1), ddof=1)) \
        / np.sqrt(K) / np.mean(path)
    assert abs(ratio - 1) < max(4 * se, 0.02), (ratio, se)


# ---------------------------------------------------------------------------------------------
# Hard cases: no NaN / Inf
# ---------------------------------------------------------------------------------------------
def _hard_scene(case):
    rng = np.random.default_rng(5)
    d = {"type": "scene", "sensor": sensor(16, origin=(0, -2.0, 4.0), target=(0, 0, 0), fov=60),
         "floor": {"type": "rectangle", "to_world": T().scale(2.0),
                   "bsdf": {"type": "diffuse", "reflectance": rgb(0.5)}}}
    if case == "zero_power":
        d["dark"] = {"type": "sphere", "center": [0.3, 0, 0.5], "radius": 0.1,
                     "emitter": {"type": "area", "radiance": rgb(0.0)}}
        d["dark_point"] = {"type": "point", "position": [-0.3, 0, 0.5], "intensity": rgb(0.0)}
        d["light"] = {"type": "sphere", "center": [0, 0.5, 1.0], "radius": 0.1,
                      "emitter": {"type": "area", "radiance": rgb(5.0)}}
    elif case == "empty_list":  # a tall wall: the light cannot reach the floor behind it
        d["wall"] = {"type": "cube", "bsdf": {"type": "diffuse"},
                     "to_world": T().translate([0.0, 0, 1.0]).scale([0.05, 2.0, 1.0])}
        d["light"] = {"type": "point", "position": [-1.0, 0, 0.3], "intensity": rgb(2.0)}
    elif case == "light_in_wall":
        d["wall"] = {"type": "cube", "bsdf": {"type": "diffuse"},
                     "to_world": T().translate([0.0, 0, 0.5]).scale([0.2, 2.0, 0.5])}
        d["buried"] = {"type": "sphere", "center": [0.0, 0.0, 0.5], "radius": 0.1,
                       "emitter": {"type": "area", "radiance": rgb(100.0)}}
        d["light"] = {"type": "sphere", "center": [-1.0, 0.5, 1.0], "radius": 0.1,
                      "emitter": {"type": "area", "radiance": rgb(5.0)}}
    elif case == "thousand_lights":
        for i in range(1000):
            p = [rng.uniform(-1.8, 1.8), rng.uniform(-1.8, 1.8), rng.uniform(0.1, 1.5)]
            d[f"l{i}"] = {"type": "sphere", "center": p, "radius": 0.005,
                          "emitter": {"type": "area", "radiance": rgb(rng.uniform(10, 500))}}
    return mi.load_dict(d)


@pytest.mark.parametrize("case", ["zero_power", "empty_list", "light_in_wall",
                                  "thousand_lights", "no_emitter"])
def test_hard_cases_stay_finite(case):
    scene = _hard_scene(case)
    img, integrator = render(scene, spp=4, seed=1)
    assert np.isfinite(img).all()
    if case == "no_emitter":  # a black image is the right answer
        assert img.max() == 0 and integrator.structure.grid.source.size == 0
        return
    assert img.mean() > 0
    pre = integrator.structure
    src, grid = pre.sources, pre.grid
    for a in (src.intensity, src.emittance[np.isfinite(src.emittance)], grid.g):
        assert np.all(np.isfinite(a)) and np.all(np.asarray(a) >= 0)
    names = src.names
    if case == "zero_power":
        dark, dark_point = names.index("dark"), names.index("dark_point")
        assert src.band[dark] == BAND_IMPLICIT  # nothing to sample explicitly
        assert dark not in grid.source and dark_point not in grid.source
        # no defensive sample is wasted on them
        assert dark_point not in src.delta_ids and dark not in src.emitter_ids
    if case == "empty_list":
        assert np.any(grid.lengths == 0)
    if case == "light_in_wall":
        assert names.index("buried") not in grid.source
    if case == "thousand_lights":
        assert np.count_nonzero(src.kind == 0) == 1000 and grid.stats["spike_list_max"] > 20


# ---------------------------------------------------------------------------------------------
# Stats, reuse, determinism, components, debug views
# ---------------------------------------------------------------------------------------------
def test_stats_reuse_components_and_debug_views():
    scene = mi.load_dict(rooms_scene(16, n_rooms=2, lights_per_room=5))
    integrator = mi.load_dict({"type": "spike_gather", **FAST, "r_thresh": 0.0})
    a = np.asarray(mi.render(scene, integrator=integrator, spp=4, seed=3))
    st = integrator.stats
    for key in ("viewing_rays", "implicit_rays", "explicit_rays", "prepass_rays",
                "prepass_seconds", "render_seconds", "cache_bytes", "visibility_rays",
                "spike_list_mean", "spike_list_max", "cells_with_lists", "grid_bytes",
                "fallback_gathers", "behind_horizon", "bounce_points", "elements", "probe_rays"):
        assert key in st, key
    assert 0 <= st["fallback_gathers"] <= st["explicit_rays"]
    assert st["prepass_rays"] >= st["visibility_rays"] + st["probe_rays"] + st["camera_rays"]
    # r_thresh = 0: every gather ray is far, so at most one explicit and one implicit ray per
    # viewing ray (one each per camera ray that hits the scene)
    vr = st["viewing_rays"]
    assert vr == 16 * 16 * 4
    assert 0.25 * vr < st["implicit_rays"] <= vr
    # one explicit ray per non-delta vertex; the gather ray that leaves it is counted unless
    # the path ends there (Russian roulette, depth), which happens once per viewing ray at most
    assert 0.9 * st["implicit_rays"] < st["explicit_rays"] <= st["implicit_rays"] + vr
    assert st["prepass_rays"] >= st["visibility_rays"] > 0
    assert st["cache_bytes"] > st["grid_bytes"] > 0 and st["prepass_seconds"] > 0
    b = np.asarray(mi.render(scene, integrator=integrator, spp=4, seed=3))
    assert integrator.stats["prepass_seconds"] == 0.0 and np.array_equal(a, b)  # reused
    fresh = mi.load_dict({"type": "spike_gather", **FAST, "r_thresh": 0.0})
    assert np.array_equal(a, np.asarray(mi.render(scene, integrator=fresh, spp=4, seed=3)))
    # direct + indirect = all (the same random decisions)
    parts = [np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "spike_gather", **FAST, "r_thresh": 0.0, "component": c}), spp=4, seed=3))
        for c in ("direct", "indirect")]
    assert np.allclose(parts[0] + parts[1], a, rtol=1e-4, atol=1e-6)
    # debug views
    length = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "spike_gather", **FAST, "debug": "list_length"}), spp=1, seed=3))
    assert np.isfinite(length).all() and length.std() > 0 and length.max() <= 1.0
    rad = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "spike_gather", **FAST, "debug": "radiosity"}), spp=1, seed=3))
    assert np.isfinite(rad).all() and rad.mean() > 0


def test_lists_are_built_for_the_sensor_rendered():
    """The lists go to the cells the *rendered* camera sees: two cameras, each looking down
    into another end room of rooms_scene, get lists in disjoint cells (the prepass once built
    them for the first sensor whatever the render's)."""
    d = rooms_scene(n_rooms=3)
    del d["sensor"]
    d["left"] = sensor(16, origin=(-2.0, -0.3, 3.0), target=(-2.0, 0.0, 0.0), fov=40)
    d["right"] = sensor(16, origin=(2.0, -0.3, 3.0), target=(2.0, 0.0, 0.0), fov=40)
    scene = mi.load_dict(d)
    cells = []
    for which in (0, 1):
        integrator = mi.load_dict({"type": "spike_gather", **FAST})
        mi.render(scene, sensor=which, integrator=integrator, spp=1)
        cells.append(set(integrator.structure.grid.list_cell.tolist()))
    assert cells[0] and cells[1]
    assert not cells[0] & cells[1]
