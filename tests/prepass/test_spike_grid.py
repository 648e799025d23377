"""Spike lists (Zimmerman & Shirley §4): the self-refining visibility rule against a plain
reference, exclusion of occluded sources, the grid lookup, the conservative contribution
estimate, and the selection pmf (sums to one; reservoir sampling draws from it, chi²)."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

import mi_twopass  # noqa: F401
from mi_twopass.prepass.spike_grid import (INVALID, VIS_ROUND, SpikeSettings, build_sources,
                                           build_spike_grid, estimate_visibility,
                                           grid_geometry)

T = mi.ScalarTransform4f


def rgb(v):
    return {"type": "rgb", "value": [v, v, v] if np.isscalar(v) else list(v)}


def camera(res=16, origin=(0, -1.5, 5), fov=60):
    return {"type": "perspective", "fov": fov,
            "to_world": T().look_at(list(origin), [0, 0, 0], [0, 0, 1]),
            "sampler": {"type": "independent", "sample_count": 4},
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}}


def floor(scale=2.0):
    return {"type": "rectangle", "to_world": T().scale([scale, scale, 1]),
            "bsdf": {"type": "diffuse", "reflectance": rgb(0.5)}}


def sphere_light(center, radius, radiance):
    return {"type": "sphere", "center": list(center), "radius": radius,
            "emitter": {"type": "area", "radiance": rgb(radiance)}}


def closed_box(center, half):
    return {"type": "cube", "to_world": T().translate(list(center)).scale(half),
            "bsdf": {"type": "diffuse", "reflectance": rgb(0.5)}}


# ---------------------------------------------------------------------------------------------
# The self-refining visibility rule (§4) against a plain per-pair reference
# ---------------------------------------------------------------------------------------------
def _reference_rule(hits, max_rays=100, occluded_rays=None):
    """Scalar reference: ``hits[k]`` rays of round k reach the source."""
    H, n, prev = 0, 0, 0.0
    for k, h in enumerate(hits[:max_rays // VIS_ROUND]):
        H += h
        n += VIS_ROUND
        if k == 0 and h == VIS_ROUND:
            return 1.0, n
        if occluded_rays is not None and H == 0 and n >= occluded_rays:
            return 0.0, n
        if k > 0 and h > 1 and abs(h / VIS_ROUND - prev) <= 0.1 + 1e-9:
            return H / n, n
        prev = H / n
    return H / n, n


@pytest.mark.parametrize("max_rays", [100, 40])
def test_self_refining_visibility_matches_the_rule(max_rays):
    rng = np.random.default_rng(4)
    n_pairs = 3000
    p = np.concatenate([np.zeros(500), np.ones(500), rng.uniform(0, 1, 2000)])
    table = rng.binomial(VIS_ROUND, p[:, None], size=(n_pairs, 10))
    table[:50, 0] = 1  # one ray only: the rounds must go on
    table[50:100, :] = 1

    def trace(pairs, k):
        return table[pairs, k]

    g, rays = estimate_visibility(trace, n_pairs, max_rays)
    ref = np.array([_reference_rule(table[i], max_rays) for i in range(n_pairs)])
    assert np.allclose(g, ref[:, 0]) and np.array_equal(rays, ref[:, 1])
    # fully visible: g = 1 after one round; fully occluded: excluded after every ray allowed
    assert np.all(g[500:1000] == 1) and np.all(rays[500:1000] == VIS_ROUND)
    assert np.all(g[100:500] == 0) and np.all(rays[100:500] == max_rays)
    assert np.all(rays[50:100] == max_rays)  # one ray per round never settles
    # partially visible pairs are refined: their g is within a few binomial σ of p
    mid = slice(1000, None)
    sigma = np.sqrt(p[mid] * (1 - p[mid]) / rays[mid]) + 0.05
    assert np.mean(np.abs(g[mid] - p[mid]) < 4 * sigma) > 0.97


def test_pairs_no_ray_reached_are_excluded_after_the_occluded_rays():
    """``occluded_rays``: a pair with no hit after that many rays is done with g = 0; every
    other pair follows the paper's rule unchanged."""
    rng = np.random.default_rng(5)
    n_pairs = 2000
    p = np.concatenate([np.zeros(400), rng.uniform(0, 0.3, 1600)])
    table = rng.binomial(VIS_ROUND, p[:, None], size=(n_pairs, 10))

    def trace(pairs, k):
        return table[pairs, k]

    g, rays = estimate_visibility(trace, n_pairs, 100, occluded_rays=20)
    ref = np.array([_reference_rule(table[i], 100, 20) for i in range(n_pairs)])
    assert np.allclose(g, ref[:, 0]) and np.array_equal(rays, ref[:, 1])
    assert np.all(g[:400] == 0) and np.all(rays[:400] == 20)  # 20 rays, not 100
    g_paper, rays_paper = estimate_visibility(trace, n_pairs, 100)
    first_two = table[:, :2].sum(axis=1)
    same = first_two > 0  # a ray reached the source early: the paper's rule throughout
    assert np.array_equal(g[same], g_paper[same]) and np.array_equal(rays[same], rays_paper[same])
    assert rays.sum() < 0.7 * rays_paper.sum()


