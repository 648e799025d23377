"""Image error metrics: MSE, relMSE (ε = 0.01) and FLIP (package ``flip-evaluator``).

All take linear-radiance images as arrays of shape (H, W, C) (numpy or anything ``np.asarray``
accepts, Mitsuba tensors included).
"""
import numpy as np

#: ε of relMSE: keeps dark pixels from dominating (docs/design.md "Measuring speed against error").
RELMSE_EPS = 0.01
#: the bias bound of ``check`` (and of twopass's choices): relMSE of BLOCK × BLOCK-pixel block
#: means at most BLOCK_RELMSE_MAX (:mod:`mi_twopass.evaluation.check`)
BLOCK = 8
BLOCK_RELMSE_MAX = 3e-3


def _pair(x, ref):
    x = np.asarray(x, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if x.shape != ref.shape:
        raise ValueError(f"image shape {x.shape} differs from reference shape {ref.shape}")
    return x, ref


def mse(x, ref) -> float:
    """mean((x − ref)²) over pixels and channels."""
    x, ref = _pair(x, ref)
    return float(np.mean((x - ref) ** 2))


def relmse(x, ref, eps: float = RELMSE_EPS) -> float:
    """Relative MSE: mean((x − ref)² / (ref² + ε)) over pixels and channels."""
    x, ref = _pair(x, ref)
    return float(np.mean((x - ref) ** 2 / (ref**2 + eps)))


def flip(x, ref) -> float:
    """Mean HDR-FLIP error of ``x`` against ``ref`` (NVIDIA's ꟻLIP, ``flip_evaluator``).

    Negative and non-finite values are clamped to 0 first (FLIP expects non-negative HDR input).
    """
    import flip_evaluator

    x, ref = _pair(x, ref)
    if x.ndim == 2:
        x, ref = x[..., None], ref[..., None]
    if x.shape[-1] == 1:
        x, ref = np.repeat(x, 3, -1), np.repeat(ref, 3, -1)
    x = np.nan_to_num(np.maximum(x[..., :3], 0), nan=0.0, posinf=0.0).astype(np.float32)
    ref = np.nan_to_num(np.maximum(ref[..., :3], 0), nan=0.0, posinf=0.0).astype(np.float32)
    _, mean_error, _ = flip_evaluator.evaluate(ref, x, "HDR", applyMagma=False)
    return float(mean_error)


def all_metrics(x, ref) -> dict:
    return {"mse": mse(x, ref), "relmse": relmse(x, ref), "flip": flip(x, ref)}
