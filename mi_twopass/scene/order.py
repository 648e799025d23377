"""The scene's shapes in an order that is the same every time the scene is loaded.

Mitsuba 3.9 hands out ``scene.shapes()`` (and ``scene.shapes_dr()``) in an order that changes
from one load of a scene file to the next, in one process or across processes, with
``mi.load_file(..., parallel=False)`` too. A prepass that numbered patches or rexes in that
order drew its random points for other surfaces each time, so one seed gave a statistically
different image in every run, where Mitsuba's ``path`` gave the same bytes. Every prepass walks
the shapes through :func:`stable_shapes` instead; ``tests/scene/test_order.py`` loads one room
with its shapes listed in two orders. ``tools/load_order.py SCENE --integrators
path,radiosity_gather,spike_gather,radiance_cache,rex,twopass`` renders in two processes and
compares: on scenes_xml/mixed_room.xml all six now give the same bytes (at session 29's code
the four prepass integrators differed).

What stays: where Mitsuba reorders the *emitters* too, ``path``'s own image changes from one
load to the next, and so do ours (emitter sampling, and the photons and particles each emitter
is given): ``tools/load_order.py SCENE --integrators '' --processes 6`` read six emitter orders
in six processes on many_lights.xml, office.xml and ../shared/scenes/staircase2, one or two on
veach-bidir, one on mixed_room.

The key is what a shape *is*, not where it sits in memory: its id, its class, its primitive
and vertex counts, its bounding box and the ids of its BSDF and emitter (host values all: no
Dr.Jit kernel runs to sort). Shapes that agree on all of it are the same surface twice (their
prepass data would be the same whichever came first); they keep Mitsuba's relative order.
Meshes that share a BSDF are merged by Mitsuba in the order they were given: that merged mesh
is a different mesh, which no order of shapes can undo.
"""
import math

import drjit as dr
import mitsuba as mi


def _number(x) -> float:
    """A float that sorts: NaN (an empty bounding box) as +inf."""
    x = float(x)
    return math.inf if math.isnan(x) else x


def shape_key(shape) -> tuple:
    """The sort key of one ``mi.Shape`` (see the module docstring)."""
    bbox = shape.bbox()
    corners = tuple(_number(v) for c in (bbox.min, bbox.max) for v in (c.x, c.y, c.z))
    bsdf, emitter = shape.bsdf(), shape.emitter()
    vertices = shape.vertex_count() if shape.is_mesh() else 0
    return (shape.id(), shape.class_name(), int(shape.primitive_count()), int(vertices),
            corners, bsdf.id() if bsdf is not None else "",
            emitter.id() if emitter is not None else "", shape.is_emitter())


def stable_shapes(scene) -> list:
    """``[(index, shape), ...]``: every shape of ``scene`` with its index in ``scene.shapes()``,
    sorted by :func:`shape_key` (ties in Mitsuba's order)."""
    shapes = list(scene.shapes())
    keys = [shape_key(s) for s in shapes]
    order = sorted(range(len(shapes)), key=lambda i: keys[i])
    return [(i, shapes[i]) for i in order]


def registry_id(shape) -> int:
    """The id that ``dr.reinterpret_array(mi.UInt32, si.shape)`` reads for ``shape``."""
    return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])
