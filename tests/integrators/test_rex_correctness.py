"""Root causes of wrong ``rex`` images on scenes it was not written for, each pinned by a scene
that reproduced it: the image mean against Mitsuba's ``path`` (max_depth −1 unless stated)
within a z-bound, or the exact behaviour asked for.

* A room of two-sided walls whose normals point out (veach-bidir): the probe that finds rex
  buckets buried inside closed objects took the back faces of two-sided walls for the inside
  of an object, so every bucket of the room was "half buried" and its irradiance doubled
  (veach-bidir 1.78× path; ×1.0 now). Only the back of a one-sided surface walls a point in.
* A lamp shade (veach-bidir's sconce): its triangles are far smaller than a pixel or missed
  by the size pass, so their cap was level 0 and each stayed one bucket, whatever the photon
  count; the camera sees a rim of each triangle, not its average (bulb alone: 1.26× path
  with direct="rex", 1.085× with "shadow", the same at 4× the photons). The cap is soft now.
* Infinite emitters (constant, envmap, sunsky, directional) in a room of rectangles sharing a
  BSDF: Mitsuba 3.9 merges them into one mesh whose bbox leaves them out, so the emitters'
  bounding sphere (their ``sample_ray``) was too small and photons started inside the room
  (1.98× with a constant sky). Photons of infinite emitters leave a sphere around the
  geometry's own bounds.
* Instances (shapegroup + instance): the Instance has no surface area (crash); instanced
  surfaces are path traced now.
* bumpmap / normalmap around a diffuse BSDF have a diffuse BSDF's flags, but shade with a
  tilted normal: read from a rex they were 2.6 % / 0.7 % too bright. Rexes hold light only
  on Lambertian BSDFs (diffuse, and twosided / blendbsdf of them).
* A finite max_depth: the rexes held photons of every depth up to max_depth − 2 and were read
  at any eye depth (after a mirror too), and max_depth = 0 rendered the emitters.
* A scene at 1e-4 m: Mitsuba's ray offset is at least 89 µm (most of the scene), and the
  photons of an area light started in the middle of the box (1.11× the unscaled image).
* A medium: rex has no volume transport; it refuses the scene with a ValueError.
* A rough dielectric: 1.4 % of its glossy samples (1.9 % of those from inside) are ones
  Mitsuba's own sampling discards (weight 0: a microfacet event whose direction lands on the
  other side). The photons weighted them by the BSDF's value over the density of the event
  that does reach that side, 0.2 on average where the sample is worth 0: 0.6 % more light
  out of a glass bounce from inside. They are discarded now, and the density is the sample's
  own (``bs.pdf``, equal to ``bsdf.pdf`` wherever Mitsuba keeps a sample). On caustic.xml
  with a rough glass sphere (alpha 0.15) the image mean did not move within the noise
  (1.0039 → 1.0037 of path's, ``check`` at 128², 64 spp).

Statistics. Every renderer renders K = 2 independent images (fresh prepass per seed). The
standard error of an image mean comes from the spread of its 4×4-pixel block means across
the renders (16 blocks: ~16 degrees of freedom per side, assuming blocks independent); the
test is |m_rex − m_path| ≤ Z_MAX·sqrt(se_rex² + se_path²) + BLUR·m_path. BLUR is rex's bucket
blur, the bias its class docstring states for image means at these photon counts (1 %); it is
not tuned per scene.
"""
import math
import os
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_twopass  # noqa: F401
from mi_twopass.evaluation.statistics import block_means
from mi_twopass.prepass.rex_textures import RexSettings
from mi_twopass.prepass.rex_textures import build as build_rexes
from mi_twopass.scene.bounds import scene_bounds
from mi_twopass.scene.lambertian import is_lambertian

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import hard_scenes as hs  # noqa: E402

T = mi.ScalarTransform4f
Z_MAX = 4.0
#: rex's bias on an image mean from the bucket blur (RexIntegrator docstring, "Paths")
BLUR = 0.01
K = 2
PHOTONS = 65536


