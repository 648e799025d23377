"""radiosity_gather: consistency with path, prepass_scene, stats, hard cases."""
import os
import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_twopass.evaluation.statistics import block_z_scores
from mi_twopass.integrators.base import R_THRESH_REL

SCENES = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(__file__))), "scenes_xml")
CORNELL = os.path.join(SCENES, "cornell_box.xml")
FURNACE = os.path.join(SCENES, "furnace.xml")


def renders(scene, spec, k, spp, seed0=0):
    out = []
    for s in range(k):
        integrator = mi.load_dict(spec)
        out.append(np.asarray(mi.render(scene, integrator=integrator, spp=spp, seed=seed0 + s)))
    return np.stack(out), integrator


def test_large_r_thresh_agrees_with_path():
    """r_thresh → ∞ is path tracing: per-block z-test against Mitsuba's path."""
    scene = mi.load_file(CORNELL, res=32)
    a, _ = renders(scene, {"type": "radiosity_gather", "r_thresh": 1e6,
                           "max_patches": 256}, 6, 32)
    b, _ = renders(scene, {"type": "path", "max_depth": -1}, 6, 32, seed0=100)
    z = block_z_scores(a, b, 8)
    assert np.all(np.isfinite(a))
    assert np.max(np.abs(z)) < 4.0, z
    assert np.mean(z**2) < 2.5, z


def test_default_is_close_to_path_on_cornell():
    """The two-pass default is biased only by the radiosity solution: mean within 2 %."""
    scene = mi.load_file(CORNELL, res=32)
    a, integ = renders(scene, {"type": "radiosity_gather"}, 2, 64)
    b, _ = renders(scene, {"type": "path", "max_depth": -1}, 2, 256, seed0=50)
    assert abs(a.mean() / b.mean() - 1) < 0.02
    assert integ.stats["implicit_rays"] > 0


def test_furnace_integrator_exact():
    """Closed furnace: radiance Le/(1-ρ) everywhere, also through the gather."""
    rho = 0.9
    scene = mi.load_file(FURNACE, res=16, albedo=rho)
    img, _ = renders(scene, {"type": "radiosity_gather", "r_thresh": 0.0, "max_patches": 64}, 1, 64)
    assert np.all(np.isfinite(img))
    assert img.mean() == pytest.approx(1.0 / (1 - rho), rel=0.01)


#: the Cornell box's light: a one-sided rectangle facing down (−y) in the plane y = 0.99
CORNELL_LIGHT_Y = 0.99


def first_hits(scene, spp, seed=0):
    """Counts over the camera rays of ``mi.render(scene, spp=spp, seed=seed)``:
    ``(front, lit, behind)``.

    The rays are the render's own: Mitsuba's render draws each sample's film position from the
    sampler (seeded by ``seed``) before it calls ``sample``, so an integrator that only looks at
    the camera ray's first hit sees the same rays as radiosity_gather did. With the box filter a
    pixel holds the mean of its ``spp`` values, so the image sum × spp counts the rays exactly.

    * ``front``: the first hit is the front of a surface (cos θ_i > 0). Every Cornell box surface
      is diffuse with a non-zero albedo, so its BSDF sample has pdf > 0 and weight ρ ≠ 0 there.
    * ``lit``: front and strictly in front of the light's plane (y < 0.99 − 1e-3), where every
      point of the light faces the shading point: emitter sampling returns a non-zero weight.
    * ``behind``: front and strictly behind the light's plane (y > 0.99 + 1e-3: the ceiling and
      the top of the walls), where no point of the one-sided light faces it: weight 0.
    The light itself lies in its own plane (cos = 0 up to round-off) and is in neither."""
    class FirstHits(mi.SamplingIntegrator):
        def sample(self, scene, sampler, ray, medium=None, active=True):
            si = scene.ray_intersect(ray, active)
            front = active & si.is_valid() & (mi.Frame3f.cos_theta(si.wi) > 0)
            lit = front & (si.p.y < CORNELL_LIGHT_Y - 1e-3)
            behind = front & (si.p.y > CORNELL_LIGHT_Y + 1e-3)
            value = mi.Spectrum(dr.select(front, 1.0, 0.0), dr.select(lit, 1.0, 0.0),
                                dr.select(behind, 1.0, 0.0))
            return value, mi.Bool(True), []

    img = np.asarray(mi.render(scene, integrator=FirstHits(mi.Properties()), spp=spp, seed=seed),
                     dtype=np.float64)
    counts = np.rint(img.sum(axis=(0, 1)) * spp).astype(int)
    return tuple(int(c) for c in counts)


