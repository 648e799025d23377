"""Moving Dr.Jit vectors to numpy (mi_twopass/host_arrays.py) compiles no kernel per array
size (``np.array`` of a nested array did: its size is a literal of the interleaving kernel),
and numpy arrays handed to Dr.Jit compile no kernel per memory alignment (a mapped array that
is not 64-byte aligned made Dr.Jit compile another kernel)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_twopass  # noqa: F401  (libLLVM, variant)
from mi_twopass.host_arrays import ALIGNMENT, aligned, columns, jit


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


def _unaligned(n, dtype=np.float32):
    """A numpy array of ``n`` values 0, 1, … whose data do not start on an ALIGNMENT boundary."""
    itemsize = np.dtype(dtype).itemsize
    buf = np.empty((n + ALIGNMENT) * itemsize, np.uint8)
    start = -buf.ctypes.data % ALIGNMENT + itemsize  # one element past a boundary
    a = buf[start:start + n * itemsize].view(dtype)
    a[:] = np.arange(n)
    assert a.ctypes.data % ALIGNMENT != 0
    return a


def test_aligned_copies_only_what_is_not_aligned():
    a = _unaligned(1000)
    b = aligned(a)
    assert b.ctypes.data % ALIGNMENT == 0 and b.flags.c_contiguous
    np.testing.assert_array_equal(a, b)
    assert aligned(b) is b
    c = aligned(np.arange(12, dtype=np.float64).reshape(3, 4)[:, 1])  # strided: copied
    assert c.flags.c_contiguous and c.ctypes.data % ALIGNMENT == 0
    np.testing.assert_array_equal(c, [1, 5, 9])


def test_jit_passes_other_arguments_through():
    assert jit(mi.Float, 0.5)[0] == 0.5
    x = dr.arange(mi.Float, 4)
    assert dr.all(jit(mi.Float, x) == x)
    p = jit(mi.Point3f, _unaligned(5), np.zeros(5, np.float32), 1.0)
    np.testing.assert_array_equal(np.asarray(p.x), np.arange(5))
    assert dr.all(p.z == 1.0)


def test_one_kernel_whatever_the_numpy_alignment():
    """The same computation on an aligned and an unaligned numpy array, both through ``jit``,
    runs one kernel (same hash); straight through ``mi.Float`` Dr.Jit maps the memory and the
    unaligned one compiles a kernel of its own."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        def kernel_hash(x):
            dr.kernel_history()
            y = x * 3.0 + 1.0
            dr.eval(y)
            h = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]
            assert len(h) == 1
            return h[0]["hash"]

        n = 4099
        good = aligned(np.arange(n, dtype=np.float32))
        bad = _unaligned(n)
        assert kernel_hash(jit(mi.Float, good)) == kernel_hash(jit(mi.Float, bad))
        # the cause, as Dr.Jit 1.5 behaves: mapped memory, a kernel per alignment
        assert kernel_hash(mi.Float(good)) != kernel_hash(mi.Float(bad))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