@pytest.fixture(autouse=True, scope="module")
def _register_rex():
    import mi_twopass.integrators.rex  # noqa: F401


def rgb(v):
    return {"type": "rgb", "value": [v, v, v] if np.isscalar(v) else list(v)}


def diffuse(v):
    return {"type": "diffuse", "reflectance": rgb(v)}


def camera(origin, target, fov=45, res=16, up=(0, 0, 1)):
    return {"type": "perspective", "fov": fov,
            "to_world": T().look_at(list(origin), list(target), list(up)),
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}}


def mean_and_se(images, block=4):
    """Image mean of K renders and its standard error, from the spread of block means."""
    b = block_means(np.stack(images), block)  # (K, hb, wb)
    nb = b.shape[1] * b.shape[2]
    var = b.var(axis=0, ddof=1).sum() / nb**2 / b.shape[0]
    return float(b.mean()), math.sqrt(var)


def renders(scene, props, spp, seeds):
    return [np.asarray(mi.render(scene, integrator=mi.load_dict(props), spp=spp, seed=s))
            for s in seeds]


def assert_matches_path(scene, rex_props=None, ref_scene=None, path_props=None, spp=64,
                        ref_spp=256, blur=BLUR):
    """rex's image mean equals path's (on ``ref_scene`` if given) within the z-bound + blur."""
    rex_imgs = renders(scene, {"type": "rex", "photons": PHOTONS, **(rex_props or {})}, spp,
                       range(K))
    assert all(np.isfinite(i).all() for i in rex_imgs)
    ref_imgs = renders(ref_scene or scene, {"type": "path", **(path_props or {})}, ref_spp,
                       range(100, 100 + K))
    m_r, se_r = mean_and_se(rex_imgs)
    m_p, se_p = mean_and_se(ref_imgs)
    bound = Z_MAX * math.hypot(se_r, se_p) + blur * abs(m_p)
    print(f"rex {m_r:.5f} ± {se_r:.5f}, path {m_p:.5f} ± {se_p:.5f}, ratio "
          f"{m_r / m_p if m_p else float('nan'):.4f}, bound {bound:.5f}")
    assert abs(m_r - m_p) <= bound, (m_r, m_p, se_r, se_p)


# ---------------------------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------------------------
def twosided_room():
    """A closed room (a cube, normals out) of two-sided diffuse walls, camera and light inside;
    a one-sided box stands on the floor (its foot is buried: the probe must still see that)."""
    return mi.load_dict({
        "type": "scene", "sensor": camera((0, -1.5, 1.6), (0, 0.8, 0.6), fov=70),
        "room": {"type": "cube", "to_world": T().translate([0, 0, 1]).scale([2, 2, 1]),
                 "bsdf": {"type": "twosided", "bsdf": diffuse(0.6)}},
        "box": {"type": "cube", "to_world": T().translate([0.6, 0.6, 0.3]).scale(0.3),
                "bsdf": diffuse([0.7, 0.4, 0.3])},
        "light": {"type": "rectangle",
                  "to_world": T().translate([0, 0.5, 1.95]).rotate([1, 0, 0], 180).scale(0.4),
                  "emitter": {"type": "area", "radiance": rgb(8.0)}}})


def _mesh(name, P, F, normals=None):
    mesh = mi.Mesh(name, len(P), len(F), has_vertex_normals=normals is not None)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.asarray(P, np.float32).ravel())
    params["faces"] = mi.UInt32(np.asarray(F, np.uint32).ravel())
    if normals is not None:
        params["vertex_normals"] = mi.Float(np.asarray(normals, np.float32).ravel())
    params.update()
    return mesh


def torus(R=0.5, r=0.2, n=24, m=12):
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n, endpoint=False),
                       np.linspace(0, 2 * np.pi, m, endpoint=False), indexing="ij")
    P = np.stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u),
                  0.3 + r * np.sin(v)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    a, b = i * m + j, ((i + 1) % n) * m + j
    c, d = ((i + 1) % n) * m + (j + 1) % m, i * m + (j + 1) % m
    F = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                        np.stack([a, c, d], -1).reshape(-1, 3)])
    return _mesh("torus", P, F)


