"""Point-to-polygon form factors (mi_twopass.form_factor) against closed forms and quadrature."""
import math

import numpy as np
import pytest

import mi_twopass  # noqa: F401  (sets up libLLVM and the variant before mitsuba/drjit)
import mitsuba as mi

from mi_twopass.form_factor import point_to_disk_approx, polygon_form_factor

RNG_SEED = 4321
Z = np.array([0.0, 0.0, 1.0])
UNIT_SQUARE = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])

# ---------------------------------------------------------------------------------------------
# Closed forms (Howell, "A Catalog of Radiation Heat Transfer Configuration Factors")


def corner_rectangle_ff(a, b, c):
    """Differential element at the origin (normal +z) to the rectangle [0,a]×[0,b] at height c,
    parallel to it, with a corner above the element (Howell B-3)."""
    A, B = a / c, b / c
    return (A / math.sqrt(1 + A * A) * math.atan(B / math.sqrt(1 + A * A))
            + B / math.sqrt(1 + B * B) * math.atan(A / math.sqrt(1 + B * B))) / (2 * math.pi)


def parallel_rectangles_ff(a, b, c):
    """Rectangle a×b to the directly opposed parallel a×b rectangle at distance c (Howell C-11)."""
    X, Y = a / c, b / c
    return 2.0 / (math.pi * X * Y) * (
        math.log(math.sqrt((1 + X * X) * (1 + Y * Y) / (1 + X * X + Y * Y)))
        + X * math.sqrt(1 + Y * Y) * math.atan(X / math.sqrt(1 + Y * Y))
        + Y * math.sqrt(1 + X * X) * math.atan(Y / math.sqrt(1 + X * X))
        - X * math.atan(X) - Y * math.atan(Y))


def perpendicular_rectangles_ff(h, w, l=1.0):
    """Rectangle w×l to the rectangle h×l sharing its edge of length l at 90° (Howell C-14)."""
    H, W = h / l, w / l
    s = H * H + W * W
    log_arg = ((1 + W * W) * (1 + H * H) / (1 + s)
               * (W * W * (1 + s) / ((1 + W * W) * s)) ** (W * W)
               * (H * H * (1 + s) / ((1 + H * H) * s)) ** (H * H))
    return (W * math.atan(1 / W) + H * math.atan(1 / H) - math.sqrt(s) * math.atan(1 / math.sqrt(s))
            + 0.25 * math.log(log_arg)) / (math.pi * W)


# ---------------------------------------------------------------------------------------------
# Helpers


def to_point(a):
    a = np.atleast_2d(a)
    return mi.Point3f(*[mi.Float(np.ascontiguousarray(a[:, k], dtype=np.float32)) for k in range(3)])


def to_vector(a):
    a = np.atleast_2d(a)
    return mi.Vector3f(*[mi.Float(np.ascontiguousarray(a[:, k], dtype=np.float32)) for k in range(3)])


def form_factor_drjit(x, n, verts):
    """polygon_form_factor through the Dr.Jit path on numpy inputs: x, n (m, 3), verts (m, K, 3)."""
    verts = np.asarray(verts, dtype=np.float64)
    if verts.ndim == 2:
        verts = np.broadcast_to(verts, (len(np.atleast_2d(x)),) + verts.shape)
    points = [to_point(verts[:, k]) for k in range(verts.shape[1])]
    return np.asarray(polygon_form_factor(to_point(x), to_vector(n), points), dtype=np.float64)


def single_form_factor(backend):
    """F(x, n, verts) for one configuration through the numpy or the Dr.Jit path."""
    if backend == "numpy":
        return polygon_form_factor
    return lambda x, n, verts: form_factor_drjit(x, n, verts)[0]


def square_quadrature(origin, e1, e2, n=16):
    """Gauss–Legendre points and area weights on the parallelogram origin + [0,1]·e1 + [0,1]·e2."""
    x, w = np.polynomial.legendre.leggauss(n)
    x, w = 0.5 * (x + 1.0), 0.5 * w
    U, V = np.meshgrid(x, x, indexing="ij")
    pts = origin + U.reshape(-1, 1) * e1 + V.reshape(-1, 1) * e2
    return pts, np.outer(w, w).reshape(-1) * np.linalg.norm(np.cross(e1, e2))


