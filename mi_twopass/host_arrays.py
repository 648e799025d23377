"""Dr.Jit arrays to numpy without a kernel per array size, and numpy arrays to Dr.Jit without
a kernel per memory alignment.

``np.array`` of a nested Dr.Jit array (``mi.Point3f``, ``mi.Color3f`` of n lanes) interleaves
its components in a kernel whose strides are the literal n, so every new size compiles a new
kernel (~20–100 ms each; a prepass whose point counts change with the seed paid it on every
render). Evaluating the components together and copying each flat component does not.

The other way, ``mi.Float(numpy_array)`` on the LLVM backend maps the array's memory without a
copy, and Dr.Jit compiles a kernel that reads 64-byte-aligned memory apart from one that reads
unaligned memory (``align 64`` against ``align 1`` in its IR). NumPy's allocations are aligned
or not by chance, so such kernels were compiled again by chance: radiance_cache's prepass on
veach-bidir at 256² spent 3.6–4.1 s of a 4.8–5.6 s build compiling 16–17 kernels in every
build after the first of one process in four, against 0.75 s for a build that compiled none
(``tools/kernel_recompiles.py``). :func:`jit` hands Dr.Jit only 64-byte-aligned NumPy memory,
so every kernel is the aligned one.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def columns(v, dtype=np.float64) -> np.ndarray:
    """A Dr.Jit array of k-component vectors (n lanes) as a numpy ``(n, k)`` array: the
    components evaluated in one kernel (no size enters it), then copied one by one."""
    comps = [v[i] for i in range(len(v))]
    dr.eval(*comps)
    return np.stack([np.asarray(c, dtype=dtype).reshape(-1) for c in comps], axis=1)


def component_sums(*vs) -> np.ndarray:
    """The sums over lanes of each component of the k-component Dr.Jit arrays ``vs`` (n lanes
    each, n ≥ 1), as a numpy ``(len(vs), k)`` float64 array: reduced in Dr.Jit and read back
    together, not copied lane by lane into numpy (:func:`columns` then ``sum``: 3–5 ms per
    262144-lane Color3f on two CPU cores)."""
    sums = [dr.sum(v[i]) for v in vs for i in range(len(v))]
    dr.eval(*sums)
    k = len(vs[0]) if vs else 0
    return np.array([float(np.asarray(x).reshape(-1)[0]) for x in sums],
                    np.float64).reshape(len(vs), k)


#: the alignment of the NumPy memory :func:`jit` hands to Dr.Jit (a cache line, AVX-512's vector)
ALIGNMENT = 64


def aligned(a: np.ndarray) -> np.ndarray:
    """``a`` as a C-contiguous array whose data start on an :data:`ALIGNMENT`-byte boundary: ``a``
    itself where it is one, else a copy."""
    a = np.ascontiguousarray(a)
    if a.ctypes.data % ALIGNMENT == 0:
        return a
    buf = np.empty(a.nbytes + ALIGNMENT, np.uint8)
    start = -buf.ctypes.data % ALIGNMENT
    out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


def jit(cls, *args, **kwargs):
    """``cls(*args, **kwargs)`` with every NumPy array among ``args`` first made
    :func:`aligned` (module docstring): the way this package turns host arrays into Dr.Jit
    arrays (``jit(mi.Float, x)`` for ``mi.Float(x)``). Other arguments pass unchanged."""
    return cls(*(aligned(a) if isinstance(a, np.ndarray) and a.ndim else a for a in args),
               **kwargs)


def vectors(x, cls):
    """The inverse of :func:`columns`: a numpy ``(n, 3)`` array as a Dr.Jit 3-vector ``cls``
    (``mi.Point3f``, ``mi.Vector3f``, ``mi.Color3f``) of n float32 lanes, one contiguous copy
    per component."""
    cols = np.asarray(x, dtype=np.float32).reshape(-1, 3).T
    return cls(*(jit(mi.Float, cols[i]) for i in range(3)))


def id_table(x, cls):
    """:func:`vectors` of ``x`` (n, 3) with a zero row appended: a per-id table whose invalid
    id ``n`` (a miss, the count of patches or elements) reads 0."""
    return vectors(np.vstack([np.asarray(x, np.float64).reshape(-1, 3), np.zeros((1, 3))]), cls)
