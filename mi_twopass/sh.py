r"""Order-2 real spherical harmonics (9 coefficients per colour channel).

The far field of the radiance cache (Arikan, Forsyth & O'Brien 2005, §4) stores the incident
radiance :math:`L_F(P, \omega)` as 9 SH coefficients per channel, fits them to traced radiance
samples by least squares (§4.1, eq. 4) and turns them into the far-field brightness
:math:`B_D = \overline{\max(N\cdot\omega, 0)} \cdot \overline{L_F}` (eq. 3) with the analytic
clamped-cosine coefficients of Ramamoorthi & Hanrahan 2001 ("An Efficient Representation for
Irradiance Environment Maps", eq. 7-8, 12).

Convention (the same for the Dr.Jit and the numpy code, which share one formula)
-------------------------------------------------------------------------------
* **Real, orthonormal** on the unit sphere: :math:`\int_{S^2} Y_i Y_j\,d\omega = \delta_{ij}`.
* **No Condon-Shortley phase**: every basis function is a polynomial in the *world* coordinates
  (x, y, z) of the unit direction with a positive constant, exactly the table of Ramamoorthi &
  Hanrahan 2001 (eq. 3):

  ====  =========  ==========================================
  k     (l, m)     :math:`Y_k(x, y, z)`
  ====  =========  ==========================================
  0     (0,  0)    0.282095                 = ½·√(1/π)
  1     (1, -1)    0.488603 · y             = √(3/4π) · y
  2     (1,  0)    0.488603 · z
  3     (1,  1)    0.488603 · x
  4     (2, -2)    1.092548 · xy            = ½·√(15/π) · xy
  5     (2, -1)    1.092548 · yz
  6     (2,  0)    0.315392 · (3z² − 1)     = ¼·√(5/π) · (3z² − 1)
  7     (2,  1)    1.092548 · xz
  8     (2,  2)    0.546274 · (x² − y²)     = ¼·√(15/π) · (x² − y²)
  ====  =========  ==========================================

  In terms of SciPy's complex harmonics :math:`Y_l^m` (polar angle θ from +z, azimuth φ from +x,
  Condon-Shortley phase included): :math:`Y_{l,m} = \sqrt2 (-1)^m \operatorname{Re} Y_l^m` for
  m > 0, :math:`Y_{l,0} = Y_l^0`, :math:`Y_{l,m} = \sqrt2 (-1)^m \operatorname{Im} Y_l^{|m|}`
  for m < 0 (tests/test_sh.py checks this against ``scipy.special.sph_harm_y``).
* Directions must be **unit** vectors (the basis is not renormalised; Y_20 uses 3z² − 1).
* Coefficients are stored **coefficient-major**: numpy arrays of shape ``(..., 9, C)`` (C
  channels, 3 for RGB); on the Dr.Jit side a list of 9 per-lane values (``mi.Float`` or
  ``mi.Color3f``).
* The coefficients of a radiance function L are :math:`L_{lm} = \int L(\omega) Y_{lm}(\omega)
  d\omega` (radiance × steradian), so a uniform sky of radiance L has :math:`L_{00} =
  \sqrt{4\pi}\,L` and irradiance :math:`E = \pi L` for every normal.

Every public function takes either Dr.Jit arrays (``mi.Vector3f`` directions, variant-agnostic:
``llvm_ad_rgb`` or ``cuda_ad_rgb``) or numpy arrays (``(..., 3)`` directions, float64) and returns
the same kind; the fitting routines (:func:`project_least_squares`, :func:`project_monte_carlo`)
are numpy only, since a cluster holds at most a few hundred samples.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

#: number of coefficients of an order-2 (bands l = 0, 1, 2) expansion
SH_COUNT = 9
#: band l and order m of coefficient k (Ramamoorthi & Hanrahan ordering)
SH_L = (0, 1, 1, 1, 2, 2, 2, 2, 2)
SH_M = (0, -1, 0, 1, -2, -1, 0, 1, 2)

# Normalisation constants of the table in the module docstring.
_C00 = 0.5 * math.sqrt(1.0 / math.pi)  # 0.282095
_C1 = math.sqrt(3.0 / (4.0 * math.pi))  # 0.488603
_C2 = 0.5 * math.sqrt(15.0 / math.pi)  # 1.092548  (xy, yz, xz)
_C20 = 0.25 * math.sqrt(5.0 / math.pi)  # 0.315392  (3z² − 1)
_C22 = 0.25 * math.sqrt(15.0 / math.pi)  # 0.546274  (x² − y²)

#: Â_l, the zonal clamped-cosine factors of Ramamoorthi & Hanrahan eq. 8: π, 2π/3, π/4
A_HAT_BAND = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)
#: Â_l repeated per coefficient k
A_HAT = tuple(A_HAT_BAND[l] for l in SH_L)

#: default Tikhonov weight of :func:`project_least_squares`
DEFAULT_REG = 1e-2
#: penalty of band 0 relative to the Laplacian weights l(l+1) (keeps the system definite)
BAND0_PENALTY = 1e-3
#: κ_k = l(l+1) + BAND0_PENALTY, the per-coefficient penalty of :func:`project_least_squares`
KAPPA = tuple(l * (l + 1) + BAND0_PENALTY for l in SH_L)


def _is_drjit(v) -> bool:
    return dr.is_array_v(v)


def _basis_xyz(x, y, z):
    """The 9 basis functions of the module table; works on numpy arrays and Dr.Jit Floats."""
    return [
        _C00 + 0.0 * x,  # same type and shape as the inputs
        _C1 * y,
        _C1 * z,
        _C1 * x,
        _C2 * x * y,
        _C2 * y * z,
        _C20 * (3.0 * z * z - 1.0),
        _C2 * x * z,
        _C22 * (x * x - y * y),
    ]


def sh_basis(d):
    """Y_k(d), k = 0..8, at unit directions ``d`` (R&H 2001 eq. 3; see the module table).

    ``d``: ``mi.Vector3f`` → list of 9 ``mi.Float``; or numpy ``(..., 3)`` → ``(..., 9)``.
    """
    if _is_drjit(d):
        return _basis_xyz(d.x, d.y, d.z)
    d = np.asarray(d, dtype=np.float64)
    return np.stack(_basis_xyz(d[..., 0], d[..., 1], d[..., 2]), axis=-1)


def clamped_cosine_coeffs(n):
    r"""SH coefficients of the clamped cosine :math:`\max(0, n\cdot\omega)` about unit normal n.

    The clamped cosine is zonal about n, so by the rotation formula (R&H 2001 eq. 7-8) its
    coefficients are :math:`c_{lm}(n) = \hat A_l\, Y_{lm}(n)`, with :math:`\hat A_0 = \pi`,
    :math:`\hat A_1 = 2\pi/3`, :math:`\hat A_2 = \pi/4`. These are the exact l ≤ 2 coefficients;
    the function itself also has bands l = 4, 6, ... which are orthogonal to an order-2 radiance
    and so do not change :func:`irradiance`.

    ``n``: ``mi.Vector3f`` → list of 9 ``mi.Float``; numpy ``(..., 3)`` → ``(..., 9)``.
    """
    Y = sh_basis(n)
    if isinstance(Y, list):
        return [a * y for a, y in zip(A_HAT, Y)]
    return Y * np.asarray(A_HAT)


def irradiance(coeffs, n):
    r"""Irradiance :math:`E(n) = \sum_{lm} \hat A_l L_{lm} Y_{lm}(n)` (R&H 2001 eq. 7).

    This is the paper's far-field term :math:`B_D = \overline{\max(N\cdot\omega,0)} \cdot
    \overline{L_F}` (Arikan et al. §4, eq. 3): exact for radiance band-limited to l ≤ 2. For a
    radiance with strong higher bands truncated to order 2 it can dip slightly below zero in the
    directions facing away from the light (ringing); clamp at the caller if a negative value hurts.

    * Dr.Jit: ``coeffs`` a sequence of 9 per-lane (or uniform) values, e.g. ``mi.Color3f`` or
      ``mi.Float``; ``n`` a ``mi.Vector3f`` → same type as ``coeffs[k] * mi.Float``.
    * numpy: ``coeffs`` ``(..., 9, C)``, ``n`` ``(..., 3)``, broadcast over the leading axes
      → ``(..., C)``.
    """
    c = clamped_cosine_coeffs(n)
    if isinstance(c, list):
        if len(coeffs) != SH_COUNT:
            raise ValueError(f"irradiance: expected {SH_COUNT} coefficients, got {len(coeffs)}")
        E = c[0] * coeffs[0]
        for k in range(1, SH_COUNT):
            E = dr.fma(c[k], coeffs[k], E)
        return E
    coeffs = np.asarray(coeffs, dtype=np.float64)
    if coeffs.ndim < 2 or coeffs.shape[-2] != SH_COUNT:
        raise ValueError(f"irradiance: coeffs must have shape (..., 9, C), got {coeffs.shape}")
    return (c[..., None, :] @ coeffs)[..., 0, :]


def evaluate(coeffs, d):
    """The order-2 function Σ_k S_k Y_k(d) (numpy: coeffs ``(..., 9, C)``, d ``(..., 3)``)."""
    Y = sh_basis(d)
    if isinstance(Y, list):
        f = Y[0] * coeffs[0]
        for k in range(1, SH_COUNT):
            f = dr.fma(Y[k], coeffs[k], f)
        return f
    return (Y[..., None, :] @ np.asarray(coeffs, dtype=np.float64))[..., 0, :]


def _as_samples(dirs, values):
    dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    values = np.asarray(values, dtype=np.float64)
    if values.shape[:1] != (len(dirs),) or values.ndim > 2:
        raise ValueError(f"expected values of shape (n,) or (n, C) for n = {len(dirs)} directions, "
                         f"got {values.shape}")
    scalar = values.ndim == 1
    return dirs, (values[:, None] if scalar else values), scalar


def project_least_squares(dirs, values, weights=None, reg=DEFAULT_REG):
    r"""Regularised least-squares SH fit to radiance samples (Arikan et al. §4.1, eq. 4).

    Solves, per channel, the Tikhonov-regularised version of :math:`C(D_i) S = R_i`:

    .. math::

        S = \arg\min_S \sum_{i=1}^n \hat w_i \,(C(D_i)\cdot S - R_i)^2
            + \mathrm{reg} \sum_{k=0}^{8} \kappa_k S_k^2,
        \qquad \kappa_k = l_k(l_k+1) + 10^{-3},
        \qquad \hat w_i = \frac{n\, w_i}{\sum_j w_j},

    i.e. :math:`(C^T \hat W C + \mathrm{reg}\,\mathrm{diag}\,\kappa)\, S = C^T \hat W R`, solved as
    an augmented least-squares system. :math:`\sum_k l(l+1) S_k^2` is the Dirichlet energy
    :math:`\int |\nabla f|^2` of the fitted function, so the penalty costs nothing for a constant
    and grows with the band: with few or clustered samples the fit shrinks toward low orders
    (one sample of value R gives nearly the constant R, and :math:`|f(\omega)| < |R|`
    everywhere); zero samples give zero. The small band-0 term keeps the system definite.

    With n well-spread samples, :math:`C^T C \approx (n/4\pi) I`, so band l is shrunk by about
    :math:`1/(1 + 4\pi\,\mathrm{reg}\,\kappa_l / n)`: with the default reg = 1e-2, 0.75 % for
    band 2 at n = 100, 8 % at n = 9. ``reg=0`` gives the plain (minimum-norm) least-squares fit
    of the paper, exact for an order-2 function sampled at ≥ 9 well-spread directions.

    Parameters
    ----------
    dirs: ``(n, 3)`` unit directions :math:`D_i` (world frame).
    values: ``(n,)`` or ``(n, C)`` radiance :math:`R_i`.
    weights: optional ``(n,)`` non-negative weights :math:`w_i` (e.g. 1/pdf to make the data term
        a quadrature of :math:`\int (f - L)^2 d\omega` when directions are not uniform); only
        their ratios matter.
    reg: Tikhonov weight (≥ 0).

    Returns ``(9,)`` for 1-D ``values``, else ``(9, C)``.
    """
    if not (reg >= 0 and math.isfinite(reg)):
        raise ValueError(f"reg={reg}: must be finite and >= 0")
    dirs, values, scalar = _as_samples(dirs, values)
    n, C = values.shape
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(n)
    if np.any(w < 0):
        raise ValueError("project_least_squares: weights must be non-negative")
    S = np.zeros((SH_COUNT, C))
    w_sum = w.sum()
    if n > 0 and w_sum > 0:
        sqrt_w = np.sqrt(w * (n / w_sum))[:, None]
        A = np.concatenate([sqrt_w * sh_basis(dirs), np.diag(np.sqrt(reg * np.asarray(KAPPA)))])
        b = np.concatenate([sqrt_w * values, np.zeros((SH_COUNT, C))])
        S = np.linalg.lstsq(A, b, rcond=None)[0]
    return S[:, 0] if scalar else S


def project_least_squares_groups(dirs, values, group, n_groups, reg=DEFAULT_REG):
    r""":func:`project_least_squares` (unit weights) of many groups of samples at once: sample i
    belongs to group ``group[i]`` ∈ [0, ``n_groups``). Each group's regularised normal equations
    :math:`(C^T C + \mathrm{reg}\,\mathrm{diag}\,\kappa)\, S = C^T R` are formed from
    the samples sorted by group and solved as one batch of 9 × 9 systems; with reg > 0 they are definite, so the
    result is the same fit (a group with no samples gets zero). ``reg = 0`` (minimum-norm fits of
    possibly singular systems) falls back to one :func:`project_least_squares` per group.

    ``dirs`` ``(n, 3)``, ``values`` ``(n, C)``, ``group`` ``(n,)`` ints → ``(n_groups, 9, C)``."""
    if not (reg >= 0 and math.isfinite(reg)):
        raise ValueError(f"reg={reg}: must be finite and >= 0")
    dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    values = np.asarray(values, dtype=np.float64).reshape(len(dirs), -1)
    group = np.asarray(group, dtype=np.int64).reshape(len(dirs))
    K, C = int(n_groups), values.shape[1]
    if reg == 0:
        return np.stack([project_least_squares(dirs[group == k], values[group == k], reg=0.0)
                         .reshape(SH_COUNT, C) for k in range(K)]) if K else \
            np.zeros((0, SH_COUNT, C))
    Y = sh_basis(dirs) if len(dirs) else np.zeros((0, SH_COUNT))
    # per-group normal equations from contiguous slices of the samples sorted by group
    order = np.argsort(group, kind="stable")
    Y, values, group = Y[order], values[order], group[order]
    bounds = np.searchsorted(group, np.arange(K + 1))
    A = np.zeros((K, SH_COUNT, SH_COUNT))
    b = np.zeros((K, SH_COUNT, C))
    for k in np.nonzero(np.diff(bounds))[0]:
        Yk = Y[bounds[k]:bounds[k + 1]]
        A[k] = Yk.T @ Yk
        b[k] = Yk.T @ values[bounds[k]:bounds[k + 1]]
    A = A + reg * np.diag(np.asarray(KAPPA, dtype=np.float64))
    return np.linalg.solve(A, b)


def project_monte_carlo(dirs, values, pdf):
    r"""Unbiased Monte Carlo projection :math:`S_k = \frac1n \sum_i R_i\,Y_k(D_i) / p(D_i)`.

    ``pdf`` is the solid-angle density the directions were drawn from (``(n,)``); samples with
    pdf = 0 contribute nothing (they cannot have been drawn). The estimate is unbiased for the
    part of the sphere where p > 0 (a hemisphere sampler only sees that hemisphere). Shapes as in
    :func:`project_least_squares`; zero samples give zero.
    """
    dirs, values, scalar = _as_samples(dirs, values)
    n, C = values.shape
    pdf = np.asarray(pdf, dtype=np.float64).reshape(n)
    S = np.zeros((SH_COUNT, C))
    if n > 0:
        inv_pdf = np.where(pdf > 0, 1.0 / np.where(pdf > 0, pdf, 1.0), 0.0)
        S = sh_basis(dirs).T @ (values * inv_pdf[:, None]) / n
    return S[:, 0] if scalar else S
