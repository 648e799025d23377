"""Dr.Jit arrays to numpy without a kernel per array size, and numpy rows back to Dr.Jit.

``np.array`` of a nested Dr.Jit array (``mi.Point3f``, ``mi.Color3f`` of n lanes) interleaves
its components in a kernel whose strides are the literal n, so every new size compiles a new
kernel (~20–100 ms each; a prepass whose point counts change with the seed paid it on every
render). Evaluating the components together and copying each flat component does not.
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


def vectors(x, cls):
    """The inverse of :func:`columns`: a numpy ``(n, 3)`` array as a Dr.Jit 3-vector ``cls``
    (``mi.Point3f``, ``mi.Vector3f``, ``mi.Color3f``) of n float32 lanes, one contiguous copy
    per component."""
    cols = np.ascontiguousarray(np.asarray(x).reshape(-1, 3).T, dtype=np.float32)
    return cls(*(mi.Float(cols[i]) for i in range(3)))
