"""Radiosity prepass (mi_twopass.prepass.radiosity): furnace, energy, analytic irradiance, hard cases.

Statistical checks compare with standard errors: from the binomial law of the hits where every
particle carries the same flux, or from the spread of independent runs (different seeds)."""
import math
import os
import time

import numpy as np
import pytest

import mi_twopass  # noqa: F401  (libLLVM + variant before mitsuba/drjit)
import drjit as dr
import mitsuba as mi

from mi_twopass.prepass import solve_radiosity
from mi_twopass.scene import build_patches
from mi_twopass.scene.patches import _subtriangle_corners

T = mi.ScalarTransform4f
Z_MAX = 5.0  # |z| beyond this fails (two-sided p ≈ 6e-7 per check)


def rgb(v):
    return {"type": "rgb", "value": v}


def furnace(rho, Le=1.0, scale=1.0):
    """Closed cube seen from inside: every face diffuse albedo ρ and emitting Le."""
    return mi.load_dict({"type": "scene", "box": {
        "type": "cube", "flip_normals": True, "to_world": T().scale(scale),
        "bsdf": {"type": "diffuse", "reflectance": rgb(rho)},
        "emitter": {"type": "area", "radiance": rgb(Le)}}})


def runs(scene, patches, n_particles, seeds, **kw):
    return [solve_radiosity(scene, patches, n_particles=n_particles, seed=s, progress=False, **kw)
            for s in seeds]


def mean_and_se(values):
    """Mean over independent runs (axis 0) and its standard error."""
    v = np.asarray(values, dtype=np.float64)
    return v.mean(axis=0), v.std(axis=0, ddof=1) / math.sqrt(v.shape[0])


def patch_integral(patches, f, level=16):
    """∫ f(x) dA / A over each patch's triangles (centroid rule on an n² sub-triangulation)."""
    c = _subtriangle_corners(level).mean(axis=1)  # (n², 2) barycentric centroids
    tv = patches.tri_vertices.astype(np.float64)
    pts = tv[:, None, 0] + c[None, :, 0:1] * (tv[:, None, 1] - tv[:, None, 0]) \
        + c[None, :, 1:2] * (tv[:, None, 2] - tv[:, None, 0])  # (T, n², 3)
    area = 0.5 * np.linalg.norm(np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), axis=1)
    vals = f(pts.reshape(-1, 3)).reshape(pts.shape[:2]).mean(axis=1) * area
    return np.bincount(patches.tri_patch, weights=vals, minlength=patches.count) / patches.area


# ---------------------------------------------------------------------------------------------
# furnace


def test_furnace_rho_0_9():
    """B = π·Le/(1−ρ) on every patch, within 1 %; the 1 % is ≥ 5 standard errors."""
    rho = 0.9
    scene = furnace(rho)
    patches = build_patches(scene, max_patches=24)
    sols = runs(scene, patches, 100_000, seeds=range(8))
    B, se = mean_and_se([s.B for s in sols])
    exact = math.pi / (1 - rho)
    rel = B / exact - 1
    print(f"furnace rho=0.9: {patches.count} patches, {8 * 100_000} particles, "
          f"{sum(s.rays for s in sols)} rays, {sum(s.seconds for s in sols):.2f} s, "
          f"max |rel err| {np.abs(rel).max():.4f}, max SE {se.max() / exact:.4f}")
    assert np.all(np.abs(rel) < 0.01)
    assert Z_MAX * se.max() / exact < 0.01  # the tolerance is not tuned below the noise
    assert np.all(np.abs(B - exact) < Z_MAX * np.maximum(se, 1e-12))
    np.testing.assert_allclose(sols[0].B_emitted, math.pi, rtol=1e-6)
    for s in sols:  # closed box: nothing escapes (but the rare ray between two triangles)
        assert np.all(s.flux_escaped <= 2e-5 * s.flux_emitted)  # ≤ 1 particle of 100 000


