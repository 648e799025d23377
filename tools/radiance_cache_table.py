"""Arikan et al.'s Table 1 columns for ``radiance_cache`` on one scene, at several spp.

    python tools/radiance_cache_table.py SCENE.xml [-D res=64] [--spp 16,64,256] [--repeat 3]
                                         [--props alpha_rel=0.03,...]

Per spp: ART (prepass + render seconds of a fresh integrator), the direct-only render time, FGO
(ART over it), FGO_render (render seconds alone over it: the per-sample cost of the cache),
NRT (rays traced for GI), NFGS (SH samples), CS (cache bytes), BVH nodes visited per viewing ray
and alpha. Timings are the median of ``--repeat`` runs (:func:`~mi_twopass.integrators.
evaluation.table1.fgo` compiles kernels untimed first): compare ratios, not seconds, on a shared
machine.
"""
import argparse
import statistics

import mi_twopass  # noqa: F401
from mi_twopass.evaluation.harness import parse_integrator_spec
from mi_twopass.evaluation.table1 import fgo
from mi_twopass.scenefile import load_scene, parse_defines


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("-D", dest="defines", action="append", default=[])
    ap.add_argument("--spp", default="16,64,256")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--props", default="", help="radiance_cache properties k=v,k=v")
    a = ap.parse_args()
    scene = load_scene(a.scene, **parse_defines(a.defines))
    spec = "radiance_cache" + "".join(":" + kv for kv in a.props.split(",") if kv)
    _, props = parse_integrator_spec(spec)
    cols = ("spp", "ART s", "direct s", "FGO", "FGO_render", "NRT", "NFGS", "CS bytes",
            "visits/ray", "alpha")
    print(" ".join(f"{c:>11s}" for c in cols))
    for spp in (int(v) for v in a.spp.split(",")):
        runs = [fgo(scene, spp=spp, **props)[1] for _ in range(a.repeat)]
        med = {k: statistics.median(r[k] for r in runs)
               for k in ("FGO", "FGO_render", "direct_seconds", "prepass_seconds",
                         "render_seconds")}
        s = runs[-1]
        row = (spp, med["prepass_seconds"] + med["render_seconds"], med["direct_seconds"],
               med["FGO"], med["FGO_render"], s["NRT"], s["NFGS"], s["CS"],
               s["bvh_visits"] / max(1, s["viewing_rays"]), s["alpha"])
        print(" ".join(f"{v:11.4g}" if isinstance(v, float) else f"{v:11d}" for v in row),
              flush=True)


if __name__ == "__main__":
    main()