def triangle_quadrature(tri, n=16):
    """Duffy-collapsed Gauss–Legendre points and area weights on a triangle."""
    x, w = np.polynomial.legendre.leggauss(n)
    x, w = 0.5 * (x + 1.0), 0.5 * w
    U, V = np.meshgrid(x, x, indexing="ij")
    U, V = U.reshape(-1, 1), V.reshape(-1, 1)
    a, b, c = tri
    pts = a + U * (1 - V) * (b - a) + U * V * (c - a)
    area2 = np.linalg.norm(np.cross(b - a, c - a))
    return pts, np.outer(w, w).reshape(-1) * U[:, 0] * area2


def area_to_polygon_ff(receiver_pts, receiver_w, receiver_n, verts):
    """F from a surface (quadrature points/weights) to a polygon: (1/A) ∫ F(x → polygon) dA_x."""
    return (polygon_form_factor(receiver_pts, receiver_n, verts) * receiver_w).sum() / receiver_w.sum()


def brute_force_ff(x, n, tri, levels):
    """(1/π) ∫ max(0, n·ω) |m·ω| / r² dA over the triangle, by the midpoint rule on 4^levels
    congruent sub-triangles (the slow obvious reference)."""
    subs = np.asarray(tri, dtype=np.float64)[None]
    for _ in range(levels):
        a, b, c = subs[:, 0], subs[:, 1], subs[:, 2]
        ab, bc, ca = 0.5 * (a + b), 0.5 * (b + c), 0.5 * (c + a)
        children = ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))
        subs = np.concatenate([np.stack(t, axis=1) for t in children])
    centroid = subs.mean(axis=1)
    normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    area = 0.5 * np.linalg.norm(normal) / len(subs)
    normal /= np.linalg.norm(normal)
    d = centroid - x
    r2 = (d * d).sum(axis=1)
    w = d / np.sqrt(r2)[:, None]
    return (np.maximum(w @ n, 0.0) * np.abs(w @ normal) / r2).sum() * area / math.pi


def random_unit(rng, n=None):
    d = rng.normal(size=(3,) if n is None else (n, 3))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# Closed forms


@pytest.mark.parametrize("a,b,c", [(1.0, 1.0, 1.0), (2.0, 0.5, 1.0), (0.1, 3.0, 0.7), (1e3, 1e3, 1.0)])
def test_differential_element_to_parallel_rectangle_above_corner(a, b, c):
    verts = np.array([[0.0, 0, c], [a, 0, c], [a, b, c], [0, b, c]])
    exact = corner_rectangle_ff(a, b, c)
    assert polygon_form_factor(np.zeros(3), Z, verts) == pytest.approx(exact, rel=1e-12)
    assert polygon_form_factor(np.zeros(3), Z, verts[::-1]) == pytest.approx(exact, rel=1e-12)  # winding
    assert form_factor_drjit(np.zeros(3), Z, verts)[0] == pytest.approx(exact, rel=1e-5)
    # the same rectangle as two triangles (the Dr.Jit triangle path)
    tris = np.stack([verts[[0, 1, 2]], verts[[0, 2, 3]]])
    assert form_factor_drjit(np.zeros((2, 3)), np.tile(Z, (2, 1)), tris).sum() == pytest.approx(exact, rel=1e-5)


def test_parallel_unit_squares():
    pts, w = square_quadrature(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    F = area_to_polygon_ff(pts, w, Z, UNIT_SQUARE + [0, 0, 1])
    assert parallel_rectangles_ff(1, 1, 1) == pytest.approx(0.1998, abs=1e-4)
    assert F == pytest.approx(parallel_rectangles_ff(1, 1, 1), abs=1e-9)


def test_perpendicular_unit_squares_sharing_an_edge():
    # receiver: z = 0, normal +z; emitter: the square in the plane y = 0 above the shared x edge
    emitter = np.array([[0.0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]])
    pts, w = square_quadrature(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    F = area_to_polygon_ff(pts, w, Z, emitter)
    assert perpendicular_rectangles_ff(1, 1) == pytest.approx(0.2000, abs=1e-4)
    assert F == pytest.approx(perpendicular_rectangles_ff(1, 1), abs=1e-9)
    # other aspect ratios (h: emitter height, depth: receiver's). The integrand behaves like
    # y·log y at the shared edge, so Gauss–Legendre converges as n⁻⁴ (≈ 1e-6 at n = 24)
    for h, depth in ((0.5, 2.0), (3.0, 0.25)):
        pts, w = square_quadrature(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, depth, 0]), n=64)
        F = area_to_polygon_ff(pts, w, Z, emitter * [1, 1, h])
        assert F == pytest.approx(perpendicular_rectangles_ff(h, depth), abs=1e-7)


