"""How noisy is `path` on the sharp light of a scene? Predicted from photons, not from path.

    .venv/bin/python tools/sharp_variance.py SCENE.xml [SCENE.xml ...] [--res 256]

Prints, per scene, :func:`mi_twopass.prepass.sharp_light.measure`: the share of the image's
radiance that is sharp light (light through delta bounces only, delta emitters' included) and
path's predicted relative variance per sample on it (the model, per emitter radiance, is that
module's docstring). twopass reads the same figure where its path pilot finds caustics carry
little of path's variance (:func:`mi_twopass.compose.choose.choose`): a pilot of a few
hundred samples catches such light now and then, photons every time. Compare it with path's
relMSE × spp in the harness (``bench``, path's curve). Measures twice per scene and prints
both times: the first compiles (or loads) its kernels, the second is what the figure costs
twopass once they are cached.
"""
import argparse
import time

import drjit as dr

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.prepass import rex_textures as R
from mi_twopass.prepass.sharp_light import measure
from mi_twopass.scenefile import load_scene, scene_label


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--res", type=int, default=256, help="film's longer side in pixels")
    ap.add_argument("--seed", type=int, default=0, help="the size pass's and probe's seed")
    args = ap.parse_args()
    print("| scene | sharp share | path's relative variance on sharp light (predicted) | "
          "seconds (first, second) |")
    print("| --- | --- | --- | --- |")
    for path in args.scenes:
        scene = load_scene(path, film_res=args.res)
        seconds = []
        for _ in range(2):  # the second with the kernels the first compiled
            t0 = time.perf_counter()
            found = measure(scene, R.RexSettings(direct="shadow"), args.seed)
            dr.sync_thread()
            seconds.append(time.perf_counter() - t0)
        print(f"| {scene_label(path)} | {found.share:.4f} | {found.relative_variance:.3g} | "
              f"{seconds[0]:.2f}, {seconds[1]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
