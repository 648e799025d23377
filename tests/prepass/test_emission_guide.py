"""Importance-driven emission (mi_twopass.prepass.emission_guide) and the guided radiosity solve.

The root case: a sun lighting a floor through a 1 m² hole in a 10 m × 10 m roof. Mitsuba's
``sample_ray`` starts the sun's particles on a disk around the whole scene, so ~0.6 % of them
pass the hole; the floor's flux (exactly irradiance × hole area: floor and roof are black) is
then a binomial estimate of a few hundred particles, ±5 % from one prepass seed to the next —
the noise that made scenes_xml/mixed_room.xml's far reads 0.98–1.03 of path's. Guided by the
camera, which looks at the floor, the particles go through the hole; the estimate stays
unbiased (the z-test against the exact flux) and its spread over seeds falls below a third of
the unguided binomial one."""
import math

import numpy as np
import pytest

import mi_twopass  # noqa: F401  (libLLVM + variant before mitsuba/drjit)
import mitsuba as mi

from mi_twopass.prepass import emission_guide as G
from mi_twopass.prepass import radiosity as R
from mi_twopass.scene.bounds import scene_bounds

T = mi.ScalarTransform4f
IRRADIANCE = 5.0
Z_MAX = 5.0


def black():
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}


def slab(cx, cy, z, hx, hy):
    """A black box 2hx × 2hy × 2 cm centred at (cx, cy, z). Boxes, not rectangles: Mitsuba 3.9
    leaves the rectangles it merges out of the scene's bounding box, and a sun's particles start
    on that box's bounding sphere."""
    return {"type": "cube", "to_world": T().translate([cx, cy, z]).scale([hx, hy, 0.01]),
            "bsdf": black()}


