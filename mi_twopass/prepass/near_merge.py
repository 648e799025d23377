"""The near field's triangles at the resolution it needs: vertex clustering of the small ones.

Arikan et al. (§5) split the scene's triangles until they are smaller than alpha near the
shading points; nothing in the paper asks for triangles much smaller than that, yet a scene
may hold millions of them (a finely tessellated statue, a plant). Each one costs the near-field
build (its BVH, the cells' leaf lists) and every cache read within alpha of it sums its form
factor: on the Cornell box with a sphere of 10^6 triangles the radiance cache's prepass took
19 s and its render per sample 10x path's, for a sphere whose near field is smooth at the scale
of alpha.

:func:`merge_small_triangles` is Rossignac and Borrel's vertex clustering ("Multi-resolution 3D
approximations for rendering complex scenes", 1993) on the near field's triangle soup, at a
cell of side ``size`` (a fraction of alpha): the corners in cells that hold a corner of a small
triangle (longest edge below ``size``) move to their cell's representative, the mean of its
corners on a rim (an edge no triangle of the same side shares) where it has any, else of all
its corners, so an open mesh keeps its outline where it meets a wall; triangles whose three
corners land in fewer than three cells vanish, and triangles that land on the same three cells
with the same winding become one. Triangles with no corner in such a cell are kept bit for bit,
so a scene without small triangles has the near field it had. Corners shared by triangles move
together (the same cell, the same mean), so a closed mesh stays closed; a corner moves by at most
the cell's diagonal, ``size``·√3.

Radiosity: each cell takes, per normal bin (the dominant axis of the normal and its sign, so
the two sides of a sheet stay apart), the area-weighted mean radiosity of the small triangles
with a corner in it, and a merged triangle the mean of its three cells' values in its bin; a
triangle with no merged corner keeps its own. The means cut an open mesh's corners and round a
closed one by a fraction of a cell: the near field then lacks (or adds) a sliver there, whose
light the far field's value in that direction stands for, as it does for every triangle beyond
alpha. A merged triangle's normal is that of its moved corners in the original
winding; one that folds over (normal against the area-weighted normal of the triangles it
replaces) is dropped.
"""
from __future__ import annotations

import numpy as np

from ..scene.patches import normal_bins

#: voxel coordinates of the clustering grid are kept to this many bits per axis
_BITS = 20
#: normal bins of the cells' radiosities (:func:`~mi_twopass.scene.patches.normal_bins`)
_BINS = 6


def _corner_ids(points):
    """uint64 id of each point (n, 3) from its float32 bits: equal positions, equal ids
    (a hash: two different positions share one with probability about n²/2^64)."""
    bits = np.ascontiguousarray(points, dtype=np.float32).view(np.uint32).astype(np.uint64)
    with np.errstate(over="ignore"):
        return (bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)
                ^ bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)
                ^ bits[:, 2] * np.uint64(0x165667B19E3779F9))


def _rim_corners(verts, tri_bin):
    """(T, 3) bool: the corners on a rim, an edge of ``verts`` (T, 3, 3) that no triangle
    of the same normal bin ``tri_bin`` (T,) runs the other way (a consistently wound surface's
    inner edges all have such a twin; the two sides of a sheet, in different bins, do not pair).
    An edge where the normal crosses into another bin reads as a rim too: its corners then
    stay nearer where they were, which costs triangles, not accuracy."""
    T = len(verts)
    ids = _corner_ids(verts.reshape(-1, 3)).reshape(T, 3)
    a, b = ids, ids[:, [1, 2, 0]]  # edge j: corner j → corner j+1
    bins = np.repeat(tri_bin.astype(np.uint64)[:, None], 3, axis=1)
    with np.errstate(over="ignore"):
        key = a * np.uint64(0xD6E8FEB86659FD93) + b * np.uint64(0xA0761D6478BD642F) + bins
        twin = b * np.uint64(0xD6E8FEB86659FD93) + a * np.uint64(0xA0761D6478BD642F) + bins
    ordered = np.sort(key.ravel())
    twin = twin.ravel()
    by_twin = np.argsort(twin)  # sorted needles: searchsorted reads the keys in order
    needles = twin[by_twin]
    at = np.minimum(np.searchsorted(ordered, needles), len(ordered) - 1)
    open_edge = np.empty(3 * T, dtype=bool)
    open_edge[by_twin] = ordered[at] != needles
    open_edge = open_edge.reshape(T, 3)
    return open_edge | open_edge[:, [2, 0, 1]]  # corner j ends edge j − 1


def _cell_keys(points, origin, size):
    """int64 key of the cell of side ``size`` of each point (n, 3)."""
    q = np.floor((points - origin) / size).astype(np.int64)
    q = np.clip(q, 0, (1 << _BITS) - 1)
    return (q[:, 0] << (2 * _BITS)) | (q[:, 1] << _BITS) | q[:, 2]