def test_furnace_rho_0_99_bounded_time():
    """ρ = 0.99: within 2 %, and RR by albedo keeps the mean path at 1/(1−ρ) = 100 rays."""
    rho = 0.99
    scene = furnace(rho)
    patches = build_patches(scene, max_patches=24)
    t0 = time.perf_counter()
    sols = runs(scene, patches, 16_000, seeds=range(8))
    seconds = time.perf_counter() - t0
    B, se = mean_and_se([s.B for s in sols])
    exact = math.pi / (1 - rho)
    rel = B / exact - 1
    rays = sum(s.rays for s in sols)
    particles = sum(s.particles for s in sols)
    print(f"furnace rho=0.99: {patches.count} patches, {particles} particles, {rays} rays, "
          f"{seconds:.2f} s, max |rel err| {np.abs(rel).max():.4f}, max SE {se.max() / exact:.4f}")
    assert np.all(np.abs(rel) < 0.02)
    assert Z_MAX * se.max() / exact < 0.02
    # path length: geometric with mean 1/(1−ρ) and sd √ρ/(1−ρ)
    mean_len, sd_len = 1 / (1 - rho), math.sqrt(rho) / (1 - rho)
    assert abs(rays / particles - mean_len) < Z_MAX * sd_len / math.sqrt(particles)
    truncated = sum(s.flux_truncated[0] for s in sols) / sum(s.flux_emitted[0] for s in sols)
    assert truncated < 1e-3  # ρ^1024 ≈ 3e-5 of the light is cut at max_bounces
    assert seconds < 60.0


def test_furnace_truncation_bias_is_reported():
    """max_bounces cuts paths: the missing light is flux_truncated, ≈ ρ^max_bounces."""
    rho, k = 0.9, 8
    scene = furnace(rho)
    patches = build_patches(scene, max_patches=24)
    sol = solve_radiosity(scene, patches, n_particles=100_000, seed=5, max_bounces=k,
                          progress=False)
    frac = sol.flux_truncated[0] / sol.flux_emitted[0]
    sd = math.sqrt(rho ** k * (1 - rho ** k) / sol.particles)  # binomial: alive after k hits
    assert abs(frac - rho ** k) < Z_MAX * sd
    # the solution lacks exactly the truncated light: ΣE·A = emitted·(1 − ρ^k)/(1 − ρ)
    deposited = (sol.E[:, 0] * patches.area).sum()
    expected = sol.flux_emitted[0] * (1 - rho ** k) / (1 - rho)
    assert abs(deposited / expected - 1) < 0.01


# ---------------------------------------------------------------------------------------------
# energy


def open_scene(light_power=1.0):
    """A floor with a sphere and a box on it under a point light: every visible side is a front."""
    return mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "to_world": T().scale(3.0),
                  "bsdf": {"type": "diffuse", "reflectance": rgb([0.8, 0.5, 0.2])}},
        "ball": {"type": "sphere", "center": [0.8, 0, 0.5], "radius": 0.5,
                 "bsdf": {"type": "diffuse", "reflectance": rgb([0.3, 0.7, 0.9])}},
        "box": {"type": "cube", "to_world": T().translate([-0.8, 0.2, 0.4]).scale(0.4),
                "bsdf": {"type": "diffuse", "reflectance": rgb(0.6)}},
        "light": {"type": "point", "position": [0.1, -0.4, 2.0], "intensity": rgb(light_power)},
    })


def test_energy_conservation_open_scene():
    """Emitted flux = absorbed (Σ(1−ρ_i)·Φ_i over patches) + escaped, per channel."""
    scene = open_scene()
    patches = build_patches(scene, max_patches=200)
    sols = runs(scene, patches, 20_000, seeds=range(8))
    emitted = sols[0].flux_emitted
    np.testing.assert_allclose(emitted, 4 * math.pi, rtol=1e-5)  # point light: 4π·I
    # physical: absorption of the solution's irradiance plus the light that left
    balance = [((1 - patches.albedo) * s.E * patches.area[:, None]).sum(axis=0)
               + s.flux_escaped + s.flux_truncated for s in sols]
    # bookkeeping of the particle tracer (expected absorption at each hit)
    ledger = [s.flux_absorbed + s.flux_escaped + s.flux_truncated for s in sols]
    for totals in (balance, ledger):
        m, se = mean_and_se(totals)
        assert np.all(np.abs(m - emitted) < Z_MAX * se), (m, emitted, se)
        assert np.all(se < 0.01 * emitted)  # a meaningful test: 5 SE is ≤ 5 % of the flux
    esc = np.mean([s.flux_escaped for s in sols], axis=0)
    assert np.all(esc > 0.2 * emitted)  # an open scene: much light leaves


