"""Root causes of wrong images in the far-gather integrators (radiosity_gather, spike_gather),
each pinned by a scene that reproduced it: the image mean against Mitsuba's ``path`` (or an exact
answer) within a z-bound over independent renders.

* A BSDF with a diffuse lobe and anything else (blendbsdf of diffuse and conductor, plastic) was
  taken for a diffuse patch: its radiosity was read as B/π (blendbsdf: 0.83× here, 2.8× on a
  colleague's scene). Only Lambertian reflection is cached now
  (``mi_twopass.scene.lambertian.is_lambertian``).
* A virtual luminaire sampled from behind its own surface: the shadow ray ends on the surface
  from the back, unoccluded, and |cos| let the lit side's radiosity through a wall (veach-bidir
  1.37×). A patch emits into its own side only.
* A patch or receiving element cut by a wall (a floor running under a partition) collected
  particles on one side and showed them on the other: the radiosity light leak. Patches cut by
  geometry are found by lifted segments between their sample points and are not cached.
* A finite ``max_depth``: the radiosity holds light of every path length, so reading it added
  light ``path`` does not have (+33 % at max_depth 2). With a finite max_depth the far gather and
  the virtual luminaires are off.
"""
import numpy as np
import pytest

import mitsuba as mi

INTEGRATORS = ("radiosity_gather", "spike_gather")
#: smaller prepasses for a 16-pixel box (every render seed builds its own prepass)
SMALL = {"radiosity_gather": {"max_patches": 256},
         "spike_gather": {"max_patches": 256, "visibility_max_rays": 20, "camera_res": 16}}
WHITE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.6, 0.5]}}


def box_scene(bsdf=WHITE, res=16):
    """A diffuse box open towards the camera with a small area light under the ceiling;
    ``bsdf`` on every wall."""
    T = mi.ScalarTransform4f
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 50,
                    "to_world": T().look_at(origin=[0, 0, 3.5], target=[0, 0, 0], up=[0, 1, 0]),
                    "sampler": {"type": "independent"},
                    "film": {"type": "hdrfilm", "width": res, "height": res,
                             "rfilter": {"type": "box"}}},
         "light": {"type": "rectangle",
                   "to_world": T().translate([0, 0.99, 0]).rotate([1, 0, 0], 90).scale(0.3),
                   "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 10.0}}}}
    walls = {"floor": ([0, -1, 0], [1, 0, 0], -90), "ceiling": ([0, 1, 0], [1, 0, 0], 90),
             "back": ([0, 0, -1], [0, 1, 0], 0), "left": ([-1, 0, 0], [0, 1, 0], 90),
             "right": ([1, 0, 0], [0, 1, 0], -90)}
    for name, (t, axis, angle) in walls.items():
        d[name] = {"type": "rectangle", "to_world": T().translate(t).rotate(axis, angle),
                   "bsdf": bsdf}
    return mi.load_dict(d)


def image_means(scene, props, spp, seeds):
    """Channel-averaged image mean of ``len(seeds)`` independent renders."""
    integrator = mi.load_dict(props)
    return np.array([float(np.mean(np.asarray(mi.render(scene, integrator=integrator, spp=spp,
                                                          seed=s))[..., :3])) for s in seeds])


def assert_same_mean(scene, props, spp=16, ref_spp=64, k=6, z_max=4.0):
    """The method's mean over k renders equals path's within z_max standard errors."""
    ref_props = {"type": "path", "max_depth": props.get("max_depth", -1)}
    a = image_means(scene, props, spp, range(k))
    b = image_means(scene, ref_props, ref_spp, range(100, 100 + k))
    se = np.sqrt(a.var(ddof=1) / k + b.var(ddof=1) / k)
    z = (a.mean() - b.mean()) / se
    assert abs(z) < z_max, (f"{props}: mean {a.mean():.5f} vs path {b.mean():.5f} "
                            f"(ratio {a.mean() / b.mean():.3f}, z = {z:.1f})")


def test_the_box_scene_is_lit():
    assert image_means(box_scene(), {"type": "path"}, 4, [0])[0] > 0.05


@pytest.mark.parametrize("name", INTEGRATORS)
@pytest.mark.parametrize("bsdf", [
    {"type": "blendbsdf", "weight": 0.5, "bsdf_0": WHITE, "bsdf_1": {"type": "conductor"}},
    {"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": 0.6}},
], ids=["blend_diffuse_conductor", "plastic"])
def test_mixed_bsdf_is_path_traced_not_cached(name, bsdf):
    assert_same_mean(box_scene(bsdf), {"type": name, **SMALL[name]})


@pytest.mark.parametrize("name", INTEGRATORS)
@pytest.mark.parametrize("max_depth", [1, 2, 3])
def test_finite_max_depth_means_what_it_means_for_path(name, max_depth):
    assert_same_mean(box_scene(), {"type": name, "max_depth": max_depth, **SMALL[name]})


def two_rooms(res=16):
    """Two closed rooms sharing one two-sided diffuse wall (x = 0); the light is in the left
    room, the camera in the right one, which no light can reach: the exact image is black."""
    T = mi.ScalarTransform4f
    grey = {"type": "twosided", "bsdf": {"type": "diffuse",
                                         "reflectance": {"type": "rgb", "value": 0.8}}}
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 70,
                   "to_world": T().look_at(origin=[1.8, 0, 0], target=[0, 0, 0], up=[0, 1, 0]),
                   "sampler": {"type": "independent"},
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}}},
        "rooms": {"type": "cube", "to_world": T().scale([2, 1, 1]), "bsdf": grey},
        "wall": {"type": "rectangle", "to_world": T().rotate([0, 1, 0], 90), "bsdf": grey},
        "light": {"type": "rectangle",
                  "to_world": T().translate([-1, 0.99, 0]).rotate([1, 0, 0], 90).scale(0.3),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 20.0}}},
    })


@pytest.mark.parametrize("name", INTEGRATORS)
def test_no_light_through_a_two_sided_wall(name):
    """The lit side of the wall is a virtual luminaire; the dark room behind it stays black."""
    scene = two_rooms()
    integrator = mi.load_dict({"type": name, "vl_threshold": 0.05, "vl_contrast": 0.0,
                               **SMALL[name]})
    img = np.asarray(mi.render(scene, integrator=integrator, spp=16))
    assert image_means(scene, {"type": "path"}, 16, [0])[0] == 0.0  # the exact answer
    assert np.all(np.isfinite(img))
    # the lit room's walls are ~1 (radiance 20 × a small light); 1e-6 is float round-off of
    # the fixed-point deposits, a leak is of the order of the lit side's radiosity
    assert float(np.max(img)) < 1e-6, f"{name}: light leaked, max {float(np.max(img)):.3g}"
