"""Statistical comparison of two Monte Carlo renderers (rendering regression tests).

Each renderer produces K independent images (different seeds). For every B×B block of pixels the
K block means give a mean and a standard error; the z-score of the difference between the two
renderers, z = (m_a − m_b) / sqrt(se_a² + se_b²), is ~N(0, 1) per block when both converge to
the same image. A test then bounds max |z| (Bonferroni over blocks) and the mean of z².
"""
import numpy as np


def block_means(images, block: int) -> np.ndarray:
    """(K, H, W, C) images → (K, H/B, W/B) luminance-free channel-mean block means."""
    x = np.asarray(images, dtype=np.float64)
    k, h, w = x.shape[:3]
    x = x.reshape(k, h, w, -1).mean(axis=-1)
    hb, wb = h // block, w // block
    x = x[:, : hb * block, : wb * block].reshape(k, hb, block, wb, block)
    return x.mean(axis=(2, 4))


def block_z_scores(images_a, images_b, block: int = 8) -> np.ndarray:
    """z-scores of the per-block mean difference between two sets of independent renders."""
    a, b = block_means(images_a, block), block_means(images_b, block)
    ma, mb = a.mean(0), b.mean(0)
    va = a.var(0, ddof=1) / a.shape[0]
    vb = b.var(0, ddof=1) / b.shape[0]
    se = np.sqrt(va + vb)
    return np.where(se > 0, (ma - mb) / np.where(se > 0, se, 1.0), 0.0)
