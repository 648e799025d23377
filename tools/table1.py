"""The papers' Table 1 columns for one scene and integrator (README "Results").

    python tools/table1.py SCENE.xml INTEGRATOR[:key=value...] [-D res=64] [--spp 16]

Renders once untimed (kernel compilation), then once with a fresh integrator, and prints its
stats: Zimmerman & Shirley's viewing / implicit / explicit rays and times, Arikan et al.'s
ART, FGO (radiance_cache only), NRT, NFGS, CS, Heckbert's light rays / % hit / rex leaves.
"""
import argparse
import json

import mi_twopass  # noqa: F401
import mitsuba as mi

from mi_twopass.evaluation.harness import make_integrator, parse_integrator_spec
from mi_twopass.scenefile import load_scene, parse_defines


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("integrator")
    ap.add_argument("-D", dest="defines", action="append", default=[])
    ap.add_argument("--spp", type=int, default=16)
    a = ap.parse_args()
    scene = load_scene(a.scene, **parse_defines(a.defines))
    mi.render(scene, integrator=make_integrator(a.integrator), spp=1)  # warm-up
    integ = make_integrator(a.integrator)
    mi.render(scene, integrator=integ, spp=a.spp)
    stats = dict(integ.stats)
    name, props = parse_integrator_spec(a.integrator)
    if name == "radiance_cache":
        from mi_twopass.evaluation.table1 import fgo

        stats["FGO"], _ = fgo(scene, spp=a.spp, **props)
    stats["implicit_per_viewing_ray"] = stats.get("implicit_rays", 0) / max(1, stats["viewing_rays"])
    stats["explicit_per_viewing_ray"] = stats.get("explicit_rays", 0) / max(1, stats["viewing_rays"])
    print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in stats.items()},
                     indent=1, default=str))


if __name__ == "__main__":
    main()
