"""Side-by-side images at equal time: reference | path | other integrators (README figures).

    python tools/equal_time_figure.py SCENE.xml --seconds 2 --integrators rex -D res=64 -o out.png

Each integrator renders at doubling spp (fresh integrator, prepass included, as the harness
does) and the last image whose time is within ``--seconds`` is shown, with its spp, time and
relMSE against the cached path reference.
"""
import argparse
import os

import mi_twopass  # noqa: F401
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from mi_twopass.evaluation.harness import timed_render
from mi_twopass.evaluation.images import srgb_tonemap
from mi_twopass.evaluation.metrics import relmse
from mi_twopass.evaluation.reference import reference_image
from mi_twopass.scenefile import load_scene, parse_defines


def at_time(scene, spec, seconds):
    timed_render(scene, spec, 1, 12345)  # warm-up (kernel compilation), untimed
    best, spp = None, 1
    while spp <= 1 << 16:
        img, t, _ = timed_render(scene, spec, spp, spp)
        if t > seconds and best is not None:
            break
        best = (img, t, spp)
        if t > seconds:
            break
        spp *= 2
    return best


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--integrators", default="rex")
    ap.add_argument("-D", dest="defines", action="append", default=[])
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--exposure", type=float, default=0.0)
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args()
    params = parse_defines(a.defines)
    ref = reference_image(a.scene, params, spp=a.ref_spp)
    scene = load_scene(a.scene, **params)
    panels = [("reference (path, %d spp)" % a.ref_spp, ref)]
    for spec in ["path"] + a.integrators.split(","):
        img, t, spp = at_time(scene, spec, a.seconds)
        label = f"{spec}: {spp} spp, {t:.2f} s\nrelMSE {relmse(img, ref):.2e}"
        print(label.replace("\n", "  "))
        panels.append((label, img))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.6), dpi=100)
    for ax, (label, img) in zip(axes, panels):
        ax.imshow(srgb_tonemap(img, a.exposure), interpolation="nearest")
        ax.set_title(label, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(a.output)), exist_ok=True)
    fig.savefig(a.output)
    print("wrote", a.output)


if __name__ == "__main__":
    main()
