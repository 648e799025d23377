"""A prepass built with another seed launches the same kernels: no size, count or scale that
follows the random numbers is baked into a kernel as a literal (each such kernel is compiled
again for every render seed: 0.1–1.2 s a render on scenes_xml/mixed_room.xml and staircase2
before session 16, ``tools/render_recompiles.py --first-seed``).

Kernels are matched by operation count (a kernel whose structure follows the data, such as a
loop run as many times as a bounce finds lanes, is another kernel, compiled once per shape)
and compared by their IR with names and buffer alignment left out (alignment:
tests/test_host_arrays.py). Kernels of fewer than ``MIN_OPERATIONS`` operations are left out:
they compile in a few milliseconds, and some come in two shapes, an input of one element
(read once and broadcast) or of many, which is a finite set of kernels, not one per seed."""
import os
import re

import drjit as dr
import mitsuba as mi
import pytest

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.scenefile import load_scene

#: kernels at least this large are compared (see the module docstring)
MIN_OPERATIONS = 16
SCENES = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(__file__))), "scenes_xml")


def _normalised(ir) -> str:
    text = ir.getvalue() if hasattr(ir, "getvalue") else str(ir)
    return re.sub(r", align \d+", "", re.sub(r"@drjit_[0-9a-f]+", "@kernel", text))


def _kernels(build):
    """{operation count: {normalised IR}} of the JIT kernels ``build()`` launches."""
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()  # clears it
        build()
        dr.sync_thread()
        out = {}
        for k in dr.kernel_history():
            if k["type"] == dr.KernelType.JIT and "ir" in k and \
                    k.get("operation_count", 0) >= MIN_OPERATIONS:
                out.setdefault(k.get("operation_count"), set()).add(_normalised(k["ir"]))
    return out


@pytest.mark.parametrize("name, scene_file", [("radiosity_gather", "mixed_room.xml"),
                                              ("rex", "caustic.xml"),
                                              ("radiance_cache", "caustic.xml")])
def test_prepass_kernels_do_not_follow_the_seed(name, scene_file):
    """mixed_room.xml: a sky and a sun beside area lights (the radiosity solve's emission guide,
    whose pilot batches have a size that follows the seed); caustic.xml: glass and a
    mirror (rex's photon records, whose count and largest flux follow the seed) and the
    radiance cache's clusters (their count follows it)."""
    scene = load_scene(os.path.join(SCENES, scene_file), film_res=24)
    sensor = scene.sensors()[0]
    per_seed = [_kernels(lambda s=seed: mi.load_dict({"type": name}).ensure_prepass(
        scene, s, sensor)) for seed in (1, 2, 3)]
    base = per_seed[0]
    assert base
    for other in per_seed[1:]:
        changed = [ops for ops, irs in other.items() if ops in base and not irs <= base[ops]]
        assert not changed, f"kernels with {changed} operations differ between seeds"


@pytest.mark.parametrize("name", ["radiosity_gather", "spike_gather", "radiance_cache"])
def test_render_kernels_do_not_follow_the_seed(name):
    """A whole render (prepass and sample loop) with another seed launches the same kernels.
    The far gather's r_thresh is a literal of the render loop; measured on the camera's view
    with a jitter that followed the seed, it compiled 1 (radiosity_gather) and 5 (spike_gather)
    kernels again for every render seed (scenes_xml/office.xml, ``render_recompiles.py``).
    radiance_cache's alpha, which ends its paths on the coarse solution, follows the camera's
    shading points the same way (a literal for one commit of session 20: 0.2 s a render)."""
    scene = load_scene(os.path.join(SCENES, "window_interior.xml"), film_res=24)
    per_seed = [_kernels(lambda s=seed: mi.render(scene, integrator=mi.load_dict({"type": name}),
                                                  spp=1, seed=s))
                for seed in (1, 2)]
    base, other = per_seed
    assert base
    changed = [ops for ops, irs in other.items() if ops in base and not irs <= base[ops]]
    assert not changed, f"kernels with {changed} operations differ between seeds"