def test_ray_counts_at_max_depth_2_are_the_first_hits():
    """max_depth = 2: one vertex, so exactly one gather ray per camera ray that hits the front of
    a surface (the BSDF sample at the first vertex: no Russian roulette before rr_depth = 5,
    pdf > 0 and weight ρ ≠ 0 on every Cornell surface), and one shadow ray where emitter
    sampling returns a non-zero weight: at least every ``lit`` hit, at most the ``front`` hits
    that are not ``behind`` the one-sided light (:func:`first_hits`). A finite max_depth has no
    far gather and no virtual luminaire (``far_gather_exact``), so nothing else is counted."""
    scene = mi.load_file(CORNELL, res=16)
    for seed in (0, 3):
        integ = mi.load_dict({"type": "radiosity_gather", "max_depth": 2, "max_patches": 128})
        mi.render(scene, integrator=integ, spp=4, seed=seed)
        s = integ.stats
        front, lit, behind = first_hits(scene, 4, seed)
        assert 0 < lit < front < s["viewing_rays"] and behind > 0
        assert s["implicit_rays"] == front, (s, front)
        assert lit <= s["explicit_rays"] <= front - behind, (s, lit, front, behind)


def test_stats_have_table1_rows():
    scene = mi.load_file(CORNELL, res=16)
    integ = mi.load_dict({"type": "radiosity_gather", "max_patches": 128})
    mi.render(scene, integrator=integ, spp=4)
    s = integ.stats
    for key in ("viewing_rays", "implicit_rays", "explicit_rays", "prepass_rays",
                "prepass_seconds", "render_seconds", "cache_bytes"):
        assert key in s
    assert s["viewing_rays"] == 16 * 16 * 4
    assert s["prepass_rays"] > 0 and s["prepass_seconds"] > 0 and s["render_seconds"] > 0
    # Lower bounds: the first vertex of every camera ray that hits the front of a surface casts
    # one gather ray (Russian roulette starts at rr_depth = 5) and, where it is lit (in front
    # of the light's plane), one shadow ray to the light; later vertices and virtual luminaires
    # only add rays (first_hits: the render's own camera rays).
    front, lit, _ = first_hits(scene, 4, 0)
    assert front <= s["implicit_rays"] <= s["viewing_rays"] * 64
    assert lit <= s["explicit_rays"] and s["cache_bytes"] > 0
    # a second render reuses the prepass
    mi.render(scene, integrator=integ, spp=4, seed=0)
    assert integ.stats["prepass_seconds"] == 0.0


def test_r_thresh_zero_uses_one_implicit_ray_per_view_ray():
    scene = mi.load_file(CORNELL, res=16)
    integ = mi.load_dict({"type": "radiosity_gather", "r_thresh": 0.0, "max_patches": 128,
                          "vl_threshold": 2.0})
    mi.render(scene, integrator=integ, spp=4)
    s = integ.stats
    # pure two-pass: one gather ray per camera ray that hits the front of a surface, and one
    # shadow ray at each such hit in front of the light (first_hits: the render's own rays);
    # a gather ray ends at the patch it hits, except on the few patches cut by geometry
    # (split_patches: not cached, traced on), which add a vertex, so the counts exceed these
    # bounds only by those continuations
    front, lit, _ = first_hits(scene, 4, 0)
    assert front <= s["implicit_rays"] <= s["viewing_rays"]
    assert lit <= s["explicit_rays"] <= s["viewing_rays"]