def sky_room(emitter, optimize=True):
    """A torus in a 4×4×2 room with a window in its right wall. The walls and the ceiling share
    a BSDF, so Mitsuba merges these rectangles into one mesh whose bbox leaves them out; the
    scene's bbox is then the floor and the torus only (bounding radius 2.8 < the room's 3.5)."""
    wall = diffuse(0.6)
    d = {"type": "scene", "sensor": camera((0, -1.8, 1.0), (0, 0, 0.4), fov=70),
         "floor": {"type": "rectangle", "to_world": T().scale([2, 2, 1]), "bsdf": diffuse(0.5)},
         "torus": torus(), "sky": emitter}
    for name, t in {"ceiling": T().translate([0, 0, 2]).rotate([1, 0, 0], 180).scale([2, 2, 1]),
                    "back": T().translate([0, 2, 1]).rotate([1, 0, 0], 90).scale([2, 1, 1]),
                    "front": T().translate([0, -2, 1]).rotate([1, 0, 0], -90).scale([2, 1, 1]),
                    "left": T().translate([-2, 0, 1]).rotate([0, 1, 0], 90).scale([1, 2, 1]),
                    "right_low": T().translate([2, 0, 0.4]).rotate([0, 1, 0], -90)
                    .scale([0.4, 2, 1]),
                    "right_high": T().translate([2, 0, 1.7]).rotate([0, 1, 0], -90)
                    .scale([0.3, 2, 1])}.items():
        d[name] = {"type": "rectangle", "to_world": t, "bsdf": wall}
    return mi.load_dict(d, optimize=optimize)


def _sky_bitmap():
    """An envmap brighter above the horizon, with a warm blob (16×32 lat-long)."""
    theta = (np.arange(16) + 0.5) / 16 * np.pi
    phi = (np.arange(32) + 0.5) / 32 * 2 * np.pi
    img = np.empty((16, 32, 3), np.float32)
    base = 0.2 + 1.5 * np.clip(np.cos(theta), 0, None)[:, None]
    blob = 6.0 * np.exp(-((theta[:, None] - 1.0) ** 2 + (phi[None, :] - 0.3) ** 2) / 0.05)
    img[..., 0] = base + blob
    img[..., 1] = base + 0.6 * blob
    img[..., 2] = base
    return mi.Bitmap(img)


SKIES = {
    "constant": lambda: {"type": "constant", "radiance": rgb(1.0)},
    "envmap": lambda: {"type": "envmap", "bitmap": _sky_bitmap(),
                       "to_world": T().rotate([1, 0, 0], 90)},
    "sunsky": lambda: {"type": "sunsky", "sun_direction": [1.0, 0.2, 0.6]},
    "directional": lambda: {"type": "directional", "direction": [-1.0, 0.1, -0.5],
                            "irradiance": rgb(3.0)},
}


def instances():
    """Two instances of a shape group (a cube and a sphere) on a floor under a point light."""
    return mi.load_dict({
        "type": "scene", "sensor": camera((0, -4, 3), (0, 0, 0.3)),
        "floor": {"type": "rectangle", "to_world": T().scale([2, 2, 1]), "bsdf": diffuse(0.5)},
        "group": {"type": "shapegroup",
                  "cube": {"type": "cube", "to_world": T().scale(0.25),
                           "bsdf": diffuse([0.7, 0.3, 0.2])},
                  "ball": {"type": "sphere", "center": [0, 0, 0.5], "radius": 0.2,
                           "bsdf": diffuse(0.8)}},
        "a": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
              "to_world": T().translate([-0.7, 0, 0.25])},
        "b": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
              "to_world": T().translate([0.7, 0.3, 0.25]).rotate([0, 0, 1], 30)},
        "light": {"type": "point", "position": [0.3, -0.5, 2.0], "intensity": rgb(6.0)}})


def _bump_texture():
    rng = np.random.default_rng(1)
    return {"type": "bitmap", "bitmap": mi.Bitmap(rng.random((32, 32, 1)).astype(np.float32)),
            "raw": True}


