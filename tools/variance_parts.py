"""Where an integrator's noise comes from: its per-pixel variance split into direct and indirect
light, at render time only (one prepass, other samples), beside ``path``'s.

    .venv/bin/python tools/variance_parts.py SCENE.xml SPEC [SPEC...] [--res 128] [--spp 16]
        [--renders 8] [--emitters]

For each integrator spec (``NAME[:key=value...]``, as the bench takes them) the prepass is built
once; ``--renders`` renders of ``--spp`` samples then differ only in their samples
(``sample_seed_offset``). Printed per spec and part (``component`` = all, direct, indirect):

* **relvar**: the mean over pixels of var / (m² + 0.01), with m ``path``'s mean image over its
  own renders (the relMSE denominator of the harness, ``metrics.RELMSE_EPS``): the noise part
  of the relMSE of one ``--spp`` render;
* **seconds**: the median render time (prepass excluded);
* **efficiency**: path's relvar × seconds over the spec's (> 1: less noise per second than
  path, before the prepass and any bias).

``--emitters`` (scenes with at most 4 emitters): the same for the scene with one emitter on at
a time (the others' radiance scaled to 0 through ``mi.traverse``), to see which light the noise
comes from. Issue 13 asked where radiosity_gather's variance comes from on the office: run
``tools/variance_parts.py scenes_xml/office.xml radiosity_gather spike_gather``.
"""
import argparse
import statistics
import time

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.evaluation.harness import make_integrator, parse_integrator_spec
from mi_twopass.evaluation.metrics import RELMSE_EPS
from mi_twopass.scenefile import load_scene


def renders(scene, spec, n, spp):
    """(n images, median seconds) of one integrator: one prepass, other samples each."""
    integrator = make_integrator(spec)
    ours = hasattr(integrator, "sample_seed_offset")
    mi.render(scene, integrator=integrator, spp=spp, seed=0)  # prepass and kernels, untimed
    images, seconds = [], []
    for i in range(n):
        if ours:
            integrator.sample_seed_offset = 1000 + i
        dr.sync_thread()
        t0 = time.perf_counter()
        img = np.asarray(mi.render(scene, integrator=integrator, spp=spp,
                                   seed=0 if ours else 1000 + i))[..., :3]
        seconds.append(time.perf_counter() - t0)
        images.append(img)
    return np.stack(images), statistics.median(seconds)


def with_component(spec, component):
    name, props = parse_integrator_spec(spec)
    if component == "all":
        return spec
    if name == "path":  # Mitsuba's path has no component: direct = paths of two segments
        return "path:max_depth=2" if component == "direct" else None
    return spec + f":component={component}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("specs", nargs="+")
    ap.add_argument("--res", type=int, default=128, help="film's longer side")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--renders", type=int, default=8)
    ap.add_argument("--emitters", action="store_true")
    a = ap.parse_args()
    if a.renders < 2:
        ap.error("--renders must be >= 2 (a variance needs two)")
    scene = load_scene(a.scene, film_res=a.res)
    path_imgs, path_s = renders(scene, "path", a.renders, a.spp)
    norm = path_imgs.mean(axis=0) ** 2 + RELMSE_EPS

    def relvar(imgs):
        return float((imgs.var(axis=0, ddof=1) / norm).mean())

    v_path = relvar(path_imgs)
    print(f"{a.scene} at {a.res} px, {a.spp} spp, {a.renders} renders per row")
    print(f"{'spec':40s} {'part':9s} {'relvar':>9s} {'seconds':>8s} {'efficiency':>10s}")
    print(f"{'path':40s} {'all':9s} {v_path:9.4f} {path_s:8.3f} {1.0:10.2f}")
    for spec in a.specs:
        for part in ("all", "direct", "indirect"):
            s = with_component(spec, part)
            if s is None:
                continue
            imgs, sec = renders(scene, s, a.renders, a.spp)
            v = relvar(imgs)
            eff = v_path * path_s / (v * sec) if v > 0 else float("inf")
            print(f"{spec:40s} {part:9s} {v:9.4f} {sec:8.3f} {eff:10.2f}", flush=True)
    if not a.emitters:
        return
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.endswith("radiance.value")
            or k.endswith("irradiance.value") or k.endswith("intensity.value")]
    if not 0 < len(keys) <= 4:
        print(f"--emitters: {len(keys)} emitter values; only scenes with 1-4 are split")
        return
    values = {k: type(params[k])(params[k]) for k in keys}
    for on in keys:
        for k in keys:
            params[k] = values[k] if k == on else type(values[k])(0.0)
        params.update()
        for spec in ["path", *a.specs]:
            imgs, _ = renders(scene, spec, a.renders, a.spp)
            print(f"{spec:40s} {'only ' + on.split('.')[0]:9s} {relvar(imgs):9.4f}", flush=True)
    for k in keys:
        params[k] = values[k]
    params.update()


if __name__ == "__main__":
    main()
