"""Tiny scenes for the cross-integrator hard-case matrix (tests/test_hard_cases.py).

Every builder returns a ``mi.load_dict`` dictionary (``build(name)`` loads one by name). The
scenes are 16×16 pixels; most are variations of one small lit box: five inward-facing walls of
[-1, 1]³ (open towards the camera at +z) with a rectangular area light under the ceiling, hidden
from the camera at (0, 0, 3.5) by a lintel over the opening. Scenes with an exact answer say it in :data:`EXACT`.
"""
import math

import mitsuba as mi
import numpy as np

T = mi.ScalarTransform4f
RES = 16


def rgb(v):
    return {"type": "rgb", "value": [v, v, v] if np.isscalar(v) else list(v)}


def diffuse(albedo=0.6):
    return {"type": "diffuse", "reflectance": rgb(albedo)}


WHITE = {"type": "diffuse", "reflectance": rgb([0.7, 0.6, 0.5])}


def sensor(origin, target, up=(0, 1, 0), fov=50.0, scale=1.0, res=RES):
    """A perspective camera whose clip planes follow the scene's scale."""
    return {"type": "perspective", "fov": fov,
            "near_clip": 1e-3 * scale, "far_clip": 1e3 * scale,
            "to_world": T().look_at(origin=list(origin), target=list(target), up=list(up)),
            "sampler": {"type": "independent"},
            "film": {"type": "hdrfilm", "width": res, "height": res, "pixel_format": "rgb",
                     "rfilter": {"type": "box"}}}


def box(bsdf=WHITE, scale=1.0, light=True, floor_bsdf=None, wall_bsdfs=None):
    """The small lit box (× ``scale``): ``bsdf`` on every wall, ``floor_bsdf`` on the floor,
    ``wall_bsdfs`` (wall name → BSDF) on some walls, a diffuse lintel over the opening."""
    s = scale
    S = T().scale(s)
    d = {"type": "scene", "sensor": sensor([0, 0, 3.5 * s], [0, 0, 0], scale=s)}
    if light:
        d["light"] = {"type": "rectangle",
                      "to_world": S @ T().translate([0, 0.99, 0]).rotate([1, 0, 0], 90).scale(0.3),
                      "emitter": {"type": "area", "radiance": rgb(10.0)}}
    walls = {"floor": ([0, -1, 0], [1, 0, 0], -90), "ceiling": ([0, 1, 0], [1, 0, 0], 90),
             "back": ([0, 0, -1], [0, 1, 0], 0), "left": ([-1, 0, 0], [0, 1, 0], 90),
             "right": ([1, 0, 0], [0, 1, 0], -90)}
    for name, (t, axis, angle) in walls.items():
        b = floor_bsdf if (name == "floor" and floor_bsdf is not None) else bsdf
        b = (wall_bsdfs or {}).get(name, b)
        d[name] = {"type": "rectangle", "to_world": S @ T().translate(t).rotate(axis, angle),
                   "bsdf": b}
    # a lintel across the top of the opening (facing inward) hides the light from the camera:
    # pixels partly covering a visible emitter of radiance 10 made 2 % of noise in the image
    # mean, shared by every integrator rendered with the same seeds
    d["lintel"] = {"type": "rectangle", "bsdf": WHITE,
                   "to_world": S @ T().translate([0, 0.8, 1]).rotate([0, 1, 0], 180)
                   .scale([1, 0.2, 1])}
    return d


# --------------------------------------------------------------------------------------------
# scenes with an exact answer


def furnace(rho, Le=1.0):
    """scenes_xml/furnace.xml as a dict: a closed cube, flip_normals (inward normals: the
    emitting side and the BSDF's front face the inside), diffuse ρ, emitting Le; the camera
    inside. Exact radiance Le / (1 − ρ) everywhere."""
    return {"type": "scene",
            "sensor": sensor([0.1, -0.2, 0.3], [1, 1, -1], fov=90),
            "enclosure": {"type": "cube", "flip_normals": True, "bsdf": diffuse(rho),
                          "emitter": {"type": "area", "radiance": rgb(Le)}}}


POINT = dict(rho=0.5, intensity=2.0, h=1.0, cam=2.0, fov=40.0)


