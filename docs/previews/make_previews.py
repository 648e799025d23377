"""Render a preview of every scene in scenes_xml/ with Mitsuba's ``path`` and write
``docs/previews/<name>.png`` (tone-mapped 8-bit sRGB).

Usage (from the repository root)::

    python docs/previews/make_previews.py [--res 128] [--spp-scale 1.0] [--only caustic office]

Each scene has its own sample count and exposure (in stops) below, chosen so that the whole run
takes well under three minutes on two CPU cores with the LLVM backend at res 128.
"""
import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, ROOT)

import mi_twopass  # noqa: E402,F401  (sets DRJIT_LIBLLVM_PATH, selects llvm_ad_rgb)
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

# name: (spp at res 128, exposure in stops)
SCENES = {
    "cornell_box": (1024, 0.0),
    "many_lights": (2048, 0.0),
    "caustic": (8192, 0.0),
    "window_interior": (2048, 1.5),
    "furnace": (64, -1.5),      # radiance 2 everywhere at the default albedo 0.5
    "office": (1024, 0.0),
    "mixed_room": (1024, 0.0),
}


def to_srgb8(image, exposure=0.0):
    """Linear RGB → 8-bit sRGB through mi.Bitmap (values clipped to [0, 1] before the curve)."""
    x = np.clip(np.nan_to_num(np.asarray(image, dtype=np.float32)) * 2.0**exposure, 0.0, 1.0)
    bmp = mi.Bitmap(np.ascontiguousarray(x), pixel_format=mi.Bitmap.PixelFormat.RGB)
    return bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", type=int, default=128, help="film width and height (default 128)")
    ap.add_argument("--spp-scale", type=float, default=1.0,
                    help="multiply every scene's sample count (default 1)")
    ap.add_argument("--only", nargs="*", default=None, help="render only these scenes")
    ap.add_argument("--out", default=HERE, help="output folder (default docs/previews)")
    args = ap.parse_args(argv)

    # Sample counts are set for res 128; keep the number of samples per image about constant.
    pixel_scale = (128.0 / args.res) ** 2
    os.makedirs(args.out, exist_ok=True)
    t_all = time.time()
    for name, (spp, exposure) in SCENES.items():
        if args.only and name not in args.only:
            continue
        spp = max(1, int(round(spp * args.spp_scale * min(1.0, pixel_scale))))
        path = os.path.join(ROOT, "scenes_xml", name + ".xml")
        scene = mi.load_file(path, res=args.res, spp=spp)
        t0 = time.time()
        image = np.array(mi.render(scene, spp=spp, seed=0))
        dt = time.time() - t0
        out = os.path.join(args.out, name + ".png")
        to_srgb8(image, exposure).write(out)
        print(f"{name:16s} {args.res}x{args.res} {spp:5d} spp  {dt:6.1f} s  "
              f"mean {image.mean():.4f}  finite {bool(np.isfinite(image).all())}  -> {out}")
    print(f"total {time.time() - t_all:.1f} s")


if __name__ == "__main__":
    main()