# ---------------------------------------------------------------------------------------------
# irradiance against closed forms (one emitter, every particle carries the same flux)


def check_irradiance(sol, E_exact):
    """z-test per patch with the binomial standard error of the hit counts."""
    patches = sol.patches
    phi = sol.flux_emitted[0]
    p = np.clip(E_exact * patches.area / phi, 0, 1)  # probability a particle hits patch i
    se = phi * np.sqrt(p * (1 - p) / sol.particles) / patches.area
    E = sol.E.mean(axis=1)
    z = (E - E_exact) / se
    assert np.all(np.abs(z) < Z_MAX), np.abs(z).max()
    n = z.size  # and the z's are spread like N(0, 1): mean z² = 1 ± √(2/n)
    assert abs(np.mean(z ** 2) - 1) < Z_MAX * math.sqrt(2 / n)
    return z


def plane_scene(emitter):
    return mi.load_dict({"type": "scene",
                         "floor": {"type": "rectangle", "to_world": T().scale(2.0),
                                   "bsdf": {"type": "diffuse", "reflectance": rgb(0.5)}},
                         "light": emitter})


def test_point_light_over_plane():
    """E = I·cosθ/r² integrated over each patch."""
    I, pos = 5.0, np.array([0.3, 0.2, 1.0])
    scene = plane_scene({"type": "point", "position": pos.tolist(), "intensity": rgb(I)})
    patches = build_patches(scene, max_patches=128)
    sol = solve_radiosity(scene, patches, n_particles=400_000, seed=3, progress=False)

    def E_point(x):
        r = pos - x
        d2 = (r * r).sum(axis=1)
        return I * r[:, 2] / d2 ** 1.5

    check_irradiance(sol, patch_integral(patches, E_point))
    np.testing.assert_allclose(sol.B_reflected, 0.5 * sol.E, rtol=1e-6)
    assert np.all(sol.B_emitted == 0)


def test_directional_light_over_plane():
    """A sun of irradiance E_d (on a plane facing it) gives E_d·cosθ everywhere."""
    d = np.array([0.3, 0.2, -1.0])
    scene = plane_scene({"type": "directional", "direction": d.tolist(), "irradiance": rgb(3.0)})
    patches = build_patches(scene, max_patches=32)
    sol = solve_radiosity(scene, patches, n_particles=200_000, seed=4, progress=False)
    cos = -d[2] / np.linalg.norm(d)
    check_irradiance(sol, np.full(patches.count, 3.0 * cos))


def test_uniform_sky_over_plane():
    """A constant environment of radiance L gives irradiance π·L on an unoccluded plane."""
    L = 2.0
    scene = plane_scene({"type": "constant", "radiance": rgb(L)})
    patches = build_patches(scene, max_patches=32)
    sol = solve_radiosity(scene, patches, n_particles=200_000, seed=5, progress=False)
    check_irradiance(sol, np.full(patches.count, math.pi * L))


# ---------------------------------------------------------------------------------------------
# render-time queries, determinism


def test_radiance_queries_and_determinism():
    scene = open_scene()
    patches = build_patches(scene, max_patches=100)
    sol = solve_radiosity(scene, patches, n_particles=20_000, seed=11, progress=False)
    again = solve_radiosity(scene, patches, n_particles=20_000, seed=11, progress=False)
    other = solve_radiosity(scene, patches, n_particles=20_000, seed=12, progress=False)
    assert np.array_equal(sol.B_reflected, again.B_reflected) and sol.rays == again.rays
    assert not np.array_equal(sol.B_reflected, other.B_reflected)

    rng = np.random.default_rng(0)
    n = 2000
    o = np.tile([0.0, 0.0, 3.0], (n, 1))
    target = np.c_[rng.uniform(-4, 4, (n, 2)), np.zeros(n)]
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(o[:, i]) for i in range(3))),
                   mi.Vector3f(*(mi.Float(d[:, i]) for i in range(3))))
    si = scene.ray_intersect(ray)
    pid = np.array(patches.lookup(si, True))
    Lr = np.array(sol.reflected_radiance(si, True)).T
    B = np.array(sol.radiosity(si, True)).T
    valid = pid < patches.count
    assert valid.sum() > 500 and (~valid).sum() > 100  # hits and misses
    np.testing.assert_allclose(Lr[valid], sol.B_reflected[pid[valid]] / math.pi, rtol=1e-5)
    np.testing.assert_allclose(B[valid], sol.B[pid[valid]], rtol=1e-5)
    assert np.all(Lr[~valid] == 0) and np.all(B[~valid] == 0)
    assert sol.nbytes > patches.nbytes > 0


