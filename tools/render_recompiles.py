"""Kernels a render compiles again on a second, third, … render of the same scene.

    .venv/bin/python tools/render_recompiles.py SCENE.xml [--integrators a,b] [--res 64]
        [--spp 4] [--renders 3]

Per integrator: ``--renders`` renders in one process, each with a fresh integrator (its
prepass built again) and its own seed, Dr.Jit's kernel history on. The first render may
compile; later ones should not, since the kernels are the same. Prints, per integrator, the
kernels each later render compiled (cache misses) and their compile milliseconds. A kernel
that bakes in the seed is compiled once per seed and then found in Dr.Jit's disk cache: give
``--first-seed`` a value no earlier run used to see it. A kernel
compiled again points to a literal that changes per render (``dr.opaque`` it) or to NumPy
memory mapped with another alignment (``host_arrays.jit``); ``tools/kernel_recompiles.py``
shows which for a prepass.
"""
import argparse
import time

import drjit as dr
import mitsuba as mi

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.scenefile import load_scene

DEFAULT = "path,radiosity_gather,spike_gather,radiance_cache,rex,twopass"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--integrators", default=DEFAULT)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--renders", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0,
                    help="render r uses seed first_seed + r: seeds no earlier run used show "
                         "kernels compiled per seed, which the disk cache hides otherwise")
    a = ap.parse_args()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    scene = load_scene(a.scene, film_res=a.res)
    for name in a.integrators.split(","):
        lines = []
        for r in range(a.renders):
            integrator = mi.load_dict({"type": name})
            dr.kernel_history_clear()
            t0 = time.perf_counter()
            try:
                mi.render(scene, integrator=integrator, spp=a.spp, seed=a.first_seed + r).numpy()
            # RuntimeError: mi.render's wrapper around an integrator's refusal
            except (ValueError, NotImplementedError, RuntimeError) as err:
                lines.append(f"refused: {' '.join(str(err).split())[:60]}")
                break
            dr.sync_thread()
            seconds = time.perf_counter() - t0
            compiled = [k for k in dr.kernel_history()
                        if "ir" in k and not k.get("cache_hit", True)]
            ms = sum(k.get("codegen_time", 0.0) + k.get("backend_time", 0.0) for k in compiled)
            if r:
                lines.append(f"render {r}: {seconds:.3f} s, {len(compiled)} compiled ({ms:.0f} ms)")
        print(f"{name}: " + "; ".join(lines), flush=True)


if __name__ == "__main__":
    main()
