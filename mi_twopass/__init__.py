"""mi_twopass: two-pass global-illumination integrators for Mitsuba 3.

``import mi_twopass`` does three things, in this order:

1. finds a libLLVM that drjit 1.5 can use and sets ``DRJIT_LIBLLVM_PATH`` (unless the user set it)
   before drjit's LLVM backend starts (see :mod:`mi_twopass._llvm`);
2. imports Mitsuba and, if no variant is active yet, selects ``llvm_ad_rgb``;
3. registers every integrator of the suite for the active ``*_rgb`` JIT variant, and again whenever
   the variant changes (``mi.detail.add_variant_callback``).
"""
from . import _llvm

_llvm.configure()

import mitsuba as mi  # noqa: E402

DEFAULT_VARIANT = "llvm_ad_rgb"

if mi.variant() is None:
    mi.set_variant(DEFAULT_VARIANT)

from .integrators import register_for_variant, registered_names  # noqa: E402

register_for_variant(mi.variant())
mi.detail.add_variant_callback(lambda old, new: register_for_variant(new))

__all__ = ["register_for_variant", "registered_names", "DEFAULT_VARIANT"]
__version__ = "0.1.0"
