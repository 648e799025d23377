"""Issue 13's first target, per scene: each integrator's prepass against ``path``'s 32 spp.

    .venv/bin/python tools/prepass_vs_path.py scenes_xml/*.xml ../shared/scenes/*/*.xml \\
        [--res 256] [--integrators radiosity_gather,spike_gather,radiance_cache,rex]

For every scene (the film's longer side set to ``--res``): ``path`` renders 32 spp twice and
the second, kernels compiled, is its time; each integrator's prepass is built twice with a
fresh integrator (``ensure_prepass``, the render's seed 0) and the faster build counts, so
both sides are a user's second run. Prints a Markdown table: seconds, and the prepass over
path's time (≤ 1.00 meets the target). An integrator that refuses the scene (a medium, for
example) shows the start of its message.
"""
import argparse
import time

import drjit as dr
import mitsuba as mi

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.scenefile import load_scene, scene_label

PATH_SPP = 32
DEFAULT_INTEGRATORS = "radiosity_gather,spike_gather,radiance_cache,rex"


def path_seconds(scene, spp: int = PATH_SPP) -> float:
    """``path`` at ``spp``, the second of two renders (kernels compiled by the first)."""
    integrator = mi.load_dict({"type": "path"})
    seconds = None
    for _ in range(2):
        t0 = time.perf_counter()
        mi.render(scene, integrator=integrator, spp=spp).numpy()
        dr.sync_thread()
        seconds = time.perf_counter() - t0
    return seconds


def prepass_seconds(scene, name: str, builds: int = 2):
    """The fastest of ``builds`` prepass builds of fresh ``name`` integrators (a spec,
    ``NAME[:key=value...]`` as the bench takes), or the
    integrator's refusal (``ValueError`` / ``NotImplementedError``) as a string."""
    best = None
    for _ in range(builds):
        integrator = make_integrator(name)
        t0 = time.perf_counter()
        try:
            integrator.ensure_prepass(scene, 0, scene.sensors()[0])
        except (ValueError, NotImplementedError) as err:
            return "refused: " + " ".join(str(err).split())[:48]
        dr.sync_thread()
        seconds = time.perf_counter() - t0
        best = seconds if best is None else min(best, seconds)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--integrators", default=DEFAULT_INTEGRATORS)
    a = ap.parse_args()
    names = a.integrators.split(",")
    print(f"| scene ({a.res} px) | path {PATH_SPP} spp s | "
          + " | ".join(f"{n} s (× path)" for n in names) + " |")
    print("| --- " * (2 + len(names)) + "|")
    for path in a.scenes:
        scene = load_scene(path, film_res=a.res)
        base = path_seconds(scene)
        cells = []
        for name in names:
            s = prepass_seconds(scene, name)
            cells.append(s if isinstance(s, str) else f"{s:.3f} ({s / base:.2f})")
        print(f"| {scene_label(path)} | {base:.3f} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