def point_over_plane():
    """A point light of intensity I at height h over a diffuse plane z = 0 (albedo ρ, half-width
    10, nothing else), the camera straight above it looking down."""
    p = POINT
    return {"type": "scene",
            "sensor": sensor([0, 0, p["cam"]], [0, 0, 0], fov=p["fov"]),
            "plane": {"type": "rectangle", "to_world": T().scale(10.0), "bsdf": diffuse(p["rho"])},
            "light": {"type": "point", "position": [0, 0, p["h"]], "intensity": rgb(p["intensity"])}}


def point_over_plane_exact():
    """Image mean: the film maps uniformly onto the square [-a, a]² of the plane (parallel to
    it), a = cam·tan(fov/2); E = I·cosθ/r² = I·h/r³, whose integral over the square is I × the
    square's solid angle from the light, Ω = 4·atan(a² / (h·√(2a² + h²))). L = ρE/π."""
    p = POINT
    a = p["cam"] * math.tan(math.radians(p["fov"] / 2))
    omega = 4 * math.atan(a * a / (p["h"] * math.sqrt(2 * a * a + p["h"] ** 2)))
    return p["rho"] / math.pi * p["intensity"] * omega / (4 * a * a)


SKY = dict(rho=0.5, L=1.0)


def sky_over_plane():
    """A diffuse plane under a uniform sky (``constant`` emitter) and nothing else, seen from
    above: its whole upper hemisphere is sky, E = π·L, radiance ρ·L."""
    return {"type": "scene",
            "sensor": sensor([0, 0, 1.0], [0, 0, 0], fov=40.0),
            "plane": {"type": "rectangle", "to_world": T().scale(10.0), "bsdf": diffuse(SKY["rho"])},
            "sky": {"type": "constant", "radiance": rgb(SKY["L"])}}


def no_emitters():
    """The box without its light: black."""
    return box(light=False)


def camera_in_sphere():
    """The lit box with a closed two-sided diffuse sphere around the camera (no light inside):
    the outside of the sphere is lit, the inside black."""
    d = box()
    d["sensor"] = sensor([0, 0, 0], [0, -0.3, -1], fov=70)
    d["shell"] = {"type": "sphere", "center": [0, 0, 0], "radius": 0.4,
                  "bsdf": {"type": "twosided", "bsdf": diffuse(0.8)}}
    return d


# --------------------------------------------------------------------------------------------
# scenes compared with path


def corner():
    """A closed diffuse room [-1, 1]³ (cube, inward normals) lit by a ceiling rectangle; the
    camera 1 cm from two walls under the ceiling, looking into the opposite lower corner."""
    return {"type": "scene",
            "sensor": sensor([0.99, 0.9, 0.99], [-1, -1, -1], fov=60),
            "room": {"type": "cube", "flip_normals": True, "bsdf": diffuse(0.7)},
            "light": {"type": "rectangle",
                      "to_world": T().translate([0, 0.98, 0]).rotate([1, 0, 0], 90).scale(0.3),
                      "emitter": {"type": "area", "radiance": rgb(10.0)}}}


def tiny_light():
    """The box lit by a sphere of radius 5 mm and radiance 1e4 (the power of the usual light)
    instead of its rectangle, near the opening: the box's lintel hides it from the camera,
    which would otherwise see it in a few samples worth 1e4 each."""
    d = box(light=False)
    d["light"] = {"type": "sphere", "center": [0, 0.9, 0.8], "radius": 0.005,
                  "emitter": {"type": "area", "radiance": rgb(1e4)}}
    return d


def sliver_mesh():
    """A floating panel (two triangles) plus a zero-area triangle (repeated vertex), a zero-area
    collinear triangle and a 1.6 m long, 1e-6 m wide sliver."""
    V = np.array([[-0.5, -0.3, -0.5], [0.5, -0.3, -0.5], [0.5, 0.3, -0.2], [-0.5, 0.3, -0.2],
                  [0.0, 0.0, 0.0], [0.2, 0.1, 0.3], [0.4, 0.2, 0.6],  # collinear
                  [-0.8, -0.5, 0.3], [0.8, -0.5, 0.3], [0.0, -0.5 + 1e-6, 0.3]],  # sliver
                 dtype=np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 4, 5], [4, 5, 6], [7, 8, 9]], dtype=np.uint32)
    mesh = mi.Mesh("slivers", len(V), len(F))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(V.ravel())
    params["faces"] = mi.UInt32(F.ravel())
    params.update()
    return mesh


def slivers():
    d = box()
    d["slivers"] = sliver_mesh()
    return d