def test_prepass_scene_is_used(tmp_path):
    """GSII: the prepass runs on a simplified (massing) copy; far gathers read its patches."""
    text = open(CORNELL).read()
    # the massing model: the same room without the two boxes
    simplified = re.sub(r'<shape type="cube".*?</shape>', "", text, flags=re.S)
    assert simplified != text
    p = tmp_path / "massing.xml"
    p.write_text(simplified)
    scene = mi.load_file(CORNELL, res=16)
    full = mi.load_dict({"type": "radiosity_gather", "max_patches": 256, "r_thresh": 0.0})
    simp = mi.load_dict({"type": "radiosity_gather", "max_patches": 256, "r_thresh": 0.0,
                         "prepass_scene": str(p)})
    a = np.asarray(mi.render(scene, integrator=full, spp=16))
    b = np.asarray(mi.render(scene, integrator=simp, spp=16))
    assert np.all(np.isfinite(b))
    assert simp.structure.scene is not scene and simp.structure.simplified
    # the prepass ran on the massing model: less surface, and far gathers read its patches
    assert simp.structure.patches.area.sum() < 0.9 * full.structure.patches.area.sum()
    assert not np.allclose(a, b)


def test_missing_prepass_scene_fails_at_load(tmp_path):
    # mi.load_dict wraps the plugin constructor's exception in a RuntimeError with its message
    missing = str(tmp_path / "nope.xml")
    with pytest.raises(RuntimeError,
                       match="SceneFileError: prepass_scene: file not found: "
                             + re.escape(missing)):
        mi.load_dict({"type": "radiosity_gather", "prepass_scene": missing})


@pytest.mark.parametrize("bad, message", [
    ({"max_patches": 0}, "max_patches=0: must be >= 1"),
    ({"r_thresh": -1.0}, "r_thresh=-1: must be >= 0"),
    ({"component": "nonsense"}, "component='nonsense': expected one of all, direct, indirect"),
    ({"debug": "what"}, "debug='what': expected one of none, radiosity, patches, virtual")])
def test_bad_parameters_fail_at_load(bad, message):
    # the readers' ValueError, wrapped by mi.load_dict in a RuntimeError
    with pytest.raises(RuntimeError, match="ValueError: " + re.escape(message) + "$"):
        mi.load_dict({"type": "radiosity_gather", **bad})


@pytest.mark.parametrize("mode", ["radiosity", "patches", "virtual"])
def test_debug_modes(mode):
    scene = mi.load_file(CORNELL, res=16)
    img = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "radiosity_gather", "debug": mode, "max_patches": 128}), spp=2))
    assert np.all(np.isfinite(img)) and img.max() > 0


def test_components_sum_to_all():
    scene = mi.load_file(CORNELL, res=16)
    parts = {}
    for c in ("all", "direct", "indirect"):
        integ = mi.load_dict({"type": "radiosity_gather", "component": c, "max_patches": 128})
        parts[c] = np.asarray(mi.render(scene, integrator=integ, spp=64, seed=1)).mean()
    assert parts["direct"] > 0 and parts["indirect"] > 0
    assert parts["direct"] + parts["indirect"] == pytest.approx(parts["all"], rel=0.03)


# -- hard cases: no NaN, no Inf ------------------------------------------------------------

def box_scene(scale=1.0, albedo=0.5, emit=True, extra=None):
    d = {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 60,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0.9 * scale],
                                                              target=[0, 0, 0], up=[0, 1, 0]),
                   "near_clip": 1e-3 * scale, "far_clip": 10 * scale,
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "box": {"type": "cube", "flip_normals": True,
                "to_world": mi.ScalarTransform4f().scale(scale),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": albedo}}},
    }
    if emit:
        d["light"] = {"type": "point", "position": [0, 0.5 * scale, 0],
                      "intensity": {"type": "rgb", "value": scale * scale}}
    if extra:
        d.update(extra)
    return mi.load_dict(d)


