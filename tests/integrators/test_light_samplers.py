"""Direct light behind one interface (mi_twopass/integrators/light_samplers.py): each sampler's
``pmf`` is the probability its ``sample`` drew with and sums to one; the generic direct-light
halves equal Mitsuba's fused ones for Mitsuba's emitter choice; and direct light estimated with
the spike lists has the same expectation as with Mitsuba's choice (only the variance differs)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_twopass  # noqa: F401
from mi_twopass.integrators.light_samplers import (EmitterSampler, SpikeListSampler,
                                                   emission_mis, receiver, sample_emitter_mis)
from mi_twopass.integrators.pathtrace import emission_mis as fused_emission_mis
from mi_twopass.integrators.pathtrace import emitter_sample_mis as fused_emitter_sample_mis
from mi_twopass.prepass.spike_grid import INVALID, SpikeSettings, build_sources, build_spike_grid

T = mi.ScalarTransform4f


def _rgb(v):
    return {"type": "rgb", "value": [v, v, v]}


@pytest.fixture(scope="module")
def lit_floor():
    """A diffuse floor under 12 sphere lights of different sizes and radiances and a wall
    that hides some of them from part of the floor, with its spike lists (emitters only)."""
    rng = np.random.default_rng(3)
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 60,
                    "to_world": T().look_at([0, -1.5, 5], [0, 0, 0], [0, 0, 1]),
                    "film": {"type": "hdrfilm", "width": 16, "height": 16}},
         "floor": {"type": "rectangle", "to_world": T().scale([2, 2, 1]),
                   "bsdf": {"type": "diffuse", "reflectance": _rgb(0.5)}},
         "wall": {"type": "cube", "bsdf": {"type": "diffuse"},
                  "to_world": T().translate([0.2, 0, 0.4]).scale([0.05, 1.5, 0.4])}}
    for i in range(12):
        d[f"l{i}"] = {"type": "sphere", "radius": float(rng.uniform(0.03, 0.1)),
                      "center": [float(rng.uniform(-1.6, 1.6)), float(rng.uniform(-1.6, 1.6)),
                                 float(rng.uniform(0.3, 1.0))],
                      "emitter": {"type": "area", "radiance": _rgb(float(rng.uniform(1, 40)))}}
    scene = mi.load_dict(d)
    src = build_sources(scene, None, seed=1)
    grid = build_spike_grid(scene, src, SpikeSettings(grid_res=6, camera_res=32, cell_points=8),
                            seed=1)
    return scene, grid


def _floor_points(scene, n, seed):
    """``n`` surface interactions on the floor (hit from above) in its central part."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1.5, 1.5, size=(n, 2)).astype(np.float32)
    o = mi.Point3f(mi.Float(xy[:, 0]), mi.Float(xy[:, 1]), mi.Float(2.5))
    si = scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(0, 0, -1)))
    assert bool(dr.all(si.is_valid()))
    return si


def _sampler(n, seed=0):
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    return sampler


@pytest.mark.parametrize("selection", SpikeListSampler.SELECTIONS)
def test_spike_sampler_pmf_is_what_it_sampled_with_and_sums_to_one(lit_floor, selection):
    scene, grid = lit_floor
    lights = SpikeListSampler(grid, len(scene.emitters()), r_thresh=0.0, defensive=0.1,
                              selection=selection)
    n, S = 256, grid.sources.count
    si = _floor_points(scene, n, 1)
    bsdf = si.bsdf()
    nr, two = receiver(si, bsdf)
    sid, P, ctx = lights.sample(si, nr, two, _sampler(n), mi.Bool(True))
    sid_np, P_np = np.array(sid), np.array(P)
    assert np.all(sid_np != INVALID) and np.all(P_np > 0)
    assert np.array(ctx.has_list).mean() > 0.5  # the lists, not the fallback, chose mostly
    np.testing.assert_allclose(np.array(lights.pmf(ctx, sid, mi.Bool(True))), P_np, rtol=1e-5)
    # over every source, the pmf at each point sums to one
    rep = dr.arange(mi.UInt32, n * S) // S
    every = dr.arange(mi.UInt32, n * S) % S
    ctx_rep = dr.gather(type(ctx), ctx, rep)
    pmf = np.array(lights.pmf(ctx_rep, every, mi.Bool(True))).reshape(n, S)
    assert np.all(pmf >= 0)
    np.testing.assert_allclose(pmf.sum(axis=1), 1.0, atol=2e-5)


