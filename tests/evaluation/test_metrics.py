"""Metrics on known inputs (mi_twopass/evaluation/metrics.py)."""
import numpy as np
import pytest

from mi_twopass.evaluation import metrics


@pytest.fixture
def ref():
    rng = np.random.default_rng(1)
    return rng.uniform(0.0, 2.0, size=(12, 10, 3))


def test_identical_images_give_zero(ref):
    assert metrics.mse(ref, ref) == 0.0
    assert metrics.relmse(ref, ref) == 0.0
    assert metrics.flip(ref, ref) == 0.0


def test_constant_offset_closed_form(ref):
    c = 0.1
    assert metrics.mse(ref + c, ref) == pytest.approx(c * c, rel=1e-12)
    expected = np.mean(c * c / (ref**2 + metrics.RELMSE_EPS))
    assert metrics.relmse(ref + c, ref) == pytest.approx(expected, rel=1e-12)


def test_relmse_on_constant_reference():
    ref = np.full((4, 4, 3), 1.0)
    # (0.5)^2 / (1 + 0.01)
    assert metrics.relmse(ref * 1.5, ref) == pytest.approx(0.25 / 1.01, rel=1e-12)
    # zero reference: ε alone in the denominator
    assert metrics.relmse(np.full((2, 2, 3), 0.1), np.zeros((2, 2, 3))) == pytest.approx(1.0)


def test_flip_grows_with_error(ref):
    small = metrics.flip(ref * 1.02, ref)
    large = metrics.flip(ref * 1.5, ref)
    assert 0.0 < small < large <= 1.0


def test_flip_tolerates_nan_and_negative(ref):
    x = ref.copy()
    x[0, 0] = np.nan
    x[1, 1] = -1.0
    assert np.isfinite(metrics.flip(x, ref))


def test_shape_mismatch_is_an_error(ref):
    with pytest.raises(ValueError, match="shape"):
        metrics.relmse(ref[:5], ref)
