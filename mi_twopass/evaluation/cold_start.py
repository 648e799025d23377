"""``python -m mi_twopass bench --cold``: what the first render of a session costs.

Dr.Jit compiles every kernel the first time it meets it and keeps the machine code in an
on-disk cache (``$DRJIT_CACHE_DIR``, else ``~/.drjit``). The harness renders an untimed warm-up
before its timed points, so its times leave compilation out; a user's first render pays it.
This measures it, per integrator, on one scene:

* **cold**: the first render in a fresh Python process whose ``DRJIT_CACHE_DIR`` is a new,
  empty temporary folder: every kernel is compiled;
* **warm**: the same first render in a fresh process on the cache the cold run filled, run
  twice and the second reported (a fresh process has no in-memory cache, so warm is what
  a user's first render costs on a second day).

Each process is :data:`SNIPPET` run as ``sys.executable -c``; it reports, for the scene's
loading and for the render apart, the wall time and Dr.Jit's kernel history
(``dr.JitFlag.KernelHistory``; :func:`kernel_counts`). The render's time is
:func:`mi_twopass.evaluation.harness.timed_render`'s: a fresh integrator, its prepass, the
render and the copy to numpy after ``dr.sync_thread()``.

Kernel counts (entries of type ``dr.KernelType.JIT``; Dr.Jit 1.5 marks each with
``cache_hit``, found in the in-memory or on-disk cache, and ``cache_disk``, found on disk):
*launches* (every JIT kernel run), *unique* (distinct hashes), *compiled* (not found in either
cache: LLVM compiled it, ``backend_time`` ms) and *from disk*. A warm run can still compile a
few kernels: a kernel that differs between processes misses the cache. Most of those were
NumPy arrays mapped at an alignment that differed between processes, until session 16 handed
Dr.Jit only aligned ones (:func:`mi_twopass.host_arrays.jit`); spike_gather still compiles one
now and then (docs/results/prepass-cost-2026-11-27c).

Written into the output folder: ``cold.json`` (machine, versions, command, and per integrator
every run's numbers) and ``cold.md`` (:data:`COLUMNS`). Run time: per integrator three
processes, each Python's start and imports (about 0.5 s) and a scene load, plus the render
itself (cold: up to a second of compiling; warm: about the harness's time). The default run
(cornell_box, 128², 16 spp, path and the five of the suite) took 44 s on a 2-core AMD EPYC,
rex's three renders 31 s of it; :func:`estimate_seconds` says 6 × 10 s = 60 s.
"""
from __future__ import annotations

import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

from .runs import markdown_report, table_line

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DEFAULT_SCENE = os.path.join(ROOT, "scenes_xml", "cornell_box.xml")
#: the film's size (``-D res=PX`` where the scene has ``$res``, else its longer side)
DEFAULT_RES = 128
DEFAULT_SPP = 16
#: seconds a child process may take before it is stopped (a hung compile must not hang the run)
CHILD_TIMEOUT = 900.0
#: warm runs per integrator; the last is reported (the first may still fill the cache)
WARM_RUNS = 2
#: the line of a child's stdout that carries its result as JSON
RESULT_MARK = "MI_TWOPASS_COLD_START "
#: per integrator, for :func:`estimate_seconds`: three processes' start, imports and scene
#: load (~0.5 s each) and the three renders. Measured on the Cornell box at 128², 16 spp, on
#: a 2-core AMD EPYC: 1-4 s per integrator, rex 31 s (its renders take 9-11 s themselves),
#: 44 s for the six; 10 s an integrator rounds that up
SECONDS_PER_INTEGRATOR = 10.0
#: cold.md's columns, in order
COLUMNS = ("integrator", "cold s", "warm s", "cold / warm", "kernels compiled cold",
           "kernels total", "unique kernels", "compile ms cold", "compiled warm",
           "scene load cold / warm s")