def glass_light():
    """A spherical light inside a glass (dielectric) sphere in the box: every path from it
    crosses the glass (no shadow ray reaches it)."""
    d = box(light=False)
    d["light"] = {"type": "sphere", "center": [0, 0.3, 0], "radius": 0.1,
                  "emitter": {"type": "area", "radiance": rgb(30.0)}}
    d["glass"] = {"type": "sphere", "center": [0, 0.3, 0], "radius": 0.25,
                  "bsdf": {"type": "dielectric"}}
    return d


def lampshade():
    """A small spherical bulb inside an open two-sided diffuse cylinder (the shade); light
    leaves through its open ends only."""
    d = box(light=False)
    d["bulb"] = {"type": "sphere", "center": [0, 0.2, 0], "radius": 0.05,
                 "emitter": {"type": "area", "radiance": rgb(100.0)}}
    d["shade"] = {"type": "cylinder", "p0": [0, 0.0, 0], "p1": [0, 0.45, 0], "radius": 0.2,
                  "bsdf": {"type": "twosided", "bsdf": diffuse(0.7)}}
    return d


def lampshade_panel():
    """A small one-sided emitting panel (two-sided diffuse, facing down) inside the open
    two-sided diffuse cylinder: the shade's inside is lit steeply, near the panel only."""
    d = box(light=False)
    d["bulb"] = {"type": "rectangle",
                 "to_world": T().translate([0, 0.2, 0]).rotate([1, 0, 0], 90).scale(0.05),
                 "bsdf": {"type": "twosided", "bsdf": diffuse(0.7)},
                 "emitter": {"type": "area", "radiance": rgb(400.0)}}
    d["shade"] = {"type": "cylinder", "p0": [0, 0.0, 0], "p1": [0, 0.45, 0], "radius": 0.2,
                  "bsdf": {"type": "twosided", "bsdf": diffuse(0.7)}}
    return d


def sky_in_open_box():
    """The box without its light under a uniform sky: light enters through the open front."""
    d = box(light=False)
    d["sky"] = {"type": "constant", "radiance": rgb(1.0)}
    return d


def sky_room():
    """The box closed by a front wall with a window slit, a ball on the floor, a uniform sky
    outside; the camera inside. Mitsuba 3.9 merges the room's rectangles (one BSDF) into a mesh
    that ``scene.bbox()`` leaves out, so the scene's box is the ball's and a sky's own
    ``sample_ray`` starts its rays on a sphere *inside* the room (the radiosity prepass's
    particles did: radiosity_gather and spike_gather 1.46× ``path`` in a room like this)."""
    d = box(light=False)
    del d["lintel"]
    d["sensor"] = sensor([0, 0.2, 0.9], [0, -0.3, -1], fov=70)
    for name, (y, h) in {"front_low": (-0.35, 0.65), "front_high": (0.85, 0.15)}.items():
        d[name] = {"type": "rectangle", "bsdf": WHITE, "to_world":
                   T().translate([0, y, 1]).rotate([0, 1, 0], 180).scale([1, h, 1])}
    d["ball"] = {"type": "sphere", "center": [0.3, -0.65, -0.2], "radius": 0.35,
                 "bsdf": diffuse(0.5)}
    d["sky"] = {"type": "constant", "radiance": rgb(1.0)}
    return d


def directional_only():
    """A floor with a cube on it under a directional light (the only emitter)."""
    return {"type": "scene",
            "sensor": sensor([0, 2.5, 3.5], [0, 0, 0], fov=50),
            "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3.0),
                      "bsdf": WHITE},
            "block": {"type": "cube", "to_world": T().translate([0, 0.5, 0]).scale(0.5),
                      "bsdf": diffuse(0.6)},
            "sun": {"type": "directional", "direction": [-1, -2, -0.5], "irradiance": rgb(2.0)}}


