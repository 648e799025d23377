"""Command line: ``python -m mi_twopass render | compare | check | bench | demo``.

    python -m mi_twopass render SCENE.xml -o out.exr [--integrator T] [-D key=value] [--spp N]
                                [--variant V] [--seed S] [--reference]
    python -m mi_twopass compare SCENE.xml --integrators path,radiosity_gather --budget 10
                                 [--repeats N] [--repeat-below S]
    python -m mi_twopass check SCENE.xml [--integrators a,b] [--spp 64] [--res PX] [--renders 2]
                               [--ref-spp N] [-D key=value] [--json PATH]
    python -m mi_twopass bench [SCENE.xml ...] [--corpus] [--integrators a,b] [--budget S]
                               [--res PX] [-D key=value] [--ref-spp N] [-o benchmarks]
                               [--repeats N] [--repeat-below S]
    python -m mi_twopass bench --sweep [64,128,...] [SCENE.xml ...] [--integrators a,b]
                               [--budget S] [--ref-spp N] [-o benchmarks]
    python -m mi_twopass bench --cold [SCENE.xml] [--integrators a,b] [--res PX] [--spp N]
    python -m mi_twopass bench --prepass [SCENE.xml] [--integrators a,b] [--sizes 64,...]
                               [--triangles N,...] [--emitters N,...] [--no-full-hd]
                               [--timeout S] [--quick]
    python -m mi_twopass demo

A mistake (a missing or malformed scene, an unknown integrator or parameter, a bad option)
prints one line ``error: ...`` and exits with status 2 (``MI_TWOPASS_TRACEBACK=1`` shows the
traceback instead).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time

#: the suite's best integrator for the demo scene (lower relMSE than ``path`` at equal spp and,
#: past the prepass, at equal time: see README "Results")
DEMO_INTEGRATOR = "radiosity_gather"
DEMO_SCENE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                          "scenes_xml", "cornell_box.xml")
#: lanes (pixels × spp) per render pass of ``render``, to bound memory
LANES_PER_PASS = 1 << 22
#: seed step between passes (the samplers' seed; a mi_twopass prepass keeps the render's seed)
PASS_SEED_STRIDE = 7919


class CLIError(Exception):
    """A mistake in the command line or its inputs: printed as one ``error:`` line."""


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
    r.add_argument("-o", "--output", required=True,
                   help="output .exr (the tone-mapped .png is written beside it)")
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
    _add_repeat_args(c)

    k = sub.add_parser("check", help="each integrator against the path reference: mean ratio "
                                     "and 8x8-block relMSE, OUT of bounds marked")
    _add_scene_args(k)
    k.add_argument("--integrators", default=None,
                   help="comma-separated integrator specs NAME[:key=value...] (default: "
                        "path,radiosity_gather,spike_gather,rex,radiance_cache; path shows "
                        "the noise at this spp)")
    k.add_argument("--spp", type=int, default=None, help="samples per pixel (default 64)")
    k.add_argument("--res", type=int, default=None, metavar="PX",
                   help="the film's longer side in pixels, aspect ratio kept (for scenes "
                        "without a $res parameter)")
    k.add_argument("--ref-spp", type=int, default=None, help="reference spp (default 1024)")
    k.add_argument("--renders", type=int, default=1, choices=(1, 2),
                   help="renders per integrator (default 1); 2: other samples, the same "
                        "prepass, and the part of the block relMSE that their samples' noise "
                        "does not explain (the bias part) decides OUT")
    k.add_argument("--json", default=None, metavar="PATH", help="also write the report as JSON")

    b = sub.add_parser(
        "bench", help="speed-vs-error curves of every integrator on every scene, as one "
                      "report (results.md, plots, image strips, bench.json)",
        description="Run the speed-vs-error harness over scenes x integrators and write "
                    "results.md, bench.json, <scene>.json, <scene>.png and <scene>_images.png "
                    "into the output folder (mi_twopass/evaluation/bench.py). Run time: each "
                    "(scene, integrator) at most its budget + about 4 s (warm-up, metrics), "
                    "plus the references when not cached (about 30 s a scene at 128 px, "
                    "4096 spp, on 2 cores); the default run is 7 scenes x 6 integrators "
                    "x (25 + 4) s + 7 x 30 s = 1428 s, about 24 min.")
    b.add_argument("scenes", nargs="*", metavar="SCENE.xml",
                   help="scenes to run (default: every scenes_xml/*.xml)")
    b.add_argument("--corpus", action="store_true",
                   help="also run every scenes_xml/*.xml when scenes are given")
    b.add_argument("--integrators", default=None,
                   help="comma-separated integrator specs NAME[:key=value...] (default: path "
                        "and every integrator of the suite; path is always added: the baseline)")
    b.add_argument("--budget", type=float, default=None, metavar="SECONDS",
                   help="seconds per integrator per scene (default 25)")
    b.add_argument("--res", type=int, default=None, metavar="PX",
                   help="film size: -D res=PX where the scene has $res (a -D res wins), else "
                        "the film's longer side (default 128)")
    b.add_argument("-D", dest="defines", action="append", default=[], metavar="KEY=VALUE",
                   help="scene parameter ($KEY in the XML), for every scene")
    b.add_argument("--ref-spp", type=int, default=None, help="reference spp (default 4096)")
    b.add_argument("-o", "--output-dir", default=None, help="output folder (default benchmarks/)")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--variant", default=None, help="Mitsuba variant (default llvm_ad_rgb)")
    _add_repeat_args(b)
    b.add_argument(
        "--sweep", nargs="?", const="64,128,256,512,1024", default=None, metavar="SIZES",
        help="resolution sweep instead (mi_twopass/evaluation/sweep.py): the harness on each "
             "scene at each film size (comma-separated, default 64,128,256,512,1024); writes "
             "sweep.md, sweep.png (speed-up over path against pixels) and sweep.json. Default "
             "scenes many_lights, caustic, window_interior, each with path, its home "
             "integrator (spike_gather, rex, radiance_cache) and twopass. --budget (default "
             "10) and --ref-spp (default 2048) are given at 128 px and scaled by side / 128 "
             "(budget) and 128 / side (reference spp). Default run on 2 cores: budgets "
             "9 x 10 s x (0.5+1+2+4+8) = 1395 s, warm-ups and metrics (FLIP per point, "
             "about 0.07 s per 128x128 of image) 9 x 77 s = 690 s, references "
             "3 x 15 s x 15.5 = 698 s: about 2783 s, 46 min")
    b.add_argument(
        "--cold", action="store_true",
        help="cold start instead (mi_twopass/evaluation/cold_start.py): per integrator (path "
             "and the suite, or --integrators) the first render in a fresh Python process "
             "with an empty Dr.Jit kernel cache, beside the same with the cache filled (run "
             "twice, the second reported), and the kernels compiled; one scene (default "
             "scenes_xml/cornell_box.xml), --res (default 128), --spp (default 16); writes "
             "cold.md and cold.json. Default run: 6 integrators x 3 processes, about "
             "6 x 10 s = 1 min (measured 44 s on 2 cores, rex's slow renders 31 s of it)")
    b.add_argument("--spp", type=int, default=None,
                   help="with --cold: samples per pixel of the measured render (default 16)")
    _add_prepass_args(b)

    d = sub.add_parser("demo", help="render the demo scene and print time and relMSE")
    d.add_argument("--integrator", default=DEMO_INTEGRATOR)
    d.add_argument("--spp", type=int, default=64)
    d.add_argument("-o", "--output", default="out/demo.exr")
    return parser


def _add_repeat_args(p):
    """``--repeats`` and ``--repeat-below`` of the harness's curves (``compare``, ``bench``;
    :func:`mi_twopass.evaluation.harness.timed_point`)."""
    p.add_argument("--repeats", type=int, default=None, metavar="N",
                   help="render a point that took less than --repeat-below seconds N times "
                        "in all (fresh integrators, the same seed) and keep the run of the "
                        "median time, its image with it (default 3; 1: every point once)")
    p.add_argument("--repeat-below", type=float, default=None, metavar="SECONDS",
                   help="points faster than this are repeated (default 1.0)")


def _repeat_options(args) -> dict:
    """``{repeats, repeat_below}`` of the command line, defaults filled; a value ≤ 0 is an
    error."""
    from .evaluation import harness

    for option, value in (("--repeats", args.repeats), ("--repeat-below", args.repeat_below)):
        if value is not None and value <= 0:
            raise CLIError(f"{option} {value}: must be > 0")
    return {"repeats": harness.DEFAULT_REPEATS if args.repeats is None else args.repeats,
            "repeat_below": harness.REPEAT_BELOW_SECONDS if args.repeat_below is None
            else args.repeat_below}


def _add_prepass_args(b):
    """``bench --prepass`` and its options (mi_twopass/evaluation/prepass_scaling.py)."""
    from .evaluation import prepass_scaling as ps

    def csv(values):
        return ",".join(map(str, values))

    b.add_argument(
        "--prepass", action="store_true",
        help="prepass scaling instead (mi_twopass/evaluation/prepass_scaling.py): per "
             "integrator (the suite, or --integrators; path renders 32 spp as the reference "
             "line) the prepass's seconds and peak memory, each in a fresh process beside a "
             "process that only loads the scene, against the film size (one scene, default "
             "scenes_xml/cornell_box.xml, also --scene), the triangles of a sphere mesh and "
             "the number of small area lights in the Cornell box (128 px), and at 1920x1080 "
             "(the 2 GB target); writes prepass_scaling.md, .json and .png. " + ps.estimate_text())
    b.add_argument("--scene", dest="prepass_scene", default=None, metavar="SCENE.xml",
                   help="with --prepass: the scene of the film-size and full-HD studies")
    b.add_argument("--sizes", default=None, metavar="PX,...",
                   help=f"with --prepass: film sizes (longer side; default {csv(ps.DEFAULT_SIZES)}"
                        f", --quick {csv(ps.QUICK_SIZES)})")
    b.add_argument("--triangles", default=None, metavar="N,...",
                   help="with --prepass: about this many triangles in the sphere mesh (default "
                        f"{csv(ps.DEFAULT_TRIANGLES)}, --quick {csv(ps.QUICK_TRIANGLES)})")
    b.add_argument("--emitters", default=None, metavar="N,...",
                   help="with --prepass: numbers of area lights (default "
                        f"{csv(ps.DEFAULT_EMITTERS)}, --quick {csv(ps.QUICK_EMITTERS)})")
    b.add_argument("--full-hd", action=argparse.BooleanOptionalAction, default=None,
                   help="with --prepass: also measure at 1920x1080 (default on, --quick "
                        "too)")
    b.add_argument("--timeout", type=float, default=None, metavar="SECONDS",
                   help="with --prepass: seconds a measurement may take before it is stopped "
                        f"and recorded as timeout (default {ps.DEFAULT_TIMEOUT:g})")
    b.add_argument("--quick", action="store_true",
                   help="with --prepass: fewer points (" + ps.estimate_text(quick=True) + ")")


def _setup(variant):
    import mitsuba as mi

    import mi_twopass  # noqa: F401  (libLLVM, default variant, plugins)

    if variant:
        if variant not in mi.variants():
            raise CLIError(f"--variant {variant}: unknown; available: {', '.join(mi.variants())}")
        mi.set_variant(variant)
    return mi


def _ref_spp(args):
    from .evaluation.reference import DEFAULT_REFERENCE_SPP

    return args.ref_spp or DEFAULT_REFERENCE_SPP


def make_integrator(spec: str, option: str = "--integrator"):
    """:func:`~mi_twopass.evaluation.harness.make_integrator` with one-line errors
    (:class:`CLIError`) for an unknown name or a parameter the integrator refuses."""
    from .evaluation.harness import make_integrator as _make
    from .integrators import PLUGINS
    from .scenefile import mitsuba_error_message

    try:
        return _make(spec)
    except (RuntimeError, ValueError) as e:
        msg = mitsuba_error_message(e)
        missing = re.search(r'Plugin "([^"]+)" not found', msg)
        if missing:
            msg = (f"no integrator named {missing.group(1)!r} (this suite's: "
                   f"{', '.join(sorted(PLUGINS))}; or one of Mitsuba's, such as path)")
        raise CLIError(f"{option} {spec}: {msg}") from e


def _check_output(output) -> str:
    """The PNG path for EXR ``output``, after checking that ``output`` ends in .exr and that
    its folder exists or can be made (before anything is rendered)."""
    stem, ext = os.path.splitext(output)
    if ext.lower() != ".exr":
        raise CLIError(f"-o {output}: the output must be an .exr file (the tone-mapped .png "
                       "is written beside it, with the same name)")
    if os.path.isdir(output):
        raise CLIError(f"-o {output}: is a folder")
    _make_folder(output, "-o")
    return stem + ".png"


def _make_folder(path, option) -> None:
    """Create the folder of output ``path`` (a :class:`CLIError` naming the regular file in the
    way, or the OS's reason)."""
    folder = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as e:
        part = folder
        while part and not os.path.exists(part) and os.path.dirname(part) != part:
            part = os.path.dirname(part)
        if os.path.exists(part) and not os.path.isdir(part):
            raise CLIError(f"{option} {path}: {part} is a file, not a folder") from e
        raise CLIError(f"{option} {path}: cannot create the folder {folder}: "
                       f"{e.strerror or e}") from e


def pass_sizes(spp: int, pixels: int, lanes: int | None = None) -> list:
    """spp of each render pass so that a pass traces at most ``lanes`` (default
    :data:`LANES_PER_PASS`) pixel samples; they add up to ``spp``."""
    lanes = LANES_PER_PASS if lanes is None else lanes
    per_pass = max(1, min(spp, lanes // max(1, pixels)))
    return [min(per_pass, spp - done) for done in range(0, spp, per_pass)]


def merge_pass_stats(total: dict, stats: dict, structural) -> dict:
    """Add one pass's ``stats`` into ``total``: per-render counts and seconds add up; the
    keys in ``structural`` (the prepass's structure: patch counts, bytes, ...) and
    non-numbers keep the first pass's value."""
    for key, v in stats.items():
        if key in structural or isinstance(v, bool) or not isinstance(v, (int, float)):
            total.setdefault(key, v)
        else:
            total[key] = total.get(key, 0) + v
    return total


def render_command(scene_path, output, integrator_spec=None, spp=0, defines=(), seed=0,
                   reference=False, ref_spp=None, exposure=0.0, variant=None, out=print):
    """Render, write EXR + PNG, print time, stats and (optionally) error. Returns a dict with
    the image, seconds, summed stats, ``passes`` and ``prepass_builds`` (passes that ran a
    prepass: 1 for a mi_twopass integrator, whatever the number of passes)."""
    mi = _setup(variant)
    import drjit as dr
    import numpy as np

    from .evaluation.check import refusal_of
    from .evaluation.images import write_exr, write_png
    from .integrators.base import TwoPassIntegrator
    from .progress import progress
    from .scenefile import load_scene, parse_defines

    if spp < 0:
        raise CLIError(f"--spp {spp}: must be >= 1 (or 0 for the scene's own sample count)")
    png = _check_output(output)
    params = parse_defines(defines)
    scene = load_scene(scene_path, **params)
    if not len(scene.sensors()):
        raise CLIError(f"{scene_path}: the scene has no sensor")
    sensor = scene.sensors()[0]
    spp = spp or int(sensor.sampler().sample_count())
    integrator = make_integrator(integrator_spec) if integrator_spec else scene.integrator()
    two_pass = isinstance(integrator, TwoPassIntegrator)
    if hasattr(integrator, "planned_spp"):  # twopass chooses for the whole render, not a pass
        integrator.planned_spp = spp
    w, h = (int(v) for v in sensor.film().crop_size())
    sizes = pass_sizes(spp, w * h)
    t0 = time.perf_counter()
    acc = np.zeros((h, w, 3))
    stats = {}
    prepass_builds = 0
    name = integrator_spec or type(integrator).__name__
    with progress(total=spp, desc="render", unit="spp") as bar:
        for k, n in enumerate(sizes):
            # a mi_twopass integrator keeps the render's seed (hence its prepass) and offsets
            # its samplers; any other integrator gets the pass's seed
            if two_pass:
                integrator.sample_seed_offset = PASS_SEED_STRIDE * k
            try:
                img = mi.render(scene, integrator=integrator, spp=n,
                                seed=seed if two_pass else seed + PASS_SEED_STRIDE * k)
            except (ValueError, NotImplementedError, RuntimeError) as e:
                cause = refusal_of(e)
                if cause is None:
                    raise
                raise CLIError(f"{name} refused {scene_path}: {cause}") from e
            finally:
                if two_pass:
                    integrator.sample_seed_offset = 0
            acc += np.asarray(img, dtype=np.float64)[..., :3] * n
            dr.sync_thread()
            s = dict(getattr(integrator, "stats", {}) or {})
            prepass_builds += int(s.get("prepass_seconds", 0.0) > 0.0)
            merge_pass_stats(stats, s, getattr(integrator, "structure_stat_keys", ()))
            bar.update(n)
    image = (acc / spp).astype(np.float32)
    seconds = time.perf_counter() - t0
    if not np.all(np.isfinite(image)):
        out(f"warning: {int(np.sum(~np.isfinite(image)))} non-finite values in the image")
    write_exr(output, image)
    write_png(png, image, exposure)
    passes = f" in {len(sizes)} passes" if len(sizes) > 1 else ""
    out(f"rendered {os.path.basename(scene_path)} with {name} at {w}x{h}, {spp} spp{passes} "
        f"in {seconds:.2f} s → {output}, {png}")
    if stats:
        out("stats: " + json.dumps(stats, default=str))
    result = {"seconds": seconds, "image": image, "stats": stats, "exr": output, "png": png,
              "passes": len(sizes), "prepass_builds": prepass_builds}
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


def _specs(text, option) -> list:
    """Comma-separated integrator specs, each checked to make an integrator."""
    specs = [s.strip() for s in (text or "").split(",") if s.strip()]
    if not specs:
        raise CLIError(f"{option} is empty")
    for spec in specs:
        make_integrator(spec, option)
    return specs


def compare_command(args, out=print):
    _setup(args.variant)
    from .evaluation import harness
    from .scenefile import SceneFileError, parse_defines

    if not os.path.isfile(args.scene):
        raise SceneFileError(f"scene file not found: {args.scene}")
    if args.budget <= 0:
        raise CLIError(f"--budget {args.budget}: must be > 0 seconds")
    params = parse_defines(args.defines)
    specs = _specs(args.integrators, "--integrators")
    if not any(s.split(":")[0] == "path" for s in specs):
        specs.insert(0, "path")  # the baseline is always measured in the same run
    repeat = _repeat_options(args)
    out(f"compare {args.scene} {params} budget {args.budget} s per integrator")
    curves = harness.run_compare(args.scene, specs, args.budget, params,
                                 ref_spp=_ref_spp(args), seed=args.seed, log=out, **repeat)
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


def check_command(args, out=print):
    """``check``: the table of :mod:`mi_twopass.evaluation.check` (exit status 0 whatever
    the rows say: it is a report)."""
    _setup(args.variant)
    from .evaluation import check
    from .scenefile import SceneFileError, parse_defines

    if not os.path.isfile(args.scene):
        raise SceneFileError(f"scene file not found: {args.scene}")
    spp = check.DEFAULT_SPP if args.spp is None else args.spp
    ref_spp = check.DEFAULT_REF_SPP if args.ref_spp is None else args.ref_spp
    for option, value in (("--spp", spp), ("--ref-spp", ref_spp), ("--res", args.res)):
        if value is not None and value < 1:
            raise CLIError(f"{option} {value}: must be >= 1")
    if args.json:
        _make_folder(args.json, "--json")
    params = parse_defines(args.defines)
    specs = _specs(args.integrators or ",".join(check.DEFAULT_INTEGRATORS), "--integrators")
    result = check.run_check(args.scene, specs, spp=spp, film_res=args.res, ref_spp=ref_spp,
                             params=params, seed=args.seed, renders=args.renders)
    out(check.format_table(result))
    if args.json:
        check.write_json(result, args.json)
        out(f"wrote {args.json}")
    return result


def _bench_scenes(args, default) -> list:
    """The scenes of a ``bench`` command: those given (``default`` when none), plus the corpus
    with ``--corpus``, each once, each checked to exist and parse."""
    from .evaluation import bench
    from .scenefile import SceneFileError

    scenes = list(args.scenes) or list(default)
    if args.corpus:
        scenes += bench.corpus_scenes()
    seen, unique = set(), []
    for path in scenes:
        if os.path.abspath(path) not in seen:
            seen.add(os.path.abspath(path))
            unique.append(path)
    if not unique:
        raise CLIError(f"no scenes: none given and none in {bench.CORPUS_DIR}")
    for path in unique:
        if not os.path.isfile(path):
            raise SceneFileError(f"scene file not found: {path}")
        bench.has_res_parameter(path)  # malformed XML: an error now, not after an hour
    return unique


def bench_command(args, out=print):
    """``bench``: check the command line, then :func:`mi_twopass.evaluation.bench.run_bench`
    (or, with ``--sweep`` / ``--cold``, :func:`bench_sweep_command` /
    :func:`bench_cold_command`)."""
    _setup(args.variant)
    from .evaluation import bench
    from .scenefile import parse_defines

    if args.prepass:
        return bench_prepass_command(args, out)
    _no_prepass_options(args)
    if args.sweep is not None and args.cold:
        raise CLIError("--sweep and --cold: choose one")
    for option, value in (("--repeats", args.repeats), ("--repeat-below", args.repeat_below)):
        if value is not None and (args.sweep is not None or args.cold):
            raise CLIError(f"{option}: only for the bench's curves (not with --sweep or --cold)")
    if args.spp is not None and not args.cold:
        raise CLIError(f"--spp {args.spp}: only with --cold (the harness doubles spp itself)")
    if args.sweep is not None:
        return bench_sweep_command(args, out)
    if args.cold:
        return bench_cold_command(args, out)
    budget = bench.DEFAULT_BUDGET if args.budget is None else args.budget
    res = bench.DEFAULT_RES if args.res is None else args.res
    out_dir = args.output_dir or bench.DEFAULT_OUTPUT_DIR
    if budget <= 0:
        raise CLIError(f"--budget {args.budget}: must be > 0 seconds")
    for option, value in (("--res", res), ("--ref-spp", args.ref_spp)):
        if value is not None and value < 1:
            raise CLIError(f"{option} {value}: must be >= 1")
    unique = _bench_scenes(args, bench.corpus_scenes())
    params = parse_defines(args.defines)
    specs = _specs(args.integrators or ",".join(bench.suite_integrators()), "--integrators")
    if not any(s.split(":")[0] == "path" for s in specs):
        specs.insert(0, "path")  # the baseline is always measured in the same run
    repeat = _repeat_options(args)
    _make_folder(os.path.join(out_dir, "results.md"), "-o")
    return bench.run_bench(unique, specs, budget=budget, res=res, params=params,
                           ref_spp=_ref_spp(args), seed=args.seed, out_dir=out_dir,
                           argv=getattr(args, "argv", ()), log=out, **repeat)


def bench_sweep_command(args, out=print):
    """``bench --sweep``: check the options, then
    :func:`mi_twopass.evaluation.sweep.run_sweep`."""
    from .evaluation import bench, sweep
    from .scenefile import parse_defines

    try:
        sizes = sweep.parse_sizes(args.sweep)
    except ValueError as e:
        raise CLIError(f"--sweep {args.sweep}: {e}") from e
    if args.res is not None:
        raise CLIError(f"--res {args.res}: not with --sweep (it sets the film sizes)")
    budget = sweep.DEFAULT_BUDGET if args.budget is None else args.budget
    ref_spp = sweep.DEFAULT_REF_SPP if args.ref_spp is None else args.ref_spp
    if budget <= 0:
        raise CLIError(f"--budget {args.budget}: must be > 0 seconds")
    if ref_spp < 1:
        raise CLIError(f"--ref-spp {ref_spp}: must be >= 1")
    params = parse_defines(args.defines)
    if "res" in params:
        raise CLIError("-D res: not with --sweep (it sets the film sizes)")
    scenes = _bench_scenes(args, sweep.DEFAULT_SCENES)
    specs = None
    if args.integrators:
        specs = _specs(args.integrators, "--integrators")
        if not any(s.split(":")[0] == "path" for s in specs):
            specs.insert(0, "path")  # the baseline is always measured in the same run
    out_dir = args.output_dir or bench.DEFAULT_OUTPUT_DIR
    _make_folder(os.path.join(out_dir, "sweep.md"), "-o")
    return sweep.run_sweep(scenes, sizes, specs, budget=budget, ref_spp=ref_spp, params=params,
                           seed=args.seed, out_dir=out_dir, argv=getattr(args, "argv", ()),
                           log=out)


def bench_cold_command(args, out=print):
    """``bench --cold``: check the options, then
    :func:`mi_twopass.evaluation.cold_start.run_cold`."""
    from .evaluation import bench, cold_start
    from .scenefile import parse_defines

    for option, value in (("--budget", args.budget), ("--ref-spp", args.ref_spp)):
        if value is not None:
            raise CLIError(f"{option} {value}: not with --cold (it renders once, no reference)")
    if args.corpus:
        raise CLIError("--corpus: not with --cold (it measures one scene)")
    if len(args.scenes) > 1:
        raise CLIError(f"--cold measures one scene; {len(args.scenes)} given")
    res = cold_start.DEFAULT_RES if args.res is None else args.res
    spp = cold_start.DEFAULT_SPP if args.spp is None else args.spp
    for option, value in (("--res", res), ("--spp", spp)):
        if value < 1:
            raise CLIError(f"{option} {value}: must be >= 1")
    scene = _bench_scenes(args, [cold_start.DEFAULT_SCENE])[0]
    params = parse_defines(args.defines)
    specs = _specs(args.integrators or ",".join(bench.suite_integrators()), "--integrators")
    if not any(s.split(":")[0] == "path" for s in specs):
        specs.insert(0, "path")
    out_dir = args.output_dir or bench.DEFAULT_OUTPUT_DIR
    _make_folder(os.path.join(out_dir, "cold.md"), "-o")
    return cold_start.run_cold(scene, specs, res=res, spp=spp, params=params, seed=args.seed,
                               out_dir=out_dir, variant=args.variant,
                               argv=getattr(args, "argv", ()), log=out)


#: options only ``bench --prepass`` reads, with their argparse dest
PREPASS_OPTIONS = (("--scene", "prepass_scene"), ("--sizes", "sizes"),
                   ("--triangles", "triangles"), ("--emitters", "emitters"),
                   ("--full-hd / --no-full-hd", "full_hd"), ("--timeout", "timeout"),
                   ("--quick", "quick"))


def _no_prepass_options(args):
    for option, dest in PREPASS_OPTIONS:
        value = getattr(args, dest, None)
        if value is not None and not (dest == "quick" and value is False):
            raise CLIError(f"{option}: only with --prepass")


def bench_prepass_command(args, out=print):
    """``bench --prepass``: check the options, then
    :func:`mi_twopass.evaluation.prepass_scaling.run_prepass_scaling`."""
    from .evaluation import bench
    from .evaluation import prepass_scaling as ps
    from .scenefile import parse_defines

    if args.sweep is not None or args.cold:
        raise CLIError(f"--prepass and {'--sweep' if args.sweep is not None else '--cold'}: "
                       "choose one")
    for option, value in (("--budget", args.budget), ("--ref-spp", args.ref_spp),
                          ("--res", args.res), ("--spp", args.spp)):
        if value is not None:
            raise CLIError(f"{option} {value}: not with --prepass (see --sizes; path renders "
                           f"{ps.PATH_SPP} spp, twopass chooses for {ps.TWOPASS_SPP})")
    if args.corpus:
        raise CLIError("--corpus: not with --prepass (it measures one scene)")
    scenes = list(args.scenes) + ([args.prepass_scene] if args.prepass_scene else [])
    if len(scenes) > 1:
        raise CLIError(f"--prepass measures one scene; {len(scenes)} given")
    lists = {}
    for option, value, default, quick in (
            ("--sizes", args.sizes, ps.DEFAULT_SIZES, ps.QUICK_SIZES),
            ("--triangles", args.triangles, ps.DEFAULT_TRIANGLES, ps.QUICK_TRIANGLES),
            ("--emitters", args.emitters, ps.DEFAULT_EMITTERS, ps.QUICK_EMITTERS)):
        if value is None:
            lists[option] = list(quick if args.quick else default)
            continue
        try:
            lists[option] = ps.parse_counts(value, option[2:])
        except ValueError as e:
            raise CLIError(f"{option} {value}: {e}") from e
    timeout = ps.DEFAULT_TIMEOUT if args.timeout is None else args.timeout
    if not timeout > 0:
        raise CLIError(f"--timeout {args.timeout}: must be > 0 seconds")
    full_hd = True if args.full_hd is None else args.full_hd
    args.scenes = scenes
    scene = _bench_scenes(args, [ps.DEFAULT_SCENE])[0]
    params = parse_defines(args.defines)
    specs = _specs(args.integrators or ",".join(bench.suite_integrators()), "--integrators")
    if not any(s.split(":")[0] == "path" for s in specs):
        specs.insert(0, "path")  # the reference line
    out_dir = args.output_dir or bench.DEFAULT_OUTPUT_DIR
    _make_folder(os.path.join(out_dir, "prepass_scaling.md"), "-o")
    return ps.run_prepass_scaling(scene, specs, sizes=lists["--sizes"],
                                  triangles=lists["--triangles"], emitters=lists["--emitters"],
                                  full_hd=full_hd, timeout=timeout, params=params,
                                  seed=args.seed, out_dir=out_dir, variant=args.variant,
                                  argv=getattr(args, "argv", ()), log=out)


def main(argv=None):
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    from .scenefile import SceneFileError

    try:
        if args.command == "render":
            render_command(args.scene, args.output, args.integrator, args.spp, args.defines,
                           args.seed, args.reference, args.ref_spp, args.exposure, args.variant)
        elif args.command == "compare":
            compare_command(args)
        elif args.command == "check":
            check_command(args)
        elif args.command == "bench":
            bench_command(args)
        elif args.command == "demo":
            render_command(DEMO_SCENE, args.output, args.integrator, args.spp, ["res=64"],
                           reference=True, ref_spp=1024)
    except (CLIError, SceneFileError) as e:
        if os.environ.get("MI_TWOPASS_TRACEBACK"):
            raise
        print("error: " + " ".join(str(e).split()), file=sys.stderr)
        return 2
    return 0
