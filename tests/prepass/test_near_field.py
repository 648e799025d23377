"""Near-field correction B_C (Arikan et al. §5–7): the BVH traversal against a brute-force numpy
sum, the open plane, the corner and degenerate inputs."""
import mitsuba as mi
import numpy as np
import pytest

import mi_twopass  # noqa: F401
from mi_twopass.form_factor import polygon_form_factor
from mi_twopass.prepass import near_field as near_field_module
from mi_twopass.prepass.near_field import (PLANE_MIN_POINTS, build_near_field,
                                           correction_numpy, split_near_triangles)


def to_dr(a, cls):
    a = np.asarray(a, dtype=np.float32).reshape(-1, 3)
    return cls(*(mi.Float(a[:, k]) for k in range(3)))


def normals_of(verts):
    n = np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def run(nf, x, n, B_D, alpha, **kw):
    B_C, visits = nf.correction(to_dr(x, mi.Point3f), to_dr(n, mi.Vector3f),
                                to_dr(B_D, mi.Color3f), alpha, **kw)
    return np.asarray(B_C).T, np.asarray(visits)


def grid_plane(m, size=2.0, z=0.0):
    """An m×m grid of squares (2 triangles each) on [-size/2, size/2]² at height z, facing +z."""
    s = np.linspace(-size / 2, size / 2, m + 1)
    tris = []
    for i in range(m):
        for j in range(m):
            a, b = [s[i], s[j], z], [s[i + 1], s[j], z]
            c, d = [s[i + 1], s[j + 1], z], [s[i], s[j + 1], z]
            tris += [[a, b, c], [a, c, d]]
    return np.asarray(tris, dtype=np.float64)


def random_case(rng, T=80, P=150):
    c = rng.uniform(-1, 1, (T, 1, 3))
    verts = c + 0.25 * rng.normal(size=(T, 3, 3))
    x = rng.uniform(-1, 1, (P, 3))
    n = rng.normal(size=(P, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return verts, normals_of(verts), rng.uniform(0, 1, (T, 3)), x, n, rng.uniform(0, 1, (P, 3))


@pytest.mark.parametrize("seed", [0, 1])
def test_bvh_matches_brute_force(seed):
    """With the disk approximation off (open_factor = inf) the stackless traversal sums exactly
    the triangles the O(T) numpy loop sums: agreement to float32 round-off."""
    verts, tn, tB, x, n, B_D = random_case(np.random.default_rng(seed))
    nf = build_near_field(verts, tn, tB)
    for alpha in (0.3, 0.9, 5.0):
        ref = correction_numpy(x, n, B_D, alpha, verts, tn, tB)
        got, _ = run(nf, x, n, B_D, alpha, open_factor=np.inf)
        assert np.abs(ref).max() > 0.01  # the case is not trivially zero
        np.testing.assert_allclose(got, ref, atol=2e-5 * max(1.0, np.abs(ref).max()))


def test_brute_force_is_the_sum_of_form_factors():
    """correction_numpy itself: one triangle facing the point is (R − B_D)·F."""
    tri = np.array([[[-0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.0, 0.5, 1.0]]])
    tn = np.array([[0.0, 0.0, -1.0]])  # faces the point below it
    x, n = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    F = polygon_form_factor(x[0], n[0], tri[0])
    got = correction_numpy(x, n, [[0.2, 0.2, 0.2]], 2.0, tri, tn, [[1.0, 0.5, 0.0]])
    np.testing.assert_allclose(got[0], (np.array([1.0, 0.5, 0.0]) - 0.2) * F, rtol=1e-12)
    # the same triangle seen from its back (one-sided) contributes nothing
    assert np.all(correction_numpy(x, n, [[0.2] * 3], 2.0, tri, -tn, [[1.0] * 3]) == 0)


def test_disk_clusters_close_to_exact():
    """§7: nodes farther than 4 bounding radii summed as disks. A fine plane seen from above:
    the clustered sum stays within 10 % of the exact one (Baum et al.'s bound) and visits fewer
    nodes than there are triangles."""
    verts = grid_plane(24, size=2.0)
    tn = normals_of(verts)
    rng = np.random.default_rng(3)
    tB = rng.uniform(0.5, 1.0, (len(verts), 3))
    x = np.column_stack([rng.uniform(-0.5, 0.5, 20), rng.uniform(-0.5, 0.5, 20),
                         rng.uniform(0.05, 0.5, 20)])
    n = np.tile([0.0, 0.0, -1.0], (20, 1))
    B_D = np.full((20, 3), 0.1)
    nf = build_near_field(verts, tn, tB)
    exact, v_exact = run(nf, x, n, B_D, 10.0, open_factor=np.inf)
    approx, v_approx = run(nf, x, n, B_D, 10.0)
    np.testing.assert_allclose(approx, exact, rtol=0.1)
    assert v_approx.mean() < 0.5 * v_exact.mean() and v_approx.mean() < len(verts)


def test_open_plane_has_no_correction():
    """Points on a single flat plane see none of its (coplanar) triangles: B_C = 0 exactly."""
    verts = grid_plane(8)
    nf = build_near_field(verts, normals_of(verts), np.full((len(verts), 3), 0.7))
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(-1, 1, 64), rng.uniform(-1, 1, 64), np.zeros(64)])
    n = np.tile([0.0, 0.0, 1.0], (64, 1))
    got, _ = run(nf, x, n, np.full((64, 3), 0.3), 0.5)
    assert np.all(got == 0.0)


