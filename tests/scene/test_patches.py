"""Patches (mi_twopass.scene.patches): budget, areas, properties, O(1) lookup vs brute force."""
import math
import os

import numpy as np
import pytest

import mi_twopass  # noqa: F401  (libLLVM + variant before mitsuba/drjit)
import drjit as dr
import mitsuba as mi

from mi_twopass.scene import build_patches
from mi_twopass.scene.patches import (_choose_target_area, _count, _mesh_split,
                                      _subtriangle_corners, _subtriangle_index_np,
                                      scene_shapes)

T = mi.ScalarTransform4f


# ---------------------------------------------------------------------------------------------
# helpers


def make_mesh(name, V, F, bsdf=None, flip=False):
    """A Mitsuba mesh from numpy vertices (n, 3) and faces (m, 3)."""
    props = mi.Properties()
    if flip:
        props["flip_normals"] = True
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf)
    mesh = mi.Mesh(name, V.shape[0], F.shape[0], props=props)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.asarray(V, np.float32).ravel())
    params["faces"] = mi.UInt32(np.asarray(F, np.uint32).ravel())
    params.update()
    return mesh


def grid_mesh(n, size=2.0, z=0.0, bump=0.0):
    """An n×n grid of quads (2n² triangles) over [-size/2, size/2]², optionally bumpy."""
    x = np.linspace(-size / 2, size / 2, n + 1)
    X, Y = np.meshgrid(x, x, indexing="ij")
    Z = z + bump * np.sin(3 * X) * np.cos(2 * Y)
    V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    F = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                        np.stack([a, c, d], -1).reshape(-1, 3)])
    return V, F


def assert_rows(actual, row, rtol=1e-5):
    assert actual.shape[0] > 0
    np.testing.assert_allclose(actual, np.broadcast_to(row, actual.shape), rtol=rtol)


def mesh_area(V, F):
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                axis=1).sum()


def point_triangle_distance(p, A, B, C):
    """Distance from points p (n, 3) to triangles (A, B, C each (m, 3)): (n, m) (Ericson 5.1.5)."""
    p = p[:, None, :]
    ab, ac, ap = B - A, C - A, p - A
    d1, d2 = np.einsum("ijk,jk->ij", ap, ab), np.einsum("ijk,jk->ij", ap, ac)
    bp = p - B
    d3, d4 = np.einsum("ijk,jk->ij", bp, ab), np.einsum("ijk,jk->ij", bp, ac)
    cp = p - C
    d5, d6 = np.einsum("ijk,jk->ij", cp, ab), np.einsum("ijk,jk->ij", cp, ac)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        q = A + v[..., None] * ab + w[..., None] * ac  # interior
        cases = [
            ((d1 <= 0) & (d2 <= 0), A + 0 * q),
            ((d3 >= 0) & (d4 <= d3), B + 0 * q),
            ((d6 >= 0) & (d5 <= d6), C + 0 * q),
            ((vc <= 0) & (d1 >= 0) & (d3 <= 0), A + (d1 / (d1 - d3))[..., None] * ab),
            ((vb <= 0) & (d2 >= 0) & (d6 <= 0), A + (d2 / (d2 - d6))[..., None] * ac),
            ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
             B + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[..., None] * (C - B)),
        ]
        done = np.zeros(d1.shape, bool)
        for mask, point in cases:
            m = mask & ~done
            q = np.where(m[..., None], point, q)
            done |= m
    return np.linalg.norm(p - q, axis=-1)


def random_rays(scene, n, seed, targets=None):
    """Rays from random points of the (enlarged) bounding box, in random directions or towards
    random points near ``targets`` (m, 3)."""
    rng = np.random.default_rng(seed)
    bbox = scene.bbox()
    lo = np.array(bbox.min).ravel()
    hi = np.array(bbox.max).ravel()
    ext = hi - lo
    o = lo - 0.25 * ext + 1.5 * ext * rng.random((n, 3))
    if targets is None:
        d = rng.normal(size=(n, 3))
    else:
        aim = targets[rng.integers(0, len(targets), n)] + 0.05 * ext * rng.normal(size=(n, 3))
        d = aim - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return mi.Ray3f(mi.Point3f(*(mi.Float(o[:, i].astype(np.float32)) for i in range(3))),
                    mi.Vector3f(*(mi.Float(d[:, i].astype(np.float32)) for i in range(3)))), d


