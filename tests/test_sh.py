"""Order-2 real SH (mi_twopass.sh) against scipy, quadrature and known projections."""
import math

import numpy as np
import pytest
import scipy.special

import mi_twopass  # noqa: F401  (sets up libLLVM and the variant before mitsuba/drjit)
import mitsuba as mi

from mi_twopass import sh

RNG_SEED = 1234


def random_dirs(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def fibonacci_dirs(n):
    """n well-spread unit directions (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (1.0 + math.sqrt(5.0)) * i
    s = np.sqrt(1.0 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def frame(axis):
    """Orthonormal (t, b, axis)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    t = np.cross(axis, helper)
    t /= np.linalg.norm(t)
    return t, np.cross(axis, t), axis


def sphere_quadrature(axis=(0, 0, 1), n_z=16, n_phi=32):
    """Directions and weights (Σw = 4π) exact for polynomials of degree < 2·n_z in cosθ about
    ``axis`` and trigonometric degree < n_phi in φ. Gauss–Legendre on [-1, 0] and [0, 1]
    separately, so a function with a kink on the great circle ⟂ axis (the clamped cosine about
    ``axis``) is integrated exactly when it is polynomial on each half."""
    x, w = np.polynomial.legendre.leggauss(n_z)
    z = np.concatenate([0.5 * (x - 1.0), 0.5 * (x + 1.0)])
    wz = np.concatenate([0.5 * w, 0.5 * w])
    phi = 2.0 * math.pi * np.arange(n_phi) / n_phi
    Z, PHI = np.meshgrid(z, phi, indexing="ij")
    W = np.outer(wz, np.full(n_phi, 2.0 * math.pi / n_phi))
    s = np.sqrt(1.0 - Z * Z)
    t, b, a = frame(axis)
    d = (s * np.cos(PHI))[..., None] * t + (s * np.sin(PHI))[..., None] * b + Z[..., None] * a
    return d.reshape(-1, 3), W.reshape(-1)


def to_vec(d):
    return mi.Vector3f(*[mi.Float(np.ascontiguousarray(d[:, k], dtype=np.float32)) for k in range(3)])


def to_np(values):
    """A list of mi.Float (or one mi.Float/Color3f) → numpy (n, k)."""
    if isinstance(values, list):
        return np.stack([np.asarray(v, dtype=np.float64) for v in values], axis=-1)
    return np.asarray(values, dtype=np.float64).T


# ---------------------------------------------------------------------------------------------
# Basis


def real_sh_from_scipy(l, m, d):
    """Real SH without Condon–Shortley phase, built from scipy's complex sph_harm_y."""
    theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2.0 * math.pi)
    Y = scipy.special.sph_harm_y(l, abs(m), theta, phi)
    if m > 0:
        return math.sqrt(2.0) * (-1) ** m * Y.real
    if m < 0:
        return math.sqrt(2.0) * (-1) ** m * Y.imag
    return Y.real


def test_basis_matches_scipy():
    d = random_dirs(np.random.default_rng(RNG_SEED), 500)
    Y = sh.sh_basis(d)
    assert Y.shape == (500, 9)
    for k, (l, m) in enumerate(zip(sh.SH_L, sh.SH_M)):
        np.testing.assert_allclose(Y[:, k], real_sh_from_scipy(l, m, d), atol=1e-12, err_msg=f"l={l} m={m}")


