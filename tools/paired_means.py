"""Image means of K renders with fixed seeds, saved, and two such runs compared pair by pair.

    PYTHONPATH=/tmp/base .venv/bin/python tools/paired_means.py run SCENE.xml out/old.npy \
        [--spec radiance_cache] [--res 64] [--spp 128] [-k 6]
    .venv/bin/python tools/paired_means.py run SCENE.xml out/new.npy ...
    .venv/bin/python tools/paired_means.py compare out/old.npy out/new.npy

``run``: K renders of a fresh integrator each (prepass included), seeds 1000 + 17·k, and the
mean of each image (channel mean). Run it once per version of the code, e.g. the old one from
a worktree through PYTHONPATH. ``compare``: the mean and standard error of new/old − 1 over
the pairs. The same seeds give both versions the same samples where their code agrees, so a
shift far below either image's noise shows (README "Right on real scenes" for the absolute
check against ``path``: ``tools/image_means.py``).
"""
import argparse

import numpy as np


def run(a):
    import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
    import mitsuba as mi

    from mi_twopass.evaluation.harness import make_integrator
    from mi_twopass.scenefile import load_scene

    scene = load_scene(a.scene, film_res=a.res)
    means = []
    for k in range(a.k):
        img = np.asarray(mi.render(scene, integrator=make_integrator(a.spec), spp=a.spp,
                                   seed=1000 + 17 * k))
        means.append(float(img[..., :3].mean()))
    np.save(a.out, np.array(means))
    print(a.spec, np.array(means))


def compare(a):
    old, new = np.load(a.old), np.load(a.new)
    if old.shape != new.shape:
        raise SystemExit(f"{a.old} has {old.size} renders, {a.new} {new.size}")
    d = new / old - 1.0
    se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else float("nan")
    print(f"new / old − 1 = {d.mean():+.4f} ± {se:.4f} over {len(d)} pairs")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("scene")
    r.add_argument("out")
    r.add_argument("--spec", default="radiance_cache")
    r.add_argument("--res", type=int, default=64)
    r.add_argument("--spp", type=int, default=128)
    r.add_argument("-k", type=int, default=6)
    c = sub.add_parser("compare")
    c.add_argument("old")
    c.add_argument("new")
    a = ap.parse_args()
    run(a) if a.cmd == "run" else compare(a)


if __name__ == "__main__":
    main()