def mixed_scene():
    """Every supported shape kind, flipped normals, a two-sided BSDF, fine and coarse meshes."""
    V, F = grid_mesh(24, size=1.0, z=0.0, bump=0.05)  # fine mesh: merged into clusters
    fine = make_mesh("fine", V + np.array([0.0, 0.0, -1.5]), F)
    twosided = {"type": "twosided", "bsdf": {"type": "diffuse"},
                "bsdf2": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.2}}}
    return mi.load_dict({
        "type": "scene",
        "sphere": {"type": "sphere", "center": [0, 0, 0], "radius": 0.5},
        "disk": {"type": "disk", "to_world": T().translate([1.5, 0, 0]).scale(0.7)},
        "cyl": {"type": "cylinder", "p0": [-1.5, 0, -0.5], "p1": [-1.5, 0, 0.5], "radius": 0.4,
                "flip_normals": True},
        "rect": {"type": "rectangle", "to_world": T().translate([0, 1.5, 0]).rotate([1, 0, 0], 90)
                 .scale(1.2), "bsdf": twosided},
        "cube": {"type": "cube", "to_world": T().translate([0, -1.5, 0]).scale(0.4),
                 "flip_normals": True},
        "fine": fine,
    })


# ---------------------------------------------------------------------------------------------
# subdivision indexing


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_subtriangle_index_matches_corners(n):
    """The O(1) index of a barycentric point is the sub-triangle that contains it."""
    corners = _subtriangle_corners(n)  # (n², 3, 2)
    assert corners.shape == (n * n, 3, 2)
    rng = np.random.default_rng(n)
    w = rng.dirichlet([1, 1, 1], size=(n * n, 4))  # points strictly inside each sub-triangle
    pts = np.einsum("kij,kjl->kil", w, corners)  # (n², 4, 2)
    idx = _subtriangle_index_np(pts[..., 0], pts[..., 1], n)
    assert np.array_equal(idx, np.repeat(np.arange(n * n)[:, None], 4, axis=1))
    # equal areas, tiling the triangle
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    areas = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    np.testing.assert_allclose(areas, 0.5 / (n * n), rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# budget and areas


def test_fine_mesh_merges_under_budget():
    """A 20 000-triangle bumpy sheet becomes ≤ max_patches clusters of similar area."""
    V, F = grid_mesh(100, size=2.0, bump=0.1)
    scene = mi.load_dict({"type": "scene", "sheet": make_mesh("sheet", V, F)})
    patches = build_patches(scene, max_patches=200)
    assert F.shape[0] == 20000
    assert 50 <= patches.count <= 200
    np.testing.assert_allclose(patches.area.sum(), mesh_area(V, F), rtol=1e-6)
    assert patches.tri_vertices.shape[0] == F.shape[0]  # every triangle in exactly one patch
    assert np.array_equal(np.sort(np.unique(patches.tri_patch)), np.arange(patches.count))
    # roughly uniform: interior clusters are full grid cells (border ones partial)
    med = np.median(patches.area)
    assert patches.area.max() < 3.0 * med
    assert np.all(np.isfinite(patches.normal)) and np.all(np.isfinite(patches.center))


@pytest.mark.parametrize("budget", [40, 300, 2000, 9000])
def test_target_area_search_fits_the_budget_and_counts_as_the_split(budget):
    """The search's target area fits the budget and is the smallest that does, to 0.5 %;
    its count of a mesh's patches is the split's own."""
    scene = mixed_scene()
    geoms = scene_shapes(scene)
    origin = np.array(scene.bbox().min, dtype=np.float64).ravel()
    a = _choose_target_area(geoms, budget, origin)
    n = _count(geoms, a, origin)
    assert n <= budget
    assert _count(geoms, a / 1.005 ** 2, origin) > budget
    mesh = next(g for g in geoms if g.shape.id() == "fine")
    res, _, _, clusters = _mesh_split(mesh, a, origin)
    assert _count([mesh], a, origin) == int((res * res).sum()) + clusters


def test_single_rectangle_subdivides():
    """One big rectangle (2 triangles) gets enough patches to show a gradient."""
    scene = mi.load_dict({"type": "scene", "floor": {"type": "rectangle",
                                                    "to_world": T().scale(5.0)}})
    patches = build_patches(scene, max_patches=512)
    assert 128 <= patches.count <= 512
    np.testing.assert_allclose(patches.area, patches.area[0], rtol=1e-6)
    np.testing.assert_allclose(patches.area.sum(), 100.0, rtol=1e-6)
    np.testing.assert_allclose(patches.normal, np.tile([0.0, 0.0, 1.0], (patches.count, 1)),
                               atol=1e-6)


def test_areas_sum_to_surface_area_per_shape():
    scene = mixed_scene()
    patches = build_patches(scene, max_patches=600)
    assert patches.count <= 600
    for i, shape in enumerate(scene.shapes()):
        expected = float(np.asarray(shape.surface_area()).ravel()[0])
        if shape.is_mesh():
            V = np.array(shape.vertex_positions_buffer()).reshape(-1, 3).astype(np.float64)
            F = np.array(shape.faces_buffer()).reshape(-1, 3)
            expected = mesh_area(V, F)
        for side in (0, 1):
            sel = (patches.shape_index == i) & (patches.side == side)
            if side == 1 and shape.id() != "rect":
                assert not sel.any(), "only the two-sided shape has back patches"
                continue
            np.testing.assert_allclose(patches.area[sel].sum(), expected, rtol=1e-5,
                                       err_msg=shape.id())
        # triangles of analytic shapes approximate the curved surface from inside
        tri = patches.tri_vertices[np.isin(patches.tri_patch,
                                           np.nonzero((patches.shape_index == i)
                                                      & (patches.side == 0))[0])]
        tri_area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                                        axis=1).sum()
        assert 0.97 * expected <= tri_area <= expected * (1 + 1e-5), shape.id()
    # triangle windings agree with the stored normals, which face the patch's side
    tv = patches.tri_vertices.astype(np.float64)
    cross = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    big = np.linalg.norm(cross, axis=1) > 1e-8
    assert np.all(np.einsum("ij,ij->i", cross[big], patches.tri_normal[big]) > 0)