# ---------------------------------------------------------------------------------------------
# hard cases: no NaN / Inf


def assert_finite(sol):
    for arr in (sol.B_emitted, sol.B_reflected, sol.E, sol.flux_absorbed, sol.flux_escaped):
        assert np.all(np.isfinite(arr))


@pytest.mark.parametrize("scale", [1e-3, 1e4])
def test_furnace_at_extreme_scales(scale):
    """Radiance is scale-free: the furnace answer holds at 1 mm and 10 km, without leaks."""
    rho = 0.5
    scene = furnace(rho, scale=scale)
    patches = build_patches(scene, max_patches=24)
    sols = runs(scene, patches, 25_000, seeds=range(4))
    for s in sols:
        assert_finite(s)
        assert np.all(s.flux_escaped <= 1e-4 * s.flux_emitted)
    B, se = mean_and_se([s.B for s in sols])
    exact = math.pi / (1 - rho)
    assert np.all(np.abs(B - exact) < Z_MAX * np.maximum(se, 1e-6 * exact))
    assert np.all(np.abs(B / exact - 1) < 0.01)


def test_zero_area_triangle_and_lights_of_zero_power():
    V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [0, 0, 0.5], [0, 0, 0.5]],
                 dtype=np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 4], [0, 0, 1]], dtype=np.uint32)  # 2 degenerate
    mesh = mi.Mesh("m", 6, 4)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(V.ravel())
    params["faces"] = mi.UInt32(F.ravel())
    params.update()
    for light in ({"type": "point", "position": [0, 0, 1], "intensity": rgb(1.0)},
                  {"type": "point", "position": [0, 0, 1], "intensity": rgb(0.0)}):
        scene = mi.load_dict({"type": "scene", "m": mesh, "light": light,
                              "dark": {"type": "disk", "to_world": T().translate([0, 0, 2]),
                                       "emitter": {"type": "area", "radiance": rgb(0.0)}}})
        patches = build_patches(scene, max_patches=32)
        sol = solve_radiosity(scene, patches, n_particles=20_000, seed=1, progress=False)
        assert_finite(sol)
        zero = patches.area == 0
        assert zero.any() and np.all(sol.E[zero] == 0)
        if light["intensity"]["value"] == 0.0:
            assert np.all(sol.B_reflected == 0) and np.all(sol.B_emitted == 0)
            assert sol.rays == 0
        else:
            assert sol.B_reflected.max() > 0


def test_scene_without_emitters():
    scene = mi.load_dict({"type": "scene", "floor": {"type": "rectangle"},
                          "ball": {"type": "sphere", "center": [0, 0, 1], "radius": 0.3}})
    patches = build_patches(scene, max_patches=16)
    sol = solve_radiosity(scene, patches, n_particles=1000, seed=0, progress=False)
    assert_finite(sol)
    assert np.all(sol.B_reflected == 0) and np.all(sol.B_emitted == 0) and sol.rays == 0


def test_empty_patch_set():
    """A scene whose only shape has no patches (a null BSDF) still solves, to nothing."""
    scene = mi.load_dict({"type": "scene",
                          "ghost": {"type": "rectangle", "bsdf": {"type": "null"}},
                          "light": {"type": "point", "position": [0, 0, 1]}})
    patches = build_patches(scene)
    assert patches.count == 0
    sol = solve_radiosity(scene, patches, n_particles=1000, seed=0, progress=False)
    assert sol.B.shape == (0, 3)
    assert np.all(np.isclose(sol.flux_escaped, sol.flux_emitted))


