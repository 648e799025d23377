"""Kernels a prepass compiles again on a second, third, … build of the same scene and seed.

    .venv/bin/python tools/kernel_recompiles.py SCENE.xml [--integrator radiance_cache]
        [--res 256] [--builds 6]

Builds the prepass ``--builds`` times in one process (fresh integrator, seed 0) with Dr.Jit's
kernel history on. The first build may compile; later ones should not. For each later build
it prints the seconds, the kernels compiled (cache misses) and their compile milliseconds, and
for the first such kernel the lines of its LLVM IR that differ from the first build's kernel
of the same size and operation count — what made the kernel new.

Found with it (session 16): mapped NumPy arrays. ``mi.Float(numpy_array)`` maps the array's
memory without a copy, and Dr.Jit compiles a kernel reading a 64-byte-aligned array apart
from one reading an unaligned one (``align 64`` against ``align 1`` in the IR). NumPy's
allocations are aligned or not by chance, so radiance_cache's prepass on veach-bidir at 256²
compiled 16–19 kernels again in some builds (1.8–4.1 s of compilation in a 2.7–5.6 s build,
against 0.75 s for a build that compiled none). With ``--first-seed`` (session 16 too): values
that follow the seed baked into kernels as literals (``dr.mean`` of a Color3f, ``np.array`` of
one, scatter-adds in ``Expand`` mode, a quantum).
"""
import argparse
import difflib
import time

import drjit as dr
import mitsuba as mi

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.scenefile import load_scene


def _ir(kernel) -> str:
    ir = kernel.get("ir")
    return ir.getvalue() if hasattr(ir, "getvalue") else str(ir or "")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--integrator", default="radiance_cache")
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--builds", type=int, default=6)
    ap.add_argument("--first-seed", type=int, default=None,
                    help="build b uses seed first_seed + b (default: seed 0 for every build); "
                         "kernels are then matched to build 0's by operation count alone, as "
                         "their sizes may follow the seed")
    a = ap.parse_args()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    scene = load_scene(a.scene, film_res=a.res)
    first = {}

    def key(k):
        ops = k.get("operation_count")
        return ops if a.first_seed is not None else (k["size"], ops)

    for build in range(a.builds):
        integrator = mi.load_dict({"type": a.integrator})
        dr.kernel_history_clear()
        t0 = time.perf_counter()
        seed = 0 if a.first_seed is None else a.first_seed + build
        integrator.ensure_prepass(scene, seed, scene.sensors()[0])
        dr.sync_thread()
        seconds = time.perf_counter() - t0
        history = [k for k in dr.kernel_history() if "ir" in k]
        compiled = [k for k in history if not k.get("cache_hit", True)]
        ms = sum(k.get("codegen_time", 0.0) + k.get("backend_time", 0.0) for k in compiled)
        print(f"build {build}: {seconds:.3f} s, {len(compiled)} kernels compiled ({ms:.0f} ms)")
        if build == 0:
            for k in history:
                first.setdefault(key(k), _ir(k))
            continue
        for k in compiled:
            old = first.get(key(k))
            if old is None:
                print(f"  size {k['size']}, {k.get('operation_count')} operations: no kernel of "
                      "build 0 has that shape (a kernel whose structure follows the data)")
                continue
            diff = [line for line in difflib.unified_diff(old.splitlines(), _ir(k).splitlines(),
                                                          lineterm="", n=0)
                    if line[:1] in "+-" and not line.startswith(("+++", "---"))]
            print(f"  size {k['size']}, {k.get('operation_count')} operations: IR lines that "
                  "differ from build 0's kernel:")
            for line in diff[1:9]:  # the first pair is the kernel's name (its hash)
                print("   ", line.strip()[:140])
            break


if __name__ == "__main__":
    main()
