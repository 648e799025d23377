"""The block z-test itself: calibrated on synthetic noise, sensitive to a real offset."""
import numpy as np

from mi_twopass.evaluation.statistics import block_z_scores


def test_same_distribution_gives_unit_z():
    rng = np.random.default_rng(3)
    a = rng.exponential(1.0, (8, 64, 64, 3))
    b = rng.exponential(1.0, (8, 64, 64, 3))
    z = block_z_scores(a, b, 8)
    assert z.shape == (8, 8)
    assert 0.5 < np.mean(z**2) < 1.6
    assert np.max(np.abs(z)) < 4.5


def test_offset_is_detected():
    rng = np.random.default_rng(4)
    a = rng.exponential(1.0, (8, 64, 64, 3))
    b = rng.exponential(1.0, (8, 64, 64, 3)) * 1.15
    assert np.mean(block_z_scores(a, b, 8) ** 2) > 4
