"""Did a refactor change what the integrators compute? Render, then compare two runs.

    .venv/bin/python tools/same_images.py render before.npz [--scenes cornell_box,caustic]
    (check out the other commit)
    .venv/bin/python tools/same_images.py render after.npz
    .venv/bin/python tools/same_images.py compare before.npz after.npz

``render`` renders every integrator of the suite on each scene of ``scenes_xml/`` named (48 px,
16 spp, seed 3, a fresh integrator each) and stores the images and ray counters. ``compare``
prints, per (scene, integrator), "identical" or the largest pixel difference and both image
means, and the ray counters side by side. Two processes of the same commit can differ on scenes
whose emitters Mitsuba loads in a different order (``tools/load_order.py``; the shapes' order
no longer matters since session 30): run ``render`` twice on one commit to see which outcomes
a scene has before reading a difference as a change.
"""
import argparse

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
import mitsuba as mi
import numpy as np

from mi_twopass.scenefile import load_scene

INTEGRATORS = ("radiosity_gather", "spike_gather", "rex", "radiance_cache", "twopass")
COUNTERS = ("implicit_rays", "explicit_rays", "eye_rays")


def render(out, scenes, res, spp):
    stored = {}
    for name in scenes:
        scene = load_scene(f"scenes_xml/{name}.xml", res, spp=spp)
        for integ_name in INTEGRATORS:
            integ = mi.load_dict({"type": integ_name})
            image = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=3))
            stored[f"{name}/{integ_name}"] = image
            stored[f"{name}/{integ_name}/rays"] = np.array(
                [float(integ.stats.get(k, 0)) for k in COUNTERS])
    np.savez(out, **stored)


def compare(a_path, b_path):
    a, b = np.load(a_path), np.load(b_path)
    for key in a.files:
        if key not in b.files:
            print(f"{key}: only in {a_path}")
            continue
        x, y = a[key], b[key]
        if key.endswith("/rays"):
            print(f"{key}: " + ", ".join(f"{k} {u:.0f} / {v:.0f}"
                                         for k, u, v in zip(COUNTERS, x, y)))
        elif np.array_equal(x, y):
            print(f"{key}: identical")
        else:
            print(f"{key}: max |diff| {np.abs(x - y).max():.3g}, means {x.mean():.6f} / "
                  f"{y.mean():.6f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render")
    r.add_argument("out")
    r.add_argument("--scenes", default="cornell_box,caustic,many_lights")
    r.add_argument("--res", type=int, default=48)
    r.add_argument("--spp", type=int, default=16)
    c = sub.add_parser("compare")
    c.add_argument("a")
    c.add_argument("b")
    args = ap.parse_args()
    if args.cmd == "render":
        render(args.out, args.scenes.split(","), args.res, args.spp)
    else:
        compare(args.a, args.b)


if __name__ == "__main__":
    main()
