"""Vertex clustering of the near field's small triangles (mi_twopass.prepass.near_merge)."""
import numpy as np

from mi_twopass.evaluation.prepass_scaling import sphere_mesh
from mi_twopass.prepass.near_field import correction_numpy
from mi_twopass.prepass.near_merge import merge_small_triangles


def grid_square(n, z=0.0):
    """A unit square in the plane z, facing +z, as 2 n² triangles (soup)."""
    t = np.linspace(0.0, 1.0, n + 1)
    X, Y = np.meshgrid(t, t, indexing="ij")
    P = np.stack([X, Y, np.full_like(X, z)], axis=-1)
    a, b, c, d = P[:-1, :-1], P[1:, :-1], P[1:, 1:], P[:-1, 1:]
    tris = np.concatenate([np.stack([a, b, c], axis=2).reshape(-1, 3, 3),
                           np.stack([a, c, d], axis=2).reshape(-1, 3, 3)])
    return tris, np.tile([0.0, 0.0, 1.0], (len(tris), 1))


def soup(verts, faces):
    tris = verts[faces]
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    keep = np.linalg.norm(cross, axis=1) > 0
    tris, cross = tris[keep], cross[keep]
    return tris, cross / np.linalg.norm(cross, axis=1, keepdims=True)


def areas(tris):
    return 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]),
                                axis=1)


def test_triangles_larger_than_the_cell_come_back_unchanged():
    tris, n = grid_square(4)  # edges 0.25 and 0.35: none below 0.2
    B = np.random.default_rng(0).random((len(tris), 3))
    v, nn, BB, merged = merge_small_triangles(tris, n, B, 0.2)
    assert merged == 0
    assert np.array_equal(v, tris) and np.array_equal(nn, n) and np.array_equal(BB, B)
    assert merge_small_triangles(tris, n, B, 0.0)[3] == 0


def test_a_fine_square_becomes_a_coarse_one_facing_the_same_way():
    tris, n = grid_square(64)  # 8192 triangles of edge 1/64
    B = np.tile([0.5, 0.25, 1.0], (len(tris), 1))
    v, nn, BB, merged = merge_small_triangles(tris, n, B, 0.1)
    assert len(v) < len(tris) / 20 and merged == len(tris) - len(v)
    np.testing.assert_allclose(nn, np.tile([0.0, 0.0, 1.0], (len(v), 1)), atol=1e-12)
    np.testing.assert_allclose(v[..., 2], 0.0)  # corners stay on the plane
    np.testing.assert_allclose(BB, B[: len(v)])  # a uniform radiosity is kept
    # no two triangles overlap: their area is at most the square's; the rim's corners move
    # along the rim, so only the square's own corners are cut (measured 99.3 %)
    total = areas(v).sum()
    assert 0.98 <= total <= 1.0 + 1e-9


def test_the_two_sides_of_a_sheet_stay_apart():
    front, n = grid_square(32)
    back = front[:, [0, 2, 1]]
    tris = np.concatenate([front, back])
    normals = np.concatenate([n, -n])
    B = np.concatenate([np.ones((len(front), 3)), np.zeros((len(back), 3))])
    v, nn, BB, _ = merge_small_triangles(tris, normals, B, 0.125)
    up = nn[:, 2] > 0
    assert up.any() and (~up).any()
    np.testing.assert_allclose(np.abs(nn[:, 2]), 1.0)
    np.testing.assert_allclose(BB[up], 1.0)  # each side keeps its own radiosity
    np.testing.assert_allclose(BB[~up], 0.0)
    np.testing.assert_allclose(areas(v[up]).sum(), areas(v[~up]).sum())


def test_a_winding_against_the_normal_is_read_by_the_normal():
    tris, n = grid_square(32)
    reversed_ = tris[:, [0, 2, 1]]  # the winding says -z, the normals +z
    v, nn, _, _ = merge_small_triangles(reversed_, n, np.ones((len(tris), 3)), 0.125)
    np.testing.assert_allclose(nn[:, 2], 1.0)


def test_a_smooth_radiosity_is_kept_to_the_cell_scale():
    tris, n = grid_square(64)
    x = tris.mean(axis=1)[:, 0]
    B = np.stack([x, 1.0 - x, np.ones_like(x)], axis=1)
    v, _, BB, _ = merge_small_triangles(tris, n, B, 0.1)
    xc = v.mean(axis=1)[:, 0]
    assert np.abs(BB[:, 0] - xc).max() < 0.1
    assert np.abs(BB[:, 1] - (1.0 - xc)).max() < 0.1


def test_a_fine_sphere_keeps_its_form_factor():
    """A closed mesh of 20k triangles merged at a fifth of its radius: the form factor it
    offers a point facing it (the near field's correction with R = 1, B_D = 0, every triangle
    near) within 2 % of the fine mesh's, from 1/30 of the triangles."""
    V, F = sphere_mesh(20000, centre=(0.0, 0.0, 0.0), radius=1.0)
    tris, n = soup(V, F)
    B = np.ones((len(tris), 3))
    v, nn, BB, merged = merge_small_triangles(tris, n, B, 0.2)
    assert len(v) * 20 < len(tris)
    x = np.array([[0.0, 0.0, 1.5], [0.3, -0.2, 1.4]])
    normal = -x / np.linalg.norm(x, axis=1, keepdims=True)
    zero = np.zeros((2, 3))
    fine = correction_numpy(x, normal, zero, 100.0, tris, n, B)
    coarse = correction_numpy(x, normal, zero, 100.0, v, nn, BB)
    assert fine[:, 0].min() > 0.1
    np.testing.assert_allclose(coarse, fine, rtol=0.02)


def test_a_big_triangle_beside_small_ones_keeps_its_far_corners():
    """A big triangle with one corner among small ones: that corner moves to its cell, the
    two far ones stay where they are, even where they share a cell no small triangle
    reaches (they are not one point)."""
    fine, n = grid_square(32)  # edges 1/32, below the cell of 0.25
    # one corner on the grid's rim, the other two in one cell (x = 1.6 / 0.25 = 6.4) that no
    # small triangle reaches
    big = np.array([[[1.0, 0.0, 0.0], [1.6, 0.0, 0.0], [1.6, 0.1, 0.0]]])
    tris = np.concatenate([fine, big])
    normals = np.concatenate([n, [[0.0, 0.0, 1.0]]])
    v, nn, _, _ = merge_small_triangles(tris, normals, np.ones((len(tris), 3)), 0.25)
    far = [np.any(np.all(np.isclose(v, c), axis=-1)) for c in ([1.6, 0.0, 0.0], [1.6, 0.1, 0.0])]
    assert all(far)  # both far corners survive, in one triangle
    assert np.allclose(nn[:, 2], 1.0)