# ---------------------------------------------------------------------------------------------
# Lists of a scene
# ---------------------------------------------------------------------------------------------
BLOCKER_XY = np.array([1.2, -1.2])
BOXED = [1.5, 1.5, 1.2]  # its shadow from "visible" falls beyond the floor


@pytest.fixture(scope="module")
def occluded_scene():
    """A floor under a visible sphere light; a sphere light and a point light sealed in a box
    under the floor; a lamp just above a small blocker (a partial shadow)."""
    return mi.load_dict({
        "type": "scene", "sensor": camera(16), "floor": floor(2.0),
        "visible": sphere_light([-0.5, 0.3, 2.5], 0.1, 10.0),
        "sealed": sphere_light([0.5, 0.5, -0.5], 0.05, 50.0),
        "box": closed_box([0.5, 0.5, -0.5], 0.2),
        "sealed_point": {"type": "point", "position": [0.5, 0.5, -0.5], "intensity": rgb(3.0)},
        "blocker": {"type": "rectangle", "bsdf": {"type": "diffuse"},
                    "to_world": T().translate([*BLOCKER_XY, 0.3]).scale(0.2)},
        "lamp": {"type": "point", "position": [*BLOCKER_XY, 0.6], "intensity": rgb(2.0)},
        # above the floor's horizon, so only the visibility rays can exclude it
        "boxed": sphere_light(BOXED, 0.05, 50.0),
        "shell": closed_box(BOXED, 0.15),
    })


def _grid(scene, **kw):
    src = build_sources(scene, None, seed=1)
    settings = SpikeSettings(**{"grid_res": 8, "camera_res": 32, "cell_points": 8, **kw})
    return src, build_spike_grid(scene, src, settings, seed=1)