def _normal_texture():
    """Normals tilted by ~45° on average (a constant lean plus noise), encoded as (n + 1) / 2."""
    rng = np.random.default_rng(2)
    n = np.stack([0.9 + 0.2 * rng.standard_normal((32, 32)),
                  -0.4 + 0.2 * rng.standard_normal((32, 32)), np.ones((32, 32))], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return {"type": "bitmap", "bitmap": mi.Bitmap(((n + 1) / 2).astype(np.float32)),
            "raw": True, "filter_type": "nearest"}


BSDFS = {
    "blend_diffuse_conductor": lambda: {"type": "blendbsdf", "weight": 0.5, "a": diffuse(0.6),
                                        "b": {"type": "conductor"}},
    "blend_two_diffuse": lambda: {"type": "blendbsdf", "weight": 0.3, "a": diffuse(0.6),
                                  "b": diffuse([0.2, 0.5, 0.8])},
    "thindielectric": lambda: {"type": "thindielectric"},
    "roughconductor": lambda: {"type": "roughconductor", "alpha": 0.3},
    "plastic": lambda: {"type": "plastic"},
    "roughplastic": lambda: {"type": "roughplastic", "alpha": 0.2},
    "principled": lambda: {"type": "principled", "roughness": 0.4},
    "dielectric": lambda: {"type": "dielectric"},
    "roughdielectric": lambda: {"type": "roughdielectric", "alpha": 0.2},
    "twosided_two_albedos": lambda: {"type": "twosided", "a": diffuse(0.7), "b": diffuse(0.2)},
    "mask": lambda: {"type": "mask", "opacity": 0.4, "bsdf": diffuse(0.7)},
    "bumpmap": lambda: {"type": "bumpmap", "arbitrary": _bump_texture(), "scale": 0.3,
                        "bsdf": diffuse(0.7)},
    "normalmap": lambda: {"type": "normalmap", "normalmap": _normal_texture(),
                          "bsdf": diffuse(0.7)},
}


def bsdf_scene(bsdf):
    """A sphere and a tilted panel of ``bsdf`` on a diffuse floor before a green wall."""
    return mi.load_dict({
        "type": "scene", "sensor": camera((0, -3.5, 1.6), (0, 0, 0.5)),
        "floor": {"type": "rectangle", "to_world": T().scale([2, 2, 1]), "bsdf": diffuse(0.5)},
        "wall": {"type": "rectangle",
                 "to_world": T().translate([0, 1.2, 1]).rotate([1, 0, 0], 90).scale([2, 1, 1]),
                 "bsdf": diffuse([0.3, 0.6, 0.3])},
        "ball": {"type": "sphere", "center": [-0.45, 0, 0.45], "radius": 0.4, "bsdf": bsdf},
        "panel": {"type": "rectangle", "bsdf": bsdf,
                  "to_world": T().translate([0.55, 0.2, 0.5]).rotate([0, 0, 1], -30)
                  .rotate([1, 0, 0], 80).scale(0.45)},
        "light": {"type": "rectangle",
                  "to_world": T().translate([0.3, -0.5, 2.2]).rotate([1, 0, 0], 180).scale(0.4),
                  "emitter": {"type": "area", "radiance": rgb(12.0)}}})


def normalmap_reflector():
    """A floor lit only by a normal-mapped wall (a light faces the wall): the floor's rexes
    hold photons that left a non-symmetric BSDF (normal mapping tilts one side's frame)."""
    return mi.load_dict({
        "type": "scene", "sensor": camera((0, -2.5, 2.0), (0, 0.3, 0), fov=40),
        "floor": {"type": "rectangle", "to_world": T().scale([2, 2, 1]), "bsdf": diffuse(0.6)},
        "wall": {"type": "rectangle", "bsdf": BSDFS["normalmap"](),
                 "to_world": T().translate([0, 1.5, 1.2]).rotate([1, 0, 0], 90)
                 .scale([2, 1.2, 1])},
        "light": {"type": "rectangle",
                  "to_world": T().translate([0, -1.0, 1.5]).rotate([1, 0, 0], -90).scale(0.3),
                  "emitter": {"type": "area", "radiance": rgb(20.0)}}})


def smooth_blob():
    """A low-polygon sphere with interpolated normals (shading ≠ geometric normal)."""
    n, m = 8, 6
    th, ph = np.meshgrid(np.pi * np.arange(m + 1) / m, 2 * np.pi * np.arange(n) / n,
                         indexing="ij")
    N = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    N = N.reshape(-1, 3)
    i, j = np.meshgrid(np.arange(m), np.arange(n), indexing="ij")
    a, b = i * n + j, i * n + (j + 1) % n
    c, d = (i + 1) * n + (j + 1) % n, (i + 1) * n + j
    F = np.concatenate([np.stack([a, d, c], -1).reshape(-1, 3),
                        np.stack([a, c, b], -1).reshape(-1, 3)])
    return mi.load_dict({
        "type": "scene", "sensor": camera((0, -2.5, 1.2), (0, 0, 0.45), fov=40),
        "floor": {"type": "rectangle", "to_world": T().scale([3, 3, 1]), "bsdf": diffuse(0.5)},
        "blob": _mesh("blob", N * 0.5 + [0, 0, 0.5], F, normals=N),
        "light": {"type": "point", "position": [1.0, -1.0, 1.5], "intensity": rgb(3.0)}})


CASES = {"twosided_room": lambda: (twosided_room(), None),
         "normalmap_reflector": lambda: (normalmap_reflector(), None),
         "instances": lambda: (instances(), None),
         "smooth_normals": lambda: (smooth_blob(), None)}
for _name, _sky in SKIES.items():
    # path on the same scene loaded without merging (a right bbox) is the reference
    CASES[f"sky_{_name}"] = (lambda s: lambda: (sky_room(s()), sky_room(s(), optimize=False)))(_sky)
for _name, _bsdf in BSDFS.items():
    CASES[f"bsdf_{_name}"] = (lambda b: lambda: (bsdf_scene(b()), None))(_bsdf)


@pytest.mark.filterwarnings("ignore:scene.bbox\\(\\) misses part")  # the sky rooms, on purpose
@pytest.mark.parametrize("case", sorted(CASES))
def test_image_mean_matches_path(case):
    scene, ref_scene = CASES[case]()
    assert_matches_path(scene, ref_scene=ref_scene, ref_spp=1024)


# ---------------------------------------------------------------------------------------------
# Finite max_depth
# ---------------------------------------------------------------------------------------------
def cornell(s=1.0, mirror=False):
    """Mitsuba's Cornell box scaled by ``s`` (camera too: the same image at every scale), the
    camera tilted 8° down so that the light is out of view (its edges are the noisiest pixels);
    ``mirror``: the tall box is a mirror (rexes read after a delta bounce)."""
    d = mi.cornell_box()
    d.pop("integrator", None)
    sensor = d["sensor"]
    sensor["film"].update(width=16, height=16, rfilter={"type": "box"})
    sensor.update(to_world=T().look_at([0, 0, 3.9 * s], [0, -0.55 * s, 0], [0, 1, 0]),
                  near_clip=1e-3 * s, far_clip=100.0 * s, focus_distance=1000.0 * s)
    for key, value in d.items():
        if isinstance(value, dict) and "to_world" in value and key != "sensor":
            value["to_world"] = T().scale(s) @ value["to_world"]
    if mirror:
        d["large-box"]["bsdf"] = {"type": "conductor"}
    return mi.load_dict(d)


@pytest.mark.parametrize("max_depth", [1, 2, 3])
@pytest.mark.parametrize("direct", ["shadow", "rex"])
def test_finite_max_depth_matches_path(max_depth, direct):
    """A path of at most max_depth segments, as Mitsuba's path (1: emitters seen directly, none
    here; 2: direct light; 3: one bounce, also after the mirror: rexes read at eye depth 1
    must hold only direct light then)."""
    assert_matches_path(cornell(mirror=True), {"direct": direct, "max_depth": max_depth},
                        path_props={"max_depth": max_depth}, spp=512, ref_spp=4096)


def test_max_depth_zero_is_black():
    """As path: no segment, no light, not even the light seen directly (in view here)."""
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=16, height=16)
    scene = mi.load_dict(d)
    lit = np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 1}),
                               spp=4))
    assert lit.max() > 1  # the light is in view
    img = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "rex", "photons": PHOTONS, "max_depth": 0}), spp=4))
    assert img.max() == 0


