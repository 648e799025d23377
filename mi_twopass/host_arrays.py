"""Dr.Jit arrays to numpy without a kernel per array size.

``np.array`` of a nested Dr.Jit array (``mi.Point3f``, ``mi.Color3f`` of n lanes) interleaves
its components in a kernel whose strides are the literal n, so every new size compiles a new
kernel (~20–100 ms each; a prepass whose point counts change with the seed paid it on every
render). Evaluating the components together and copying each flat component does not.
"""
from __future__ import annotations

import drjit as dr
import numpy as np


def columns(v, dtype=np.float64) -> np.ndarray:
    """A Dr.Jit array of k-component vectors (n lanes) as a numpy ``(n, k)`` array: the
    components evaluated in one kernel (no size enters it), then copied one by one."""
    comps = [v[i] for i in range(len(v))]
    dr.eval(*comps)
    return np.stack([np.asarray(c, dtype=dtype).reshape(-1) for c in comps], axis=1)