def test_basis_is_orthonormal():
    d, w = sphere_quadrature()
    Y = sh.sh_basis(d)
    np.testing.assert_allclose((Y * w[:, None]).T @ Y, np.eye(9), atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Clamped cosine and irradiance


def test_clamped_cosine_coeffs_match_quadrature():
    for n in random_dirs(np.random.default_rng(RNG_SEED + 1), 5):
        d, w = sphere_quadrature(axis=n)
        exact = (sh.sh_basis(d) * (w * np.maximum(d @ n, 0.0))[:, None]).sum(axis=0)
        np.testing.assert_allclose(sh.clamped_cosine_coeffs(n), exact, atol=1e-12)


def test_irradiance_of_uniform_sky_is_pi_L():
    L = np.array([0.5, 1.0, 2.0])
    coeffs = np.zeros((9, 3))
    coeffs[0] = math.sqrt(4.0 * math.pi) * L  # ∫ L·Y_00 dω
    normals = random_dirs(np.random.default_rng(RNG_SEED + 2), 100)
    np.testing.assert_allclose(sh.irradiance(coeffs, normals), np.broadcast_to(math.pi * L, (100, 3)), rtol=1e-12)
    E_dr = sh.irradiance([mi.Color3f(*map(float, c)) for c in coeffs], to_vec(normals))
    np.testing.assert_allclose(to_np(E_dr), np.broadcast_to(math.pi * L, (100, 3)), rtol=1e-6)


def test_irradiance_matches_quadrature_for_order2_radiance():
    rng = np.random.default_rng(RNG_SEED + 3)
    S = rng.normal(size=(9, 3))
    for n in random_dirs(rng, 5):
        d, w = sphere_quadrature(axis=n)
        L = sh.evaluate(S, d)
        exact = ((w * np.maximum(d @ n, 0.0))[:, None] * L).sum(axis=0)
        np.testing.assert_allclose(sh.irradiance(S, n), exact, atol=1e-12)


def test_irradiance_broadcasts_per_point_coefficients():
    rng = np.random.default_rng(RNG_SEED + 4)
    S = rng.normal(size=(7, 9, 3))
    n = random_dirs(rng, 7)
    E = sh.irradiance(S, n)
    assert E.shape == (7, 3)
    for i in range(7):
        np.testing.assert_allclose(E[i], sh.irradiance(S[i], n[i]), rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Least-squares projection


@pytest.mark.parametrize("n_dirs", [9, 50, 400])
def test_least_squares_reproduces_order2_functions(n_dirs):
    rng = np.random.default_rng(RNG_SEED + n_dirs)
    dirs = fibonacci_dirs(n_dirs) if n_dirs < 400 else random_dirs(rng, n_dirs)
    S = rng.normal(size=(9, 3))
    np.testing.assert_allclose(sh.project_least_squares(dirs, sh.evaluate(S, dirs), reg=0.0), S, atol=1e-5)
    constant = np.zeros(9)
    constant[0] = 2.5 * math.sqrt(4.0 * math.pi)
    np.testing.assert_allclose(sh.project_least_squares(dirs, np.full(n_dirs, 2.5), reg=0.0), constant, atol=1e-5)


def test_least_squares_of_clamped_cosine_with_quadrature_weights():
    # The clamped cosine is not band-limited; weighting the samples by an exact quadrature rule
    # makes the (unregularised) least-squares fit the orthogonal projection R&H eq. 8.
    for n in random_dirs(np.random.default_rng(RNG_SEED + 5), 3):
        d, w = sphere_quadrature(axis=n)
        fit = sh.project_least_squares(d, np.maximum(d @ n, 0.0), weights=w, reg=0.0)
        np.testing.assert_allclose(fit, sh.clamped_cosine_coeffs(n), atol=1e-5)


def test_least_squares_solves_the_documented_normal_equations():
    rng = np.random.default_rng(RNG_SEED + 6)
    dirs = random_dirs(rng, 40)
    R = rng.uniform(0, 3, size=(40, 3))
    w = rng.uniform(0.1, 2.0, size=40)
    reg = 0.3
    S = sh.project_least_squares(dirs, R, weights=w, reg=reg)
    C = sh.sh_basis(dirs)
    w_hat = w * len(w) / w.sum()
    lhs = (C * w_hat[:, None]).T @ C + reg * np.diag(sh.KAPPA)
    np.testing.assert_allclose(lhs @ S, (C * w_hat[:, None]).T @ R, rtol=1e-9, atol=1e-9)


def test_least_squares_default_reg_shrinks_as_documented():
    # With n well-spread samples band l is shrunk by ≈ 1/(1 + 4π·reg·κ_l/n).
    n_dirs = 4000
    dirs = fibonacci_dirs(n_dirs)
    S = np.random.default_rng(RNG_SEED + 7).normal(size=9)
    fit = sh.project_least_squares(dirs, sh.evaluate(S[:, None], dirs)[:, 0])
    predicted = S / (1.0 + 4.0 * math.pi * sh.DEFAULT_REG * np.asarray(sh.KAPPA) / n_dirs)
    # the Fibonacci Gram matrix differs from (n/4π)·I by O(1/n)
    np.testing.assert_allclose(fit, predicted, atol=10.0 / n_dirs * np.abs(S).max())


def test_least_squares_with_no_samples_is_zero():
    assert np.array_equal(sh.project_least_squares(np.zeros((0, 3)), np.zeros((0, 3))), np.zeros((9, 3)))
    assert np.array_equal(sh.project_least_squares(np.zeros((0, 3)), np.zeros(0)), np.zeros(9))


def single_direction_tolerance():
    """How far from the constant R a fit to samples R from (nearly) one direction D may be.

    The penalised fit to one direction is S ∝ Λ⁻¹ C(D): band l carries a weight proportional to
    (2l+1)/κ_l, so the fit is R·(1 − ε)·[P_0 + δ_1 P_1(ω·D) + δ_2 P_2(ω·D)]/(1 + δ_1 + δ_2) with
    δ_l = κ_0 (2l+1)/κ_l and shrinkage ε = 1/(1 + q), q = n Σ_l (2l+1)/(4π reg κ_l) ≥ that of
    n = 1; |P_l − 1| ≤ 2 bounds the relative deviation.
    """
    delta = sum(sh.KAPPA[0] * (2 * l + 1) / sh.KAPPA[l * l] for l in (1, 2))
    q = sum((2 * l + 1) / (4.0 * math.pi * sh.DEFAULT_REG * sh.KAPPA[l * l]) for l in (0, 1, 2))
    return 2.0 * delta / (1.0 + delta) + 1.0 / (1.0 + q)


def test_least_squares_with_one_sample_is_nearly_constant_and_bounded():
    d_eval = fibonacci_dirs(2000)
    for R in (1.0, -3.0, 1e4):
        S = sh.project_least_squares(np.array([[0.0, 0.6, 0.8]]), np.array([R]))
        f = sh.evaluate(S[:, None], d_eval)[:, 0]
        assert np.all(np.isfinite(S))
        assert np.all(np.abs(f) <= abs(R))  # proven bound, see project_least_squares
        np.testing.assert_allclose(f, R, rtol=single_direction_tolerance())


def test_least_squares_with_three_samples_is_finite_and_bounded():
    d_eval = fibonacci_dirs(2000)
    # three nearly identical directions: the unregularised system is singular
    dirs = np.array([[0.0, 0.0, 1.0], [1e-4, 0.0, 1.0], [0.0, 1e-4, 1.0]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    # consistent data: the fit is the constant
    f = sh.evaluate(sh.project_least_squares(dirs, np.full(3, 2.0))[:, None], d_eval)[:, 0]
    np.testing.assert_allclose(f, 2.0, rtol=single_direction_tolerance())
    # contradictory data: finite, and J(S) ≤ J(0) bounds each coefficient
    R = np.array([0.0, 1.0, 100.0])
    S = sh.project_least_squares(dirs, R)
    assert np.all(np.isfinite(S))
    assert np.all(np.abs(S) <= np.sqrt((R**2).sum() / (sh.DEFAULT_REG * np.asarray(sh.KAPPA))))
    assert np.all(np.abs(sh.evaluate(S[:, None], d_eval)) <= np.abs(R).max())


# ---------------------------------------------------------------------------------------------
# Monte Carlo projection


def assert_within_standard_error(samples, estimate, exact, n_sigma=5.0):
    """``samples`` (n, k): per-sample contributions whose mean is ``estimate``."""
    stderr = samples.std(axis=0, ddof=1) / math.sqrt(len(samples))
    assert np.all(np.abs(estimate - exact) <= n_sigma * stderr + 1e-12), (estimate - exact) / (stderr + 1e-300)


def test_monte_carlo_projection_of_order2_function():
    rng = np.random.default_rng(RNG_SEED + 8)
    S = rng.normal(size=9)
    dirs = random_dirs(rng, 20000)
    pdf = np.full(len(dirs), 1.0 / (4.0 * math.pi))
    values = sh.evaluate(S[:, None], dirs)[:, 0]
    est = sh.project_monte_carlo(dirs, values, pdf)
    assert_within_standard_error(sh.sh_basis(dirs) * (values / pdf)[:, None], est, S)


def test_monte_carlo_projection_of_clamped_cosine():
    rng = np.random.default_rng(RNG_SEED + 9)
    n = random_dirs(rng, 1)[0]
    t, b, a = frame(n)
    u1, u2 = rng.uniform(size=(2, 20000))  # cosine-weighted hemisphere about n
    r, phi = np.sqrt(u1), 2.0 * math.pi * u2
    cos = np.sqrt(1.0 - u1)
    dirs = (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * b + cos[:, None] * a
    pdf = cos / math.pi
    values = np.maximum(dirs @ n, 0.0)
    est = sh.project_monte_carlo(dirs, values, pdf)
    assert_within_standard_error(sh.sh_basis(dirs) * (values / pdf)[:, None], est, sh.clamped_cosine_coeffs(n))


def test_monte_carlo_ignores_zero_pdf_samples():
    dirs = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    est = sh.project_monte_carlo(dirs, np.array([[1.0], [5.0]]), np.array([0.25, 0.0]))
    np.testing.assert_allclose(est[:, 0], sh.sh_basis(dirs[0]) * 1.0 / 0.25 / 2)
    assert np.array_equal(sh.project_monte_carlo(np.zeros((0, 3)), np.zeros(0), np.zeros(0)), np.zeros(9))


# ---------------------------------------------------------------------------------------------
# Dr.Jit and numpy agree


def test_drjit_matches_numpy():
    rng = np.random.default_rng(RNG_SEED + 10)
    d = random_dirs(rng, 256)
    S = rng.normal(size=(9, 3))
    dv = to_vec(d)
    np.testing.assert_allclose(to_np(sh.sh_basis(dv)), sh.sh_basis(d), atol=1e-6)
    np.testing.assert_allclose(to_np(sh.clamped_cosine_coeffs(dv)), sh.clamped_cosine_coeffs(d), atol=1e-5)
    S_dr = [mi.Color3f(*map(float, c)) for c in S]
    np.testing.assert_allclose(to_np(sh.irradiance(S_dr, dv)), sh.irradiance(S, d), atol=1e-5)
    np.testing.assert_allclose(to_np(sh.evaluate(S_dr, dv)), sh.evaluate(S, d), atol=1e-5)
    # per-lane coefficients (as gathered from a cache) and single-channel mi.Float
    S_lane = [mi.Float(np.full(256, c, dtype=np.float32)) for c in S[:, 0]]
    np.testing.assert_allclose(np.asarray(sh.irradiance(S_lane, dv)), sh.irradiance(S[:, :1], d)[:, 0], atol=1e-5)


@pytest.mark.parametrize("reg", [1e-2, 0.0])
def test_grouped_least_squares_matches_one_fit_per_group(reg):
    rng = np.random.default_rng(7)
    n, K = 600, 7
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    vals = rng.uniform(0, 2, size=(n, 3))
    group = rng.integers(0, K - 1, n)  # group K - 1 stays empty
    group[:3] = 2  # and group 2 is not special: just more samples
    S = sh.project_least_squares_groups(d, vals, group, K, reg=reg)
    assert S.shape == (K, sh.SH_COUNT, 3)
    for k in range(K - 1):
        ref = sh.project_least_squares(d[group == k], vals[group == k], reg=reg)
        np.testing.assert_allclose(S[k], ref, rtol=1e-8, atol=1e-10)
    assert np.all(S[K - 1] == 0.0)
