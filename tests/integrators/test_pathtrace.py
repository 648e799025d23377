"""The shared per-vertex steps of mi_twopass/integrators/pathtrace.py."""
import numpy as np
import pytest

import mi_twopass  # noqa: F401
import drjit as dr
import mitsuba as mi

from mi_twopass.integrators.pathtrace import (by_component, emitter_sample_mis,
                                              first_nondelta_hit, mis_weight, russian_roulette)


def test_mis_weights_of_two_strategies_sum_to_one_and_are_finite():
    a = mi.Float([0.0, 1.0, 2.0, 1e-10, np.inf, 0.0])
    b = mi.Float([1.0, 1.0, 0.5, 1e10, 1.0, 0.0])
    wa, wb = np.array(mis_weight(a, b)), np.array(mis_weight(b, a))
    assert np.all(np.isfinite(wa)) and np.all(np.isfinite(wb))
    np.testing.assert_allclose((wa + wb)[:4], 1.0, rtol=1e-6)
    assert wa[0] == 0.0 and wa[1] == pytest.approx(0.5) and wa[2] == pytest.approx(16 / 17)
    assert wa[5] == 0.0 and wb[5] == 0.0  # both pdfs 0: no weight, no NaN


def test_russian_roulette_keeps_the_expected_throughput():
    n = 200_000
    beta = mi.Spectrum(0.3, 0.2, 0.1)
    beta = dr.zeros(mi.Spectrum, n) + beta
    rng = mi.PCG32(size=n)
    out, survive = russian_roulette(beta, mi.Float(1.0), mi.Bool(True), rng.next_float32())
    kept = np.array(dr.select(survive, out, 0.0))
    np.testing.assert_allclose(kept.mean(axis=-1), [0.3, 0.2, 0.1], rtol=0.02)
    # lanes where it is off pass through untouched
    out, survive = russian_roulette(beta, mi.Float(1.0), mi.Bool(False), mi.Float(0.99))
    assert bool(dr.all(survive)) and np.allclose(np.array(out)[..., 0], [0.3, 0.2, 0.1])


def test_by_component_splits_direct_and_indirect():
    v = mi.Spectrum(1.0)
    is_direct = mi.Bool([True, False])
    assert np.array(by_component(v, is_direct, True, False))[0].tolist() == [1.0, 0.0]
    assert np.array(by_component(v, is_direct, False, True))[0].tolist() == [0.0, 1.0]
    assert np.array(by_component(v, is_direct, True, True))[0].tolist() == [1.0, 1.0]


def _mirror_scene():
    """A camera looking down at a mirror (45°) that shows a diffuse floor lit by a point light
    under the mirror."""
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 5,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0, 5], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 4, "height": 4}},
        "mirror": {"type": "rectangle", "bsdf": {"type": "conductor", "material": "none"},
                   "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 45)},
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"},
                  "to_world": mi.ScalarTransform4f().translate([0, -3, 0])
                  @ mi.ScalarTransform4f().rotate([1, 0, 0], -90)
                  @ mi.ScalarTransform4f().scale(5)},
        "light": {"type": "point", "position": [0, -1, 0], "intensity": 1.0},
    })


def test_first_nondelta_hit_follows_the_mirror_to_the_floor():
    scene = _mirror_scene()
    n = 16
    zero = dr.zeros(mi.Float, n)
    ray = mi.Ray3f(mi.Point3f(zero, zero, zero + 5), mi.Vector3f(zero, zero, zero - 1))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, n)
    si, _, beta, Le, found = first_nondelta_hit(scene, sampler, ray, mi.Bool(True))
    assert bool(dr.all(found))
    np.testing.assert_allclose(np.array(si.p.y), -3.0, atol=1e-3)  # on the floor
    np.testing.assert_allclose(np.array(beta), 1.0, rtol=1e-4)  # a perfect mirror
    assert np.array(Le).max() == 0.0

    # and one emitter sample there sees the point light: f·I·cos/r² with f = 0.5/π
    ctx = mi.BSDFContext()
    Ld, cast = emitter_sample_mis(scene, si, si.bsdf(), ctx, mi.Point2f(0.5, 0.5), found)
    assert bool(dr.all(cast))
    expected = 0.5 / np.pi * 1.0 / 4.0  # light 2 m straight above the floor point (0, -3, 0)
    np.testing.assert_allclose(np.array(Ld)[0], expected, rtol=1e-3)


def test_an_occluded_emitter_sample_counts_as_a_shadow_ray():
    scene = mi.load_dict({
        "type": "scene", "floor": {"type": "rectangle"},
        "blocker": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, 1])},
        "light": {"type": "point", "position": [0, 0, 2]}})
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.p, si.n = mi.Point3f(0, 0, 1e-3), mi.Vector3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(si.n)
    si.wi = mi.Vector3f(0, 0, 1)
    bsdf = mi.load_dict({"type": "diffuse"})
    Ld, cast = emitter_sample_mis(scene, si, bsdf, mi.BSDFContext(), mi.Point2f(0.5, 0.5),
                                  mi.Bool(True))
    assert bool(dr.all(cast)) and np.array(Ld).max() == 0.0