def test_properties_albedo_emission_specular():
    twosided = {"type": "twosided",
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.1, 0.2, 0.3]}},
                "bsdf2": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.8, 0.9]}}}
    scene = mi.load_dict({
        "type": "scene",
        "tw": {"type": "rectangle", "bsdf": twosided},
        "light": {"type": "disk", "to_world": T().translate([0, 0, 2]).rotate([1, 0, 0], 180),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1, 2, 3]}}},
        "mirror": {"type": "sphere", "center": [3, 0, 0], "radius": 0.5,
                   "bsdf": {"type": "conductor"}},
        "glossy": {"type": "rectangle", "to_world": T().translate([0, 0, -3]),
                   "bsdf": {"type": "roughconductor"}},
    })
    patches = build_patches(scene, max_patches=64)
    names = [s.id() for s in scene.shapes()]
    by = {name: patches.shape_index == names.index(name) for name in names}
    front, back = patches.side == 0, patches.side == 1
    assert_rows(patches.albedo[by["tw"] & front], [0.1, 0.2, 0.3])
    assert_rows(patches.albedo[by["tw"] & back], [0.7, 0.8, 0.9])
    assert np.all(patches.is_diffuse[by["tw"]])
    assert_rows(patches.Le[by["light"]], [1.0, 2.0, 3.0])
    assert np.all(patches.Le[~by["light"]] == 0)
    for name in ("mirror", "glossy"):  # not diffuse: albedo 0 (roughconductor's would be 25)
        assert not patches.is_diffuse[by[name]].any()
        assert np.all(patches.albedo[by[name]] == 0)