# ---------------------------------------------------------------------------------------------
# Brute force, reciprocity, clipping


def random_configurations(rng, count):
    """(x, n, triangle, straddles) with the point at least 0.3 from the triangle's vertices and
    0.05/|N| from its plane; alternately straddling the point's tangent plane and wholly above it."""
    configs = []
    while len(configs) < count:
        tri = rng.uniform(-1.0, 1.0, size=(3, 3))
        x = rng.uniform(-1.5, 1.5, size=3)
        n = random_unit(rng)
        h = (tri - x) @ n
        straddles = h.min() < 0 < h.max()
        if not straddles and h.min() <= 0:
            continue
        N = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        if np.linalg.norm(tri - x, axis=1).min() < 0.3 or abs(N @ (x - tri[0])) < 0.05:
            continue
        if straddles == (len(configs) % 2 == 0):
            configs.append((x, n, tri, straddles))
    return configs


def test_matches_brute_force_quadrature_on_random_triangles():
    for x, n, tri, straddles in random_configurations(np.random.default_rng(RNG_SEED), 12):
        F = polygon_form_factor(x, n, tri)
        coarse, fine = brute_force_ff(x, n, tri, 6), brute_force_ff(x, n, tri, 7)
        # the midpoint rule converges as h²: its error at `fine` is about |fine − coarse|/3
        assert abs(F - fine) <= 2.0 * abs(fine - coarse) + 1e-7, (straddles, F, fine, coarse)


def test_clipping_keeps_only_the_part_above_the_tangent_plane():
    # a vertical rectangle straddling the horizon of a point with normal +z: only z ≥ 0 counts
    full = np.array([[-0.5, 1.0, -1.0], [0.5, 1.0, -1.0], [0.5, 1.0, 1.0], [-0.5, 1.0, 1.0]])
    upper = full * [1, 1, 0] + [0, 0, 1] * (full[:, 2:] > 0)
    F_full = polygon_form_factor(np.zeros(3), Z, full)
    F_upper = polygon_form_factor(np.zeros(3), Z, upper)
    assert F_full > 0 and F_full == pytest.approx(F_upper, rel=1e-12)
    assert polygon_form_factor(np.zeros(3), -Z, full) == pytest.approx(F_upper, rel=1e-12)  # lower half
    # wholly behind the point
    assert polygon_form_factor(np.zeros(3), Z, UNIT_SQUARE - [0, 0, 1]) == 0.0
    # the triangle path clips the same way
    tris = np.stack([full[[0, 1, 2]], full[[0, 2, 3]]])
    assert form_factor_drjit(np.zeros((2, 3)), np.tile(Z, (2, 1)), tris).sum() == pytest.approx(F_upper, rel=1e-5)


def facing_triangle_pair(rng):
    """Two random triangles, each entirely on the front side of the other."""
    while True:
        ti = rng.uniform(-0.5, 0.5, size=(3, 3)) * [1, 1, 0.2]
        tj = rng.uniform(-0.5, 0.5, size=(3, 3)) * [1, 1, 0.2] + rng.uniform(-0.3, 0.3, size=3) + [0, 0, 1]
        ni = np.cross(ti[1] - ti[0], ti[2] - ti[0])
        nj = np.cross(tj[1] - tj[0], tj[2] - tj[0])
        ni, nj = ni * np.sign(ni[2]) / np.linalg.norm(ni), -nj * np.sign(nj[2]) / np.linalg.norm(nj)
        if ((tj - ti[0]) @ ni).min() > 0.05 and ((ti - tj[0]) @ nj).min() > 0.05:
            return ti, ni, tj, nj


def test_reciprocity():
    rng = np.random.default_rng(RNG_SEED + 1)
    for _ in range(5):
        ti, ni, tj, nj = facing_triangle_pair(rng)
        pi, wi = triangle_quadrature(ti)
        pj, wj = triangle_quadrature(tj)
        AF_ij = (polygon_form_factor(pi, ni, tj) * wi).sum()
        AF_ji = (polygon_form_factor(pj, nj, ti) * wj).sum()
        assert AF_ij == pytest.approx(AF_ji, rel=1e-8)