def test_occluded_sources_are_excluded_and_visible_ones_get_g_one(occluded_scene):
    src, grid = _grid(occluded_scene)
    names = [n for n in src.names]
    visible, sealed, sealed_point, lamp, boxed = (
        names.index(k) for k in ("visible", "sealed", "sealed_point", "lamp", "boxed"))
    lists = [grid.list_of_source(i) for i in range(grid.count)]
    assert grid.count > 10
    pts = [grid.points[grid.point_offsets[i]:grid.point_offsets[i + 1]] for i in range(grid.count)]
    on_floor = [i for i, q in enumerate(pts) if np.any(q[:, 2] < 0.01)]
    assert len(on_floor) > 10 and all(visible in lists[i] for i in on_floor)
    # cells that hold only points of the visible light's own sphere (the camera sees it): it
    # cannot light itself (L' = 0 there), so it is not even a candidate
    centre = np.array([-0.5, 0.3, 2.5])
    on_light = [i for i, q in enumerate(pts) if np.all(np.linalg.norm(q - centre, axis=1) < 0.11)]
    assert on_light and not any(visible in lists[i] for i in on_light)
    assert grid.stats["behind_horizon"] > 0
    # the visible light is seen from every floor sample point away from the blocker's small
    # shadow: g = 1 (10/10 in the first round)
    far = [i for i, q in enumerate(pts) if np.all(q[:, 2] < 0.01)
           and np.all(np.linalg.norm(q[:, :2] - BLOCKER_XY, axis=1) > 0.5)]
    assert len(far) > 10 and all(lists[i][visible] == 1.0 for i in far)
    # the sealed sources are never listed (g = 0 after 100 rays, or behind every point's
    # horizon), nor is the light boxed above the floor, which floor points see above their
    # horizon: the point-sampled visibility excluded it from those cells
    assert not any(k in lst for lst in lists for k in (sealed, sealed_point, boxed))
    assert grid.stats["visibility_excluded"] >= len(on_floor)
    # the partly shadowed lamp: listed somewhere with 0 < g < 1 and with g = 1 elsewhere
    g_lamp = np.array([lst.get(lamp, 0.0) for lst in lists])
    assert np.any((g_lamp > 0) & (g_lamp < 1)) and np.any(g_lamp == 1)
    # (under the floor: culled as behind every floor point's horizon, or g = 0 after 100 rays)
    assert grid.stats["visibility_excluded"] + grid.stats["behind_horizon"] >= 2 * grid.count
    # the sealed point light stays reachable by the defensive mixture
    assert sealed_point in src.delta_ids.tolist()


def test_cells_reached_by_near_gather_rays_get_lists():
    """A camera looking straight down at a floor; a wall stands beside the view. With
    gather_reach, the cells of the wall that the floor's gather rays reach get lists (and every
    bounce point lies within reach); without it, only floor cells do."""
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": T().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "floor": floor(2.0),
        "wall": {"type": "rectangle", "bsdf": {"type": "diffuse"},
                 "to_world": T().translate([1.5, 0, 1]).rotate([0, 1, 0], -90)},
        "lamp": {"type": "point", "position": [0, 0, 1.5], "intensity": rgb(1.0)},
    })
    src = build_sources(scene, None, seed=1)
    base = dict(grid_res=8, camera_res=32, cell_points=8)
    plain = build_spike_grid(scene, src, SpikeSettings(**base), seed=1)
    reach = 1.0
    bounce = build_spike_grid(scene, src, SpikeSettings(**base, gather_reach=reach), seed=1)

    def wall_lists(grid):
        pts = [grid.points[grid.point_offsets[i]:grid.point_offsets[i + 1]]
               for i in range(grid.count)]
        return sum(1 for q in pts if np.any(q[:, 2] > 0.05))

    assert plain.stats["bounce_points"] == 0 and wall_lists(plain) == 0
    assert bounce.stats["bounce_points"] > 0 and wall_lists(bounce) > 0
    assert bounce.count > plain.count
    from mi_twopass.prepass.spike_grid import bounce_points, camera_points
    P, N, _ = camera_points(scene, res=32, seed=1)
    Pb, _, rays = bounce_points(scene, P, N, reach, seed=1)
    assert rays == P.shape[0] and Pb.shape[0] > 0
    assert np.min(np.linalg.norm(Pb[:, None, :] - P[None, :, :], axis=2), axis=1).max() <= reach


def test_cell_lookup_matches_numpy(occluded_scene):
    _, grid = _grid(occluded_scene)
    rng = np.random.default_rng(0)
    p = rng.uniform(-2.5, 2.5, size=(5000, 3))
    cells = np.array(grid.cell_index(mi.Point3f(*(mi.Float(p[:, i]) for i in range(3)))))
    assert np.array_equal(cells, grid.cell_of_np(p))
    # list_at: the list of a cell holding a camera point, INVALID elsewhere
    lid = np.array(grid.list_at(mi.Point3f(*(mi.Float(p[:, i]) for i in range(3)))))
    table = np.full(int(np.prod(grid.dims)), INVALID, np.int64)
    table[grid.list_cell] = np.arange(grid.count)
    assert np.array_equal(lid, table[cells])