# ---------------------------------------------------------------------------------------------
# Scene scale
# ---------------------------------------------------------------------------------------------
def test_tiny_scene_matches_unscaled_path():
    """At 1e-4 m, rex's own rays (photons, their bounces, eye continuations) are offset
    relative to the scene; the reference is path on the unscaled box (Mitsuba's own path is
    0.90× there). direct="rex": the eye pass casts no shadow ray (see the next test)."""
    assert_matches_path(cornell(1e-4), {"direct": "rex"}, ref_scene=cornell(1.0))


def slab(s):
    """A floor with a strip 0.3·s above it that a low light makes cast a shadow beside it (in
    view), all scaled by s."""
    sensor = camera((0, -0.5 * s, 4 * s), (0, 0, 0), fov=35)
    sensor.update(near_clip=1e-3 * s, far_clip=100.0 * s)
    return mi.load_dict({
        "type": "scene", "sensor": sensor,
        "floor": {"type": "rectangle", "to_world": T().scale(s), "bsdf": diffuse(0.6)},
        "strip": {"type": "rectangle", "bsdf": diffuse(0.3),
                  "to_world": T().translate([-0.15 * s, 0, 0.3 * s]).scale([0.15 * s, s, 1])},
        "light": {"type": "rectangle",
                  "to_world": T().translate([s, 0, 1.2 * s]).rotate([0, 1, 0], 225)
                  .scale(0.2 * s),
                  "emitter": {"type": "area", "radiance": rgb(40.0)}}})


