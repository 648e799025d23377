"""Error and render time at a fixed sample count, per integrator spec: relMSE × seconds.

    .venv/bin/python tools/efficiency.py scenes_xml/many_lights.xml scenes_xml/office.xml \\
        --res 128 --spp 64 path spike_gather spike_gather:selection=point

For each scene and spec, ``--seeds`` renders (seeds 1, 2, ...) at ``--spp``, each after an
untimed 4-spp render with the same seed (its prepass, whose seed is the render's, and kernel
compilation), so that only the render is timed (after ``dr.sync_thread()``, via the numpy
conversion). relMSE is against the harness's cached ``path`` reference (4096 spp, built on a
miss). Prints the mean relMSE, the fastest render, and their product (lower is better: the
error reached per second of rendering, the prepass left out).
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import numpy as np

from mi_twopass.evaluation.harness import make_integrator, render_only_seconds
from mi_twopass.evaluation.metrics import relmse
from mi_twopass.evaluation.reference import reference_image
from mi_twopass.scenefile import load_scene


def measure(scene, ref, spec: str, spp: int, seeds: int) -> tuple[float, float]:
    """(mean relMSE, fastest render seconds) of ``seeds`` renders of ``spec``."""
    errors, seconds = [], []
    for seed in range(1, seeds + 1):
        image, s = render_only_seconds(scene, make_integrator(spec), spp, seed)
        seconds.append(s)
        errors.append(relmse(image[..., :3], ref))
    return float(np.mean(errors)), float(min(seconds))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+", help="scene files, then integrator specs "
                                              "NAME[:key=value...] (everything not ending .xml)")
    ap.add_argument("--res", type=int, default=128, help="film's longer side in pixels")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--reference-spp", type=int, default=4096)
    a = ap.parse_args()
    scenes = [s for s in a.scenes if s.endswith(".xml")]
    specs = [s for s in a.scenes if not s.endswith(".xml")]
    if not scenes or not specs:
        ap.error("give at least one scene file (.xml) and one integrator spec")
    print(f"| scene | spec | relMSE @ {a.spp} spp | render s | relMSE × s |")
    print("| --- | --- | --- | --- | --- |")
    for path in scenes:
        ref = reference_image(path, {}, a.reference_spp, film_res=a.res)
        scene = load_scene(path, film_res=a.res)
        for spec in specs:
            err, sec = measure(scene, ref, spec, a.spp, a.seeds)
            print(f"| {path} | `{spec}` | {err:.3e} | {sec:.3f} | {err * sec:.3e} |", flush=True)


if __name__ == "__main__":
    main()
