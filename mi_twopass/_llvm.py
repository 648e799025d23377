"""Find a libLLVM that drjit 1.5's LLVM backend can use, before drjit initialises.

drjit 1.5 emits LLVM IR (``llvm.minimum``/``fminimum``) that LLVM 15's instruction selector
cannot lower ("LLVM ERROR: Cannot select ... fminimum"), so a machine whose default libLLVM is
15 crashes on the first kernel. LLVM 16 and newer work. drjit reads ``DRJIT_LIBLLVM_PATH`` when
its LLVM backend starts; :func:`configure` sets it to the newest usable library it finds, unless
the user already set it.
"""
from __future__ import annotations

import glob
import os
import re
import sys

#: Oldest LLVM major version drjit 1.5 works with (15 crashes, 19 is verified).
MIN_LLVM_MAJOR = 16

#: Where Linux distributions put libLLVM (Debian/Ubuntu multiarch, llvm-N trees, Fedora, local).
DEFAULT_SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib/llvm-*/lib",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
)

_NAME_PATTERNS = (
    re.compile(r"^libLLVM-(\d+)(?:\.\d+)*\.so(?:\.\d+)*$"),  # libLLVM-19.so, libLLVM-14.0.6.so.1
    re.compile(r"^libLLVM\.so\.(\d+)(?:\.\d+)*$"),  # libLLVM.so.19.1
    re.compile(r"^libLLVM-(\d+)\.dylib$"),
)

FIX_MESSAGE = (
    "mi_twopass: no libLLVM >= {min} found (searched: {dirs}; found: {found}). drjit 1.5 crashes "
    "with LLVM 15. Fix: `apt-get update && apt-get install -y libllvm19` (what `make setup` does), "
    "or point DRJIT_LIBLLVM_PATH at a libLLVM of version {min} or newer."
)


class LLVMNotFoundError(ImportError):
    """No usable libLLVM: the message says how to install one."""


def llvm_major(path: str) -> int | None:
    """LLVM major version encoded in a library file name, or None if it is not a libLLVM."""
    name = os.path.basename(path)
    for pat in _NAME_PATTERNS:
        m = pat.match(name)
        if m:
            return int(m.group(1))
    return None


def find_libllvm(search_dirs=DEFAULT_SEARCH_DIRS, min_major: int = MIN_LLVM_MAJOR):
    """Return ``(best_path, all_candidates)``: the newest libLLVM with major >= ``min_major``.

    ``all_candidates`` is a list of ``(major, path)`` of every libLLVM seen, usable or not, so an
    error can say what was found. ``best_path`` is None when nothing is new enough.
    """
    candidates = []
    for pattern in search_dirs:
        for d in sorted(glob.glob(pattern)):
            if not os.path.isdir(d):
                continue
            for f in sorted(os.listdir(d)):
                major = llvm_major(f)
                full = os.path.join(d, f)
                if major is not None and os.path.exists(full):
                    candidates.append((major, full))
    usable = [c for c in candidates if c[0] >= min_major]
    # Newest major first; among equals prefer the fully versioned real file (stable ordering).
    usable.sort(key=lambda c: (c[0], len(os.path.basename(c[1]))), reverse=True)
    return (usable[0][1] if usable else None), candidates


def configure(environ=None, search_dirs=DEFAULT_SEARCH_DIRS, platform: str | None = None) -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` in ``environ`` (default ``os.environ``) unless already set.

    Returns the path in force. Raises :class:`LLVMNotFoundError` on Linux when no usable library
    exists. On other platforms drjit's own search is left alone.
    """
    environ = os.environ if environ is None else environ
    platform = sys.platform if platform is None else platform
    if environ.get("DRJIT_LIBLLVM_PATH"):
        return environ["DRJIT_LIBLLVM_PATH"]
    if not platform.startswith("linux"):
        return None
    best, found = find_libllvm(search_dirs)
    if best is None:
        raise LLVMNotFoundError(
            FIX_MESSAGE.format(
                min=MIN_LLVM_MAJOR,
                dirs=", ".join(search_dirs),
                found=", ".join(p for _, p in found) or "none",
            )
        )
    environ["DRJIT_LIBLLVM_PATH"] = best
    return best
