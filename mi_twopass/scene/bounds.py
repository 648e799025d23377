"""The bounds of a scene's geometry: the length every relative offset and distance is measured in.

Not ``scene.bbox()``: Mitsuba 3.9 leaves the rectangles it merges into one mesh (shapes that
share a BSDF) out of that mesh's bounding box, so the scene's box of a room of rectangles can be
empty, or that of a torus inside it. Meshes are bounded here by their vertices, other shapes by
their own ``bbox()``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SceneBounds:
    """Axis-aligned bounds of a scene's geometry (``empty``: no shape had finite bounds, and
    ``lo``/``hi`` are the unit cube around the origin) and its bounding sphere."""

    lo: tuple
    hi: tuple
    empty: bool = False

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (np.asarray(self.lo) + np.asarray(self.hi))

    @property
    def diagonal(self) -> float:
        """Length of the diagonal; 1 where it is 0 or not finite (a point, an empty scene)."""
        d = float(np.linalg.norm(np.asarray(self.hi) - np.asarray(self.lo)))
        return d if d > 0 and math.isfinite(d) else 1.0

    @property
    def radius(self) -> float:
        """Bounding-sphere radius, a hair larger than half the diagonal (rays start outside)."""
        return 0.5 * self.diagonal * (1.0 + 1e-3)


def scene_bounds(scene) -> SceneBounds:
    """Bounds of every shape of ``scene``: meshes from their vertices, others from ``bbox()``."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for shape in scene.shapes():
        if shape.is_mesh():
            if shape.vertex_count() == 0:
                continue
            V = np.asarray(shape.vertex_positions_buffer(), np.float64).reshape(-1, 3)
            b_lo, b_hi = V.min(axis=0), V.max(axis=0)
        else:
            bbox = shape.bbox()
            b_lo = np.asarray(bbox.min, np.float64).ravel()[:3]
            b_hi = np.asarray(bbox.max, np.float64).ravel()[:3]
        if np.isfinite(b_lo).all() and np.isfinite(b_hi).all() and (b_hi >= b_lo).all():
            lo, hi = np.minimum(lo, b_lo), np.maximum(hi, b_hi)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        return SceneBounds((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), empty=True)
    return SceneBounds(tuple(lo), tuple(hi))


def infinite_light_leaks(scene, bounds: SceneBounds | None = None) -> bool:
    """``scene`` has an infinite emitter (sky, sun, envmap) and ``scene.bbox()`` misses part of
    its geometry (Mitsuba 3.9 leaves the rectangles it merges into one mesh out of it): then
    Mitsuba's emitter sampling ends shadow rays 2R from the shading point, R the radius around
    that short box, and they pass walls — Mitsuba's ``path`` lets the sky into closed rooms
    (:func:`mi_twopass.rays.shadow_ray` is ours). Loading the scene with ``optimize=False``
    avoids the merge."""
    from .emission import has_infinite_emitters

    if not has_infinite_emitters(scene):
        return False
    bounds = bounds if bounds is not None else scene_bounds(scene)
    if bounds.empty:
        return False
    box = scene.bbox()
    if not box.valid():
        return True
    lo = np.asarray(box.min, np.float64).ravel()[:3]
    hi = np.asarray(box.max, np.float64).ravel()[:3]
    tol = 1e-4 * bounds.diagonal
    return not (np.all(lo <= np.asarray(bounds.lo) + tol)
                and np.all(hi >= np.asarray(bounds.hi) - tol))


def scene_diagonal(scene) -> float:
    """The diagonal of :func:`scene_bounds` (1 for an empty scene)."""
    return scene_bounds(scene).diagonal


def ray_scale(scene) -> float:
    """The length a ray offset is relative to (:mod:`mi_twopass.rays`): min(1, diagonal), so
    that the offset is Mitsuba's own for scenes of a metre and more."""
    return min(1.0, scene_diagonal(scene))