def test_corner_is_negative_and_finite():
    """A floor point next to a darker wall (R < B_D) gets B_C < 0, growing toward the corner but
    bounded (the exact form factor is ≤ 1, so |B_C| ≤ B_D). Half the hemisphere is wall at the
    corner, so B_C → (0.05 − 0.5)/2."""
    floor = grid_plane(6, size=2.0)  # z = 0, facing +z, x in [-1, 1]
    wall = grid_plane(6, size=2.0)[:, :, [2, 1, 0]] + np.array([1.0, 0.0, 1.0])  # x = 1
    wall_n = normals_of(wall)
    wall_n = np.where(wall_n[:, :1] > 0, -wall_n, wall_n)  # faces -x, into the room
    verts = np.concatenate([floor, wall])
    tn = np.concatenate([normals_of(floor), wall_n])
    tB = np.concatenate([np.full((len(floor), 3), 0.5), np.full((len(wall), 3), 0.05)])
    nf = build_near_field(verts, tn, tB)
    d = np.array([0.5, 0.2, 0.05, 1e-3, 1e-6, 0.0])
    x = np.column_stack([1.0 - d, np.zeros_like(d), np.zeros_like(d)])
    n = np.tile([0.0, 0.0, 1.0], (len(d), 1))
    B_D = np.full((len(d), 3), 0.5)
    got, _ = run(nf, x, n, B_D, 0.8)
    assert np.all(np.isfinite(got))
    assert np.all(got[:4, 0] < 0)
    assert np.all(np.diff(got[:4, 0]) < 0)  # more negative toward the corner
    # closer than the in-plane tolerance (~1e-5 relative) the point counts as on the wall: finite
    assert np.all(got[:, 0] >= -0.5 - 1e-5)  # bounded by (0.05 - 0.5)·Σ F, Σ F ≤ 1
    assert got[3, 0] == pytest.approx(-0.225, abs=0.01)
    np.testing.assert_allclose(got[:, 0], correction_numpy(x, n, B_D, 0.8, verts, tn, tB)[:, 0],
                               atol=0.05 * 0.45)


def test_degenerate_inputs_stay_finite():
    """Zero-area and sliver triangles, points on vertices and edges, alpha larger than the
    scene, an empty triangle set: no NaN or Inf."""
    rng = np.random.default_rng(5)
    verts = rng.uniform(-1, 1, (30, 3, 3))
    verts[:5, 2] = verts[:5, 1]  # zero area
    verts[5:10, 2] = verts[5:10, 1] + 1e-7  # slivers
    tn = normals_of(verts)
    nf = build_near_field(verts, tn, rng.uniform(0, 1, (30, 3)))
    x = np.concatenate([verts[10:20, 0], 0.5 * (verts[10:20, 0] + verts[10:20, 1])])
    n = normals_of(verts[10:30])
    got, _ = run(nf, x, n, np.full((20, 3), 0.4), 100.0)
    assert np.all(np.isfinite(got))
    empty = build_near_field(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3)))
    got, _ = run(empty, x, n, np.full((20, 3), 0.4), 1.0)
    assert np.all(got == 0)