@pytest.mark.parametrize("case", ["albedo_0.99", "scale_1e-3", "scale_1e4", "no_emitters",
                                  "zero_area_triangle"])
def test_hard_cases_finite(case):
    extra = None
    if case == "zero_area_triangle":
        m = mi.Mesh("degenerate", 3, 1)
        params = mi.traverse(m)
        params["vertex_positions"] = [0, 0, 0, 0.5, 0, 0, 1.0, 0, 0]  # collinear: area 0
        params["faces"] = [0, 1, 2]
        params.update()
        extra = {"degenerate": m}
    scene = {
        "albedo_0.99": lambda: box_scene(albedo=0.99),
        "scale_1e-3": lambda: box_scene(scale=1e-3),
        "scale_1e4": lambda: box_scene(scale=1e4),
        "no_emitters": lambda: box_scene(emit=False),
        "zero_area_triangle": lambda: box_scene(extra=extra),
    }[case]()
    integ = mi.load_dict({"type": "radiosity_gather", "max_patches": 96})
    img = np.asarray(mi.render(scene, integrator=integ, spp=8))
    assert np.all(np.isfinite(img))
    if case == "no_emitters":
        assert np.all(img == 0)
    else:
        assert img.mean() > 0


def test_scale_invariance():
    """The same box at 1e-3 m and at 1e4 m (point light scaled to keep irradiance) looks alike."""
    a = np.asarray(mi.render(box_scene(1e-3), integrator=mi.load_dict(
        {"type": "radiosity_gather", "max_patches": 96}), spp=64))
    b = np.asarray(mi.render(box_scene(1e4), integrator=mi.load_dict(
        {"type": "radiosity_gather", "max_patches": 96}), spp=64))
    assert a.mean() == pytest.approx(b.mean(), rel=0.05)


def test_elements_resolve_the_far_gather():
    """elements_per_patch builds a finer receiving mesh (stats: elements), 1 turns it off, and
    r_thresh = 0 with elements is closer to path than the plain patch means on the Cornell box
    (a patch mean reads dark where gather rays land)."""
    scene = mi.load_file(CORNELL, res=16)
    ref, _ = renders(scene, {"type": "path", "max_depth": -1}, 1, 1024, seed0=70)
    means = {}
    for k in (1, 16):
        img, integ = renders(scene, {"type": "radiosity_gather", "r_thresh": 0.0,
                                     "max_patches": 64, "elements_per_patch": k}, 1, 256)
        means[k] = img.mean() / ref.mean()
        sol = integ.structure
        assert (sol.elements is None) == (k == 1)
        assert integ.stats["elements"] == (0 if k == 1 else sol.elements.count)
        assert np.all(np.isfinite(img))
    assert abs(means[16] - 1) < abs(means[1] - 1), means


def test_default_r_thresh_follows_what_the_camera_sees():
    """r_thresh_rel × the diagonal of what the camera sees (2 m quad, 3 m away), not of the
    scene's bounds, which a 200 m ground plane behind the camera sets."""
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 3], target=[0, 0, 0],
                                                              up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "quad": {"type": "rectangle"},
        "ground": {"type": "rectangle",
                   "to_world": mi.ScalarTransform4f().translate([0, 0, 10]).scale(100)},
        "light": {"type": "constant"},
    })
    integ = mi.load_dict({"type": "radiosity_gather", "max_patches": 64})
    assert integ.r_thresh(scene) == pytest.approx(R_THRESH_REL * 200 * np.sqrt(2), rel=1e-3)
    mi.render(scene, integrator=integ, spp=1)  # no prepass yet above: the scene's bounds
    assert R_THRESH_REL * 2.0 < integ.r_thresh(scene) <= R_THRESH_REL * 2 * np.sqrt(2) + 1e-4
    fixed = mi.load_dict({"type": "radiosity_gather", "max_patches": 64, "r_thresh": 5.0})
    mi.render(scene, integrator=fixed, spp=1)
    assert fixed.r_thresh(scene) == 5.0