# ---------------------------------------------------------------------------------------------
# Hard cases: near edges and corners, in the plane, degenerate triangles


def test_limits_at_an_edge_and_a_corner_from_above():
    # a unit square seen (looking down) from height h above an edge midpoint → 1/2, above a corner → 1/4
    for h in (1e-1, 1e-2, 1e-4):
        at_edge = polygon_form_factor(np.array([0.5, 0.0, h]), -Z, UNIT_SQUARE)
        assert at_edge == pytest.approx(2.0 * corner_rectangle_ff(0.5, 1.0, h), rel=1e-9)
        at_corner = polygon_form_factor(np.array([0.0, 0.0, h]), -Z, UNIT_SQUARE)
        assert at_corner == pytest.approx(corner_rectangle_ff(1.0, 1.0, h), rel=1e-9)
    assert polygon_form_factor(np.array([0.5, 0.0, 1e-4]), -Z, UNIT_SQUARE) == pytest.approx(0.5, abs=1e-3)
    assert polygon_form_factor(np.array([0.0, 0.0, 1e-4]), -Z, UNIT_SQUARE) == pytest.approx(0.25, abs=1e-3)


@pytest.mark.parametrize("backend", ["numpy", "drjit"])
def test_finite_and_bounded_at_1e_minus_9_from_edges_and_corners(backend):
    rng = np.random.default_rng(RNG_SEED + 2)
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0.3, 0.8, 0]])
    targets = [tri[0], tri[1], tri[2], 0.5 * (tri[0] + tri[1]), 0.5 * (tri[1] + tri[2])]
    x, n = [], []
    for p in targets:
        for offset in [*random_unit(rng, 6), Z, -Z, [1.0, 0, 0], [0, 0, 0]]:
            for normal in [Z, -Z, [0, 1.0, 0], [1.0, 0, 0], random_unit(rng)]:
                x.append(p + 1e-9 * np.asarray(offset))
                n.append(normal)
    x, n = np.array(x), np.array(n)
    F = polygon_form_factor(x, n, tri) if backend == "numpy" else form_factor_drjit(x, n, tri)
    assert np.all(np.isfinite(F)) and np.all((F >= 0) & (F <= 1))


@pytest.mark.parametrize("backend", ["numpy", "drjit"])
def test_point_in_the_polygons_plane_sees_it_edge_on(backend):
    ff = single_form_factor(backend)
    # a shading point on the triangle itself, or on a coplanar neighbour, with the surface normal
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert ff(np.array([0.2, 0.2, 0.0]), Z, tri) == 0.0  # inside (would be 1 from just above)
    assert ff(np.array([0.5, 0.5, 0.0]), Z, tri) == 0.0  # on the hypotenuse
    assert ff(np.array([2.0, 3.0, 0.0]), Z, tri) == 0.0  # outside
    assert ff(np.array([0.2, 0.2, 0.0]), np.array([0.0, 0.6, 0.8]), tri) == 0.0  # tilted normal
    # the same far from the origin, in float32 for the Dr.Jit path
    offset = np.array([1e3, -2e3, 5e2])
    assert ff(np.array([0.2, 0.2, 0.0]) + offset, Z, tri + offset) == 0.0


@pytest.mark.parametrize("backend", ["numpy", "drjit"])
def test_degenerate_triangles(backend):
    ff = single_form_factor(backend)
    x = np.array([0.1, 0.2, -1.0])
    n = np.array([0.0, 0.0, 1.0])
    assert ff(x, n, np.array([[0.0, 0, 0], [1, 1, 0], [2, 2, 0]])) == 0.0  # collinear
    noisy = ff(x, n, np.array([[0.1, 0.7, 0.3], [0.3, 1.1, 0.9], [0.7, 1.9, 2.1]]))  # collinear, rounded
    assert np.isfinite(noisy) and 0.0 <= noisy <= 1e-6
    assert ff(x, n, np.array([[0.0, 0, 0], [0, 0, 0], [1, 0, 0]])) == 0.0  # repeated vertex
    assert ff(x, n, np.zeros((3, 3))) == 0.0  # a point
    assert ff(np.zeros(3), n, np.zeros((3, 3))) == 0.0  # a point at x
    sliver = ff(x, n, np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 1e-9, 0]]))
    assert np.isfinite(sliver) and 0.0 <= sliver <= 1e-6


