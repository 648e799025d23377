"""The radiosity solution's bright, unevenly lit elements against ``path``: their area means, and
what the gather rays from one pixel see of them.

    .venv/bin/python tools/element_reads.py ../shared/scenes/veach-bidir/scene.xml \\
        --pixel 81,72 [--res 128] [--integrator spike_gather] [--contrast 4] \\
        [--points 4096] [--rays 262144] [--samples 64]

The solution is the one of ``--integrator``'s prepass at seed 0. Its *bright uneven* elements are
those uncached as unevenly lit (``Patches.is_uneven``) whose reflected radiosity B_r is at least
``--contrast`` times the area-weighted mean of the cached ones: the surfaces the far gather
traces on from rather than reads.

1. **Per element**, the solution's B_r/π beside ``path``'s outgoing radiance at ``--points``
   uniform points on it (``--samples`` paths each, traced from just above the point along its
   side's normal). The table gives the mean and the 10th, 50th and 90th percentiles.
2. **Seen from ``--pixel``**, ``--rays`` cosine-distributed rays leave the pixel centre's first
   hit, on the side the camera sees. For each bright element they land on, the table gives the
   rays, the solution's B_r/π (the element's mean, or its cell's where it is refined) and
   ``path``'s radiance along those rays (``--samples`` paths each).

Session 27 found with it that veach-bidir's lamp-shade elements have the right area means, while
the wall below sees their rims at about 0.65× that mean (docs/results/rex-gate-2026-11-28).
"""
import argparse

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_twopass  # noqa: F401  (libLLVM, variant, plugins)
from mi_twopass.evaluation.harness import make_integrator
from mi_twopass.scenefile import load_scene


def rays_of(origins, directions):
    """``mi.Ray3f`` from (n, 3) numpy origins and directions."""
    return mi.Ray3f(mi.Point3f(*(mi.Float(origins[:, i]) for i in range(3))),
                    mi.Vector3f(*(mi.Float(directions[:, i]) for i in range(3))))


def path_radiance(scene, origins, directions, samples: int, seed: int) -> np.ndarray:
    """(n,) ``path``'s radiance (channel mean) along each ray, averaged over ``samples`` paths."""
    n = len(origins)
    integrator = mi.load_dict({"type": "path", "max_depth": -1})
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n * samples)
    L, _, _ = integrator.sample(scene, sampler, rays_of(np.repeat(origins, samples, axis=0),
                                                        np.repeat(directions, samples, axis=0)))
    return np.asarray(L).reshape(3, -1).mean(axis=0).reshape(n, samples).mean(axis=1)


def bright_uneven(solution, contrast: float) -> np.ndarray:
    """Ids of the elements uncached as unevenly lit with B_r ≥ ``contrast`` × the cached mean."""
    elements = solution.elements
    Br = np.asarray(solution.B_reflected_elements).mean(axis=1)
    area = np.asarray(elements.area, dtype=np.float64)
    cached = np.asarray(elements.is_diffuse, dtype=bool)
    mean = float(np.sum(Br[cached] * area[cached]) / max(np.sum(area[cached]), 1e-30))
    uneven = np.zeros(elements.count, bool) if elements.is_uneven is None else \
        np.asarray(elements.is_uneven, dtype=bool)
    return np.nonzero(uneven & (Br >= contrast * mean) & (Br > 0))[0]


def uniform_points(elements, element: int, count: int, rng):
    """(points, side normals) of ``count`` uniform points on ``element``'s triangles."""
    tri = np.nonzero(np.asarray(elements.tri_patch) == element)[0]
    v = np.asarray(elements.tri_vertices, dtype=np.float64)[tri]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    pick = rng.choice(len(tri), count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    p = (v[pick, 0] * (1 - s)[:, None] + v[pick, 1] * (s * (1 - r2))[:, None]
         + v[pick, 2] * (s * r2)[:, None])
    return p, np.asarray(elements.tri_normal, dtype=np.float64)[tri][pick]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--pixel", required=True, help="X,Y film pixel whose first hit gathers")
    ap.add_argument("--res", type=int, default=128, help="film's longer side in pixels")
    ap.add_argument("--integrator", default="spike_gather",
                    help="whose radiosity prepass (a spec, NAME[:key=value...])")
    ap.add_argument("--contrast", type=float, default=4.0)
    ap.add_argument("--points", type=int, default=4096)
    ap.add_argument("--rays", type=int, default=1 << 18)
    ap.add_argument("--samples", type=int, default=64)
    a = ap.parse_args()
    scene = load_scene(a.scene, film_res=a.res)
    sensor = scene.sensors()[0]
    integrator = make_integrator(a.integrator)
    integrator.ensure_prepass(scene, 0, sensor)
    structure = integrator.structure
    solution = getattr(structure, "solution", None) or structure.radiosity.solution
    elements = solution.elements
    Br = np.asarray(solution.B_reflected_elements).mean(axis=1)
    ids = bright_uneven(solution, a.contrast)
    rng = np.random.default_rng(3)

    print(f"{len(ids)} bright uneven elements (B_r ≥ {a.contrast} × the cached mean)\n")
    print("| element | B_r/π | path: mean | 10 % | 50 % | 90 % | area m² |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for e in ids:
        p, n = uniform_points(elements, int(e), a.points, rng)
        L = path_radiance(scene, p + 2e-3 * n, -n, a.samples, int(e))
        print(f"| {e} | {Br[e] / np.pi:.3g} | {L.mean():.3g} | {np.percentile(L, 10):.3g} | "
              f"{np.percentile(L, 50):.3g} | {np.percentile(L, 90):.3g} | "
              f"{float(np.asarray(elements.area)[e]):.4f} |")

    px, py = (int(v) for v in a.pixel.split(","))
    width, height = sensor.film().crop_size()
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(3, a.rays)
    pixel = mi.Point2f((px + 0.5) / width, (py + 0.5) / height) + dr.zeros(mi.Point2f, a.rays)
    camera_ray, _ = sensor.sample_ray(0.0, 0.5, pixel, mi.Point2f(0.5, 0.5))
    first = scene.ray_intersect(camera_ray)
    local = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
    local = dr.select(mi.Frame3f.cos_theta(first.wi) < 0, -local, local)  # the side seen
    gather = first.spawn_ray(first.to_world(local))
    hit = scene.ray_intersect(gather)
    x = np.asarray(first.p)[:, 0]
    o, d = np.asarray(gather.o).T, np.asarray(gather.d).T
    receiver = solution.receiver_at(hit, hit.is_valid())
    rid = np.asarray(receiver)
    read = np.asarray(solution.receiver_reflected_radiance(receiver, hit.is_valid(), hit.p)) \
        .reshape(3, -1).mean(axis=0)
    on = np.isin(rid, ids)
    print(f"\nfrom pixel ({px}, {py}), first hit {x.round(3)}: {int(on.sum())} of {a.rays} rays "
          "land on them\n")
    if not on.any():
        return
    L = path_radiance(scene, o[on], d[on], a.samples, 7)
    print("| element | rays | B_r/π read | path along the rays |")
    print("| --- | --- | --- | --- |")
    for e in np.unique(rid[on]):
        m = rid[on] == e
        print(f"| {e} | {int(m.sum())} | {read[on][m].mean():.3g} | {L[m].mean():.3g} |")
    print(f"| all | {int(on.sum())} | {read[on].mean():.3g} | {L.mean():.3g} |")
    dr.sync_thread()


if __name__ == "__main__":
    main()
