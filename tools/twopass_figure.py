"""What ``twopass`` chose on a scene, as a picture: path and twopass at equal time, and the two
debug views of the chosen composition (which structure serves the direct and the indirect
light at each pixel's first non-delta vertex).

    python tools/twopass_figure.py scenes_xml/mixed_room.xml --spp 256 -D res=256 \
        -o docs/results/mixed_room_twopass.png

Prints the choice, its reason and both renders' seconds and relMSE against a path reference
(cached, ``--ref-spp``).
"""
from __future__ import annotations

import argparse
import time

import drjit as dr
import mitsuba as mi
import numpy as np
from PIL import Image, ImageDraw

import mi_twopass  # noqa: F401  (variant, plugins)
from mi_twopass.evaluation.images import srgb_tonemap
from mi_twopass.evaluation.metrics import relmse
from mi_twopass.evaluation.reference import reference_image
from mi_twopass.scenefile import load_scene, parse_defines


def timed(scene, integrator, spp, seed=0):
    t0 = time.perf_counter()
    img = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    dr.sync_thread()
    return np.asarray(img)[..., :3], time.perf_counter() - t0


def panel(image, label, tonemap=True):
    rgb = srgb_tonemap(image) if tonemap else (np.clip(image, 0, 1) * 255).astype(np.uint8)
    im = Image.fromarray(rgb)
    ImageDraw.Draw(im).text((4, 4), label, fill=(255, 255, 255))
    return im


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--ref-spp", type=int, default=8192)
    ap.add_argument("-D", dest="defines", action="append", default=[])
    ap.add_argument("-o", "--output", required=True)
    args = ap.parse_args(argv)
    params = parse_defines(args.defines)
    scene = load_scene(args.scene, **params)
    ref = np.asarray(reference_image(args.scene, params, args.ref_spp))[..., :3]

    tp = mi.load_dict({"type": "twopass"})
    img_tp, t_tp = timed(scene, tp, args.spp)
    stats = dict(tp.stats)
    # path for the same wall time (its samples per pixel scaled by the measured rate)
    img_p1, t_p1 = timed(scene, mi.load_dict({"type": "path"}), args.spp)
    spp_path = max(1, int(args.spp * t_tp / max(t_p1, 1e-9)))
    img_p, t_p = timed(scene, mi.load_dict({"type": "path"}), spp_path, seed=1)
    print(f"twopass chose {stats['twopass_choice']}")
    print(f"  why: {stats['twopass_reason']}")
    print(f"  skipped: {stats['twopass_skipped']}")
    print(f"twopass {args.spp} spp: {t_tp:.2f} s (prepass+pilot {stats['prepass_seconds']:.2f} s),"
          f" relMSE {relmse(img_tp, ref):.4g}")
    print(f"path {spp_path} spp: {t_p:.2f} s, relMSE {relmse(img_p, ref):.4g}")

    views = []
    for mode in ("direct_technique", "indirect_technique"):
        chosen = tp.structure.decision.chosen  # forced: no pilot; its prepass is reused
        dbg = mi.load_dict({"type": "twopass", "debug": mode, "direct": chosen.direct,
                            "indirect": chosen.indirect, "caustics": chosen.caustics})
        dbg._candidates = tp._candidates
        img, _ = timed(scene, dbg, args.spp)
        views.append(img)
    panels = [panel(ref, f"path {args.ref_spp} spp (reference)"),
              panel(img_p, f"path {spp_path} spp, {t_p:.1f} s"),
              panel(img_tp, f"twopass {args.spp} spp, {t_tp:.1f} s"),
              panel(views[0], "direct: orange = spike list", tonemap=False),
              panel(views[1], "indirect: blue radiosity, green cache, magenta rex",
                    tonemap=False)]
    w, h = panels[0].size
    strip = Image.new("RGB", (w * len(panels), h))
    for k, p in enumerate(panels):
        strip.paste(p, (k * w, 0))
    strip.save(args.output)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