def test_directional_far_field_matches_brute_force():
    """Eq. 5 variant: each triangle compared with π·L_F in its own direction; the BVH walk and
    the numpy sum agree, and a constant L_F gives back eq. 6 with B_D = π·L."""
    rng = np.random.default_rng(7)
    verts, tn, tB, x, n, B_D = random_case(rng, T=60, P=100)
    L_F = rng.normal(0.0, 0.2, (len(x), 9, 3))
    nf = build_near_field(verts, tn, tB)
    coeffs = [mi.Color3f(*(mi.Float(L_F[:, j, c].astype(np.float32)) for c in range(3)))
              for j in range(9)]
    got, _ = nf.correction(to_dr(x, mi.Point3f), to_dr(n, mi.Vector3f), to_dr(B_D, mi.Color3f),
                           0.9, open_factor=np.inf, L_F=coeffs)
    ref = correction_numpy(x, n, B_D, 0.9, verts, tn, tB, L_F=L_F)
    np.testing.assert_allclose(np.asarray(got).T, ref, atol=1e-4 * max(1.0, np.abs(ref).max()))
    const = np.zeros((len(x), 9, 3))
    const[:, 0, :] = 0.3 / 0.28209479177387814  # L = 0.3 everywhere
    np.testing.assert_allclose(correction_numpy(x, n, None, 0.9, verts, tn, tB, L_F=const),
                               correction_numpy(x, n, np.full((len(x), 3), 0.3 * np.pi), 0.9,
                                                verts, tn, tB), atol=1e-9)


def tri_area(v):
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)


def point_triangle_distance(x, v):
    """Distance from each point x (P, 3) to each triangle v (T, 3, 3) by dense sampling of the
    triangle (an upper bound, tight to the sampling step): (P, T)."""
    u = np.linspace(0.0, 1.0, 41)
    a, b = np.meshgrid(u, u)
    keep = a + b <= 1.0
    a, b = a[keep], b[keep]
    q = (v[:, None, 0] + a[None, :, None] * (v[:, None, 1] - v[:, None, 0])
         + b[None, :, None] * (v[:, None, 2] - v[:, None, 0]))  # (T, S, 3)
    return np.linalg.norm(x[:, None, None] - q[None], axis=-1).min(axis=-1)


def test_lazy_split_reaches_alpha_near_the_points_and_keeps_area():
    """§5: triangles near the shading points are split until their longest edge is ≤ alpha,
    those far from every point stay whole; total area, normals, radiosity, winding preserved."""
    big = np.array([[[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 3.0, 0.0]],
                    [[10.0, 0.0, 0.0], [14.0, 0.0, 0.0], [10.0, 0.0, 3.0]]])  # second: far away
    tn = normals_of(big)
    tB = np.array([[0.3, 0.2, 0.1], [0.9, 0.8, 0.7]])
    pts = np.array([[0.5, 0.5, 0.2], [1.0, 1.5, -0.1]])
    alpha = 0.4
    v, n, B, complete = split_near_triangles(big, tn, tB, pts, alpha)
    assert complete
    np.testing.assert_allclose(tri_area(v).sum(), tri_area(big).sum(), rtol=1e-12)
    near = point_triangle_distance(pts, v).min(axis=0) <= alpha
    edge = np.linalg.norm(v[:, [1, 2, 0]] - v, axis=2).max(axis=1)
    assert near.sum() > 10 and np.all(edge[near] <= alpha)
    assert edge.max() > alpha  # the part far from the points was not split to alpha
    assert any(np.allclose(t, big[1]) for t in v)  # the far triangle untouched
    np.testing.assert_allclose(normals_of(v), n, atol=1e-9)  # winding kept
    own = np.where(np.all(v[:, :, 2] == 0.0, axis=1), 0, 1)  # the near one lies in z = 0
    np.testing.assert_array_equal(B, tB[own])


