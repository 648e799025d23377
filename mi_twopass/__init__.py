"""mi_twopass: two-pass global-illumination integrators for Mitsuba 3.

``import mi_twopass`` does three things, in this order:

1. finds a libLLVM that drjit 1.5 can use and sets ``DRJIT_LIBLLVM_PATH`` (unless the user set it)
   before drjit's LLVM backend starts (see :mod:`mi_twopass._llvm`); a session that chose a CUDA
   variant first (``mi.set_variant('cuda_ad_rgb')`` before the import, or
   ``MI_TWOPASS_VARIANT=cuda_ad_rgb``) needs no libLLVM and skips the search;
2. imports Mitsuba and, if no variant is active yet, selects ``$MI_TWOPASS_VARIANT`` or
   ``llvm_ad_rgb``;
3. registers every integrator of the suite for the active ``*_rgb`` JIT variant, and again whenever
   the variant changes (``mi.detail.add_variant_callback``).
"""
import os as _os
import sys as _sys

from . import _llvm

DEFAULT_VARIANT = _os.environ.get("MI_TWOPASS_VARIANT") or "llvm_ad_rgb"


def _chosen_variant():
    mitsuba = _sys.modules.get("mitsuba")
    return (mitsuba.variant() if mitsuba is not None else None) or DEFAULT_VARIANT


if not _chosen_variant().startswith("cuda"):
    _llvm.configure()

import mitsuba as mi  # noqa: E402

if mi.variant() is None:
    mi.set_variant(DEFAULT_VARIANT)

from .integrators import register_for_variant, registered_names  # noqa: E402

register_for_variant(mi.variant())
mi.detail.add_variant_callback(lambda old, new: register_for_variant(new))

__all__ = ["register_for_variant", "registered_names", "DEFAULT_VARIANT"]
__version__ = "0.1.0"