def test_zero_area_triangles_no_nan():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 0], [3, 3, 0], [4, 4, 0],
                  [5, 5, 5]], dtype=np.float64)
    F = np.array([[0, 1, 2], [3, 4, 5], [6, 6, 6], [1, 1, 2]])  # 3 degenerate triangles
    scene = mi.load_dict({"type": "scene", "m": make_mesh("m", V, F)})
    patches = build_patches(scene, max_patches=16)
    for arr in (patches.area, patches.center, patches.normal, patches.albedo, patches.Le):
        assert np.all(np.isfinite(arr))
    np.testing.assert_allclose(patches.area.sum(), 0.5, rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(patches.normal, axis=1), 1.0, rtol=1e-6)
    p, n, pdf = patches.sample_points(dr.arange(mi.UInt32, patches.count),
                                      mi.Point2f(0.3, 0.6))
    assert np.all(np.isfinite(np.array(p))) and np.all(np.isfinite(np.array(pdf)))
    zero = patches.area == 0
    assert np.all(np.array(pdf)[zero] == 0)


def test_property_points_read_each_meshs_own_faces():
    """The property points of every mesh read the albedo of the face they lie on: a per-face
    albedo (``mesh_attribute``) on the second of two meshes, one of them flipped. The points
    are made in Dr.Jit from tables over all meshes; the face they hand Mitsuba must be the
    face's index in its own mesh (the concatenation's index read past the second mesh's faces
    and crashed on ../shared/scenes/staircase2)."""
    V1, F1 = grid_mesh(2, z=0.0)
    first = make_mesh("first", V1, F1, bsdf={"type": "diffuse"}, flip=True)
    quads = 6
    x = np.linspace(0.0, 6.0, quads + 1)
    V2 = np.array([[xi, y, 1.0] for xi in x for y in (0.0, 1.0)])
    F2 = np.concatenate([[[2 * i, 2 * i + 2, 2 * i + 3], [2 * i, 2 * i + 3, 2 * i + 1]]
                         for i in range(quads)])
    second = make_mesh("second", V2, F2,
                       bsdf={"type": "diffuse",
                             "reflectance": {"type": "mesh_attribute", "name": "face_albedo"}})
    shade = np.repeat(0.1 + 0.1 * np.arange(quads), 2)  # both triangles of quad i: 0.1 (i + 1)
    second.add_attribute("face_albedo", 3, np.repeat(shade, 3).astype(np.float32))
    scene = mi.load_dict({"type": "scene", "first": first, "second": second})
    patches = build_patches(scene, max_patches=4 * quads)
    of_second = patches.shape_index == [s.id() for s in scene.shapes()].index("second")
    assert of_second.sum() >= quads
    expected = 0.1 + 0.1 * np.floor(patches.center[of_second, 0])  # the quad under the centre
    np.testing.assert_allclose(patches.albedo[of_second], np.repeat(expected[:, None], 3, 1),
                               rtol=1e-5)
    assert_rows(patches.albedo[~of_second], [0.5, 0.5, 0.5])  # the flipped mesh: its own BSDF
    np.testing.assert_allclose(patches.normal[~of_second], np.broadcast_to(
        [0.0, 0.0, -1.0], patches.normal[~of_second].shape), atol=1e-6)


# ---------------------------------------------------------------------------------------------
# lookup