def test_non_positive_grid_res_is_refused(occluded_scene):
    for bad in (0, -4):
        with pytest.raises(ValueError, match="grid_res"):
            grid_geometry(occluded_scene, bad)
        with pytest.raises(ValueError, match="grid_res"):
            SpikeSettings(grid_res=bad).validate()


# ---------------------------------------------------------------------------------------------
# The contribution estimate L' is conservative
# ---------------------------------------------------------------------------------------------
def test_estimate_is_positive_wherever_the_source_can_light_the_point():
    """Brute force: sample many points on each source; where any of them lies above the
    receiver's horizon (and, for the one-sided rectangle, in front of it), L' > 0."""
    scene = mi.load_dict({
        "type": "scene",
        "sphere": sphere_light([0.0, 0.0, 0.0], 0.3, 1.0),
        "rect": {"type": "rectangle", "emitter": {"type": "area", "radiance": rgb(1.0)},
                 "to_world": T().translate([2.0, 0, 0]).rotate([0, 1, 0], 30).scale(0.4)},
    })
    src = build_sources(scene, None)
    rng = np.random.default_rng(3)
    n = 4000
    x = rng.uniform(-2, 4, size=(n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    for sid, shape in enumerate(scene.shapes()):
        m = 512
        u = rng.uniform(size=(m, 2))
        ps = shape.sample_position(0.0, mi.Point2f(mi.Float(u[:, 0]), mi.Float(u[:, 1])))
        y = np.array(ps.p).T
        ny = np.array(ps.n).T
        d = y[None, :, :] - x[:, None, :]
        above = np.einsum("nk,nmk->nm", nrm, d) > 1e-6
        front = np.einsum("mk,nmk->nm", ny, -d) > 1e-6
        can = np.any(above & front, axis=1)
        est = np.array(src.estimate(mi.UInt32(np.full(n, sid)),
                                    mi.Point3f(*(mi.Float(x[:, i]) for i in range(3))),
                                    mi.Vector3f(*(mi.Float(nrm[:, i]) for i in range(3))),
                                    mi.Bool(False), 0.0))
        assert np.all(est[can] > 0), (sid, np.count_nonzero(est[can] <= 0))
        assert np.all(np.isfinite(est)) and np.all(est >= 0)
        # and it is not vacuous: points wholly behind the rectangle get 0
        if sid == 1:
            assert np.any(est == 0)


# ---------------------------------------------------------------------------------------------
# Selection: pmf sums to one, sampling follows it
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def many_light_grid():
    rng = np.random.default_rng(7)
    d = {"type": "scene", "sensor": camera(16), "floor": floor(2.0),
         "wall": {"type": "cube", "bsdf": {"type": "diffuse"},
                  "to_world": T().translate([0.2, 0, 0.4]).scale([0.05, 1.5, 0.4])}}
    for i in range(20):
        p = [rng.uniform(-1.8, 1.8), rng.uniform(-1.8, 1.8), rng.uniform(0.2, 1.0)]
        d[f"l{i}"] = sphere_light(p, rng.uniform(0.02, 0.1), rng.uniform(1, 50))
    for i in range(3):
        d[f"p{i}"] = {"type": "point", "position": [rng.uniform(-1.5, 1.5),
                                                    rng.uniform(-1.5, 1.5), 0.6],
                      "intensity": rgb(1.0)}
    scene = mi.load_dict(d)
    src, grid = _grid(scene, grid_res=6)
    return scene, src, grid


def _query_points(grid, n, seed):
    """Random camera-seen sample points with their normals (+z: the floor) and list pairs."""
    rng = np.random.default_rng(seed)
    k = rng.integers(0, grid.points.shape[0], n)
    p = grid.points[k] + rng.uniform(-0.05, 0.05, size=(n, 3)) * [1, 1, 0]
    P = mi.Point3f(*(mi.Float(p[:, i]) for i in range(3)))
    N = mi.Vector3f(0.0, 0.0, 1.0)
    u3 = mi.Point3f(*(mi.Float(rng.uniform(size=n)) for _ in range(3)))
    a, b = grid.choose_lists(P, u3)
    return P, N, a, b


@pytest.mark.parametrize("defensive, support", [(0.0, "delta"), (0.1, "delta"),
                                                (0.1, "emitters")])
def test_selection_pmf_sums_to_one(many_light_grid, defensive, support):
    _, src, grid = many_light_grid
    n, S = 400, src.count
    P, N, a, b = _query_points(grid, n, 1)
    assert np.any(np.array(b) != INVALID)  # some queries mix two lists
    rep = dr.arange(mi.UInt32, n * S) // S
    sid = dr.arange(mi.UInt32, n * S) % S
    pmf = grid.pmf(dr.gather(mi.UInt32, a, rep), dr.gather(mi.UInt32, b, rep),
                   dr.gather(mi.Point3f, P, rep), mi.Vector3f(0, 0, 1), mi.Bool(False), sid, 0.0,
                   defensive, support=support)
    pmf = np.array(pmf).reshape(n, S)
    assert np.all(pmf >= 0) and np.all(np.isfinite(pmf))
    assert np.allclose(pmf.sum(axis=1), 1.0, atol=2e-5)
    # a source in neither list (and not a delta source) is never chosen
    for i in range(0, n, 37):
        listed = set(grid.list_of_source(int(a[i]))) | (
            set(grid.list_of_source(int(b[i]))) if int(b[i]) != INVALID else set())
        if defensive > 0:
            listed |= set(src.support_ids(support).tolist())
        outside = [s for s in range(S) if s not in listed]
        assert np.all(pmf[i, outside] == 0)


@pytest.mark.parametrize("defensive, support", [(0.0, "delta"), (0.1, "delta"),
                                                (0.2, "emitters")])
def test_reservoir_sampling_follows_the_pmf(many_light_grid, defensive, support):
    """Chi² test: one point (a two-list mixture), 200k lanes of :meth:`SpikeGrid.sample`."""
    _, src, grid = many_light_grid
    P1, _, a1, b1 = _query_points(grid, 400, 2)
    mixed = np.nonzero(np.array(b1) != INVALID)[0]
    i = int(mixed[0])
    n = 200_000
    rng = np.random.default_rng(9)
    P = dr.gather(mi.Point3f, P1, dr.full(mi.UInt32, i, n))
    a = dr.full(mi.UInt32, int(a1[i]), n)
    b = dr.full(mi.UInt32, int(b1[i]), n)
    N = mi.Vector3f(0.0, 0.0, 1.0)
    u = [mi.Float(rng.uniform(size=n).astype(np.float32)) for _ in range(3)]
    sid, prob, _, _, _ = grid.sample(a, b, P, N, mi.Bool(False), u[0], u[1], u[2], 0.0,
                                     defensive, support=support)
    sid, prob = np.array(sid), np.array(prob)
    assert np.all(sid != INVALID)
    S = src.count
    at = dr.full(mi.UInt32, i, S)
    pmf = np.array(grid.pmf(dr.full(mi.UInt32, int(a1[i]), S), dr.full(mi.UInt32, int(b1[i]), S),
                            dr.gather(mi.Point3f, P1, at), N, mi.Bool(False),
                            dr.arange(mi.UInt32, S), 0.0, defensive, support=support))
    # the probability returned with each sample is the pmf of the source drawn
    assert np.allclose(prob, pmf[sid], rtol=1e-5)
    counts = np.bincount(sid, minlength=S)
    support = pmf > 0
    assert support.sum() >= 3 and np.all(counts[~support] == 0)
    # pool tiny expected counts, then chi²
    expected = pmf[support].astype(np.float64) * n
    observed = counts[support]
    big = expected >= 5
    exp = np.append(expected[big], expected[~big].sum())
    obs = np.append(observed[big], observed[~big].sum())
    if exp[-1] == 0:
        exp, obs = exp[:-1], obs[:-1]
    exp = exp * (obs.sum() / exp.sum())  # float32 pmf: renormalise the last ulps
    _, pvalue = stats.chisquare(obs, exp)
    assert pvalue > 1e-3, (obs, exp)


@pytest.mark.parametrize("chunk", [1 << 24, 1000])
def test_candidate_pairs_on_the_device_are_the_float64_ones(chunk):
    """The Dr.Jit candidate pairs (one kernel, compressed; in chunks of cells where
    ``chunk`` pairs do not hold them all) equal the numpy float64 reference's, in its order:
    list-major, sources ascending; every BAND_ALL source in every list, no BAND_IMPLICIT one."""
    from types import SimpleNamespace
    from mi_twopass.prepass.spike_grid import (BAND_ALL, BAND_IMPLICIT, BAND_INFLUENCE,
                                               _candidate_pairs_numpy, candidate_pairs)
    rng = np.random.default_rng(7)
    S, L = 300, 200
    band = rng.choice([BAND_IMPLICIT, BAND_INFLUENCE, BAND_INFLUENCE, BAND_ALL], S)
    sources = SimpleNamespace(band=band, center=rng.uniform(-1, 1, (S, 3)),
                              radius=rng.uniform(0.0, 0.05, S),
                              intensity=rng.uniform(0.0, 2.0, S), count=S)
    lo = rng.uniform(-1, 0.9, (L, 3))
    hi = lo + 0.1
    got = candidate_pairs(sources, lo, hi, 10.0, chunk=chunk)
    ref = _candidate_pairs_numpy(sources, lo, hi, 10.0)
    assert 0 < len(ref[0]) < L * S
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])
    assert not np.isin(got[1], np.flatnonzero(band == BAND_IMPLICIT)).any()
    assert np.bincount(got[0], minlength=L).min() >= np.count_nonzero(band == BAND_ALL)