def test_lazy_split_budget_and_no_points():
    """The triangle budget stops the splitting (complete = False); without shading points
    nothing is split."""
    big = np.array([[[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 3.0, 0.0]]])
    v, _, _, complete = split_near_triangles(big, normals_of(big), np.ones((1, 3)),
                                             np.array([[1.0, 1.0, 0.0]]), 0.01,
                                             max_triangles=50)
    assert not complete and len(v) <= 50
    np.testing.assert_allclose(tri_area(v).sum(), 6.0, rtol=1e-12)
    v, _, _, complete = split_near_triangles(big, normals_of(big), np.ones((1, 3)),
                                             np.zeros((0, 3)), 0.01)
    assert complete and len(v) == 1


def test_cell_leaf_lists_sum_what_the_root_walk_sums_without_disks():
    """LeafCells: a lane in a listed cell sums its cell's leaves, exactly the triangles the walk
    from the root sums with open_factor = inf (points at, between and away from the shading
    points; those away walk from the root), visiting fewer nodes; the brute-force sum agrees.
    With another alpha the lists do not apply and every lane walks from the root."""
    rng = np.random.default_rng(11)
    verts, tn, tB, _, _, _ = random_case(rng, T=120, P=1)
    pts = rng.uniform(-1, 1, (200, 3))
    alpha = 0.5
    x = np.concatenate([pts, pts[:100] + rng.normal(0, 0.05, (100, 3)),
                        rng.uniform(-3, 3, (50, 3))])
    n = rng.normal(size=(len(x), 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    B_D = rng.uniform(0, 1, (len(x), 3))
    root = build_near_field(verts, tn, tB)
    cells = build_near_field(verts, tn, tB, points=pts, alpha=alpha, cell_size=0.25)
    assert cells.cells.listed_cells > 0 and cells.cells.entries > 0
    got_root, v_root = run(root, x, n, B_D, alpha, open_factor=np.inf)
    got, v = run(cells, x, n, B_D, alpha)
    scale = max(1.0, np.abs(got_root).max())
    np.testing.assert_allclose(got, got_root, atol=1e-6 * scale)
    assert v[:200].mean() < 0.7 * v_root[:200].mean()
    ref = correction_numpy(x, n, B_D, alpha, verts, tn, tB)
    np.testing.assert_allclose(got, ref, atol=2e-5 * scale)
    # the lanes away from the shading points walk from the root, with its open factor
    away = slice(300, 350)
    np.testing.assert_allclose(got[away], run(root, x[away], n[away], B_D[away], alpha)[0],
                               atol=1e-6 * scale)
    # another alpha: the lists do not apply, the walk starts from the root
    got2, _ = run(cells, x, n, B_D, 0.3, open_factor=4.0)
    np.testing.assert_allclose(got2, run(root, x, n, B_D, 0.3, open_factor=4.0)[0],
                               atol=1e-6 * scale)


def test_plane_lists_sum_what_the_root_walk_sums_and_visit_fewer_leaves():
    """LeafCells' plane lists: in a corner of three grids (floor z = 0, walls x = −1 and
    y = −1, facing in) with shading points on all three planes and their normals, a lane on a
    plane walks only the leaves above its plane and sums what the walk from the root sums
    (open_factor = inf) to float32 round-off, with far fewer visits than the cell's own
    list; a lane on no plane of its cell (tilted normal, or off the plane) reads the cell's
    list, and agrees too. A plane with fewer than PLANE_MIN_POINTS points gets no lists."""
    floor = grid_plane(8)
    wall_x = grid_plane(8)[:, :, [2, 0, 1]] + [-1.0, 0.0, 1.0]  # x = −1, facing +x
    wall_y = grid_plane(8)[:, :, [1, 2, 0]] + [0.0, -1.0, 1.0]  # y = −1, facing +y
    verts = np.concatenate([floor, wall_x, wall_y])
    tn = normals_of(verts)
    assert np.allclose(tn[:128], [0, 0, 1]) and np.allclose(tn[128:256], [1, 0, 0]) \
        and np.allclose(tn[256:], [0, 1, 0])
    tB = np.random.default_rng(4).uniform(0, 1, (len(verts), 3))
    rng = np.random.default_rng(8)
    u = rng.uniform(-0.95, 0.95, (3, 150, 2))
    w = rng.uniform(0.02, 1.9, (150,))
    pts = np.concatenate([np.column_stack([u[0, :, 0], u[0, :, 1], np.zeros(150)]),
                          np.column_stack([np.full(150, -1.0), u[1, :, 0], w]),
                          np.column_stack([u[2, :, 0], np.full(150, -1.0), w])])
    nrm = np.repeat(np.eye(3)[[2, 0, 1]], 150, axis=0)
    alpha = 0.4
    plain = build_near_field(verts, tn, tB, points=pts, alpha=alpha, cell_size=0.2)
    planes = build_near_field(verts, tn, tB, points=pts, alpha=alpha, cell_size=0.2,
                              normals=nrm)
    assert plain.cells.planes is None and len(planes.cells.planes.offset) == 3
    # render-time points: between the shading points, on the planes; then tilted / lifted
    x = pts.copy()
    x[:150, :2] += rng.uniform(-0.05, 0.05, (150, 2))
    x[150:300, 1:] += rng.uniform(-0.05, 0.05, (150, 2))
    x[300:, [0, 2]] += rng.uniform(-0.05, 0.05, (150, 2))
    x = np.clip(x, [-1, -1, 0], [1, 1, 2])
    B_D = rng.uniform(0, 1, (450, 3))
    root = build_near_field(verts, tn, tB)
    want, _ = run(root, x, nrm, B_D, alpha, open_factor=np.inf)
    got, v = run(planes, x, nrm, B_D, alpha)
    got_plain, v_plain = run(plain, x, nrm, B_D, alpha)
    scale = max(1.0, np.abs(want).max())
    np.testing.assert_allclose(got, want, atol=1e-6 * scale)
    np.testing.assert_allclose(got_plain, want, atol=1e-6 * scale)
    assert np.abs(want).max() > 0.01  # the corner's walls count
    assert v.mean() < 0.5 * v_plain.mean()
    # not on a plane of the cell: a tilted normal, a point lifted off the floor
    tilted = nrm + [0.05, 0.02, 0.0]
    tilted /= np.linalg.norm(tilted, axis=1, keepdims=True)
    lifted = x + 0.01 * nrm
    for xx, nn in ((x, tilted), (lifted, nrm)):
        want, _ = run(root, xx, nn, B_D, alpha, open_factor=np.inf)
        got, v = run(planes, xx, nn, B_D, alpha)
        np.testing.assert_allclose(got, want, atol=1e-6 * scale)
    few = build_near_field(verts, tn, tB, points=pts[:PLANE_MIN_POINTS - 1], alpha=alpha,
                           cell_size=0.2, normals=nrm[:PLANE_MIN_POINTS - 1])
    assert few.cells.planes is None


def test_cell_leaf_lists_hold_every_leaf_a_point_of_the_cell_may_count():
    """Every (point, triangle) pair that counts (centroid within alpha, point in front) for a
    point in a listed cell has the triangle in that cell's list."""
    rng = np.random.default_rng(3)
    verts, tn, tB, _, _, _ = random_case(rng, T=150, P=1)
    pts = rng.uniform(-1, 1, (300, 3))
    alpha = 0.4
    nf = build_near_field(verts, tn, tB, points=pts, alpha=alpha, cell_size=0.2)
    lc = nf.cells
    x = pts + rng.normal(0, 0.1, pts.shape)
    ijk = np.floor((x - lc.lo) / lc.cell).astype(np.int64)
    inside = np.all((ijk >= 0) & (ijk < lc.res), axis=1)
    cid = (ijk[:, 0] * lc.res[1] + ijk[:, 1]) * lc.res[2] + ijk[:, 2]
    centroid = nf.verts.mean(axis=1)
    checked = 0
    for i in np.flatnonzero(inside):
        c = cid[i]
        if lc.count[c] == 0:
            continue
        listed = set(nf.tri[lc.leaves[lc.first[c]:lc.first[c] + lc.count[c]]].tolist())
        near = np.linalg.norm(centroid - x[i], axis=1) <= alpha
        front = ((x[i] - nf.verts[:, 0]) * nf.tri_normal).sum(axis=1) > 1e-4 * alpha
        need = set(np.flatnonzero(near & front).tolist())
        assert need <= listed
        checked += len(need)
    assert checked > 100


def test_node_bounds_hold_every_vertex_and_centroid():
    """The bottom-up build: every node's box, bounding sphere (about the box centre) and
    centroid sphere hold all vertices and centroids of its subtree (leaves exactly); area and
    the area-weighted radiosity are the sums over its triangles."""
    verts, tn, tB, _, _, _ = random_case(np.random.default_rng(5), T=90, P=1)
    nf = build_near_field(verts, tn, tB)
    area = 0.5 * np.linalg.norm(np.cross(nf.verts[:, 1] - nf.verts[:, 0],
                                         nf.verts[:, 2] - nf.verts[:, 0]), axis=1)
    for node in range(nf.node_count):
        below = nf.tri[node:nf.skip[node]]
        t = below[below >= 0]
        v = nf.verts[t].reshape(-1, 3)
        c = nf.verts[t].mean(axis=1)
        eps = 1e-9
        assert np.all(np.abs(v - nf.center[node]) <= nf.half[node] + eps)
        assert np.linalg.norm(v - nf.center[node], axis=1).max() <= nf.radius[node] + eps
        assert np.linalg.norm(c - nf.ccenter[node], axis=1).max() <= nf.cradius[node] + eps
        np.testing.assert_allclose(nf.area[node], area[t].sum())
        np.testing.assert_allclose(nf.B[node], (area[t, None] * nf.tri_B[t]).sum(0)
                                   / area[t].sum())
        if len(t) == 1:
            np.testing.assert_allclose(nf.radius[node],
                                       np.linalg.norm(v - nf.center[node], axis=1).max())
            assert nf.cradius[node] == 0.0


def test_cell_lists_with_no_leaf_in_reach_are_empty_and_the_walk_still_runs():
    """Shading points far from every triangle: no cell lists a leaf, and every lane walks from
    the root (B_C = 0 there: no centroid within alpha)."""
    verts = grid_plane(4)
    tn = normals_of(verts)
    pts = np.array([[10.0, 10.0, 10.0], [10.2, 10.0, 10.0]])
    nf = build_near_field(verts, tn, np.ones((len(verts), 3)), points=pts, alpha=0.3)
    assert nf.cells.entries == 0
    got, _ = run(nf, pts, np.tile([0.0, 0.0, -1.0], (2, 1)), np.zeros((2, 3)), 0.3)
    assert np.all(got == 0)


def test_stable_order_is_numpys_stable_argsort():
    """The cell lists' two 16-bit radix passes order (leaf, cell) pairs exactly as a stable
    argsort: by key, ties in their input order (the root walk's leaf order)."""
    rng = np.random.default_rng(3)
    for high in (40, 1 << 20, (1 << 32) - 1, 1 << 40):  # ties, both halves, the fallback
        keys = rng.integers(0, high, 5000)
        assert np.array_equal(near_field_module._stable_order(keys), np.argsort(keys, kind="stable"))
    assert near_field_module._stable_order(np.zeros(0, np.int64)).size == 0


def test_every_inner_node_splits_its_triangles_at_the_median_of_its_longest_axis():
    """The top-down sweep's integer ranks must split as sorting by the centroid coordinate
    would, ties (a grid's shared coordinates) included: each inner node's left child holds
    the n // 2 triangles lowest along the node's longest centroid extent."""
    verts = np.concatenate([grid_plane(6), grid_plane(5, z=0.5), grid_plane(3, size=1.0, z=1.0)])
    nf = build_near_field(verts, normals_of(verts), np.ones((len(verts), 3)))
    centroid = nf.verts.mean(axis=1)

    def subtree(node):
        return [int(t) for t in nf.tri[node:nf.skip[node]] if t >= 0]

    inner = np.flatnonzero(nf.tri < 0)
    assert len(inner) == len(nf.verts) - 1
    for node in inner:
        tris = subtree(node)
        left = subtree(node + 1)
        right = [t for t in tris if t not in set(left)]
        assert len(left) == len(tris) // 2
        c = centroid[tris]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        assert centroid[left, axis].max() <= centroid[right, axis].min()