def test_spike_sampler_falls_back_to_a_uniform_emitter_without_a_list(lit_floor):
    scene, grid = lit_floor
    N = len(scene.emitters())
    lights = SpikeListSampler(grid, N, r_thresh=0.0)
    n = 64
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.p = mi.Point3f(50.0, 50.0, 50.0)  # far outside the grid: no cell, no list
    sid, P, ctx = lights.sample(si, mi.Vector3f(0, 0, 1), mi.Bool(False), _sampler(n),
                                mi.Bool(True))
    assert not np.any(np.array(ctx.has_list))
    assert np.all(np.array(sid) < N)
    np.testing.assert_allclose(np.array(P), 1.0 / N)
    np.testing.assert_allclose(np.array(lights.pmf(ctx, sid, mi.Bool(True))), 1.0 / N)


def test_emitter_sampler_sample_and_pmf_agree(lit_floor):
    scene, _ = lit_floor
    lights = EmitterSampler(scene)
    N = len(scene.emitters())
    n = 60_000
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    sid, P, _ = lights.sample(si, mi.Vector3f(0, 0, 1), mi.Bool(False), _sampler(n),
                              mi.Bool(True))
    counts = np.bincount(np.array(sid), minlength=N)
    pmf = np.array(lights.pmf((), dr.arange(mi.UInt32, N), mi.Bool(True)))
    np.testing.assert_allclose(pmf.sum(), 1.0, rtol=1e-6)
    # (a uniform choice returns P as one value for every lane)
    np.testing.assert_allclose(np.array(P + dr.zeros(mi.Float, n)), pmf[np.array(sid)], rtol=1e-6)
    # counts within 5 sigma of the pmf
    sigma = np.sqrt(n * pmf * (1 - pmf))
    assert np.all(np.abs(counts - n * pmf) < 5 * sigma)
    # every emitter's pointer maps back to its source id
    ids = lights.source_of_emitter(scene.emitters_dr(), mi.Bool(True))
    assert np.array(ids).tolist() == list(range(N))


def test_generic_emission_weight_is_mitsubas_for_its_emitter_choice(lit_floor):
    """The BSDF side of MIS: the generic weight with EmitterSampler equals
    ``Scene::pdf_emitter_direction``'s, value for value."""
    scene, _ = lit_floor
    lights = EmitterSampler(scene)
    n = 4096
    prev = _floor_points(scene, n, 2)
    bsdf = prev.bsdf()
    sampler = _sampler(n, 5)
    bs, _ = bsdf.sample(mi.BSDFContext(), prev, sampler.next_1d(), sampler.next_2d())
    si = scene.ray_intersect(prev.spawn_ray(prev.to_world(bs.wo)))
    hit_light = np.array(si.emitter(scene) != None).mean()  # noqa: E711 (a pointer array)
    assert hit_light > 0.01
    delta = mi.Bool(np.arange(n) % 7 == 0)
    ours = emission_mis(lights, scene, (), si, prev, bs.pdf, delta, mi.Bool(True))
    theirs = fused_emission_mis(scene, si, prev, bs.pdf, delta, mi.Bool(True))
    np.testing.assert_allclose(np.array(ours), np.array(theirs), rtol=1e-5, atol=1e-7)