@pytest.mark.parametrize("tail_rays", [0, 5000, 10 ** 9])
def test_the_rounds_left_traced_in_one_call_give_the_same_estimate(tail_rays):
    """``tail_rays``: once a round has at most that many rays, the rounds left are traced at
    once (``trace(pairs, k, rounds)``) and the rule read off them round by round: with the
    same hits per round, g and the rays each pair used are those of one call per round."""
    rng = np.random.default_rng(6)
    n_pairs = 3000
    p = np.concatenate([np.zeros(500), np.ones(500), rng.uniform(0, 1, 2000)])
    table = rng.binomial(VIS_ROUND, p[:, None], size=(n_pairs, 10))
    table[:50, 0] = 1
    calls = []

    def trace(pairs, k, rounds=1):
        calls.append((pairs.size, k, rounds))
        return table[pairs, k:k + rounds] if rounds > 1 else table[pairs, k]

    g_round, rays_round = estimate_visibility(trace, n_pairs, 100, occluded_rays=40)
    per_round = len(calls)
    calls.clear()
    g, rays = estimate_visibility(trace, n_pairs, 100, occluded_rays=40, tail_rays=tail_rays)
    assert np.array_equal(g, g_round) and np.array_equal(rays, rays_round)
    batched = [c for c in calls if c[2] > 1]
    if tail_rays == 0:  # never that few rays: one call per round
        assert not batched and len(calls) == per_round
    else:  # one call for the rest, from the first round with few enough rays
        assert len(batched) == 1 and batched[0][0] * VIS_ROUND <= tail_rays
        assert batched[0][1] + batched[0][2] == 10 and len(calls) < per_round
