"""Command line: ``python -m mi_twopass render | compare | demo``.

    python -m mi_twopass render SCENE.xml -o out.exr [--integrator T] [-D key=value] [--spp N]
                                [--variant V] [--seed S] [--reference]
    python -m mi_twopass compare SCENE.xml --integrators path,radiosity_gather --budget 10
    python -m mi_twopass demo
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

#: the suite's best integrator for the demo scene (lower relMSE than ``path`` at equal spp and,
#: past the prepass, at equal time: see README "Results")
DEMO_INTEGRATOR = "radiosity_gather"
DEMO_SCENE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                          "scenes_xml", "cornell_box.xml")


def _add_scene_args(p):
    p.add_argument("scene", help="Mitsuba scene XML")
    p.add_argument("-D", dest="defines", action="append", default=[], metavar="KEY=VALUE",
                   help="scene parameter ($KEY in the XML), e.g. -D res=64")
    p.add_argument("--variant", default=None, help="Mitsuba variant (default llvm_ad_rgb)")
    p.add_argument("--seed", type=int, default=0)


def build_parser():
    parser = argparse.ArgumentParser(prog="python -m mi_twopass", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a scene to EXR + tone-mapped PNG")
    _add_scene_args(r)
    r.add_argument("-o", "--output", required=True, help="output .exr (a .png is written beside)")
    r.add_argument("--integrator", default=None,
                   help="integrator spec NAME[:key=value...] (default: the scene's own)")
    r.add_argument("--spp", type=int, default=0, help="samples per pixel (default: the scene's)")
    r.add_argument("--reference", action="store_true",
                   help="also print relMSE/FLIP against the cached path reference")
    r.add_argument("--ref-spp", type=int, default=None)
    r.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops")

    c = sub.add_parser("compare", help="speed-vs-error curves against path")
    _add_scene_args(c)
    c.add_argument("--integrators", default="path",
                   help="comma-separated integrator specs NAME[:key=value...]")
    c.add_argument("--budget", type=float, default=10.0, help="seconds per integrator")
    c.add_argument("--ref-spp", type=int, default=None)
    c.add_argument("-o", "--output-dir", default="out/compare")

    d = sub.add_parser("demo", help="render the demo scene and print time and relMSE")
    d.add_argument("--integrator", default=DEMO_INTEGRATOR)
    d.add_argument("--spp", type=int, default=64)
    d.add_argument("-o", "--output", default="out/demo.exr")
    return parser


def _setup(variant):
    import mitsuba as mi

    import mi_twopass  # noqa: F401  (libLLVM, default variant, plugins)

    if variant:
        if variant not in mi.variants():
            raise SystemExit(f"error: unknown variant {variant!r}; available: {mi.variants()}")
        mi.set_variant(variant)
    return mi


def _ref_spp(args):
    from .evaluation.reference import DEFAULT_REFERENCE_SPP

    return args.ref_spp or DEFAULT_REFERENCE_SPP


def render_command(scene_path, output, integrator_spec=None, spp=0, defines=(), seed=0,
                   reference=False, ref_spp=None, exposure=0.0, variant=None, out=print):
    """Render, write EXR + PNG, print time, stats and (optionally) error. Returns a dict."""
    mi = _setup(variant)
    import drjit as dr
    import numpy as np

    from .evaluation.images import write_exr, write_png
    from .evaluation.harness import make_integrator
    from .progress import progress
    from .scenefile import load_scene, parse_defines

    params = parse_defines(defines)
    scene = load_scene(scene_path, **params)
    sensor = scene.sensors()[0]
    spp = spp or int(sensor.sampler().sample_count())
    integrator = make_integrator(integrator_spec) if integrator_spec else scene.integrator()
    w, h = (int(v) for v in sensor.film().crop_size())
    per_pass = max(1, min(spp, (1 << 22) // max(1, w * h)))
    passes = math.ceil(spp / per_pass)
    t0 = time.perf_counter()
    acc = np.zeros((h, w, 3))
    prepass_seconds = 0.0
    stats = {}
    with progress(total=spp, desc="render", unit="spp") as bar:
        done = 0
        for k in range(passes):
            n = min(per_pass, spp - done)
            img = mi.render(scene, integrator=integrator, spp=n, seed=seed + 7919 * k)
            acc += np.asarray(img, dtype=np.float64)[..., :3] * n
            dr.sync_thread()
            s = dict(getattr(integrator, "stats", {}) or {})
            for key, v in s.items():
                if key in ("prepass_seconds", "prepass_rays", "cache_bytes") or not isinstance(v, (int, float)):
                    stats.setdefault(key, v)
                else:
                    stats[key] = stats.get(key, 0) + v
            prepass_seconds += s.get("prepass_seconds", 0.0)
            done += n
            bar.update(n)
    image = (acc / spp).astype(np.float32)
    seconds = time.perf_counter() - t0
    if not np.all(np.isfinite(image)):
        out(f"warning: {int(np.sum(~np.isfinite(image)))} non-finite values in the image")
    write_exr(output, image)
    png = os.path.splitext(output)[0] + ".png"
    write_png(png, image, exposure)
    name = integrator_spec or type(integrator).__name__
    out(f"rendered {os.path.basename(scene_path)} with {name} at {w}x{h}, {spp} spp "
        f"in {seconds:.2f} s → {output}, {png}")
    if stats:
        out("stats: " + json.dumps(stats, default=str))
    result = {"seconds": seconds, "image": image, "stats": stats, "exr": output, "png": png}
    if reference:
        from .evaluation.metrics import all_metrics
        from .evaluation.reference import reference_image

        ref = reference_image(scene_path, params, spp=ref_spp or _ref_spp_default(), verbose=True)
        m = all_metrics(image, ref)
        out(f"error against path reference: relMSE {m['relmse']:.3e}  MSE {m['mse']:.3e}  "
            f"FLIP {m['flip']:.4f}")
        result.update(m)
    return result


def _ref_spp_default():
    from .evaluation.reference import DEFAULT_REFERENCE_SPP

    return DEFAULT_REFERENCE_SPP


def compare_command(args, out=print):
    _setup(args.variant)
    from .evaluation import harness
    from .scenefile import SceneFileError, parse_defines

    if not os.path.isfile(args.scene):
        raise SceneFileError(f"scene file not found: {args.scene}")
    if args.budget <= 0:
        raise SystemExit("error: --budget must be > 0 seconds")
    params = parse_defines(args.defines)
    specs = [s.strip() for s in args.integrators.split(",") if s.strip()]
    if not specs:
        raise SystemExit("error: --integrators is empty")
    if not any(s.split(":")[0] == "path" for s in specs):
        specs.insert(0, "path")  # the baseline is always measured in the same run
    out(f"compare {args.scene} {params} budget {args.budget} s per integrator")
    curves = harness.run_compare(args.scene, specs, args.budget, params,
                                 ref_spp=_ref_spp(args), seed=args.seed, log=out)
    out("")
    out(harness.format_table(curves))
    stem = os.path.splitext(os.path.basename(args.scene))[0]
    png = os.path.join(args.output_dir, f"{stem}.png")
    js = os.path.join(args.output_dir, f"{stem}.json")
    harness.write_plot(curves, png, title=f"{stem} {params}")
    harness.write_json(curves, js, meta={"scene": args.scene, "params": params,
                                         "budget": args.budget, "ref_spp": _ref_spp(args)})
    out(f"wrote {png} and {js}")
    return curves


def main(argv=None):
    args = build_parser().parse_args(argv)
    from .scenefile import SceneFileError

    try:
        if args.command == "render":
            render_command(args.scene, args.output, args.integrator, args.spp, args.defines,
                           args.seed, args.reference, args.ref_spp, args.exposure, args.variant)
        elif args.command == "compare":
            compare_command(args)
        elif args.command == "demo":
            render_command(DEMO_SCENE, args.output, args.integrator, args.spp, ["res=64"],
                           reference=True, ref_spp=1024)
    except SceneFileError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0