def _direct_mean(lights, scene, si, bsdf, k, fused=False):
    """Mean and standard error of ``k`` direct-light estimates at each of the points ``si``:
    both MIS strategies, the sampler's explicit sample and a BSDF sample whose emitter hit is
    weighted against it (either half alone depends on the sampler through its MIS weight)."""
    n = dr.width(si)
    idx = dr.arange(mi.UInt32, n * k) // k
    si_k = dr.gather(type(si), si, idx)
    bsdf_k = dr.gather(mi.BSDFPtr, bsdf, idx)
    sampler = _sampler(n * k, 11)
    ctx = mi.BSDFContext()
    on = mi.Bool(True)
    if fused:
        Ld, _ = fused_emitter_sample_mis(scene, si_k, bsdf_k, ctx, sampler.next_2d(), on)
    else:
        Ld, _, here = sample_emitter_mis(lights, scene, si_k, bsdf_k, ctx, sampler, on)
    bs, weight = bsdf_k.sample(ctx, si_k, sampler.next_1d(), sampler.next_2d(), on)
    hit = scene.ray_intersect(si_k.spawn_ray(si_k.to_world(bs.wo)))
    delta = mi.Bool(False)
    if fused:
        Le = fused_emission_mis(scene, hit, si_k, bs.pdf, delta, on)
    else:
        Le = emission_mis(lights, scene, here, hit, si_k, bs.pdf, delta, on)
    v = np.array(Ld + weight * Le).T.reshape(n, k, 3).mean(axis=2)
    return v.mean(axis=1), v.std(axis=1) / np.sqrt(k)


@pytest.mark.parametrize("selection", SpikeListSampler.SELECTIONS)
def test_spike_lists_and_mitsubas_choice_estimate_the_same_direct_light(lit_floor, selection):
    """Unbiasedness of the interface: the same estimator (one source, the emitter's own
    direction sampling and a shadow ray, one BSDF sample, MIS between them) with either
    sampler; the point means agree within their errors (z-test over 32 points)."""
    scene, grid = lit_floor
    si = _floor_points(scene, 32, 4)
    bsdf = si.bsdf()
    k = 20_000
    spike = SpikeListSampler(grid, len(scene.emitters()), r_thresh=0.0, defensive=0.1,
                             selection=selection)
    m_s, e_s = _direct_mean(spike, scene, si, bsdf, k)
    m_u, e_u = _direct_mean(EmitterSampler(scene), scene, si, bsdf, k)
    m_f, e_f = _direct_mean(None, scene, si, bsdf, k, fused=True)
    assert np.all(m_s > 0)
    for m, e in ((m_s, e_s), (m_u, e_u)):
        z = (m - m_f) / np.sqrt(e ** 2 + e_f ** 2)
        assert np.max(np.abs(z)) < 4.5, z
        # and on the whole set of points: no common drift
        assert abs(z.mean()) * np.sqrt(z.size) < 4.0
    # the lists' point: less noise than the uniform choice on this scene
    assert np.median(e_s / e_u) < 1.0


def test_cell_selection_draws_by_its_table(lit_floor):
    """Chi²-free check of the per-cell CDF: at one list, 100k draws land on each entry with the
    tabled probability (within 5 sigma), and only on listed sources."""
    scene, grid = lit_floor
    lid = int(np.argmax(grid.lengths))
    a, b = int(grid.offsets[lid]), int(grid.offsets[lid + 1])
    n = 100_000
    u = mi.Float(np.random.default_rng(2).uniform(size=n).astype(np.float32))
    sid, e = grid.cell_pick(dr.full(mi.UInt32, lid, n), u)
    sid, e = np.array(sid), np.array(e)
    prob = np.array(grid._tables["cell_prob"])[a:b]
    np.testing.assert_allclose(prob.sum(), 1.0, rtol=1e-5)
    assert np.all((e >= a) & (e < b)) and np.all(sid == grid.source[e])
    counts = np.bincount(e - a, minlength=b - a)
    sigma = np.sqrt(n * prob * (1 - prob)) + 1.0
    assert np.all(np.abs(counts - n * prob) < 5 * sigma)
