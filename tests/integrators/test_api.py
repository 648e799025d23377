"""The shared machinery of base.py: parameter readers, prepass reuse keyed on what the prepass
depends on, max_depth = 0, and the error dr.backward gives."""
import os

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_twopass.integrators import PLUGINS
from mi_twopass.integrators import base

CORNELL = "scenes_xml/cornell_box.xml"


@pytest.fixture
def cornell(request):
    import os

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    return mi.load_file(os.path.join(root, CORNELL), res=8, spp=4)


# -- readers ----------------------------------------------------------------------------------
def test_read_int_refuses_non_integers_and_accepts_integral_values():
    with pytest.raises(ValueError, match=r"^max_depth=2.5: expected an integer$"):
        base.read_int({"max_depth": 2.5}, "max_depth", -1)
    for bad in ("abc", True, float("nan"), "2.5"):
        with pytest.raises(ValueError, match="max_depth=.*expected an integer"):
            base.read_int({"max_depth": bad}, "max_depth", -1)
    assert base.read_int({"max_depth": 3}, "max_depth", -1) == 3
    assert base.read_int({"max_depth": 3.0}, "max_depth", -1) == 3
    assert base.read_int({"max_depth": " 7 "}, "max_depth", -1) == 7
    assert base.read_int({}, "max_depth", -1) == -1
    with pytest.raises(ValueError, match=r"max_depth=-2: must be >= -1"):
        base.read_int({"max_depth": -2}, "max_depth", -1, minimum=-1)


def test_read_int_maximum_says_what_it_protects():
    why = base.needs_memory(64, "the particle records")
    with pytest.raises(ValueError) as e:
        base.read_int({"n": 1e12}, "n", 1, maximum=1 << 24, why=why)
    assert str(e.value) == "n=1e+12: at most 2^24 (the particle records would need 64 TB)"
    assert base.read_int({"n": 1 << 24}, "n", 1, maximum=1 << 24, why=why) == 1 << 24
    with pytest.raises(ValueError, match=r"^n=11: at most 10 \(a reason\)$"):
        base.read_int({"n": 11}, "n", 1, maximum=10, why="a reason")


def test_read_float_and_bool():
    for bad, msg in ((float("nan"), "must be finite"), (float("inf"), "must be finite"),
                     ("abc", "expected a number"), (True, "expected a number")):
        with pytest.raises(ValueError, match=f"r=.*{msg}"):
            base.read_float({"r": bad}, "r", 0.5)
    assert base.read_float({"r": 2}, "r", 0.5) == 2.0
    assert base.read_float({"r": "0.25"}, "r", 0.5) == 0.25
    with pytest.raises(ValueError, match=r"r=0: must be > 0"):
        base.read_float({"r": 0.0}, "r", 0.5, minimum=0.0, strict=True)
    with pytest.raises(ValueError, match=r"r=3: at most 1"):
        base.read_float({"r": 3.0}, "r", 0.5, maximum=1.0)
    assert base.read_bool({"b": "false"}, "b", True) is False
    assert base.read_bool({"b": "TRUE"}, "b", False) is True
    assert base.read_bool({"b": False}, "b", True) is False
    for bad in ("yes", 1, 0.0):
        with pytest.raises(ValueError, match="b=.*expected true or false"):
            base.read_bool({"b": bad}, "b", True)


def test_load_dict_names_the_parameter():
    """Through Mitsuba's properties: an integer property is read, a bad one named."""
    assert mi.load_dict({"type": "radiosity_gather", "max_depth": 4}).max_depth == 4
    with pytest.raises(RuntimeError, match="max_depth=2.5: expected an integer"):
        mi.load_dict({"type": "radiosity_gather", "max_depth": 2.5})
    with pytest.raises(RuntimeError, match=r"particles_per_patch=1e\+12: at most 2\^24"):
        mi.load_dict({"type": "radiosity_gather", "particles_per_patch": 1e12})
    with pytest.raises(RuntimeError, match=r"max_patches=1e\+09: at most 2\^20 \(building the "
                                           r"patches would need 6 TB\)"):
        mi.load_dict({"type": "radiosity_gather", "max_patches": 1e9})
    with pytest.raises(RuntimeError, match=r"elements_per_patch=100000: at most 2\^12 \(100000 × "
                                           r"max_patches=1024 receiving elements"):
        mi.load_dict({"type": "radiosity_gather", "elements_per_patch": 100000})


