"""rex's automatic photon budget per scene, and what its prepass costs.

    .venv/bin/python tools/rex_budget.py SCENE.xml [SCENE.xml ...] [--res 256]
        [--direct shadow]

Builds rex's prepass (``rex_textures.build``, seed 0, the integrator's defaults) twice per
scene and prints one Markdown row each: the photons and the counts they are the larger of
(the noise model's, the resolution rule's), the image's sharp and whole-rex shares, the
predicted block relMSE, the records, and the second build's seconds (kernels compiled by the
first). Session 30 (docs/results/shape-order-sharp-light-2026-11-29) cites it.
"""
import argparse
import time

import drjit as dr

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)

from mi_twopass.prepass import rex_textures as R
from mi_twopass.scenefile import load_scene, scene_label


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--direct", default="shadow", choices=("shadow", "rex"))
    args = ap.parse_args()
    print("| scene | photons | noise need | resolution need | sharp share | whole-rex share | "
          "predicted block relMSE | records | prepass s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    settings = R.RexSettings(direct=args.direct)
    for path in args.scenes:
        scene = load_scene(path, film_res=args.res)
        for _ in range(2):
            t0 = time.perf_counter()
            pre = R.build(scene, settings, seed=0, progress=False)
            dr.sync_thread()
            seconds = time.perf_counter() - t0
        st = pre.stats
        print(f"| {scene_label(path)} | {st['photons']:,} | "
              f"{st.get('noise_photon_need', 0):,.0f} | {st.get('split_photon_need', 0):,.0f} | "
              f"{st.get('sharp_share', 0):.4f} | {st.get('whole_rex_share', 0):.4f} | "
              f"{st.get('predicted_relmse', 0):.2g} | {st['photon_records']:,} | "
              f"{seconds:.2f} |", flush=True)


if __name__ == "__main__":
    main()