#: what each child runs (``sys.executable -c SNIPPET CONFIG_JSON``): the clock starts before
#: any import, so ``import_seconds`` covers Python's imports of mi_twopass, Mitsuba, Dr.Jit
SNIPPET = """\
import time
_t0 = time.perf_counter()
import json, sys
import mi_twopass
from mi_twopass.evaluation.cold_start import RESULT_MARK, first_render
result = first_render(json.loads(sys.argv[1]), import_seconds=time.perf_counter() - _t0)
print(RESULT_MARK + json.dumps(result), flush=True)
"""


def kernel_counts(history) -> dict:
    """Counts from ``dr.kernel_history()`` entries (module docstring): ``launches``,
    ``unique``, ``compiled``, ``from_disk``, ``in_memory`` JIT kernels, ``backend_ms`` (LLVM's
    compile time, summed), ``codegen_ms`` (Dr.Jit's IR generation, every launch) and
    ``other_launches`` (memsets, reductions and the like, not compiled)."""
    import drjit as dr

    jit = [e for e in history if e.get("type") == dr.KernelType.JIT]
    compiled = [e for e in jit if not e.get("cache_hit")]
    return {
        "launches": len(jit),
        "unique": len({e.get("hash") for e in jit}),
        "compiled": len(compiled),
        "from_disk": sum(1 for e in jit if e.get("cache_hit") and e.get("cache_disk")),
        "in_memory": sum(1 for e in jit if e.get("cache_hit") and not e.get("cache_disk")),
        "backend_ms": float(sum(e.get("backend_time", 0.0) for e in compiled)),
        "codegen_ms": float(sum(e.get("codegen_time", 0.0) for e in jit)),
        "other_launches": len(history) - len(jit),
    }


def child_config(scene_path, spec: str, res: int, spp: int, params: dict | None = None,
                 seed: int = 0, variant: str | None = None) -> dict:
    """What a child renders: the scene (absolute path), its parameters and film size (as the
    bench sets them: :func:`mi_twopass.evaluation.bench.scene_settings`), the integrator spec,
    spp, seed and variant."""
    from .bench import scene_settings

    params, film_res = scene_settings(scene_path, res, dict(params or {}))
    return {"scene": os.path.abspath(scene_path), "params": params, "film_res": film_res,
            "spec": spec, "spp": int(spp), "seed": int(seed), "variant": variant}


def first_render(config: dict, import_seconds: float = 0.0) -> dict:
    """In the child: load the scene and render it once as ``config`` says, with Dr.Jit's
    kernel history on; returns the seconds and :func:`kernel_counts` of the load and the
    render apart, and the image's size."""
    import drjit as dr
    import mitsuba as mi

    from ..scenefile import load_scene
    from .harness import timed_render

    if config.get("variant") and mi.variant() != config["variant"]:
        mi.set_variant(config["variant"])
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    t0 = time.perf_counter()
    scene = load_scene(config["scene"], film_res=config.get("film_res"), **config["params"])
    dr.sync_thread()
    load_seconds = time.perf_counter() - t0
    load_kernels = kernel_counts(dr.kernel_history())
    image, seconds, stats = timed_render(scene, config["spec"], config["spp"], config["seed"])
    render_kernels = kernel_counts(dr.kernel_history())
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    return {"import_seconds": import_seconds, "load_seconds": load_seconds,
            "load_kernels": load_kernels, "render_seconds": seconds,
            "render_kernels": render_kernels, "size": [int(image.shape[1]), int(image.shape[0])],
            "prepass_seconds": stats.get("prepass_seconds"), "variant": mi.variant()}


def run_child(config: dict, cache_dir: str, timeout: float = CHILD_TIMEOUT) -> dict:
    """Run :data:`SNIPPET` for ``config`` in a fresh Python process (``sys.executable``) with
    ``DRJIT_CACHE_DIR=cache_dir``; returns its result plus ``process_seconds`` (the process's
    whole wall time). Raises RuntimeError with the end of its stderr if it fails."""
    env = dict(os.environ)
    env["DRJIT_CACHE_DIR"] = cache_dir
    env["PYTHONPATH"] = ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    t0 = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, "-c", SNIPPET, json.dumps(config)], env=env,
                              capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as e:
        raise RuntimeError(f"{config['spec']}: the child took more than {timeout:.0f} s") from e
    wall = time.perf_counter() - t0
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(RESULT_MARK)]
    if proc.returncode != 0 or not lines:
        tail = " ".join((proc.stderr or proc.stdout).strip().splitlines()[-3:])[-400:]
        raise RuntimeError(f"{config['spec']}: the child exited with status {proc.returncode}: "
                           f"{tail}")
    result = json.loads(lines[-1][len(RESULT_MARK):])
    result["process_seconds"] = wall
    return result