def test_drjit_matches_numpy_on_random_configurations():
    rng = np.random.default_rng(RNG_SEED + 3)
    m = 2000
    tris = rng.uniform(-1.0, 1.0, size=(m, 3, 3))
    x = rng.uniform(-1.5, 1.5, size=(m, 3))
    n = random_unit(rng, m)
    F_np = polygon_form_factor(x, n, tris)
    F_dr = form_factor_drjit(x, n, tris)
    assert F_np.shape == (m,)
    assert (F_np > 0).sum() > m // 4  # the test sees many non-trivial lanes
    np.testing.assert_allclose(F_dr, F_np, atol=2e-5)


# ---------------------------------------------------------------------------------------------
# Far-field approximation


def test_point_to_disk_is_exact_on_a_facing_disks_axis():
    # a regular 512-gon of radius 1 approximates the disk to O(1/512²)
    k = 512
    phi = 2.0 * math.pi * np.arange(k) / k
    polygon = np.stack([np.cos(phi), np.sin(phi), np.zeros(k)], axis=1)
    area = 0.5 * k * math.sin(2.0 * math.pi / k)
    for h in (0.01, 0.5, 2.0, 30.0):
        x = np.array([0.0, 0.0, h])
        approx = point_to_disk_approx(x, -Z, np.zeros(3), Z, area)
        assert approx == pytest.approx(area / (math.pi * h * h + area), rel=1e-12)
        assert approx == pytest.approx(polygon_form_factor(x, -Z, polygon), rel=1e-10)


def test_point_to_disk_within_ten_percent_beyond_four_radii():
    # Arikan et al. §7 (after Baum et al.): error < 10 % beyond 4 bounding radii, away from
    # grazing angles (both cosines ≥ 0.3 here); and it falls as (radius / distance)²
    rng = np.random.default_rng(RNG_SEED + 4)
    errors = {4: [], 16: []}
    while len(errors[16]) < 200:
        tri = rng.normal(size=(3, 3))
        tri -= tri.mean(axis=0)
        radius = np.linalg.norm(tri, axis=1).max()
        m = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        area = 0.5 * np.linalg.norm(m)
        m /= 2.0 * area
        u, n = random_unit(rng), random_unit(rng)
        if -n @ u < 0.3 or abs(m @ u) < 0.3:
            continue
        for k in errors:
            exact = polygon_form_factor(k * radius * u, n, tri)
            approx = point_to_disk_approx(k * radius * u, n, np.zeros(3), m, area)
            errors[k].append(abs(approx / exact - 1.0))
    assert max(errors[4]) < 0.1
    assert max(errors[16]) < max(errors[4]) / 4.0 * 1.5


@pytest.mark.parametrize("backend", ["numpy", "drjit"])
def test_point_to_disk_hard_cases(backend):
    x = np.array([[0.0, 0, 0], [0, 0, 1e-9], [0, 0, 1e-9], [1, 2, 3], [0, 0, 1]])
    n = np.array([[0.0, 0, 1], [0, 0, -1], [0, 0, -1], [0, 0, 1], [0, 0, -1]])
    normal = np.array([[0.0, 0, 1], [0, 0, 1], [0, 0, 0.5], [0, 0, 1], [0, 0, 1]])
    area = np.array([1.0, 1.0, 1.0, 0.0, 1e-20])
    if backend == "numpy":
        F = point_to_disk_approx(x, n, np.zeros(3), normal, area)
    else:
        F = np.asarray(point_to_disk_approx(to_point(x), to_vector(n), to_point(np.zeros((5, 3))),
                                            to_vector(normal), mi.Float(area.astype(np.float32))), dtype=np.float64)
    assert np.all(np.isfinite(F)) and np.all((F >= 0) & (F <= 1))
    assert F[0] == 0.0  # x = centre: no direction
    assert F[1] == pytest.approx(1.0, rel=1e-6)  # r → 0 on the axis: the disk fills the hemisphere
    assert F[2] == pytest.approx(0.5, rel=1e-6)  # a cluster normal of length 1/2 halves it
    assert F[3] == 0.0
