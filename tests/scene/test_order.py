"""The shapes' stable order (mi_twopass.scene.order): prepasses that do not follow the order in
which Mitsuba happens to list a scene's shapes."""
import numpy as np

import mi_twopass  # noqa: F401  (libLLVM + variant before mitsuba/drjit)
import mitsuba as mi

from mi_twopass.prepass.rex_textures import RexTables
from mi_twopass.scene import build_patches
from mi_twopass.scene.order import shape_key, stable_shapes

T = mi.ScalarTransform4f


def room_shapes():
    """A small room's shapes as ``(key, dict)``: a floor, a wall, two spheres and a cube (three
    of them unnamed, as many scene files leave them), and a light. Each mesh has a BSDF of its
    own: Mitsuba merges meshes that share one, in the order they were given."""
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.7, 0.7]}}
    red = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.2, 0.2]}}
    return [
        ("floor", {"type": "rectangle", "id": "floor", "bsdf": white,
                   "to_world": T().scale([2.0, 2.0, 1.0])}),
        ("wall", {"type": "rectangle", "id": "wall", "bsdf": red,
                  "to_world": T().translate([0.0, 2.0, 1.0]).rotate([1, 0, 0], 90)
                  .scale([2.0, 1.0, 1.0])}),
        ("ball_a", {"type": "sphere", "center": [0.5, 0.0, 0.3], "radius": 0.3, "bsdf": white}),
        ("ball_b", {"type": "sphere", "center": [-0.6, 0.4, 0.2], "radius": 0.2, "bsdf": red}),
        ("box", {"type": "cube", "bsdf": {"type": "diffuse"},
                 "to_world": T().translate([0.0, -0.8, 0.25]).scale(0.25)}),
        ("light", {"type": "rectangle", "id": "light",
                   "to_world": T().translate([0.0, 0.0, 1.9]).rotate([1, 0, 0], 180)
                   .scale(0.4),
                   "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 10.0}}}),
    ]


def load(order):
    """The room with its shapes given to Mitsuba in ``order`` (a permutation of their keys)."""
    shapes = dict(room_shapes())
    scene = {"type": "scene"}
    for key in order:
        scene[key] = shapes[key]
    return mi.load_dict(scene)


def test_stable_shapes_is_a_permutation_sorted_by_key():
    scene = load([k for k, _ in room_shapes()])
    order = stable_shapes(scene)
    assert sorted(i for i, _ in order) == list(range(len(scene.shapes())))
    assert all(scene.shapes()[i] is s or scene.shapes()[i] == s for i, s in order)
    keys = [shape_key(s) for _, s in order]
    assert keys == sorted(keys)


def test_prepass_tables_do_not_follow_mitsubas_shape_order():
    """The same room loaded with its shapes listed in two orders: the same stable order, the
    same patches (points drawn with one seed) and the same rexes."""
    keys = [k for k, _ in room_shapes()]
    a, b = load(keys), load(keys[::-1])
    assert [shape_key(s) for _, s in stable_shapes(a)] == \
        [shape_key(s) for _, s in stable_shapes(b)]
    pa = build_patches(a, max_patches=128, seed=5)
    pb = build_patches(b, max_patches=128, seed=5)
    for name in ("center", "area", "albedo", "Le", "exposure", "tri_vertices", "tri_patch"):
        np.testing.assert_array_equal(np.asarray(getattr(pa, name)),
                                      np.asarray(getattr(pb, name)), err_msg=name)
    # a patch's shape index names the same shape in both loads
    names_a = [pa.shape_names[i] for i in pa.shape_index]
    names_b = [pb.shape_names[i] for i in pb.shape_index]
    assert names_a == names_b
    ra, rb = RexTables(a), RexTables(b)
    for name in ("rex_kind", "rex_area", "rex_side", "rex_size_offset"):
        np.testing.assert_array_equal(getattr(ra, name), getattr(rb, name), err_msg=name)
    assert [s.id() for s in ra.shapes] == [s.id() for s in rb.shapes]