def objects():
    """The box with a checkerboard albedo (0.8 / 0.1) on its floor, every analytic shape
    (sphere, disk, cylinder, rectangle, cube; the walls are rectangles too) and two instances
    of a shapegroup (a cube and a sphere)."""
    checker = {"type": "diffuse", "reflectance": {
        "type": "checkerboard", "color0": rgb(0.8), "color1": rgb(0.1),
        "to_uv": mi.ScalarTransform4f().scale([4, 4, 1])}}
    d = box(floor_bsdf=checker)
    d["sphere"] = {"type": "sphere", "center": [-0.5, -0.75, 0.0], "radius": 0.25,
                   "bsdf": diffuse([0.8, 0.3, 0.3])}
    d["disk"] = {"type": "disk", "to_world": T().translate([0.5, -0.5, -0.4]).rotate([1, 0, 0], -60)
                 .scale(0.3), "bsdf": diffuse([0.3, 0.8, 0.3])}
    d["cylinder"] = {"type": "cylinder", "p0": [0.1, -1, -0.6], "p1": [0.1, -0.3, -0.6],
                     "radius": 0.12, "bsdf": {"type": "twosided", "bsdf": diffuse(0.6)}}
    d["panel"] = {"type": "rectangle", "to_world": T().translate([-0.4, 0.1, -0.5])
                  .rotate([0, 1, 0], 30).scale(0.25), "bsdf": diffuse([0.3, 0.3, 0.8])}
    d["cube"] = {"type": "cube", "to_world": T().translate([0.55, -0.85, 0.3]).scale(0.15),
                 "bsdf": diffuse(0.5)}
    d["group"] = {"type": "shapegroup",
                  "gcube": {"type": "cube", "to_world": T().scale(0.2), "bsdf": diffuse(0.5)},
                  "gball": {"type": "sphere", "center": [0, 0.35, 0], "radius": 0.15,
                            "bsdf": diffuse([0.8, 0.6, 0.3])}}
    d["inst1"] = {"type": "instance", "shape": {"type": "ref", "id": "group"},
                  "to_world": T().translate([-0.55, -0.8, -0.6])}
    d["inst2"] = {"type": "instance", "shape": {"type": "ref", "id": "group"},
                  "to_world": T().translate([0.0, -0.8, 0.55]).rotate([0, 1, 0], 30)}
    return d


def scaled(scale):
    return lambda: box(scale=scale)


# --------------------------------------------------------------------------------------------
# every BSDF plugin on the walls of the lit box (the floor stays diffuse: a receiver of the light
# the walls reflect or transmit)


