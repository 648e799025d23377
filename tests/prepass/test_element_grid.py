"""Irradiance inside unevenly lit elements (mi_twopass.prepass.element_grid): the cell map, the
cells' areas, which elements are refined, and a shadow edge read on both of its sides."""
import math

import numpy as np

import mi_twopass  # noqa: F401  (libLLVM + variant before mitsuba/drjit)
import drjit as dr
import mitsuba as mi

from mi_twopass.prepass.element_grid import (GRID_RES, MIN_EXPOSURE, ElementFrames, cell_areas,
                                             refinable)
from mi_twopass.prepass.radiosity import RadiositySettings, build
from mi_twopass.scene import build_patches

T = mi.ScalarTransform4f


def _triangle_ply():
    """A one-triangle PLY file, slanted in x, y and z (an ASCII mesh Mitsuba loads)."""
    import tempfile
    path = tempfile.NamedTemporaryFile(suffix=".ply", delete=False).name
    with open(path, "w") as f:
        f.write("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                "end_header\n0 0 0\n1 0.2 0.3\n0.1 0.9 0.5\n3 0 1 2\n")
    return path


def _square():
    """A 2 × 2 m square floor (two triangles), one patch."""
    scene = mi.load_dict({"type": "scene", "floor": {"type": "rectangle",
                                                      "bsdf": {"type": "diffuse"}}})
    return build_patches(scene, max_patches=1)


def test_cell_areas_are_exact_and_the_jit_and_numpy_maps_agree():
    """On a 2 × 2 m square (radius √2 from its centre) the cells span [−√2, √2] in K steps
    per axis, so each holds the exact product of its two clipped widths; and a point's cell is
    the same from the Dr.Jit map (the particles' deposits) and the numpy one."""
    P = _square()
    assert P.count == 1
    frames = ElementFrames(P)
    areas = cell_areas(P, frames, [0])
    K = GRID_RES
    assert areas.shape == (1, K * K)
    r = math.sqrt(2.0)
    widths = np.diff(np.clip(-r + 2 * r * np.arange(K + 1) / K, -1.0, 1.0))
    np.testing.assert_allclose(areas[0].reshape(K, K), np.outer(widths, widths), atol=1e-9)
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-1, 1, 2000), rng.uniform(-1, 1, 2000), np.zeros(2000)])
    cells_np = frames.cells_np(np.zeros(2000, np.int64), pts)
    p = mi.Point3f(*(mi.Float(pts[:, c].astype(np.float32)) for c in range(3)))
    cells_jit = np.asarray(frames.cell(dr.zeros(mi.UInt32, 2000), p, True))
    # float32 against float64 may part on a cell boundary, never elsewhere
    assert (cells_np == cells_jit).mean() > 0.99
    # points fall into cells in proportion to the cells' areas
    share = np.bincount(cells_np, minlength=K * K) / 2000
    np.testing.assert_allclose(share, areas[0] / 4.0, atol=0.03)


def test_a_triangle_clipped_to_the_cells_keeps_its_area():
    """A tilted triangular element (two world axes and a slant): its cells' areas sum to its
    area, whichever axis its cells drop."""
    scene = mi.load_dict({"type": "scene", "tri": {
        "type": "ply", "filename": _triangle_ply(), "bsdf": {"type": "diffuse"}}})
    P = build_patches(scene, max_patches=1)
    frames = ElementFrames(P)
    areas = cell_areas(P, frames, np.arange(P.count))
    tv = np.asarray(P.tri_vertices)
    true = 0.5 * np.linalg.norm(np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), axis=1)
    total = np.bincount(np.asarray(P.tri_patch), weights=true, minlength=P.count)
    np.testing.assert_allclose(areas.sum(axis=1), total, rtol=1e-6)  # float32 normals
    assert (areas > 0).sum() >= 3


def test_only_uneven_flat_exposed_elements_are_refined():
    """:func:`refinable`: uneven, flat (bend below FLAT_BEND) and exposed (≥ MIN_EXPOSURE of
    the geometric area); a cut element, which the caller leaves out of ``uneven``, never."""
    class Mesh:
        area = np.array([1.0, 1.0, 1.0, MIN_EXPOSURE * 0.9, 1.0])
        geometric_area = np.ones(5)

    uneven = np.array([True, False, True, True, True])
    bend = np.array([0.0, 0.0, 0.5, 0.0, 0.01])
    assert refinable(Mesh, uneven, bend).tolist() == [0, 4]


