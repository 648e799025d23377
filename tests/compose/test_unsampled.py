"""Light path cannot sample (mi_twopass.compose.unsampled): a sun through a glass pane.

A grey floor lit by a sun straight down through a 1 m² hole in a black roof, the camera under
the roof looking at the floor. The floor receives only the sun (the roof is black), so the
image's mean with the hole open is the sun patch's radiance seen by the camera, and ``path``
renders it. With a thin glass pane in the hole, ``path`` renders nothing of it (its shadow
rays stop at the pane), while the light there is the pane's transmittance T = (1 − R)/(1 + R)
at normal incidence (R = ((η − 1)/(η + 1))², η of Mitsuba's default BK7 glass in air) times
the open one: what the estimate must find."""
import math
import warnings

import numpy as np
import pytest

import mi_twopass  # noqa: F401  (libLLVM + variant before mitsuba/drjit)
import mitsuba as mi

from mi_twopass.compose import unsampled as U

T = mi.ScalarTransform4f
ETA = 1.5046 / 1.000277  # thindielectric's default int_ior (bk7) over ext_ior (air)
REFLECTANCE = ((ETA - 1.0) / (ETA + 1.0)) ** 2
TRANSMITTANCE = (1.0 - REFLECTANCE) / (1.0 + REFLECTANCE)


def diffuse(value):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": value}}


def slab(cx, cy, z, hx, hy, value=0.0):
    return {"type": "cube", "to_world": T().translate([cx, cy, z]).scale([hx, hy, 0.01]),
            "bsdf": diffuse(value)}


def sun_room(pane: str | None, emitter=None):
    """The module docstring's scene; ``pane``: the hole's BSDF plugin, None for an open hole."""
    d = {
        "type": "scene",
        "integrator": {"type": "path"},
        "floor": slab(0, 0, 0, 2, 2, 0.5),
        "roof_l": slab(-2.75, 0, 1, 2.25, 5),
        "roof_r": slab(2.75, 0, 1, 2.25, 5),
        "roof_f": slab(0, -2.75, 1, 0.5, 2.25),
        "roof_b": slab(0, 2.75, 1, 0.5, 2.25),
        "sun": emitter or {"type": "directional", "direction": [0, 0, -1],
                           "irradiance": {"type": "rgb", "value": 5.0}},
        "camera": {"type": "perspective", "fov": 90,
                   "to_world": T().look_at(origin=[0, 0, 0.9], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32}},
    }
    if pane is not None:
        d["pane"] = {"type": "rectangle", "to_world": T().translate([0, 0, 1]).scale(0.5),
                     "bsdf": {"type": pane}}
    return mi.load_dict(d)


def test_the_light_through_a_pane_is_the_open_light_times_the_transmittance():
    open_mean = float(np.mean(mi.render(sun_room(None), spp=256)))
    glazed = sun_room("thindielectric")
    assert float(np.mean(mi.render(glazed, spp=64))) == 0.0  # path renders none of it
    sensor = glazed.sensors()[0]
    estimates = [U.unsampled_radiance(glazed, sensor, seed) for seed in range(8)]
    mean = float(np.mean(estimates))
    se = float(np.std(estimates, ddof=1)) / math.sqrt(len(estimates))
    # a z-test on the seeds' spread; path's 256-spp mean is exact to far better than that
    assert abs(mean - TRANSMITTANCE * open_mean) < 4.0 * se, (estimates, TRANSMITTANCE * open_mean)


@pytest.mark.parametrize("case", ["open", "area light", "no camera"])
def test_nothing_is_missing_where_path_samples_it(case):
    """An open hole (path's shadow rays reach the sun), an area light over the pane (path's BSDF
    rays meet it through the glass), or no camera: 0."""
    if case == "open":
        scene = sun_room(None)
    elif case == "area light":
        scene = sun_room("thindielectric", {
            "type": "rectangle", "to_world": T().translate([0, 0, 1.5]).scale(0.5),
            "flip_normals": True, "emitter": {"type": "area"}})
    else:
        scene = sun_room("thindielectric")
    sensor = None if case == "no camera" else scene.sensors()[0]
    assert U.unsampled_radiance(scene, sensor, 0) == 0.0


def test_twopass_says_how_much_it_misses_and_warns():
    """twopass renders as path there: its stats give the share and it warns; forced to rexes it
    renders the light."""
    scene = sun_room("thindielectric")
    tp = mi.load_dict({"type": "twopass", "pilot_budget": 1e6})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mi.render(scene, integrator=tp, spp=256)
    share = tp.stats["twopass_path_unsampled_share"]
    assert share > 0.5  # the floor's only light: all of the image
    assert tp.stats["twopass_choice"].endswith("caustics=off")
    assert any('caustics="rex"' in str(w.message) for w in caught)
    rex = mi.load_dict({"type": "twopass", "caustics": "rex"})
    lit = float(np.mean(mi.render(scene, integrator=rex, spp=16)))
    open_mean = float(np.mean(mi.render(sun_room(None), spp=256)))
    assert math.isclose(lit, TRANSMITTANCE * open_mean, rel_tol=0.1), (lit, open_mean)
