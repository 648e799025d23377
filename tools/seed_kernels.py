"""Kernels an integrator compiles anew for each render seed, and what a fresh seed costs.

    .venv/bin/python tools/seed_kernels.py scenes_xml/caustic.xml radiosity_gather [--res 256] \
        [--spp 4]

Renders ``--spp`` (4) with a fresh integrator at three consecutive random seeds in one process and
prints, per render: wall seconds, Dr.Jit kernels launched, kernels compiled (not found in
memory), kernels read from the on-disk cache. The bench renders every point at a new seed, so a
kernel with the seed (or a value that follows it) as a literal is compiled at every point
(docs/design.md, "Vectorisation"). A few kernels may still be compiled once per machine: a
numpy buffer handed to Dr.Jit is read in place, and an unaligned buffer gets its own kernel.
"""
import argparse
import random
import time

import drjit as dr
import mitsuba as mi

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.scenefile import load_scene


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("integrator")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--spp", type=int, default=4,
                    help="samples per pixel (twopass builds what that many samples pay for)")
    a = ap.parse_args()
    scene = load_scene(a.scene, film_res=a.res)
    base = random.randrange(1 << 30)
    for i, seed in enumerate((base, base + 1, base + 2)):
        integrator = mi.load_dict({"type": a.integrator})
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            t0 = time.perf_counter()
            mi.render(scene, integrator=integrator, spp=a.spp, seed=seed).numpy()
            seconds = time.perf_counter() - t0
            history = dr.kernel_history()
        jit = [k for k in history if k.get("type") == dr.KernelType.JIT]
        compiled = [k for k in jit if not k.get("cache_hit")]
        disk = [k for k in jit if k.get("cache_disk")]
        print(f"{a.integrator} seed #{i}: {seconds:.2f} s, {len(jit)} kernels, "
              f"{len(compiled)} compiled, {len(disk)} from disk")


if __name__ == "__main__":
    main()