def _shadow_edge_scene(edge_x=0.1):
    """A 2 × 2 m floor (albedo 0.5) under a sun straight down (irradiance 1 W/m²), with a
    board at 0.5 m shading the floor for x < ``edge_x``: a sharp edge across elements."""
    half = (edge_x + 1.0) / 2.0
    return mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse",
                                                "reflectance": {"type": "rgb", "value": 0.5}}},
        "board": {"type": "rectangle", "bsdf": {"type": "diffuse"},
                  "to_world": T().translate([edge_x - half, 0, 0.5]).scale([half, 1.5, 1])},
        "sun": {"type": "directional", "direction": [0, 0, -1],
                "irradiance": {"type": "rgb", "value": 1.0}}})


def _edge_solution(scene):
    return build(scene, RadiositySettings(max_patches=16, particles_per_patch=1 << 15,
                                          elements_per_patch=16), seed=2, progress=False).solution


def test_a_shadow_edge_is_read_cell_by_cell():
    """The elements the edge at x = 0.1 crosses are unevenly lit and refined. At points spread
    uniformly over them, the cell's value tracks the light there, ρE/π with E 1 on the lit side
    and 0 in the shade (nothing else lights the floor): each cell reads its lit fraction, and
    the error at the points is left only in the cells the edge crosses, so its RMS is about the
    square root of their share of the area times the element mean's (0.56× measured with 4 × 4
    cells). Without a point, the mean."""
    scene = _shadow_edge_scene()
    sol = _edge_solution(scene)
    grid = sol.grid
    assert grid is not None and grid.count >= 2
    E = sol.elements
    assert np.all(E.is_uneven[grid.ids])
    floor_id = next(i for i, s in enumerate(scene.shapes()) if s.id() == "floor")
    assert np.all(np.asarray(E.shape_index)[grid.ids] == floor_id)
    n = 4096
    rid = mi.UInt32(np.repeat(grid.ids, n).astype(np.uint32))
    rng = np.random.default_rng(3)
    u = mi.Point2f(*(mi.Float(rng.random(len(grid.ids) * n).astype(np.float32))
                     for _ in range(2)))
    p, _, _ = E.sample_points(rid, u)
    cell = sol.receiver_reflected_radiance(rid, True, p)
    mean = sol.receiver_reflected_radiance(rid, True)
    read = np.asarray(cell).mean(axis=0).reshape(-1, n)
    avg = np.asarray(mean).mean(axis=0).reshape(-1, n)
    x = np.asarray(p.x).reshape(-1, n)
    truth = np.where(x > 0.1, 0.5 / math.pi, 0.0)
    rms_cell = np.sqrt(np.mean((read - truth) ** 2))
    rms_mean = np.sqrt(np.mean((avg - truth) ** 2))
    assert rms_cell < 0.75 * rms_mean, (rms_cell, rms_mean)
    # cell by cell: the mean of the truth over its points (its lit fraction) within noise
    cells = np.asarray(grid.frames.cell(rid, p, True)).reshape(-1, n)
    for k in range(len(grid.ids)):
        for c in np.unique(cells[k]):
            at = cells[k] == c
            if at.mean() < 0.05:
                continue  # a sliver: few deposits
            assert abs(read[k][at].mean() - truth[k][at].mean()) < 0.2 * 0.5 / math.pi, \
                (k, c, read[k][at].mean(), truth[k][at].mean())
    # the mean is one value per element, between the shade and the light
    assert np.allclose(avg, avg[:, :1])


def test_the_radiance_cache_holds_the_refined_elements():
    """The cache reads a refined element at the point hit, so it holds it: it is among the
    cached receivers though the solve flagged it uneven."""
    from mi_twopass.prepass.sh_cache import cached_receivers, refined_mask
    from mi_twopass.scene.lambertian import LambertianShapes

    scene = _shadow_edge_scene()
    sol = _edge_solution(scene)
    refined = refined_mask(sol)
    assert refined.any()
    cached = cached_receivers(scene, sol, LambertianShapes(scene)).cached
    assert np.all(cached[refined])
    assert not np.any(cached[sol.elements.is_uneven & ~refined])
