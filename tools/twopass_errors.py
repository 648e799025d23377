"""twopass's choice, seconds and relMSE per (samples per pixel, render seed), against a cached
``path`` reference: what a user rendering at that spp gets from each choice.

    MI_TWOPASS_CACHE=/tmp/refcache .venv/bin/python tools/twopass_errors.py \\
        scenes_xml/caustic.xml --res 256 --ref-spp 16384 --spp 32,64,128 --seeds 0,1,2

``tools/twopass_decisions.py`` says what twopass chose and why; this says what each choice
cost in error. One untimed render first compiles the kernels; then one fresh twopass per
(spp, seed), timed to the numpy copy. The reference is the harness's (rendered and cached on a
miss, which at 16384 spp takes minutes). Run two checkouts alternately (``PYTHONPATH``) to
compare a change of the cost model (docs/results/revalidate-2026-11-29-s33).
"""
import argparse
import time

import mitsuba as mi
import numpy as np

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.evaluation.bench import scene_settings
from mi_twopass.evaluation.metrics import relmse
from mi_twopass.evaluation.reference import reference_image
from mi_twopass.scenefile import load_scene
from twopass_decisions import short  # (tools/, the script's folder)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--ref-spp", type=int, default=16384)
    ap.add_argument("--spp", default="32,64,128", help="comma-separated samples per pixel")
    ap.add_argument("--seeds", default="0,1,2", help="comma-separated render seeds")
    args = ap.parse_args()
    params, film_res = scene_settings(args.scene, args.res, {})
    ref = reference_image(args.scene, params, spp=args.ref_spp, film_res=film_res, verbose=True)
    scene = load_scene(args.scene, film_res=film_res, **params)
    np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "twopass"}), spp=4, seed=99))
    print("| spp | seed | choice | seconds | relMSE |")
    print("| --- | --- | --- | --- | --- |")
    for spp in (int(s) for s in args.spp.split(",")):
        for seed in (int(s) for s in args.seeds.split(",")):
            integ = mi.load_dict({"type": "twopass"})
            t0 = time.perf_counter()
            image = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=seed))
            seconds = time.perf_counter() - t0
            print(f"| {spp} | {seed} | {short(integ.stats['twopass_choice'])} | {seconds:.2f} | "
                  f"{relmse(image, ref):.3g} |", flush=True)


if __name__ == "__main__":
    main()
