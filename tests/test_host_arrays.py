"""Moving Dr.Jit vectors to numpy (mi_twopass/host_arrays.py) compiles no kernel per array
size (``np.array`` of a nested array did: its size is a literal of the interleaving kernel)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_twopass  # noqa: F401  (libLLVM, variant)
from mi_twopass.host_arrays import columns


@pytest.fixture
def kernel_history():
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()

    def compiled():
        """Kernels compiled (not found in a cache) since the last call."""
        h = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]
        return sum(1 for k in h if not k.get("cache_hit"))

    yield compiled
    dr.set_flag(dr.JitFlag.KernelHistory, False)


def test_columns_gives_rows_of_components():
    x = dr.arange(mi.Float, 5)
    a = columns(mi.Point3f(x, 2 * x, x + 0.5))
    assert a.shape == (5, 3) and a.dtype == np.float64
    np.testing.assert_array_equal(a[:, 1], 2 * np.arange(5))
    np.testing.assert_array_equal(columns(mi.Color3f(1, 2, 3)), [[1, 2, 3]])


def test_columns_compiles_no_kernel_per_size(kernel_history):
    salt = float(np.random.default_rng().integers(1 << 20))  # a kernel no earlier run cached
    for n in (1000, 1001, 1002):
        x = dr.arange(mi.Float, n) + mi.Float(salt)  # the salt is a literal of the kernel
        columns(mi.Point3f(x, 2 * x, dr.sin(x)))
        if n == 1000:
            kernel_history()  # the first size compiles
        else:
            assert kernel_history() == 0, n


def test_vectors_is_the_inverse_of_columns():
    from mi_twopass.host_arrays import vectors

    a = np.arange(12, dtype=np.float64).reshape(4, 3) * 0.5
    v = vectors(a, mi.Vector3f)
    assert isinstance(v, mi.Vector3f) and dr.width(v) == 4
    np.testing.assert_array_equal(columns(v), a)
    np.testing.assert_array_equal(columns(vectors(a.T.copy().T, mi.Point3f)), a)  # strided in
