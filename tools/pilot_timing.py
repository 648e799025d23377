"""twopass's pilot, timed call by call: where its seconds go, before/after a change.

    .venv/bin/python tools/pilot_timing.py scenes_xml/many_lights.xml --res 256 --spp 256 \
        [--seeds 1 2]

One render at seed 0 compiles the kernels; then one fresh twopass per seed renders ``--spp``
samples per pixel. Per seed it prints the render's seconds (to the numpy copy), twopass's
``pilot_seconds`` (the pilot, prepasses left out) and its choice, and for every pilot call
(:func:`mi_twopass.compose.pilot.timed_samples`) its pixels and samples per pixel, wall
seconds, and the seconds its kernels spent compiling (code generation and backend: paid even
where the kernel cache holds the kernel) and executing (Dr.Jit's kernel history). The rest of
a call's wall time is Python tracing the estimator. Run two checkouts alternately
(``PYTHONPATH``) to compare.
"""
import argparse
import time

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)

from mi_twopass.compose import pilot as pilot_module
from mi_twopass.scenefile import load_scene

from twopass_timing import timed_renders  # noqa: E402  (tools/ is the script's own directory)

CALLS = []


def logged_timed_samples(scene, sensor, pixels, samples, estimator, seed):
    """:func:`pilot.timed_samples`, recording each call's wall, compile and execution
    seconds."""
    t0 = time.perf_counter()
    (values, seconds), compiling, executing = pilot_module.with_kernel_history(
        lambda: pilot_module.run_samples(scene, sensor, pixels, samples, estimator, seed))
    CALLS.append((len(pixels.index), samples, time.perf_counter() - t0, compiling, executing))
    return values, seconds, (executing if executing > 0.0 else seconds)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    a = ap.parse_args()
    pilot_module.timed_samples = logged_timed_samples
    scene = load_scene(a.scene, film_res=a.res)
    for seed, t, integ in timed_renders(scene, a.spp, a.seeds, before_each=CALLS.clear):
        st = integ.stats
        print(f"seed {seed}: render {t:.3f} s, pilot {st['pilot_seconds']:.3f} s, "
              f"chose {st['twopass_choice']}")
        for pixels, samples, wall, compiling, executing in CALLS:
            print(f"    {pixels} pixels x {samples} samples: wall {wall:.4f} s, compiling "
                  f"{compiling:.4f} s, executing {executing:.4f} s", flush=True)


if __name__ == "__main__":
    main()