def merge_small_triangles(verts, tri_normal, tri_B, size: float):
    """Vertex clustering of the triangles smaller than ``size`` (module docstring).

    ``verts`` (T, 3, 3) with one-sided unit normals ``tri_normal`` (T, 3) and radiosities
    ``tri_B`` (T, 3) → ``(verts, tri_normal, tri_B, merged)``, ``merged`` the input triangles
    less the output ones (vanished or made one with others). Unchanged
    (the same arrays) where ``size`` ≤ 0 or no triangle is small."""
    verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3, 3)
    tri_normal = np.asarray(tri_normal, dtype=np.float64).reshape(-1, 3)
    tri_B = np.asarray(tri_B, dtype=np.float64).reshape(-1, 3)
    T = len(verts)
    size = float(size)
    if T == 0 or not size > 0.0 or not np.isfinite(size):
        return verts, tri_normal, tri_B, 0
    edges = verts[:, [1, 2, 0]] - verts
    longest = np.sqrt((edges ** 2).sum(-1).max(axis=1))
    small = longest < size
    if not small.any():
        return verts, tri_normal, tri_B, 0
    # windings that agree with the given normals, so the merged normals keep the side
    cross = np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    flipped = (cross * tri_normal).sum(axis=1) < 0
    if flipped.any():
        verts = verts.copy()
        verts[flipped] = verts[flipped][:, [0, 2, 1]]
    origin = verts.reshape(-1, 3).min(axis=0)
    keys = _cell_keys(verts.reshape(-1, 3), origin, size)  # (3T,)
    cells, corner_cell = np.unique(keys, return_inverse=True)
    corner_cell = corner_cell.reshape(T, 3)
    C = len(cells)
    active = np.zeros(C, dtype=bool)
    active[corner_cell[small].ravel()] = True
    moved = active[corner_cell]  # (T, 3): corners that move to their cell's mean
    touched = moved.any(axis=1)
    if not touched.any():
        return verts, tri_normal, tri_B, 0
    # each active cell's representative: the mean of its rim corners where it has any (a
    # mesh's open edge, where it meets a wall, stays where it is), else of all its corners
    tri_bin = normal_bins(tri_normal)
    rim = _rim_corners(verts, tri_bin).ravel()
    flat = corner_cell.ravel()
    on = active[flat]
    has_rim = np.zeros(C, dtype=bool)
    has_rim[flat[on & rim]] = True
    use = on & (rim | ~has_rim[flat])
    pts = verts.reshape(-1, 3)
    n_in = np.bincount(flat[use], minlength=C).astype(np.float64)
    mean = np.stack([np.bincount(flat[use], weights=pts[use, k], minlength=C)
                     for k in range(3)], axis=1) / np.maximum(n_in, 1.0)[:, None]
    # radiosity per cell and normal bin (the two sides of a sheet, the two walls of a crease
    # apart)
    s_cells = (corner_cell[small] * _BINS + tri_bin[small, None]).ravel()
    w = np.repeat(area[small], 3)
    w_sum = np.bincount(s_cells, weights=w, minlength=C * _BINS)
    cell_B = np.stack([np.bincount(s_cells, weights=w * np.repeat(tri_B[small, k], 3),
                                   minlength=C * _BINS) for k in range(3)], axis=1)
    has_B = w_sum > 0
    cell_B[has_B] /= w_sum[has_B, None]

    kept = ~touched  # bit for bit
    t_idx = np.flatnonzero(touched)
    # a corner's identity after the merge: its cell where it moves, else itself (a corner that
    # stays, of a big triangle, meets no other)
    own = C + np.arange(3 * len(t_idx)).reshape(-1, 3)
    cc = np.where(moved[t_idx], corner_cell[t_idx], own)
    distinct = (cc[:, 0] != cc[:, 1]) & (cc[:, 1] != cc[:, 2]) & (cc[:, 0] != cc[:, 2])
    t_idx, cc = t_idx[distinct], cc[distinct]
    # one triangle per (three corners, winding): the corners in a canonical rotation (smallest
    # first) keep the winding; the two windings of the same cells stay two triangles
    r = np.argmin(cc, axis=1)
    rows = np.arange(len(cc))
    canon = np.stack([cc[rows, r], cc[rows, (r + 1) % 3], cc[rows, (r + 2) % 3]], axis=1)
    _, first, group = np.unique(canon, axis=0, return_index=True, return_inverse=True)
    group = group.reshape(-1)
    rep = t_idx[first]
    G = len(first)
    new_v = verts[rep].copy()
    mv = moved[rep]
    cc_rep = corner_cell[rep]
    new_v[mv] = mean[cc_rep[mv]]
    # the normal the group's triangles had, area-weighted, against the moved corners' normal
    had = np.stack([np.bincount(group, weights=area[t_idx] * tri_normal[t_idx, k], minlength=G)
                    for k in range(3)], axis=1)
    new_cross = np.cross(new_v[:, 1] - new_v[:, 0], new_v[:, 2] - new_v[:, 0])
    length = np.linalg.norm(new_cross, axis=1)
    ok = (length > 0) & ((new_cross * had).sum(axis=1) > 0)
    new_v, new_cross, length, cc_rep, mv, rep = (new_v[ok], new_cross[ok], length[ok],
                                                 cc_rep[ok], mv[ok], rep[ok])
    new_n = new_cross / length[:, None]
    # radiosity: a moved corner reads its cell in the triangle's normal bin, an unmoved one
    # (or one whose cell holds no small triangle of that bin) the triangle's own value
    slot = cc_rep * _BINS + normal_bins(new_n)[:, None]
    from_cell = mv & has_B[slot]
    corner_B = np.where(from_cell[:, :, None], cell_B[slot], tri_B[rep][:, None, :])
    new_B = corner_B.mean(axis=1)
    out_v = np.concatenate([verts[kept], new_v])
    out_n = np.concatenate([tri_normal[kept], new_n])
    out_B = np.concatenate([tri_B[kept], new_B])
    merged = T - len(out_v)
    return out_v, out_n, out_B, int(merged)


__all__ = ["merge_small_triangles"]