def test_lookup_matches_brute_force():
    """O(1) lookup of random hits == the nearest patch facing the ray (numpy brute force)."""
    scene = mixed_scene()
    patches = build_patches(scene, max_patches=400)
    ray, d = random_rays(scene, 3000, seed=7, targets=patches.center)
    si = scene.ray_intersect(ray)
    pid = np.array(patches.lookup(si, True))
    valid = np.array(si.is_valid())
    assert np.all(pid[~valid] == patches.count)
    P = np.array(si.p, dtype=np.float64).T[valid]
    dv = d[valid]
    pid = pid[valid]
    reg = np.array(dr.reinterpret_array(mi.UInt32, si.shape))[valid]
    shapes = scene.shapes()
    reg_of = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes]
    tv = patches.tri_vertices.astype(np.float64)
    degenerate = np.linalg.norm(np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), axis=1) == 0
    diag = float(np.linalg.norm(np.array(scene.bbox().extents())))
    n_checked = n_none = 0
    for i, shape in enumerate(shapes):  # brute force over the triangles of the hit's shape
        hits = np.nonzero(reg == reg_of[i])[0]
        tris = np.nonzero(np.isin(patches.tri_patch, np.nonzero(patches.shape_index == i)[0])
                          & ~degenerate)[0]  # (pole triangles of the sphere can't be hit)
        dist = point_triangle_distance(P[hits], tv[tris, 0], tv[tris, 1], tv[tris, 2])
        facing = (dv[hits] @ patches.tri_normal[tris].T) < 0  # the side the ray arrives on
        # chord error of the flat triangles approximating curved shapes
        tol = (1e-5 if shape.is_mesh() else 1e-3) * diag
        for k, h in enumerate(hits):
            cand = facing[k] & (dist[k] <= dist[k].min() + tol)
            expected = set(patches.tri_patch[tris[cand]].tolist())
            if not expected:  # back of a one-sided surface: no patch
                assert pid[h] == patches.count, (shape.id(), h)
                n_none += 1
            else:
                assert pid[h] in expected, (shape.id(), h, pid[h], expected)
                assert patches.shape_index[pid[h]] == i
                n_checked += 1
    assert n_checked > 1000 and n_none > 50
    # every kind of patch was exercised: sides, subdivided, merged and analytic patches
    hit = pid[pid < patches.count]
    assert np.any(patches.side[hit] == 1)
    assert len(np.unique(patches.shape_index[hit])) == len(scene.shapes())


def test_sample_points_uniform_on_patch():
    """Sampled points lie on their patch (lookup agrees) and are uniform: mean → centroid."""
    scene = mixed_scene()
    patches = build_patches(scene, max_patches=300)
    n = 256
    ids = np.repeat(np.arange(patches.count), n).astype(np.uint32)
    rng = np.random.default_rng(3)
    u = rng.random((ids.size, 2)).astype(np.float32)
    p, nrm, pdf = patches.sample_points(mi.UInt32(ids), mi.Point2f(mi.Float(u[:, 0]),
                                                                    mi.Float(u[:, 1])))
    p, nrm, pdf = np.array(p, np.float64).T, np.array(nrm, np.float64).T, np.array(pdf)
    tv = patches.tri_vertices.astype(np.float64)
    tri_area = 0.5 * np.linalg.norm(np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), axis=1)
    flat_area = np.bincount(patches.tri_patch, weights=tri_area, minlength=patches.count)
    np.testing.assert_allclose(pdf, 1.0 / flat_area[ids], rtol=1e-4)
    # rays from just off the point, along -n, find the same patch
    diag = float(np.linalg.norm(np.array(scene.bbox().extents())))
    o = p + nrm * 1e-3 * diag
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(o[:, i].astype(np.float32)) for i in range(3))),
                   mi.Vector3f(*(mi.Float((-nrm[:, i]).astype(np.float32)) for i in range(3))))
    si = scene.ray_intersect(ray)
    found = np.array(patches.lookup(si, True))
    assert np.mean(found == ids) > 0.97  # the rest: samples within 1e-3 of a patch border
    # uniformity: per patch, the sample mean is the area-weighted centroid of its triangles
    centroid = np.stack([np.bincount(patches.tri_patch, weights=tri_area * tv[:, :, k].mean(1),
                                     minlength=patches.count) for k in range(3)], 1)
    centroid /= flat_area[:, None]
    mean = p.reshape(-1, n, 3).mean(1)
    se = p.reshape(-1, n, 3).std(1, ddof=1) / math.sqrt(n)
    z = (mean - centroid) / np.maximum(se, 1e-12)
    ok = se > 1e-9
    assert np.all(np.abs(z[ok]) < 5.5)
    assert abs(np.mean(z[ok] ** 2) - 1.0) < 0.2  # z² averages 1 when the sampler is uniform


# ---------------------------------------------------------------------------------------------
# exposed area: parts of a patch buried in closed geometry


