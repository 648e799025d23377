"""Does a scene load (and render with ``path``) the same way in two processes?

    .venv/bin/python tools/load_order.py scenes_xml/office.xml [--res 64] [--spp 4] [--serial]

Loads the scene in two fresh Python processes and prints, per process, a fingerprint of the
order of ``scene.shapes()`` (each shape's primitive count and surface area, in order) and of a
``path`` render (same seed), then whether the two agree. Mitsuba's XML loader builds shapes in
parallel; ``--serial`` loads with ``parallel=False``. docs/design.md ("Timing and randomness")
cites what it found.
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
path, res, spp, parallel = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
scene = mi.load_file(path, parallel=parallel, res=res) if "$res" in open(path).read() \
    else mi.load_file(path, parallel=parallel)
order = [(s.primitive_count(), round(float(s.surface_area()[0]), 5)) for s in scene.shapes()]
img = np.ascontiguousarray(np.asarray(mi.render(scene, spp=spp, seed=3)))
print(json.dumps({"order": hashlib.md5(repr(order).encode()).hexdigest()[:12],
                  "path": hashlib.md5(img.tobytes()).hexdigest()[:12]}))
"""


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--serial", action="store_true", help="load with parallel=False")
    a = ap.parse_args()
    runs = []
    for k in range(2):
        out = subprocess.run([sys.executable, "-c", CHILD, a.scene, str(a.res), str(a.spp),
                              "0" if a.serial else "1"], capture_output=True, text=True,
                             check=True)
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(f"process {k + 1}: shapes order {runs[-1]['order']}, path image {runs[-1]['path']}")
    for key, what in (("order", "shapes order"), ("path", "path image")):
        print(f"{what}: {'same' if runs[0][key] == runs[1][key] else 'DIFFERENT'}")


if __name__ == "__main__":
    main()