def test_elements_refine_patches_without_changing_them():
    """Elements (a finer patch mesh) receive the same particles: the patch solution is the same
    bit for bit, each patch's flux equals the flux of the elements inside it, and the finer
    solution resolves the fall-off of a point light's irradiance on a plane."""
    scene = plane_scene({"type": "point", "position": [0.0, 0.0, 1.0],
                         "intensity": rgb(1.0)})
    patches = build_patches(scene, max_patches=16)
    elements = build_patches(scene, max_patches=256)
    plain = solve_radiosity(scene, patches, n_particles=1 << 16, seed=5, progress=False)
    sol = solve_radiosity(scene, patches, n_particles=1 << 16, seed=5, progress=False,
                          elements=elements)
    np.testing.assert_array_equal(sol.E, plain.E)
    assert plain.elements is None and sol.elements is elements
    np.testing.assert_allclose((sol.E_elements * elements.area[:, None]).sum(0),
                               (sol.E * patches.area[:, None]).sum(0), rtol=1e-6)
    np.testing.assert_allclose(sol.B_reflected_elements, elements.albedo * sol.E_elements)
    # the brightest element (under the light) is brighter than its patch's mean
    assert sol.E_elements.max() > 1.5 * sol.E.max()
    # queries: the element value at a hit
    ray = mi.Ray3f(mi.Point3f(0.01, 0.02, 1.0), mi.Vector3f(0, 0, -1))
    si = scene.ray_intersect(ray)
    L = np.array(sol.reflected_radiance(si)).ravel()
    eid = int(np.array(elements.lookup(si))[0])
    np.testing.assert_allclose(L, sol.B_reflected_elements[eid] / math.pi, rtol=1e-5)
    again = solve_radiosity(scene, patches, n_particles=1 << 16, seed=5, progress=False,
                            elements=elements)
    np.testing.assert_array_equal(again.E_elements, sol.E_elements)


def test_shared_build_and_virtual_luminaire_sampler_agree_with_their_pmf():
    """prepass.radiosity.build: one call makes patches, elements, the solve and the virtual
    luminaires; VirtualLuminaires.sample draws patch i with probability pmf(i) ∝ its power
    (a chi² test of 2^16 draws), only among the patches whose B_r ≥ vl_threshold × max B_r
    (the contrast bound off: ``vl_contrast`` = 0)."""
    from scipy import stats

    from mi_twopass.prepass.radiosity import RadiositySettings, build

    scenes = os.path.join(os.path.dirname(__file__), "..", "..", "scenes_xml")
    scene = mi.load_file(os.path.join(scenes, "cornell_box.xml"), res=8)
    pre = build(scene, RadiositySettings(max_patches=64, particles_per_patch=64,
                                         elements_per_patch=4, vl_threshold=0.2,
                                         vl_contrast=0.0), seed=3)
    assert pre.scene is scene and not pre.simplified and pre.elements is not None
    assert pre.stats["patches"] == pre.patches.count and pre.stats["radiosity_rays"] > 0
    vl = pre.virtual
    Br = np.asarray(pre.solution.B_reflected).mean(axis=1)
    expected = np.nonzero((Br >= 0.2 * Br.max()) & (Br > 0) & pre.patches.is_diffuse)[0]
    assert vl.count == len(expected) > 1
    n = 1 << 16
    pid = np.asarray(vl.sample(mi.Float(np.random.default_rng(0).random(n).astype(np.float32))))
    assert set(np.unique(pid)) <= set(expected.tolist())
    pmf = np.asarray(vl.pmf(mi.UInt32(np.arange(pre.patches.count, dtype=np.uint32))))
    others = np.setdiff1d(np.arange(len(pmf)), expected)
    assert abs(pmf.sum() - 1) < 1e-5 and np.all(pmf[others] == 0)
    counts = np.bincount(pid, minlength=pre.patches.count)[expected]
    _, p = stats.chisquare(counts, pmf[expected] * n / pmf[expected].sum())
    assert p > 1e-3
    assert np.all(np.asarray(vl.contains(mi.UInt32(expected.astype(np.uint32)))))