def cache_bytes(folder: str) -> int:
    """Bytes of the files in ``folder`` (Dr.Jit's kernel cache)."""
    total = 0
    for entry in os.scandir(folder):
        if entry.is_file():
            total += entry.stat().st_size
    return total


def measure_integrator(config: dict, warm_runs: int = WARM_RUNS, keep_cache: bool = False,
                       timeout: float = CHILD_TIMEOUT) -> dict:
    """Cold then ``warm_runs`` warm first renders of one integrator (module docstring), in a
    new temporary kernel cache removed afterwards (unless ``keep_cache``). Returns
    ``{"cold": result, "warm": [results], "cache_bytes", "cache_dir"}``."""
    cache_dir = tempfile.mkdtemp(prefix="mi_twopass_drjit_cache_")
    try:
        cold = run_child(config, cache_dir, timeout)
        size = cache_bytes(cache_dir)
        warm = [run_child(config, cache_dir, timeout) for _ in range(warm_runs)]
    finally:
        if not keep_cache:
            shutil.rmtree(cache_dir, ignore_errors=True)
    return {"cold": cold, "warm": warm, "cache_bytes": size, "cache_dir": cache_dir}


def table_row(spec: str, measured: dict | None, failed: str | None = None) -> dict:
    """cold.md's numbers for one integrator: the cold run and the last warm run."""
    if measured is None:
        return {"integrator": spec, "failed": failed}
    cold, warm = measured["cold"], measured["warm"][-1]
    return {"integrator": spec, "failed": None,
            "cold_seconds": cold["render_seconds"], "warm_seconds": warm["render_seconds"],
            "compiled_cold": cold["render_kernels"]["compiled"],
            "launches": cold["render_kernels"]["launches"],
            "unique": cold["render_kernels"]["unique"],
            "backend_ms_cold": cold["render_kernels"]["backend_ms"],
            "compiled_warm": warm["render_kernels"]["compiled"],
            "load_cold_seconds": cold["load_seconds"], "load_warm_seconds": warm["load_seconds"],
            "prepass_seconds_warm": warm.get("prepass_seconds"),
            "cache_bytes": measured["cache_bytes"]}


def format_row(row: dict) -> str:
    """One Markdown table line of :func:`table_row`'s dict."""
    if row["failed"]:
        cells = [f"`{row['integrator']}`", row["failed"]] + ["—"] * (len(COLUMNS) - 2)
    else:
        ratio = (row["cold_seconds"] / row["warm_seconds"]) if row["warm_seconds"] > 0 else None
        cells = [f"`{row['integrator']}`", f"{row['cold_seconds']:.3g}",
                 f"{row['warm_seconds']:.3g}", "—" if ratio is None else f"{ratio:.1f}×",
                 str(row["compiled_cold"]), str(row["launches"]), str(row["unique"]),
                 f"{row['backend_ms_cold']:.0f}", str(row["compiled_warm"]),
                 f"{row['load_cold_seconds']:.3g} / {row['load_warm_seconds']:.3g}"]
    return table_line(cells)


def format_table(rows, header: str) -> str:
    """cold.md: the header, the table and what each column means."""
    return markdown_report(header, COLUMNS, [format_row(r) for r in rows], [
        "- **cold s**: the first render (fresh integrator, prepass, render, copy to numpy) in a "
        "fresh Python process with an empty Dr.Jit kernel cache (`DRJIT_CACHE_DIR` a new "
        "folder): every kernel is compiled.",
        f"- **warm s**: the same in a fresh process on the cache the cold run filled; "
        f"{WARM_RUNS} runs, the last reported.",
        "- **kernels compiled cold**: JIT kernels of the cold render found in no cache (LLVM "
        "compiled them); **kernels total**: JIT kernel launches of the render; **unique "
        "kernels**: distinct kernel hashes among them.",
        "- **compile ms cold**: LLVM's compile time of those kernels, summed "
        "(`backend_time` of `dr.kernel_history()`).",
        "- **compiled warm**: kernels the warm render still compiled (kernels whose code "
        "differs between processes miss the cache).",
        "- **scene load**: seconds of loading the scene before the render, cold / warm "
        "(not in the render's seconds).",
    ])


