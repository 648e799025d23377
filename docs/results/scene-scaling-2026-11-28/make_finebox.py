"""The Cornell box with its floor and two boxes as fine meshes (320,010 triangles in all).

    .venv/bin/python docs/results/scene-scaling-2026-11-28/make_finebox.py /tmp/finebox

Writes floor.obj (a 200 x 200 grid of [-1, 1]^2 facing +z, 80,000 triangles), cube.obj (each
face of [-1, 1]^3 a 100 x 100 grid, 120,000 triangles) and finebox.xml (scenes_xml/cornell_box.xml
with those in place of its floor rectangle and its two cubes, same transforms) into the folder.
path renders the same image mean as the Cornell box (0.14857 against 0.14858 at 128 px, 64 spp).
"""
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def grid(n):
    """Vertices and faces of an n x n grid of quads over [-1, 1]^2 (z = 0), facing +z."""
    t = np.linspace(-1.0, 1.0, n + 1)
    X, Y = np.meshgrid(t, t, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    F = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                        np.stack([a, c, d], -1).reshape(-1, 3)])
    return V, F


def cube(n):
    """The six faces of [-1, 1]^3, each an n x n grid, wound outward."""
    Vg, Fg = grid(n)
    Vs, Fs, off = [], [], 0
    for ax in range(3):
        for s in (1.0, -1.0):
            o = [k for k in range(3) if k != ax]
            P = np.zeros_like(Vg)
            P[:, o[0]], P[:, o[1]], P[:, ax] = Vg[:, 0], Vg[:, 1], s
            cyclic = (o[0], o[1], ax) in ((0, 1, 2), (1, 2, 0), (2, 0, 1))
            F = Fg if cyclic == (s > 0) else Fg[:, [0, 2, 1]]
            Vs.append(P)
            Fs.append(F + off)
            off += len(P)
    return np.concatenate(Vs), np.concatenate(Fs)


def write_obj(path, V, F):
    with open(path, "w") as f:
        f.writelines("v %.9g %.9g %.9g\n" % tuple(v) for v in V)
        f.writelines("f %d %d %d\n" % tuple(t + 1) for t in F)


def main(folder):
    os.makedirs(folder, exist_ok=True)
    write_obj(os.path.join(folder, "floor.obj"), *grid(200))
    write_obj(os.path.join(folder, "cube.obj"), *cube(100))
    with open(os.path.join(ROOT, "scenes_xml", "cornell_box.xml")) as f:
        xml = f.read()
    obj = '<shape type="obj" id="{}"><string name="filename" value="{}"/>' \
          '<boolean name="face_normals" value="true"/>'
    for name, mesh in (("small-box", "cube"), ("large-box", "cube"), ("floor", "floor")):
        kind = "rectangle" if name == "floor" else "cube"
        xml = xml.replace(f'<shape type="{kind}" id="{name}">',
                          obj.format(name, os.path.join(os.path.abspath(folder), mesh + ".obj")))
    with open(os.path.join(folder, "finebox.xml"), "w") as f:
        f.write(xml)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "finebox")