def test_reclassification_does_not_follow_the_noise_of_the_brightest_patch():
    """GSII's rule alone (B_r ≥ 0.5 × max B_r) on a flat field of 1000 patches (B_r = 1 ± 5 %)
    picks every patch or one, as the noise of its brightest patch has it (scenes_xml/office.xml:
    1 to 300 patches over solve seeds); with the contrast bound (≥ 4 × the area-weighted mean)
    it picks none in either case, and still a small patch that does stand out (B_r = 40),
    unless it carries too little of the reflected power to pay for being sampled."""
    from mi_twopass.prepass.radiosity import VL_CONTRAST, reclassified_patches

    rng = np.random.default_rng(0)
    Br = 1.0 + 0.05 * rng.standard_normal(1000)
    area = np.ones(1000)
    diffuse = np.ones(1000, bool)
    calm, spiked = Br.copy(), Br.copy()
    spiked[7] = 2.5  # a noisy outlier: half of it is below every other patch
    assert reclassified_patches(calm, area, diffuse, 0.5, 0.0).size == 1000
    assert reclassified_patches(spiked, area, diffuse, 0.5, 0.0).tolist() == [7]
    assert VL_CONTRAST == 4.0
    assert reclassified_patches(calm, area, diffuse, 0.5).size == 0
    assert reclassified_patches(spiked, area, diffuse, 0.5).size == 0
    bright = calm.copy()
    bright[3] = 40.0  # 3.9 % of the reflected power
    assert reclassified_patches(bright, area, diffuse, 0.5).tolist() == [3]
    faint = calm.copy()
    faint[3] = 10.0  # stands out, but 1 % of the power: not worth its sampling code
    assert reclassified_patches(faint, area, diffuse, 0.5).size == 0
    assert reclassified_patches(faint, area, diffuse, 0.5, 0.0).tolist() == [3]
    # only cached (diffuse) patches count, and a finite threshold is needed
    assert reclassified_patches(bright, area, diffuse & (np.arange(1000) != 3), 0.5).size == 0
    assert reclassified_patches(bright, area, diffuse, math.inf).size == 0


def test_receivers_lit_unevenly_are_not_cached():
    """A floor under a point light 5 cm above one corner: the patch holding that corner gets
    most of its flux there (its flux centroid far off its centre), so it is not cached (far
    gathers trace on); under a light 10 m up the same floor is lit evenly and stays cached."""
    from mi_twopass.prepass.radiosity import RadiositySettings, build

    def floor_under(position):
        return mi.load_dict({
            "type": "scene",
            "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}},
            "light": {"type": "point", "position": position,
                      "intensity": {"type": "rgb", "value": 1.0}}})

    settings = RadiositySettings(max_patches=4, particles_per_patch=4096, elements_per_patch=1)
    near = build(floor_under([0.9, 0.9, 0.05]), settings, seed=1).patches
    far = build(floor_under([0.0, 0.0, 10.0]), settings, seed=1).patches
    assert near.count == far.count >= 2
    corner = int(np.argmin(np.linalg.norm(near.center[:, :2] - [0.9, 0.9], axis=1)))
    assert near.is_uneven[corner] and not near.is_diffuse[corner]
    assert not far.is_uneven.any() and far.is_diffuse.all()


def test_virtual_luminaire_points_are_reached_only_where_the_radiosity_is_cached():
    """The explicit (virtual-luminaire) strategy and the implicit gather must split the points
    of a bright patch between them: where an element is not cached the gather ray traces on,
    so a ray aimed at a point there does not count for the explicit strategy (it counted the
    light twice: veach-bidir +2.6 %). The floor under a light 5 cm above its corner: its
    patches are virtual luminaires, the elements at the corner are unevenly lit."""
    from mi_twopass.prepass.radiosity import RadiositySettings, build, virtual_point_reached
    from mi_twopass.prepass.sh_cache import refined_mask

    scene = mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}},
        "light": {"type": "point", "position": [0.9, 0.9, 0.05],
                  "intensity": {"type": "rgb", "value": 1.0}}})
    pre = build(scene, RadiositySettings(max_patches=4, particles_per_patch=16384,
                                         elements_per_patch=16, vl_threshold=0.0,
                                         vl_contrast=0.0), seed=1)
    el = pre.elements
    assert pre.virtual.count == pre.patches.count and el.is_uneven.any() \
        and not el.is_uneven.all()
    # a ray straight down from 1 m above the centre of every element
    top = mi.Point3f(*(mi.Float(el.center[:, c].astype(np.float32) + (1.0 if c == 2 else 0))
                       for c in range(3)))
    si = dr.zeros(mi.SurfaceInteraction3f, el.count)
    si.p, si.n = top, mi.Normal3f(0, 0, -1)
    si.wi = mi.Vector3f(0, 0, 1)
    probe = mi.Ray3f(top, mi.Vector3f(0, 0, -1))
    pid = pre.patches.lookup(scene.ray_intersect(probe))

    def reached():
        return np.asarray(virtual_point_reached(scene, pre.solution, si, mi.Vector3f(0, 0, -1),
                                                pid, mi.Float(1.0), 1.0, True))

    # an uneven element refined into cells is cached (the gather reads its cell) and reached
    refined = refined_mask(pre.solution)
    assert np.array_equal(reached(), ~el.is_uneven | refined)
    # without its cells it is not cached, and the explicit strategy leaves it out
    pre.solution.grid = None
    assert np.array_equal(reached(), ~el.is_uneven)


