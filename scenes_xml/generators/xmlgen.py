"""Tiny helpers to write Mitsuba 3 XML scenes (used to generate the corpus; output is committed)."""


def fmt(v):
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def vec(*v):
    return ", ".join(fmt(float(x)) for x in v)


HEADER = """<?xml version="1.0" encoding="utf-8"?>
{comment}
<scene version="3.0.0">
    <default name="spp" value="64"/>
    <default name="res" value="128"/>
    <default name="max_depth" value="-1"/>
{extra_defaults}
    <integrator type="path">
        <integer name="max_depth" value="$max_depth"/>
    </integrator>

    <sensor type="perspective">
        <float name="fov" value="{fov}"/>
        <string name="fov_axis" value="x"/>
        <transform name="to_world">
            <lookat origin="{origin}" target="{target}" up="0, 1, 0"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="$spp"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="$res"/>
            <integer name="height" value="$res"/>
            <string name="pixel_format" value="rgb"/>
            <rfilter type="box"/>
        </film>
    </sensor>
"""


class Scene:
    def __init__(self, comment, origin, target, fov, extra_defaults=""):
        self.out = [HEADER.format(comment=comment, origin=vec(*origin), target=vec(*target),
                                  fov=fmt(float(fov)), extra_defaults=extra_defaults)]
        self.n = {}

    def _id(self, prefix):
        self.n[prefix] = self.n.get(prefix, 0) + 1
        return f"{prefix}_{self.n[prefix]:03d}"

    def raw(self, text):
        self.out.append(text)

    def comment(self, text):
        self.out.append(f"\n    <!-- {text} -->")

    def diffuse(self, id, rgb):
        self.out.append(f'    <bsdf type="diffuse" id="{id}">\n'
                        f'        <rgb name="reflectance" value="{vec(*rgb)}"/>\n    </bsdf>')

    def box(self, lo, hi, bsdf, prefix="box", rot_y=0.0):
        """Axis-aligned box [lo, hi] (optionally rotated about its vertical axis)."""
        c = [(a + b) / 2 for a, b in zip(lo, hi)]
        h = [(b - a) / 2 for a, b in zip(lo, hi)]
        rot = f'\n            <rotate y="1" angle="{fmt(float(rot_y))}"/>' if rot_y else ""
        self.out.append(
            f'    <shape type="cube" id="{self._id(prefix)}">\n'
            f'        <transform name="to_world">\n'
            f'            <scale value="{vec(*h)}"/>{rot}\n'
            f'            <translate value="{vec(*c)}"/>\n'
            f'        </transform>\n'
            f'        <ref id="{bsdf}"/>\n    </shape>')

    def emitter_xml(self, radiance):
        return (f'        <emitter type="area">\n'
                f'            <rgb name="radiance" value="{vec(*radiance)}"/>\n'
                f'        </emitter>\n')

    def sphere_light(self, center, radius, radiance, prefix="sphere_light", bsdf="lamp"):
        self.out.append(
            f'    <shape type="sphere" id="{self._id(prefix)}">\n'
            f'        <point name="center" value="{vec(*center)}"/>\n'
            f'        <float name="radius" value="{fmt(float(radius))}"/>\n'
            f'        <ref id="{bsdf}"/>\n' + self.emitter_xml(radiance) + '    </shape>')

    def rect(self, center, half, normal_axis, sign, bsdf, radiance=None, prefix="rect"):
        """Rectangle with half extents `half` (2 values) facing +/- normal_axis ('x', 'y', 'z')."""
        # Mitsuba's rectangle is [-1,1]^2 in the xy plane with normal +z.
        rot = {("z", 1): "", ("z", -1): '<rotate y="1" angle="180"/>',
               ("y", 1): '<rotate x="1" angle="-90"/>', ("y", -1): '<rotate x="1" angle="90"/>',
               ("x", 1): '<rotate y="1" angle="90"/>', ("x", -1): '<rotate y="1" angle="-90"/>'}[
            (normal_axis, sign)]
        em = self.emitter_xml(radiance) if radiance is not None else ""
        self.out.append(
            f'    <shape type="rectangle" id="{self._id(prefix)}">\n'
            f'        <transform name="to_world">\n'
            f'            <scale value="{vec(half[0], half[1], 1)}"/>\n'
            f'            {rot}\n'
            f'            <translate value="{vec(*center)}"/>\n'
            f'        </transform>\n'
            f'        <ref id="{bsdf}"/>\n' + em + '    </shape>')

    def disk_light(self, center, radius, normal_axis, sign, radiance, bsdf="lamp", prefix="disk_light"):
        rot = {("y", 1): '<rotate x="1" angle="-90"/>', ("y", -1): '<rotate x="1" angle="90"/>'}[
            (normal_axis, sign)]
        self.out.append(
            f'    <shape type="disk" id="{self._id(prefix)}">\n'
            f'        <transform name="to_world">\n'
            f'            <scale value="{vec(radius, radius, 1)}"/>\n'
            f'            {rot}\n'
            f'            <translate value="{vec(*center)}"/>\n'
            f'        </transform>\n'
            f'        <ref id="{bsdf}"/>\n' + self.emitter_xml(radiance) + '    </shape>')

    def sun_sky_ground(self, sun_direction, sun_irradiance, sky_radiance, ground_center,
                       ground_half):
        """What a window looks out on: a directional sun, a constant sky and a diffuse ground
        rectangle facing up (centre, half extents in x and z; it sets the scene's bounding box,
        so keep it small). The sun's and sky's values are written as Python prints them
        (``5.0``, not :func:`vec`'s ``5``)."""
        def exact(v):
            return ", ".join(str(x) for x in v)

        self.comment("Outside: sun, sky and ground")
        self.raw(f"""    <emitter type="directional" id="sun">
        <vector name="direction" value="{exact(sun_direction)}"/>
        <rgb name="irradiance" value="{exact(sun_irradiance)}"/>
    </emitter>
    <emitter type="constant" id="sky">
        <rgb name="radiance" value="{exact(sky_radiance)}"/>
    </emitter>""")
        self.diffuse("ground", (0.25, 0.3, 0.2))
        self.rect(ground_center, ground_half, "y", 1, "ground", prefix="ground")

    def window_room(self, W, H, D, T, window):
        """A closed room, inside x in [0, W], y in [0, H], z in [0, D], of overlapping boxes T
        thick (no light leaks at the edges): floor, ceiling, three solid walls and the wall
        z = 0 in four pieces around the opening ``window`` = (x0, x1, y0, y1). Materials
        "floor", "ceiling" and "wall"."""
        WX0, WX1, WY0, WY1 = window
        self.comment("The shell: floor, ceiling, three solid walls and the window wall in four pieces")
        self.box((-T, -T, -T), (W + T, 0, D + T), "floor", "floor")
        self.box((-T, H, -T), (W + T, H + T, D + T), "ceiling", "ceiling")
        self.box((-T, -T, -T), (0, H + T, D + T), "wall", "wall")           # left   (x = 0)
        self.box((W, -T, -T), (W + T, H + T, D + T), "wall", "wall")        # right  (x = W)
        self.box((-T, -T, D), (W + T, H + T, D + T), "wall", "wall")        # back   (z = D)
        self.box((-T, -T, -T), (WX0, H + T, 0), "wall", "wall")              # window wall, left of the window
        self.box((WX1, -T, -T), (W + T, H + T, 0), "wall", "wall")           # right of the window
        self.box((WX0, -T, -T), (WX1, WY0, 0), "wall", "wall")               # below the window (sill)
        self.box((WX0, WY1, -T), (WX1, H + T, 0), "wall", "wall")            # above the window (lintel)

    def table(self, x0, x1, z0, z1, top, legs):
        """A table: a top [x0, x1] x [z0, z1] from 0.72 m to 0.76 m (material ``top``) on four
        6 cm square legs 5 cm in from its corners (material ``legs``)."""
        self.box((x0, 0.72, z0), (x1, 0.76, z1), top, "table")
        for lx in (x0 + 0.05, x1 - 0.11):
            for lz in (z0 + 0.05, z1 - 0.11):
                self.box((lx, 0, lz), (lx + 0.06, 0.72, lz + 0.06), legs, "table")

    def point_light(self, pos, intensity):
        self.out.append(
            f'    <emitter type="point" id="{self._id("point_light")}">\n'
            f'        <point name="position" value="{vec(*pos)}"/>\n'
            f'        <rgb name="intensity" value="{vec(*intensity)}"/>\n    </emitter>')

    def write(self, path):
        with open(path, "w") as f:
            f.write("\n".join(self.out) + "\n</scene>\n")
