"""What twopass builds and chooses, and why, per scene and samples per pixel.

    .venv/bin/python tools/twopass_decisions.py scenes_xml/*.xml ../shared/scenes/*/*.xml \\
        [--res 256] [--spp 64,256,1024] [--seeds 0,1,2] [--why]

One render per (scene, spp, render seed) with a fresh ``twopass``, timed to the numpy copy. Prints one
Markdown row each: the choice, the render's seconds, the pilot's and prepasses' seconds
(``prepass_seconds``) and the candidates built. ``--why`` adds, under each row, every
candidate's best case; its measured score, variance and image mean over path's pilot; the
reason each skipped one was not built; the photons of a cut rex against the image's need, with
its own noise as measured or predicted per build (``twopass_fitted``, ``twopass_frozen``); and the bias tests of a suspect winner
(``twopass_best_case``, ``twopass_candidates``, ``twopass_skipped``,
``twopass_bias_checks``), and path's caustic variance as rex's photons predicted it beside
the pilot's (``twopass_caustic_prediction``). Run two checkouts alternately (``PYTHONPATH``)
to compare a change of the cost model (docs/results/rex-gate-2026-11-28).
"""
import argparse
import time

import drjit as dr
import mitsuba as mi

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.scenefile import load_scene, scene_label


def short(name: str) -> str:
    """``direct=spike,indirect=radiosity,caustics=off`` → ``spike + radiosity``."""
    parts = dict(p.split("=") for p in name.split(","))
    label = f"{parts['direct']} + {parts['indirect']}"
    return label if parts["caustics"] == "off" else label + f" (caustics {parts['caustics']})"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--spp", default="64,256,1024", help="comma-separated samples per pixel")
    ap.add_argument("--why", action="store_true", help="best cases, scores and skip reasons")
    ap.add_argument("--seeds", default="0", help="comma-separated render seeds (a row each)")
    a = ap.parse_args()
    print("| scene | spp | seed | choice | seconds | pilot + prepasses s | built |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for path in a.scenes:
        scene = load_scene(path, film_res=a.res)
        for spp, seed in ((int(n), int(k)) for n in a.spp.split(",")
                          for k in a.seeds.split(",")):
            integrator = mi.load_dict({"type": "twopass"})
            t0 = time.perf_counter()
            mi.render(scene, integrator=integrator, spp=spp, seed=seed).numpy()
            dr.sync_thread()
            seconds = time.perf_counter() - t0
            s = integrator.stats
            built = ", ".join(short(n) for n in s["twopass_candidates"])
            print(f"| {scene_label(path)} | {spp} | {seed} | {short(s['twopass_choice'])} | "
                  f"{seconds:.2f} | {s['prepass_seconds']:.2f} | {built} |", flush=True)
            if a.why:
                cp = s.get("twopass_caustic_prediction")
                if cp:
                    print(f"    path's caustic variance: {cp['predicted']:.3g} predicted by "
                          f"photons, {cp['pilot']:.3g} in the pilot (sharp light "
                          f"{cp['sharp_share']:.2%} of the image)")
                for n, m in s["twopass_candidates"].items():
                    if n not in s["twopass_best_case"]:  # path: the pilot every score reads
                        print(f"    {short(n)}: score {m['score']:.3g}, relative variance "
                              f"{m['relative_variance']:.3g}")
                for n, best in s["twopass_best_case"].items():
                    m = s["twopass_candidates"].get(n)
                    got = (f"score {m['score']:.3g}, variance {m['relative_variance']:.3g}, "
                           f"image mean over path's {m['mean_ratio']:.3f}"
                           if m else s["twopass_skipped"].get(n, "not built"))
                    print(f"    {short(n)}: best case {best:.3g}; {got}")
                for n, f in s.get("twopass_fitted", {}).items():
                    history = "; ".join(f"{h['light_paths']}: block {h['block_relmse']:.3g}"
                                        for h in s.get("twopass_frozen", {}).get(n, []))
                    print(f"    {short(n)} cut to {f['light_paths']} of the image's "
                          f"{f['image_needs']} photons; own noise {history or 'not measured'}")
                for n, checks in s["twopass_bias_checks"].items():
                    for c in checks:
                        b2 = "—" if c["bias2"] is None else f"{c['bias2']:.3g}"
                        print(f"    bias test of {short(n)} at {c['samples_per_pixel']} spp: "
                              f"b² {b2} ± {c['standard_error']:.2g}, {c['outcome']}")


if __name__ == "__main__":
    main()
