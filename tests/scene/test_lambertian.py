"""The one rule of which surfaces a cache may stand for (mi_twopass.scene.lambertian)."""
import drjit as dr
import mitsuba as mi
import numpy as np

import mi_twopass  # noqa: F401
from mi_twopass.scene.lambertian import LambertianShapes, is_lambertian, lambertian_flags

T = mi.ScalarTransform4f
DIFFUSE = {"type": "diffuse"}


def bitmap():
    return {"type": "bitmap", "raw": True,
            "data": mi.TensorXf(np.full((4, 4, 3), 0.5, np.float32))}


def test_lambertian_plugins():
    yes = [DIFFUSE, {"type": "twosided", "bsdf": DIFFUSE},
           {"type": "blendbsdf", "weight": 0.3, "bsdf_0": DIFFUSE,
            "bsdf_1": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.1] * 3}}}]
    no = [{"type": "bumpmap", "bsdf": DIFFUSE, "arbitrary": bitmap()},
          {"type": "normalmap", "bsdf": DIFFUSE, "normalmap": bitmap()},
          {"type": "twosided", "bsdf": {"type": "bumpmap", "bsdf": DIFFUSE, "arbitrary": bitmap()}},
          {"type": "blendbsdf", "weight": 0.5, "bsdf_0": DIFFUSE, "bsdf_1": {"type": "conductor"}},
          {"type": "plastic"}, {"type": "principled"}, {"type": "roughconductor"},
          {"type": "dielectric"}, {"type": "thindielectric"},
          {"type": "mask", "opacity": 0.5, "bsdf": DIFFUSE}]
    for d in yes:
        assert is_lambertian(mi.load_dict(d)), d
    for d in no:
        assert not is_lambertian(mi.load_dict(d)), d
    assert not is_lambertian(None)


def test_flags_alone_are_necessary_not_sufficient():
    bump = mi.load_dict({"type": "bumpmap", "bsdf": DIFFUSE, "arbitrary": bitmap()})
    assert lambertian_flags(int(bump.flags()))  # a bump map passes the flag test
    assert not is_lambertian(bump)
    assert not lambertian_flags(int(mi.load_dict({"type": "plastic"}).flags()))
    lanes = lambertian_flags(mi.UInt32([int(mi.load_dict(DIFFUSE).flags()),
                                        int(mi.load_dict({"type": "conductor"}).flags())]))
    assert np.array_equal(np.asarray(lanes), [True, False])


def test_per_lane_table_answers_for_the_shape_hit_and_not_for_instances():
    """Rays down onto three quads (diffuse, bump-mapped, instanced diffuse) and one miss."""
    quad = lambda x, bsdf: {"type": "rectangle", "bsdf": bsdf,  # noqa: E731
                            "to_world": T().translate([x, 0, 0]).scale(0.4)}
    scene = mi.load_dict({
        "type": "scene",
        "a": quad(0.0, DIFFUSE),
        "b": quad(1.0, {"type": "bumpmap", "bsdf": DIFFUSE, "arbitrary": bitmap()}),
        "group": {"type": "shapegroup", "q": {"type": "rectangle", "bsdf": DIFFUSE,
                                              "to_world": T().scale(0.4)}},
        "inst": {"type": "instance", "shape": {"type": "ref", "id": "group"},
                 "to_world": T().translate([2.0, 0, 0])},
    })
    table = LambertianShapes(scene)
    xs = [0.0, 1.0, 2.0, 5.0]
    ray = mi.Ray3f(mi.Point3f(mi.Float(xs), 0.0, 1.0), mi.Vector3f(0, 0, -1))
    si = scene.ray_intersect(ray)
    assert np.array_equal(np.asarray(si.is_valid()), [True, True, True, False])
    assert np.array_equal(np.asarray(table.at(si)), [True, False, False, False])
    assert dr.width(table.d_table) == table.n_ids + 1  # the sentinel entry