def window_scene(emitter):
    """A 4 m × 4 m black floor at z = 0 under a black 10 m × 10 m roof at z = 1 with a 1 m²
    hole over the floor's centre; a camera under the roof looks down at the floor."""
    return mi.load_dict({
        "type": "scene",
        "floor": slab(0, 0, 0, 2, 2),
        "roof_l": slab(-2.75, 0, 1, 2.25, 5),
        "roof_r": slab(2.75, 0, 1, 2.25, 5),
        "roof_f": slab(0, -2.75, 1, 0.5, 2.25),
        "roof_b": slab(0, 2.75, 1, 0.5, 2.25),
        "sun": emitter,
        "camera": {"type": "perspective", "fov": 90,
                   "to_world": T().look_at(origin=[0, 0, 0.9], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
    })


def sun():
    return {"type": "directional", "direction": [0, 0, -1],
            "irradiance": {"type": "rgb", "value": IRRADIANCE}}


def floor_flux(pre):
    """Flux deposited on the floor (the patches below z = 0.5), W (channel mean)."""
    sol = pre.solution
    floor = np.asarray(sol.patches.center)[:, 2] < 0.5
    flux = np.asarray(sol.E).mean(axis=1) * np.asarray(R._receiving_area(sol.patches, sol.E))
    return float(flux[floor].sum())


SETTINGS = R.RadiositySettings(max_patches=64, elements_per_patch=1)


def test_moving_dims_tell_a_suns_disk_from_a_skys_directions():
    scene = window_scene(sun())
    # a sun: one direction (u2 unused), a point of the disk facing it (u3)
    assert G.moving_dims(scene, 0) == (False, True)
    sky = mi.load_dict({"type": "scene", "floor": slab(0, 0, 0, 1, 1),
                        "sky": {"type": "constant"}})
    assert G.moving_dims(sky, 0) == (True, True)
    point = mi.load_dict({"type": "scene", "floor": slab(0, 0, 0, 1, 1),
                          "lamp": {"type": "point", "position": [0, 0, 1]}})
    assert G.moving_dims(point, 0) == (False, True)  # Mitsuba's sample_ray: u3 the direction


def test_cells_cover_each_emitters_sample_space_once():
    scene = mi.load_dict({"type": "scene", "sun": sun(), "sky": {"type": "constant"},
                          "lamp": {**slab(0, 0, 1, 0.2, 0.2), "emitter": {"type": "area"}}})
    cells = G.cells(scene)
    per_emitter = np.bincount(cells.emitter, minlength=3)
    assert sorted(per_emitter.tolist()) == sorted([1, G.GRID_2D ** 2, G.GRID_4D ** 4])
    # volumes tile [0,1)^4 per emitter; Mitsuba's own choice sums to 1
    assert np.allclose(np.bincount(cells.emitter, weights=cells.volume), 1.0)
    assert math.isclose(cells.default.sum(), 1.0, rel_tol=1e-6)  # Mitsuba's float32 pdf
    assert np.all(cells.lo >= 0) and np.all(cells.lo + cells.size <= 1 + 1e-12)


def test_many_point_lights_share_the_cell_budget():
    """200 point lights: each grid is cut coarser so that all of them stay within MAX_CELLS
    (at full resolution, 200 × 1024 cells and a pilot of 800k particles)."""
    d = {"type": "scene", "floor": slab(0, 0, 0, 5, 5)}
    for k in range(200):
        d[f"lamp{k}"] = {"type": "point", "position": [k * 0.05 - 5, 0, 1]}
    cells = G.cells(mi.load_dict(d))
    res = G.grid_resolution((False, True), 200)
    assert res == int((G.MAX_CELLS / 200) ** 0.5) < G.GRID_2D
    assert cells.count == 200 * res ** 2 <= G.MAX_CELLS
    assert np.allclose(np.bincount(cells.emitter, weights=cells.volume), 1.0)
    assert G.grid_resolution((True, True), 1) == G.GRID_4D
    assert G.grid_resolution((False, False), 1) == 1
    assert G.grid_resolution((True, True), 10 ** 6) == 1


def test_neighbours_share_and_every_cell_keeps_a_defensive_share():
    scene = window_scene(sun())
    cells = G.cells(scene)
    rms = np.zeros(cells.count)
    rms[5 * G.GRID_2D + 7] = 1.0
    near = G.neighbour_max(cells, rms).reshape(G.GRID_2D, G.GRID_2D)
    assert near[4:7, 6:9].min() == 1.0 and near.sum() == 9.0
    guide = G.fitted(cells, np.arange(cells.count), rms)
    assert np.all(guide.pmf > 0) and math.isclose(guide.pmf.sum(), 1.0, rel_tol=1e-9)
    assert G.fitted(cells, np.arange(cells.count), np.zeros(cells.count)) is None


def test_no_guide_without_a_camera_or_with_area_lights_only():
    scene = window_scene(sun())
    patches = R.build_patches(scene, max_patches=64)
    assert R.guide_emission(scene, None, patches)[0] is None
    lamp = mi.load_dict({"type": "scene", "floor": slab(0, 0, 0, 2, 2),
                         "lamp": {**slab(0, 0, 1, 0.2, 0.2), "emitter": {"type": "area"}},
                         "camera": {"type": "perspective"}})
    assert R.guide_emission(lamp, lamp.sensors()[0],
                            R.build_patches(lamp, max_patches=16))[0] is None


def test_a_sun_through_a_hole_is_unbiased_and_far_less_noisy_when_guided():
    scene = window_scene(sun())
    sensor = scene.sensors()[0]
    exact = IRRADIANCE * 1.0  # W through the 1 m² hole onto the black floor
    seeds = range(6)
    guided = [R.build(scene, SETTINGS, seed=s, progress=False, sensor=sensor) for s in seeds]
    assert all(p.guide_cells == G.GRID_2D ** 2 for p in guided)
    flux = np.array([floor_flux(p) for p in guided])
    se = flux.std(ddof=1) / math.sqrt(len(flux))
    assert abs(flux.mean() - exact) < Z_MAX * se + 1e-3 * exact, (flux, exact)
    # unguided: a binomial count of the particles that pass the hole
    plain = R.build(scene, SETTINGS, seed=0, progress=False)
    assert plain.guide_cells == 0
    radius = scene_bounds(scene).radius
    p_hit = 1.0 / (math.pi * radius ** 2)
    n = plain.solution.particles
    plain_rel_sd = math.sqrt((1 - p_hit) / (n * p_hit))
    assert abs(floor_flux(plain) - exact) < Z_MAX * plain_rel_sd * exact
    rel_sd = flux.std(ddof=1) / exact
    assert rel_sd < plain_rel_sd / 3, (rel_sd, plain_rel_sd)


def test_first_vertex_weights_are_the_radiance_a_receiver_sends_per_unit_flux():
    """A grey floor fills the camera's view and nothing is above it: every camera path's first
    vertex is on the floor, so Σ_r first_r · A_r = ρ/π (a flux Φ spread evenly, Φ·A_r/A per
    receiver, is seen as the radiance ρΦ/(πA)); its bounces escape, so nothing is read."""
    grey = 0.5
    scene = mi.load_dict({
        "type": "scene",
        "floor": {**slab(0, 0, 0, 4, 4),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": grey}}},
        "camera": {"type": "perspective", "fov": 60,
                   "to_world": T().look_at(origin=[0, 0, 0.9], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
    })
    patches = R.build_patches(scene, max_patches=64)
    camera = G.camera_importance(scene, scene.sensors()[0], patches, seed=0, lanes=1 << 12)
    area = np.append(patches.area, 0.0)
    assert math.isclose(float(np.sum(camera.first * area)), grey / math.pi, rel_tol=1e-5)
    assert camera.read.sum() == 0.0
    assert camera.hits.sum() == 1 << 12


def test_image_noise_is_the_read_lights_noise_times_its_share_of_the_image():
    """One cell of C brings all the light read from the solution (score s), another the direct
    light at the first vertex (t); drawn uniformly, the read total's relative noise per
    particle is √(C − 1) and its share of the image s / (s + t)."""
    cells = G.cells(window_scene(sun()))
    C = cells.count
    cell_of = np.arange(C)
    read, first = np.zeros(C), np.zeros(C)
    read[3], first[700] = 1.0, 3.0
    pmf = np.full(C, 1.0 / C)
    assert math.isclose(G.image_noise(cells, pmf, cell_of, read, first, 1),
                        math.sqrt(C - 1) / 4, rel_tol=1e-9)
    assert math.isclose(G.image_noise(cells, pmf, cell_of, read, first, 100),
                        math.sqrt(C - 1) / 40, rel_tol=1e-9)
    assert G.image_noise(cells, pmf, cell_of, np.zeros(C), first, 1) == 0.0


@pytest.mark.parametrize("noise, expected", [(0.0, 1000), (R.FLUX_NOISE * math.sqrt(500), 1000),
                                             (R.FLUX_NOISE * math.sqrt(4000), 4000),
                                             (1.0, 8000)])
def test_guided_particle_count_follows_the_predicted_noise(noise, expected):
    assert R.guided_particles(1000, noise) == expected