# -- which receivers are cached: the noise floor of the spread test -------------------------
def _disk_points(rng, n):
    r, t = np.sqrt(rng.random(n)), rng.random(n) * 2 * np.pi
    return np.stack([r * np.cos(t), r * np.sin(t), np.zeros(n)], axis=1)


def _receivers(rng, K, heavy_weight, heavy_rate, light_rate=200, half=False):
    """K flat receivers (radius 1, normal +z): Poisson(light_rate) deposits of flux 1 and
    Poisson(heavy_rate) of flux ``heavy_weight``, uniform over the disk (``half``: the light
    ones on its x > 0 half only). Returns (moments, normal moments, count, flux, Σw², normals)."""
    from mi_twopass.prepass.radiosity import effective_count
    mom, flux, count, w2 = np.zeros((K, 3)), np.zeros(K), np.zeros(K, np.int64), np.zeros(K)
    for k in range(K):
        n_l, n_h = rng.poisson(light_rate), rng.poisson(heavy_rate)
        w = np.concatenate([np.ones(n_l), np.full(n_h, float(heavy_weight))])
        p = _disk_points(rng, n_l + n_h)
        if half:
            p[:n_l, 0] = np.abs(p[:n_l, 0])
        mom[k], flux[k], count[k], w2[k] = (w[:, None] * p).sum(0), w.sum(), w.size, (w * w).sum()
    normals = np.tile([0.0, 0.0, 1.0], (K, 1))
    return mom, flux[:, None] * normals, count, flux, effective_count(flux, w2, count), normals


def test_spread_test_does_not_select_receivers_by_their_luck():
    """Particles of unequal flux (a sun's beside a small lamp's): a receiver that drew a heavy
    particle has a centroid off its centre by chance. Counted with one deposit per particle,
    the noise floor was too low, those receivers were uncached, and the mean irradiance of the
    cached ones read low (the far gather 7.5 % dark on mixed_room.xml); with the effective
    count (Σw)²/Σw² the cached receivers' mean is the mean of all of them."""
    from mi_twopass.prepass.radiosity import SPREAD_MAX, receiver_spread
    rng = np.random.default_rng(5)
    mom, nmom, count, flux, n_eff, normals = _receivers(rng, 4000, 100.0, 0.5)
    se = flux.std() / np.sqrt(flux.size)
    cached = receiver_spread(mom, nmom, n_eff, flux, normals) <= SPREAD_MAX
    assert abs(flux[cached].mean() - flux.mean()) < 3 * se
    by_count = receiver_spread(mom, nmom, count, flux, normals) <= SPREAD_MAX
    assert flux[by_count].mean() < flux.mean() - 3 * se  # the former rule: biased low


def test_unevenly_lit_receivers_are_still_uncached():
    """The light on one half of each receiver (a shadow edge across it), particles of equal
    flux: the effective count is the count and the spread test still sees it. (Where heavy
    particles land too, their noise hides such an edge from the test: it then keeps the
    receiver, as the equal-weight test keeps one with few deposits.)"""
    from mi_twopass.prepass.radiosity import SPREAD_MAX, receiver_spread
    rng = np.random.default_rng(6)
    mom, nmom, count, flux, n_eff, normals = _receivers(rng, 200, 100.0, 0.0, half=True)
    assert np.array_equal(n_eff, count)
    assert np.mean(receiver_spread(mom, nmom, n_eff, flux, normals) > SPREAD_MAX) > 0.95