# -- prepass reuse ----------------------------------------------------------------------------
def _counting_integrator(uses_camera=True):
    """A TwoPassIntegrator whose prepass only counts its calls and whose estimator is 0.5."""
    from mi_twopass.integrators import base as live  # the module bound to the active variant

    class Counting(live.TwoPassIntegrator):
        PREPASS_USES_CAMERA = uses_camera

        def _read_props(self, props):
            self.builds = 0

        def prepass(self, scene, seed):
            self.builds += 1
            return ("structure", seed)

        def sample(self, scene, sampler, ray, medium=None, active=True):
            return mi.Spectrum(0.5), mi.Bool(True), []

    return Counting(mi.Properties())


def test_prepass_reused_until_something_it_depends_on_changes(cornell):
    integ = _counting_integrator()
    mi.render(cornell, integrator=integ, spp=1)
    mi.render(cornell, integrator=integ, spp=2, seed=0)
    assert integ.builds == 1 and integ.stats["prepass_seconds"] == 0.0
    params = mi.traverse(cornell)
    params["white.reflectance.value"] = mi.Color3f(0.5, 0.5, 0.5)
    params.update()
    mi.render(cornell, integrator=integ, spp=1)
    assert integ.builds == 2  # a BSDF changed
    mi.render(cornell, integrator=integ, spp=1, seed=3)
    assert integ.builds == 3  # another prepass seed
    integ.sample_seed_offset = 17
    mi.render(cornell, integrator=integ, spp=1, seed=3)
    assert integ.builds == 3  # the samplers' offset is not part of the key


def test_camera_is_part_of_the_key_only_where_the_prepass_uses_it(cornell):
    with_camera, without = _counting_integrator(True), _counting_integrator(False)
    for integ in (with_camera, without):
        mi.render(cornell, integrator=integ, spp=1)
    params = mi.traverse(cornell)
    fov = next(k for k in params.keys() if k.endswith("x_fov"))
    params[fov] = params[fov] * 0.5
    params.update()
    for integ in (with_camera, without):
        mi.render(cornell, integrator=integ, spp=1)
    assert with_camera.builds == 2 and without.builds == 1


def test_another_scene_object_gets_its_own_prepass(cornell):
    """A new scene, even one equal to the last (or one that reuses a freed scene's id), is
    never served the last scene's prepass."""
    integ = _counting_integrator()
    mi.render(cornell, integrator=integ, spp=1)
    other = mi.load_file(CORNELL, res=8, spp=4)
    mi.render(other, integrator=integ, spp=1)
    assert integ.builds == 2


def test_fingerprint_sees_parameter_changes(cornell):
    a = base.parameter_fingerprint(cornell)
    assert a == base.parameter_fingerprint(cornell)
    params = mi.traverse(cornell)
    params["light.emitter.radiance.value"] *= 1.0001
    params.update()
    assert base.parameter_fingerprint(cornell) != a


def test_fingerprint_sees_each_kind_of_array_it_copies_in_one_batch():
    """The 32-bit JIT arrays (floats, indices, a texture's tensor, a transform's matrix) are
    copied to the host in one batch: a change of one of them changes the fingerprint, and
    undoing it restores it."""
    scene = mi.load_dict({
        "type": "scene",
        "tri": {"type": "obj", "filename": _tiny_obj()},
        "rect": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {
            "type": "bitmap", "data": mi.TensorXf(np.full((2, 2, 3), 0.5, np.float32))}}}})
    params = mi.traverse(scene)
    keys = {k: v for k, v in params.items()}
    a = base.parameter_fingerprint(scene)
    assert a == base.parameter_fingerprint(scene)
    for key, change in (("tri.faces", lambda v: type(v)([0, 2, 1])),
                        ("rect.bsdf.reflectance.data", lambda v: v * 1.5),
                        ("rect.to_world", lambda v: mi.Transform4f().translate([0, 0, 1]) @ v)):
        assert key in keys
        old = type(params[key])(params[key])
        params[key] = change(params[key])
        params.update()
        assert base.parameter_fingerprint(scene) != a, key
        params[key] = old
        params.update()
        assert base.parameter_fingerprint(scene) == a, key