def test_tiny_scene_shadow_rays():
    """The eye pass's shadow rays start at a scene-relative offset too (mi_twopass.rays): with
    Mitsuba's absolute 89 µm they started above a strip 30 µm high and lost its shadow."""
    assert_matches_path(slab(1e-4), {"direct": "shadow"}, ref_scene=slab(1.0))


def test_huge_scene_matches_path():
    assert_matches_path(cornell(1e4))


# ---------------------------------------------------------------------------------------------
# What rex refuses, and the pieces behind the fixes
# ---------------------------------------------------------------------------------------------
MEDIUM = {"type": "homogeneous", "albedo": 0.8, "sigma_t": 1.0}


@pytest.mark.parametrize("where", ["sensor", "shape"])
def test_media_are_refused(where):
    d = {"type": "scene", "sensor": camera((0, -3, 2), (0, 0, 0)),
         "floor": {"type": "rectangle", "to_world": T().scale(2), "bsdf": diffuse(0.5)},
         "light": {"type": "point", "position": [0, 0, 2], "intensity": rgb(5.0)}}
    if where == "sensor":
        d["fog"] = MEDIUM
        d["sensor"]["medium"] = {"type": "ref", "id": "fog"}
    else:
        d["ball"] = {"type": "sphere", "radius": 0.3, "center": [0, 0, 0.5],
                     "bsdf": {"type": "null"}, "interior": MEDIUM}
    scene = mi.load_dict(d)
    integrator = mi.load_dict({"type": "rex", "photons": PHOTONS})
    with pytest.raises(ValueError, match=r"(?s)participating media.*HomogeneousMedium.*volpath"):
        integrator.render(scene, spp=1)
    # through mi.render the ValueError is the cause of Dr.Jit's RuntimeError
    with pytest.raises(RuntimeError) as info:
        mi.render(scene, integrator=integrator, spp=1)
    cause = info.value
    while cause.__cause__ is not None:
        cause = cause.__cause__
    assert isinstance(cause, ValueError) and "volpath" in str(cause)


