"""Does a scene load (and render) the same way in two processes?

    .venv/bin/python tools/load_order.py scenes_xml/office.xml [--res 64] [--spp 4] [--serial]
        [--integrators path,radiosity_gather,spike_gather,radiance_cache,rex,twopass]
        [--processes 2]

Loads the scene in ``--processes`` fresh Python processes (two by default) and prints, per
process, a fingerprint of the
order of ``scene.shapes()`` (each shape's primitive count and bounding box, in order), of
``scene.emitters()`` (each one's shape's bounding box, or its class and bounds) and of each
integrator's image (same render seed, a fresh integrator), with the image's mean; then, per fingerprint, how many distinct values the processes gave
("same" for one). ``--integrators ''`` renders nothing (orders only). Mitsuba's XML loader builds shapes in parallel; ``--serial`` loads
with ``parallel=False``. docs/design.md ("Timing and randomness") cites what it found.
"""
import argparse
import json
import subprocess
import sys

CHILD = r"""
import hashlib, json, sys
import numpy as np
import mi_twopass  # noqa: F401
import mitsuba as mi
from mi_twopass.scenefile import load_scene
path, res, spp, parallel, names = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), \
    sys.argv[4] == "1", sys.argv[5].split(",")
scene = load_scene(path, film_res=res) if parallel else mi.load_file(path, parallel=False)
def digest(x):
    return hashlib.md5(repr(x).encode()).hexdigest()[:12]
def emitter_key(e):
    shape = e.get_shape() if hasattr(e, "get_shape") else None
    return str(shape.bbox()) if shape is not None else e.class_name() + str(e.bbox())
out = {"shapes": digest([(s.primitive_count(), str(s.bbox())) for s in scene.shapes()]),
       "emitters": digest([emitter_key(e) for e in scene.emitters()])}
for name in filter(None, names):
    img = np.ascontiguousarray(np.asarray(
        mi.render(scene, integrator=mi.load_dict({"type": name}), spp=spp, seed=3)))
    out[name] = [hashlib.md5(img.tobytes()).hexdigest()[:12], float(img.mean())]
print(json.dumps(out))
"""


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--serial", action="store_true", help="load with parallel=False (the "
                    "scene file's own film size)")
    ap.add_argument("--integrators", default="path",
                    help="comma-separated plugin names rendered in each process")
    ap.add_argument("--processes", type=int, default=2)
    a = ap.parse_args()
    runs = []
    for k in range(max(a.processes, 2)):
        out = subprocess.run([sys.executable, "-c", CHILD, a.scene, str(a.res), str(a.spp),
                              "0" if a.serial else "1", a.integrators], capture_output=True,
                             text=True, check=True)
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        images = ", ".join(f"{n} {v[0]} (mean {v[1]:.6f})" for n, v in runs[-1].items()
                           if isinstance(v, list))
        print(f"process {k + 1}: shapes order {runs[-1]['shapes']}, emitters order "
              f"{runs[-1]['emitters']}; {images}")
    for key in runs[0]:
        values = {json.dumps(r[key]) for r in runs}
        means = {json.dumps(r[key][1]) for r in runs} if isinstance(runs[0][key], list) else values
        if len(values) == 1:
            verdict = "same"
        elif len(means) == 1:
            verdict = f"{len(values)} different byte patterns, the same mean"
        else:
            verdict = f"DIFFERENT: {len(values)} distinct in {len(runs)} processes"
        print(f"{key}: {verdict}")


if __name__ == "__main__":
    main()