def _normal_bitmap():
    """A 16×16 tangent-space normal map (bitmap from an array, no file): tilted normals."""
    u = np.linspace(0, 2 * np.pi, 16, dtype=np.float32)
    nx = 0.4 * np.sin(u)[None, :].repeat(16, 0)
    ny = 0.4 * np.cos(u)[:, None].repeat(16, 1)
    n = np.stack([nx, ny, np.ones_like(nx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return {"type": "bitmap", "raw": True, "data": mi.TensorXf(0.5 * n + 0.5)}


def _height_bitmap():
    """A 16×16 height field of smooth bumps (bitmap from an array, no file; a checkerboard has
    no ``eval_1_grad``, which bumpmap needs)."""
    u = np.linspace(0, 4 * np.pi, 16, dtype=np.float32)
    h = 0.5 + 0.5 * np.sin(u)[None, :] * np.cos(u)[:, None]
    return {"type": "bitmap", "raw": True, "data": mi.TensorXf(h[..., None].astype(np.float32))}


def bsdfs():
    base = diffuse([0.7, 0.6, 0.5])
    return {
        "diffuse": base,
        "conductor": {"type": "conductor", "material": "Au"},
        "roughconductor": {"type": "roughconductor", "alpha": 0.3},
        "plastic": {"type": "plastic", "diffuse_reflectance": rgb(0.5)},
        "roughplastic": {"type": "roughplastic", "diffuse_reflectance": rgb(0.5), "alpha": 0.2},
        "dielectric": {"type": "dielectric"},
        "roughdielectric": {"type": "roughdielectric", "alpha": 0.2},
        "thindielectric": {"type": "thindielectric"},
        "principled": {"type": "principled", "base_color": rgb([0.7, 0.5, 0.4]),
                       "roughness": 0.4, "metallic": 0.3},
        "blendbsdf": {"type": "blendbsdf", "weight": 0.5, "bsdf_0": base,
                      "bsdf_1": {"type": "roughconductor", "alpha": 0.2}},
        "twosided": {"type": "twosided", "bsdf": base},
        "bumpmap": {"type": "bumpmap", "bsdf": base, "scale": 0.5,
                    "arbitrary": _height_bitmap()},
        "normalmap": {"type": "normalmap", "bsdf": base, "normalmap": _normal_bitmap()},
        "mask": {"type": "mask", "opacity": rgb(0.5), "bsdf": base},
    }


BSDFS = list(bsdfs())

#: the BSDF scenes: group name → {wall: BSDF}; walls not named keep the group's first BSDF
#: (the floor always stays diffuse). Grouped by how the integrators treat them, to keep the
#: matrix within its time budget: purely diffuse ones (cached), glossy ones, mixed diffuse +
#: glossy ones, transmissive and null ones (path-traced); bumpmap on its own (see XFAIL).
BSDF_GROUPS = {
    "diffuse_twosided_normalmap": {"back": "diffuse", "left": "twosided", "right": "normalmap",
                                   "ceiling": "diffuse"},
    "bumpmap": {w: "bumpmap" for w in ("back", "left", "right", "ceiling")},
    "conductor_roughconductor_plastic_roughplastic": {
        "back": "conductor", "left": "roughconductor", "right": "plastic",
        "ceiling": "roughplastic"},
    "principled_blendbsdf": {"back": "principled", "left": "blendbsdf", "right": "principled",
                             "ceiling": "blendbsdf"},
    "dielectric_roughdielectric_thindielectric_mask": {
        "back": "dielectric", "left": "roughdielectric", "right": "thindielectric",
        "ceiling": "mask"},
}
assert sorted({b for g in BSDF_GROUPS.values() for b in g.values()}) == sorted(BSDFS)


def bsdf_box(group):
    table = bsdfs()
    return box(wall_bsdfs={w: table[b] for w, b in BSDF_GROUPS[group].items()},
               floor_bsdf=WHITE)

#: name → builder of the scenes compared with ``path``
VS_PATH = {
    "corner": corner,
    "tiny_light": tiny_light,
    "slivers": slivers,
    "scale_1e4": scaled(1e4),
    "glass_light": glass_light,
    "lampshade": lampshade,
    "lampshade_panel": lampshade_panel,
    "sky_open_box": sky_in_open_box,
    "sky_room": sky_room,
    "directional": directional_only,
    "objects": objects,
}

#: name → (builder, exact image mean, exact indirect part of it = exact − path(max_depth=2))
EXACT = {
    "furnace_0.5": (lambda: furnace(0.5), 1 / (1 - 0.5), 1 / (1 - 0.5) - 1.5),
    "furnace_0.9": (lambda: furnace(0.9), 1 / (1 - 0.9), 1 / (1 - 0.9) - 1.9),
    "furnace_0.99": (lambda: furnace(0.99), 1 / (1 - 0.99), 1 / (1 - 0.99) - 1.99),
    "point_over_plane": (point_over_plane, point_over_plane_exact(), 0.0),
    "sky_over_plane": (sky_over_plane, SKY["rho"] * SKY["L"], 0.0),
}

#: millimetre boxes (1e-3 and 1e-4 × the unit box, camera included) → the unit box whose image
#: they must reproduce: Mitsuba's own ray offset (≥ 89 µm) is 4 % of the 2 mm box (``path``
#: reads it 1.7 % bright) and crosses the walls of the 0.2 mm one, so ``path`` on the small
#: boxes is no reference
SCALED_TO_UNIT = {"scale_1e-3": ("scale_1", scaled(1e-3), scaled(1.0)),
                  "scale_1e-4": ("scale_1", scaled(1e-4), scaled(1.0))}

#: scenes whose exact image is black
BLACK = {"no_emitters": no_emitters, "camera_in_sphere": camera_in_sphere}


def builder(name):
    if name in VS_PATH:
        return VS_PATH[name]
    if name in EXACT:
        return EXACT[name][0]
    if name in BLACK:
        return BLACK[name]
    if name.startswith("bsdf_"):
        return lambda: bsdf_box(name[5:])
    for small, (unit, small_builder, unit_builder) in SCALED_TO_UNIT.items():
        if name == small:
            return small_builder
        if name == unit:
            return unit_builder
    raise KeyError(name)


#: scenes whose reference is rendered without Mitsuba's shape merging (``optimize=False``):
#: where the merged mesh is missing from ``scene.bbox()``, ``path``'s shadow rays towards a sky
#: end 2R from the shading point, R the radius of that short box, and pass the walls
#: (sky_room: ``path`` reads 0.0669 merged, 0.0579 unmerged, where rex, radiosity_gather,
#: spike_gather and radiance_cache, which bound infinite emitters by the geometry, read
#: 0.055–0.058 on the merged scene)
UNMERGED_REFERENCE = {"sky_room"}


def build(name, optimize=True):
    return mi.load_dict(builder(name)(), optimize=optimize)