def test_scene_bounds_include_merged_rectangles():
    """Mitsuba 3.9's bbox of rectangles merged into one mesh is empty; scene_bounds is not."""
    scene = mi.load_dict({"type": "scene",
                          "a": {"type": "rectangle", "to_world": T().scale(2),
                                "bsdf": diffuse(0.5)},
                          "b": {"type": "rectangle", "to_world": T().translate([0, 0, 1]),
                                "bsdf": diffuse(0.5)}})
    b = scene_bounds(scene)
    assert np.allclose(b.lo, [-2, -2, 0]) and np.allclose(b.hi, [2, 2, 1])


@pytest.mark.parametrize("sky", sorted(SKIES))
def test_sky_irradiance_with_merged_rectangles(sky):
    """Two rectangles sharing a BSDF (merged: Mitsuba's bbox is empty) under an infinite
    emitter: the photons' irradiance on the open floor is the emitter's ∫ L cos θ dω (from
    Mitsuba's own emitter sampling), within the photons' Poisson noise."""
    scene = mi.load_dict({
        "type": "scene", "sensor": camera((0, -3, 3), (0, 0, 0)),
        "floor": {"type": "rectangle", "bsdf": diffuse(0.5)},
        "below": {"type": "rectangle", "bsdf": diffuse(0.5),  # out of the floor's sky
                  "to_world": T().translate([0, 0, -3]).rotate([1, 0, 0], 180).scale(0.5)},
        "sky": SKIES[sky]()})
    assert not scene.bbox().valid()  # the Mitsuba 3.9 merge this guards against
    with pytest.warns(UserWarning, match=r"scene\.bbox\(\) misses part of the geometry"):
        pre = build_rexes(scene, RexSettings(photons=100_000, direct="rex"), seed=2)
    leaves = pre.rexes.leaves()
    # the floor's two triangles (area 2 each; those of "below" have 0.125)
    floor = np.isin(leaves["rex"], np.nonzero(pre.tables.rex_area > 1.0)[0])
    assert floor.any()
    E = (leaves["E_direct"][floor].mean(axis=1) * leaves["area"][floor]).sum() \
        / leaves["area"][floor].sum()
    # the exact irradiance of an unoccluded upward plane, by emitter sampling (2^16 samples)
    n = 1 << 16
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(si.n)
    si.wi = mi.Vector3f(0, 0, 1)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(7, n)
    ds, w = scene.sample_emitter_direction(si, sampler.next_2d(), False)
    E_exact = float(dr.mean(dr.mean(w, axis=0) * dr.maximum(ds.d.z, 0.0))[0])
    count = leaves["count"][floor].sum()
    assert abs(E / E_exact - 1) < 4 / math.sqrt(count) + 0.02  # + the MC reference's noise


def test_lambertian_bsdfs_only():
    """Flags alone let bumpmap / normalmap (tilted shading normals) pass as diffuse."""
    yes = [{"type": "diffuse"}, {"type": "twosided", "bsdf": {"type": "diffuse"}},
           BSDFS["blend_two_diffuse"](), BSDFS["twosided_two_albedos"]()]
    no = [BSDFS[k]() for k in BSDFS if k not in ("blend_two_diffuse", "twosided_two_albedos")]
    for d in yes:
        assert is_lambertian(mi.load_dict(d)), d["type"]
    for d in no:
        assert not is_lambertian(mi.load_dict(d)), d["type"]


def test_capped_bucket_still_refines():
    """A surface the camera sees as a dot gets the size-pass cap 0, yet its buckets must shrink
    as photons grow (a hard cap kept one bucket: the irradiance at a point was the surface's
    average whatever the photon count, 1.26× path at the veach-bidir bulb's shade)."""
    I, h = 1.0, 0.3
    scene = mi.load_dict({
        "type": "scene",
        "sensor": camera((0, -400, 300), (0, 0, 0), fov=10),  # the square: half a pixel
        "floor": {"type": "rectangle", "bsdf": diffuse(0.5)},  # [-1, 1]², facing +z
        "light": {"type": "point", "position": [-0.8, -0.8, h], "intensity": rgb(I)}})
    pre = build_rexes(scene, RexSettings(photons=200_000, direct="rex", light_levels=0), seed=1)
    assert pre.cap.max() == 0  # the size pass asks for one bucket
    E, _, level = pre.rexes.irradiance(mi.UInt32(0), mi.Point2f(0.1, 0.1), True, 1.0, 0.0)
    exact = I / h**2  # under the light: (u, v) = (0.1, 0.1) is (−0.8, −0.8)
    assert int(level[0]) >= 3
    # leaves of side 2^-level·2 m ≤ h/1.2 around the peak: their blur is ≲ 10 % (h/r³ over
    # the bucket); a single bucket gave the floor's average, 3 % of the peak
    assert abs(float(E[0][0]) / exact - 1) < 0.15, (float(E[0][0]), exact)