def _tiny_obj():
    import tempfile
    path = os.path.join(tempfile.mkdtemp(), "tri.obj")
    with open(path, "w") as f:
        f.write("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    return path


def test_emitter_change_rebuilds_a_real_prepass(cornell):
    integ = mi.load_dict({"type": "radiosity_gather", "max_patches": 32,
                          "particles_per_patch": 16, "elements_per_patch": 1})
    a = np.asarray(mi.render(cornell, integrator=integ, spp=4))
    assert integ.stats["prepass_seconds"] > 0
    b = np.asarray(mi.render(cornell, integrator=integ, spp=4))
    assert integ.stats["prepass_seconds"] == 0.0 and np.array_equal(a, b)
    params = mi.traverse(cornell)
    params["light.emitter.radiance.value"] *= 2
    params.update()
    c = np.asarray(mi.render(cornell, integrator=integ, spp=4))
    assert integ.stats["prepass_seconds"] > 0
    assert c.mean() / a.mean() == pytest.approx(2.0, rel=0.02)


# -- max_depth = 0, differentiation -----------------------------------------------------------
@pytest.mark.parametrize("name", sorted(PLUGINS))
def test_max_depth_zero_is_black_without_prepass(name, cornell):
    integ = mi.load_dict({"type": name, "max_depth": 0})
    img = mi.render(cornell, integrator=integ, spp=2)
    ref = mi.render(cornell, integrator=mi.load_dict({"type": "path", "max_depth": 0}), spp=2)
    assert img.shape == ref.shape == (8, 8, 3)
    assert float(dr.max(dr.abs(img.array))[0]) == 0.0
    assert integ.structure is None and integ.stats["prepass_seconds"] == 0.0
    assert integ.stats["viewing_rays"] == 8 * 8 * 2


def test_backward_raises_a_clear_error(cornell):
    integ = mi.load_dict({"type": "radiosity_gather", "max_patches": 32,
                          "particles_per_patch": 16, "elements_per_patch": 1})
    params = mi.traverse(cornell)
    key = "red.reflectance.value"
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(cornell, params, integrator=integ, spp=2, seed=mi.UInt32(1))
    assert float(dr.mean(img.array)[0]) > 0  # the forward render works (detached values)
    with pytest.raises(base.NotDifferentiableError, match="not differentiable.*prb"):
        dr.backward(dr.mean(img.array))


# -- one kernel per render ----------------------------------------------------------------------
@pytest.mark.parametrize("name", [n for n in PLUGINS if n != "twopass"])
def test_a_render_traces_its_paths_once(cornell, name):
    """The ray counters are reductions: unless the image is scheduled with them, evaluating
    them runs the whole path loop once more (radiosity_gather cost 2.5x ``path`` per sample on
    the office instead of 1.5x, radiance_cache 5.2x instead of 2.4x). With the prepass reused,
    a render launches exactly one full-width kernel that traces paths (one with more than
    ``LOOP_OPS`` operations: the loops have > 1000, the film's and the counters' small kernels
    < 100)."""
    LOOP_OPS = 500
    integ = mi.load_dict({"type": name})
    np.asarray(mi.render(cornell, integrator=integ, spp=4, seed=0))  # prepass, compilation
    dr.kernel_history_clear()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        np.asarray(mi.render(cornell, integrator=integ, spp=4, seed=0))
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    lanes = 8 * 8 * 4
    loops = [k for k in history if k.get("size") == lanes
             and (k.get("operation_count") or 0) > LOOP_OPS]
    assert len(loops) == 1, [(k.get("size"), k.get("operation_count")) for k in history]