def test_exposure_of_floor_under_a_box():
    """A closed diffuse cube standing on a 4×4 floor covers 1/4 of it: the floor's exposed area
    is 3/4 of its geometric area (the probe's points are random: binomial error); an open scene
    keeps exposure 1."""
    V = np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    floor = make_mesh("floor", V, F)
    scene = mi.load_dict({
        "type": "scene", "floor": floor,
        "box": {"type": "cube", "to_world": T().translate([-1.0, -1.0, 1.0]).scale(1.0)},
    })
    p = build_patches(scene, max_patches=256, seed=3)
    np.testing.assert_allclose(p.area, p.geometric_area * p.exposure)
    names = np.array(p.shape_names)[p.shape_index]
    on_floor = names == "floor"
    open_frac = p.area[on_floor].sum() / p.geometric_area[on_floor].sum()
    n_probes = on_floor.sum() * 16
    assert abs(open_frac - 0.75) < 4 * math.sqrt(0.75 * 0.25 / n_probes) + 0.02
    # the floor is an open sheet: the cube's bottom face looks into open space below it
    assert np.all(p.exposure[~on_floor] == 1.0)
    assert np.any(p.exposure[on_floor] == 0.0)  # floor patches wholly under the cube
    # three exposure rays per sample point, and at most one split-probe segment per point
    assert 3 * 16 * p.count <= p.probe_rays <= 4 * 16 * p.count
    # nothing closed in the scene: every patch fully exposed
    p_open = build_patches(mi.load_dict({"type": "scene", "floor": make_mesh("floor", V, F)}),
                           max_patches=64)
    assert np.all(p_open.exposure == 1.0)
    np.testing.assert_allclose(p_open.area, p_open.geometric_area)


def test_no_kernel_is_compiled_anew_for_each_seed():
    """The probe offset follows the random points; as a literal in the probes' kernels (85c3c95)
    it compiled them again for every seed. Kernels are compared by their IR with the alignment
    of their buffers left out (a numpy buffer handed to Dr.Jit is read in place, and an
    unaligned one gets its own kernel, compiled once per machine): every seed must launch the
    same kernels."""
    import re

    from mi_twopass.scenefile import load_scene

    def normalised(ir) -> str:
        text = ir.getvalue() if hasattr(ir, "getvalue") else str(ir)
        return re.sub(r", align \d+", "", re.sub(r"@drjit_[0-9a-f]+", "@kernel", text))

    scenes = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(__file__))),
                          "scenes_xml")
    scene = load_scene(os.path.join(scenes, "cornell_box.xml"), res=16)
    per_seed = []
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for seed in range(1, 5):
            dr.kernel_history()  # clears it
            build_patches(scene, max_patches=64, seed=seed)
            per_seed.append({normalised(k["ir"]) for k in dr.kernel_history()
                             if k["type"] == dr.KernelType.JIT})
    assert per_seed[0] and all(k == per_seed[0] for k in per_seed[1:]), \
        [len(k - per_seed[0]) for k in per_seed]


def test_shapes_read_once_build_the_same_patches():
    """Patches built from shapes read beforehand (``scene_shapes``, shared by the radiosity
    prepass's patches and elements) equal those that read the shapes themselves, for a mesh
    and a rectangle, at two budgets from one read."""
    from mi_twopass.scene.patches import scene_shapes
    V, F = grid_mesh(20, size=2.0, bump=0.1)
    scene = mi.load_dict({
        "type": "scene", "sheet": make_mesh("sheet", V, F),
        "wall": {"type": "rectangle", "to_world": T().translate([0, 0, 1.5]),
                 "emitter": {"type": "area", "radiance": 2.0}}})
    shapes = scene_shapes(scene)
    for budget in (64, 1024):
        own = build_patches(scene, max_patches=budget, seed=3)
        shared = build_patches(scene, max_patches=budget, seed=3, shapes=shapes)
        assert own.count == shared.count > 0
        for name in ("area", "center", "normal", "albedo", "Le", "exposure", "tri_patch",
                     "tri_vertices"):
            np.testing.assert_array_equal(np.asarray(getattr(own, name)),
                                          np.asarray(getattr(shared, name)), err_msg=name)
