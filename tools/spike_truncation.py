"""Truncation and bias of ``spike_gather`` settings against the path-traced reference.

    python tools/spike_truncation.py [SCENE.xml] [-D res=64] [--spp 256] [--seeds 4]
        [--ref-spp 16384] [--configs "complete=true;complete=false;..."]

For every configuration (``key=value`` pairs joined by ``:``, configurations separated by ``;``;
the empty configuration is the default) it renders ``--seeds`` independent images (a fresh
integrator, so a fresh prepass, per seed) and averages them. With the noise averaged down, what
is left of the difference to the reference is bias:

* ``bias %``: mean luminance of the averaged image over the reference's, minus one; the
  energy the estimator loses (negative) or adds, e.g. Zimmerman & Shirley §5.3's truncation
  (sources falsely excluded from a list, sources between E_low and E_high outside their
  influence region, near unlisted sources with ``complete=false``);
* ``±``: two standard errors of that mean, from the spread of the per-seed means;
* ``− first row``: the bias minus the first configuration's, with the seeds paired (the
  renders of one seed share their random numbers, so most of the noise cancels): with
  ``complete=true`` first, the truncation of the other settings;
* ``relMSE avg``: relMSE of the averaged image (residual noise / seeds + bias²);
* ``relMSE 1``: the mean relMSE of one render (what a user sees at ``--spp``);
* prepass and render seconds (means over the seeds; the first, untimed render of each
  configuration compiles kernels), explicit and implicit rays per viewing ray, spike-list
  mean length, visibility rays, and what became of the candidate (cell, source) pairs: culled
  behind every point's horizon, excluded by the point-sampled visibility (g = 0), listed.

Prints a Markdown table (README "Results") and writes it with the per-config numbers as JSON.
"""
import argparse
import json
import os
import time

import mi_twopass  # noqa: F401
import drjit as dr
import mitsuba as mi
import numpy as np

from mi_twopass.evaluation import metrics
from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.evaluation.reference import reference_image
from mi_twopass.scenefile import load_scene, parse_defines

DEFAULT_CONFIGS = "complete=true;complete=false;complete=true:defensive=0;" \
                  "visibility_max_rays=20;complete=false:visibility_max_rays=20"


def luminance(img):
    img = np.asarray(img, dtype=np.float64)[..., :3]
    return img @ np.array([0.2126, 0.7152, 0.0722])


def run_config(scene, config, spp, seeds):
    spec = "spike_gather" + (":" + config if config else "")
    mi.render(scene, integrator=make_integrator(spec), spp=1, seed=10_007)  # compile, untimed
    images, rows = [], []
    for s in range(seeds):
        integ = make_integrator(spec)
        t0 = time.perf_counter()
        img = np.array(mi.render(scene, integrator=integ, spp=spp, seed=1 + 7919 * s))
        dr.sync_thread()
        seconds = time.perf_counter() - t0
        images.append(img)
        rows.append(dict(integ.stats, seconds=seconds))
    return spec, images, rows


def summarise(spec, images, rows, ref):
    ref_lum = luminance(ref).mean()
    means = np.array([luminance(i).mean() / ref_lum - 1.0 for i in images])
    avg = np.mean(images, axis=0)
    n = len(images)
    se = float(means.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan")

    def mean_of(key):
        return float(np.mean([r.get(key, 0) for r in rows]))

    viewing = max(mean_of("viewing_rays"), 1.0)
    return dict(
        integrator=spec,
        bias_percent=100.0 * float(luminance(avg).mean() / ref_lum - 1.0),
        bias_2se_percent=200.0 * se,
        relmse_avg=float(metrics.relmse(avg, ref)),
        relmse_single=float(np.mean([metrics.relmse(i, ref) for i in images])),
        seconds=mean_of("seconds"), prepass_seconds=mean_of("prepass_seconds"),
        render_seconds=mean_of("render_seconds"),
        explicit_per_viewing=mean_of("explicit_rays") / viewing,
        implicit_per_viewing=mean_of("implicit_rays") / viewing,
        spike_list_mean=mean_of("spike_list_mean"), spike_list_max=mean_of("spike_list_max"),
        visibility_rays=mean_of("visibility_rays"),
        candidate_pairs=mean_of("candidate_pairs"),
        excluded_pairs=mean_of("visibility_excluded"), behind_horizon=mean_of("behind_horizon"),
        seeds=n, per_seed_bias=means.tolist())


def paired_difference(r, first):
    """Bias of ``r`` minus that of ``first`` (%), ± two standard errors, from the per-seed
    means: the renders of one seed share their random numbers, so most noise cancels."""
    d = np.array(r["per_seed_bias"]) - np.array(first["per_seed_bias"])
    se = d.std(ddof=1) / np.sqrt(d.size) if d.size > 1 else float("nan")
    return 100.0 * float(d.mean()), 200.0 * float(se)


def markdown(results, spp):
    head = ("| settings | bias % (±2 s.e.) | − first row, paired (%) | relMSE of mean | "
            "relMSE of one render "
            f"({spp} spp) | prepass s | render s | explicit / viewing ray | list mean | "
            "visibility rays | candidate pairs: behind horizon / excluded by rays / listed |")
    lines = [head, "|" + " --- |" * 11]
    for r in results:
        name = r["integrator"].split(":", 1)[1] if ":" in r["integrator"] else "(defaults)"
        dm, dse = paired_difference(r, results[0])
        lines.append(
            f"| {name} | {r['bias_percent']:+.2f} (±{r['bias_2se_percent']:.2f}) | "
            f"{dm:+.2f} (±{dse:.2f}) | "
            f"{r['relmse_avg']:.2e} | {r['relmse_single']:.2e} | {r['prepass_seconds']:.2f} | "
            f"{r['render_seconds']:.2f} | {r['explicit_per_viewing']:.2f} | "
            f"{r['spike_list_mean']:.1f} | {r['visibility_rays'] / 1e6:.2f} M | "
            f"{r['behind_horizon']:.0f} / {r['excluded_pairs']:.0f} / "
            f"{r['candidate_pairs'] - r['behind_horizon'] - r['excluded_pairs']:.0f} |")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", nargs="?", default="scenes_xml/many_lights.xml")
    ap.add_argument("-D", dest="defines", action="append", default=[])
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--ref-spp", type=int, default=16384)
    ap.add_argument("--configs", default=DEFAULT_CONFIGS)
    ap.add_argument("-o", "--output", default="out/results/spike_truncation.json")
    a = ap.parse_args()
    if a.seeds < 1 or a.spp < 1:
        ap.error("--seeds and --spp must be >= 1")
    params = parse_defines(a.defines or ["res=64"])
    ref = np.array(reference_image(a.scene, params, spp=a.ref_spp, verbose=True))
    scene = load_scene(a.scene, **params)
    results = []
    for config in a.configs.split(";"):
        spec, images, rows = run_config(scene, config.strip(), a.spp, a.seeds)
        results.append(summarise(spec, images, rows, ref))
        print(f"  {spec}: bias {results[-1]['bias_percent']:+.2f} %", flush=True)
    table = markdown(results, a.spp)
    print(table)
    os.makedirs(os.path.dirname(os.path.abspath(a.output)), exist_ok=True)
    with open(a.output, "w") as f:
        json.dump(dict(scene=a.scene, params=params, spp=a.spp, seeds=a.seeds,
                       ref_spp=a.ref_spp, results=results, table=table), f, indent=1)
    print(f"wrote {a.output}")


if __name__ == "__main__":
    main()
