"""Reference images: Mitsuba's ``path`` at unbounded depth and high spp, cached on disk.

The cache key is a SHA-256 of the scene file's bytes, the bytes of every file it references
(``filename="..."``), the parameters, the film size override ``film_res`` (when given), spp, seed,
variant and Mitsuba version (and a mark where the scene is rendered unmerged: a sky in a room
of rectangles Mitsuba merges, :func:`mi_twopass.scene.bounds.infinite_light_leaks`, where
Mitsuba's ``path`` would let the sky through the walls); the image lives in
``<cache_dir>/<key>.exr`` beside a JSON of what made it. The default cache directory is
``.cache/references`` under the current directory, or ``$MI_TWOPASS_CACHE``.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from ..progress import progress
from ..scene.bounds import infinite_light_leaks
from ..scenefile import load_scene
from .images import read_exr, write_exr

DEFAULT_REFERENCE_SPP = 4096
#: lanes per reference pass (pixels × spp), to bound memory
LANES_PER_PASS = 1 << 22


def default_cache_dir() -> str:
    return os.environ.get("MI_TWOPASS_CACHE", os.path.join(os.getcwd(), ".cache", "references"))


def scene_digest(scene_path) -> str:
    """SHA-256 over the scene file and the files it names."""
    h = hashlib.sha256()
    with open(scene_path, "rb") as f:
        data = f.read()
    h.update(data)
    base = os.path.dirname(os.path.abspath(scene_path))
    for name in sorted(set(re.findall(rb'filename"\s+value="([^"]+)"|filename="([^"]+)"', data))):
        name = (name[0] or name[1]).decode()
        full = os.path.join(base, name)
        if os.path.isfile(full):
            with open(full, "rb") as f:
                h.update(name.encode() + f.read())
    return h.hexdigest()


def reference_key(scene_path, params: dict, spp: int, seed: int = 0, film_res=None) -> str:
    """The cache key of a reference (the module docstring says what it covers); without
    ``film_res`` it is the key earlier versions gave, so their caches stay valid."""
    h = hashlib.sha256()
    h.update(scene_digest(scene_path).encode())
    h.update(json.dumps(sorted(params.items()), default=str).encode())
    h.update(f"{spp}|{seed}|{mi.variant()}|{mi.__version__}".encode())
    if film_res is not None:
        h.update(f"|film_res={int(film_res)}".encode())
    return h.hexdigest()[:24]


def render_path(scene, spp: int, seed: int = 0, desc="reference") -> np.ndarray:
    """Render ``scene`` with ``path`` (max_depth −1) at ``spp``, in passes that bound memory."""
    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    per_pass = max(1, min(spp, LANES_PER_PASS // max(1, w * h)))
    integrator = mi.load_dict({"type": "path", "max_depth": -1})
    total = np.zeros((h, w, 3), dtype=np.float64)
    done = 0
    with progress(total=spp, desc=desc, unit="spp") as bar:
        while done < spp:
            n = min(per_pass, spp - done)
            img = mi.render(scene, integrator=integrator, spp=n, seed=seed * 100003 + done)
            total += np.asarray(img, dtype=np.float64)[..., :3] * n
            done += n
            bar.update(n)
    return (total / spp).astype(np.float32)


def reference_image(scene_path, params: dict | None = None, spp: int = DEFAULT_REFERENCE_SPP,
                    seed: int = 0, cache_dir: str | None = None, verbose: bool = False,
                    film_res: int | None = None) -> np.ndarray:
    """The cached reference for ``scene_path`` with ``params`` (and the film's longer side set
    to ``film_res`` pixels, see :func:`~mi_twopass.scenefile.load_scene`); rendered on a cache
    miss."""
    params = dict(params or {})
    cache_dir = cache_dir or default_cache_dir()
    scene = load_scene(scene_path, film_res=film_res, **params)
    # Mitsuba's path lets a sky through merged walls (scene.bounds.infinite_light_leaks):
    # such a scene's reference is rendered unmerged (its own cache key)
    unmerged = infinite_light_leaks(scene)
    key = reference_key(scene_path, params, spp, seed, film_res) + ("u" if unmerged else "")
    exr = os.path.join(cache_dir, key + ".exr")
    if os.path.isfile(exr):
        return read_exr(exr)
    if unmerged:
        scene = load_scene(scene_path, film_res=film_res, optimize=False, **params)
    t0 = time.perf_counter()
    image = render_path(scene, spp, seed)
    seconds = time.perf_counter() - t0
    if verbose:
        res = f" film_res {film_res}" if film_res is not None else ""
        print(f"reference: {os.path.basename(scene_path)} {params}{res} at {spp} spp in "
              f"{seconds:.1f} s")
    os.makedirs(cache_dir, exist_ok=True)
    tmp = exr + f".tmp{os.getpid()}.exr"
    write_exr(tmp, image)
    os.replace(tmp, exr)  # never leave a half-written reference behind
    with open(os.path.join(cache_dir, key + ".json"), "w") as f:
        json.dump({"scene": os.path.abspath(scene_path), "params": params, "film_res": film_res,
                   "spp": spp, "unmerged": unmerged,
                   "seed": seed, "variant": mi.variant(), "mitsuba": mi.__version__,
                   "seconds": seconds}, f, indent=1, default=str)
    dr.sync_thread()
    return image