def estimate_seconds(n_integrators: int, warm_runs: int = WARM_RUNS) -> float:
    """Rough wall time of a cold-start run at the defaults (128², 16 spp):
    :data:`SECONDS_PER_INTEGRATOR` per integrator for its three processes (``warm_runs`` = 2),
    scaled by the number of processes otherwise."""
    return n_integrators * SECONDS_PER_INTEGRATOR * (1 + warm_runs) / 3


def run_cold(scene_path, specs, res: int = DEFAULT_RES, spp: int = DEFAULT_SPP,
             params: dict | None = None, seed: int = 0, out_dir: str = "benchmarks",
             variant: str | None = None, argv=(), log=print,
             warm_runs: int = WARM_RUNS) -> dict:
    """Measure every integrator of ``specs`` (module docstring), write ``cold.json`` and
    ``cold.md`` into ``out_dir``, and return cold.json's content. An integrator whose child
    fails gets a row saying so and the run goes on."""
    from .bench import command_line, machine_info, machine_label, run_label, software_info

    os.makedirs(out_dir, exist_ok=True)
    started = datetime.datetime.now().astimezone()
    info = {"machine": machine_info(), "date": started.isoformat(timespec="seconds"),
            "command": command_line(argv), "python": sys.executable, **software_info(),
            "scene": os.path.abspath(scene_path), "res": res, "spp": spp,
            "defines": dict(params or {}), "seed": seed, "warm_runs": warm_runs,
            "integrators": list(specs)}
    m = info["machine"]
    log(f"cold start: {len(specs)} integrators on {os.path.basename(scene_path)}, res {res}, "
        f"{spp} spp; {1 + warm_runs} fresh processes each, about "
        f"{estimate_seconds(len(specs), warm_runs):.0f} s, on {machine_label(m)}")
    t0 = time.perf_counter()
    runs, rows = {}, []
    for k, spec in enumerate(specs, start=1):
        config = child_config(scene_path, spec, res, spp, params, seed, variant or None)
        t1 = time.perf_counter()
        try:
            measured = measure_integrator(config, warm_runs)
        except RuntimeError as e:
            why = "failed: " + " ".join(str(e).split())[:300]
            rows.append(table_row(spec, None, why))
            runs[spec] = {"config": config, "failed": why}
            log(f"[{k}/{len(specs)}] {spec:<28} {why}")
            continue
        runs[spec] = {"config": config, **measured}
        row = table_row(spec, measured)
        rows.append(row)
        log(f"[{k}/{len(specs)}] {spec:<28} cold {row['cold_seconds']:6.2f} s "
            f"({row['compiled_cold']} kernels compiled of {row['launches']}), warm "
            f"{row['warm_seconds']:6.2f} s  ({time.perf_counter() - t1:.0f} s)")
    info["wall_seconds"] = time.perf_counter() - t0
    info["runs"] = runs
    info["rows"] = rows
    with open(os.path.join(out_dir, "cold.json"), "w") as f:
        json.dump(info, f, indent=1, default=str)
    sizes = [r["cold"]["size"] for r in runs.values() if "cold" in r]
    film = f"{sizes[0][0]}×{sizes[0][1]}" if sizes else f"res {res}"
    header = (f"Cold start of {run_label(info)}: {os.path.basename(scene_path)} at {film}, "
              f"{spp} spp; "
              f"took {info['wall_seconds']:.0f} s. Command: `{info['command']}`")
    with open(os.path.join(out_dir, "cold.md"), "w") as f:
        f.write(format_table(rows, header))
    log(f"wrote {out_dir}/cold.md and cold.json ({info['wall_seconds']:.0f} s)")
    return info