def _samples_from_both_sides(bsdf, n=1 << 15, seed=3):
    """``(si, bs, w)``: ``bsdf`` sampled in importance mode at the origin of a flat surface,
    for incident directions uniform over the sphere (the back side too: inside a glass)."""
    rng = np.random.default_rng(seed)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(si.n)
    si.uv = mi.Point2f(mi.Float(rng.random(n)), mi.Float(rng.random(n)))
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0)
    cos_t = rng.uniform(-1, 1, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    sin_t = np.sqrt(1 - cos_t**2)
    si.wi = mi.Vector3f(mi.Float(sin_t * np.cos(phi)), mi.Float(sin_t * np.sin(phi)),
                        mi.Float(cos_t))
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    bs, w = bsdf.sample(ctx, si, mi.Float(rng.random(n)),
                        mi.Point2f(mi.Float(rng.random(n)), mi.Float(rng.random(n))))
    return si, bs, w


@pytest.mark.parametrize("name", ["roughdielectric", "roughplastic", "principled", "blendbsdf",
                                  "normalmap", "mask", "diffuse"])
def test_a_photon_scatters_as_mitsuba_samples(name):
    """The photon's factor where it scatters (``photon_scatter_weight``): 0 wherever Mitsuba's
    own sample weight is 0, and elsewhere the adjoint evaluation over the density that
    ``bsdf.pdf`` gives the direction (the sample's own ``bs.pdf`` is read)."""
    from mi_twopass.prepass.rex_textures import photon_scatter_weight

    bsdf = mi.load_dict(hs.bsdfs()[name])
    si, bs, w = _samples_from_both_sides(bsdf)
    wi_geo = mi.Frame3f.cos_theta(si.wi)  # the geometric normal is the shading one here
    factor, good, smooth = photon_scatter_weight(bsdf, si, bs, w, wi_geo, mi.BSDFContext())
    si_adj = mi.SurfaceInteraction3f(si)
    si_adj.wi = bs.wo
    f_adj = bsdf.eval(mi.BSDFContext(), si_adj, si.wi, smooth)
    pdf = bsdf.pdf(mi.BSDFContext(mi.TransportMode.Importance), si, bs.wo, smooth)
    wo_geo = mi.Frame3f.cos_theta(bs.wo)
    expected = f_adj * dr.abs(wo_geo / dr.select(pdf > 0, wi_geo * pdf, 1.0))
    factor, expected = np.asarray(dr.max(factor)), np.asarray(dr.max(expected))
    glossy = np.asarray(smooth)
    discarded = glossy & (np.asarray(dr.max(w)) == 0)
    kept = glossy & ~discarded & (np.asarray(pdf) > 0)
    assert kept.mean() > 0.2
    assert np.allclose(factor[kept], expected[kept], rtol=1e-3, atol=0)
    assert np.all(factor[discarded] == 0)
    if name == "roughdielectric":
        # the samples Mitsuba discards from inside the glass, which the photons used to keep
        # with the other event's density
        # (1.4 % of the glossy samples; their factors averaged 0.2, 0.6 % of what the samples
        # from inside carried)
        inside = np.asarray(si.wi.z) < 0
        assert discarded.sum() > 1e-2 * glossy.sum()
        assert expected[discarded].sum() > 3e-3 * expected[glossy & inside].sum()
