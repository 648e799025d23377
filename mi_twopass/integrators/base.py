"""Shared machinery of every mi_twopass integrator: prepass-then-render, stats and timing.

Subclasses implement three things:

* ``_read_props(props)``: read and validate their own XML parameters (called from ``__init__``,
  so a bad value fails at load time naming the parameter);
* ``prepass(scene, seed)``: build the integrator's structure (patches, spike grid, rexes, SH
  field...) and return it; it runs once per (scene, settings, seed) and is reused by later renders;
* ``sample(...)``: Mitsuba's per-ray estimator, reading ``self.structure``.

``integrator.stats`` after a render holds at least the columns of Zimmerman & Shirley's Table 1
and Arikan et al.'s Table 1: ``viewing_rays``, ``implicit_rays``, ``explicit_rays``,
``prepass_rays``, ``prepass_seconds``, ``render_seconds``, ``cache_bytes``.
"""
from __future__ import annotations

import math
import time

import drjit as dr
import mitsuba as mi

#: keys every integrator reports after a render
STAT_KEYS = (
    "viewing_rays",
    "implicit_rays",
    "explicit_rays",
    "prepass_rays",
    "prepass_seconds",
    "render_seconds",
    "cache_bytes",
)

COMPONENTS = ("all", "direct", "indirect")

#: ``max_depth = -1`` as a UInt32 loop bound (unbounded paths)
UNBOUNDED = 0xFFFFFFFF


def read_choice(props, name, default, choices):
    """Read a string property and check it is one of ``choices``."""
    value = props.get(name, default)
    if value not in choices:
        raise ValueError(f"{name}={value!r}: expected one of {', '.join(choices)}")
    return value


def read_int(props, name, default, minimum=None):
    value = int(props.get(name, default))
    if minimum is not None and value < minimum:
        raise ValueError(f"{name}={value}: must be >= {minimum}")
    return value


def read_bool(props, name, default):
    """Read a boolean property (a bool, or the strings "true" / "false")."""
    value = props.get(name, default)
    if isinstance(value, str):
        if value.lower() not in ("true", "false"):
            raise ValueError(f"{name}={value!r}: expected true or false")
        return value.lower() == "true"
    return bool(value)


def read_float(props, name, default, minimum=None, strict=False):
    value = float(props.get(name, default))
    if not math.isfinite(value):
        raise ValueError(f"{name}={value}: must be finite")
    if minimum is not None and (value < minimum or (strict and value == minimum)):
        cmp = ">" if strict else ">="
        raise ValueError(f"{name}={value}: must be {cmp} {minimum}")
    return value


class TwoPassIntegrator(mi.SamplingIntegrator):
    """Base class: common parameters, prepass caching, stats.

    Common XML parameters (every integrator of the suite):

    .. list-table::
       * - max_depth
         - int, default -1
         - Longest path (-1: unbounded, as Mitsuba's ``path``).
       * - rr_depth
         - int, default 5
         - Depth at which Russian roulette starts on continued paths.
       * - seed
         - int, default 0
         - Added to the render's seed for every random number of the prepass.
       * - component
         - string, default "all"
         - "direct" (emission + direct light) / "indirect" (everything else) / "all".
    """

    def __init__(self, props):
        super().__init__(props)
        self.max_depth = read_int(props, "max_depth", -1, minimum=-1)
        self.rr_depth = read_int(props, "rr_depth", 5, minimum=1)
        self.seed = read_int(props, "seed", 0, minimum=0)
        self.component = read_choice(props, "component", "all", COMPONENTS)
        self.structure = None
        self._prepass_key = None
        self._in_render = False
        self._counters = {}
        self.stats = {k: 0 for k in STAT_KEYS}
        self._read_props(props)

    @property
    def depth_bound(self) -> int:
        """``max_depth`` as a loop bound: UNBOUNDED for -1."""
        return UNBOUNDED if self.max_depth < 0 else self.max_depth

    @property
    def want_direct(self) -> bool:
        """Emission and direct light at the first non-delta vertex are rendered."""
        return self.component in ("all", "direct")

    @property
    def want_indirect(self) -> bool:
        """Everything after the first non-delta vertex's direct light is rendered."""
        return self.component in ("all", "indirect")

    # -- to override ------------------------------------------------------------------------
    def _read_props(self, props):
        """Read the subclass's own parameters (validate here, not in render)."""

    def settings(self) -> tuple:
        """Every parameter the prepass depends on (part of its cache key)."""
        return ()

    def prepass(self, scene, seed: int):
        """Build and return the integrator's structure; also returns its stats via ``stats``."""
        return None

    def prepass_stats(self, structure) -> dict:
        """``prepass_rays``, ``cache_bytes`` and anything else the structure reports."""
        return {}

    # -- counting ---------------------------------------------------------------------------
    def count(self, name, value):
        """Add ``dr.count(mask)`` (or the sum of a UInt array) to a lazily evaluated counter."""
        if isinstance(value, (int, float)):
            total = value
        elif dr.is_mask_v(value):
            total = dr.count(value)
        else:
            total = dr.sum(mi.UInt32(value))
        self._counters.setdefault(name, []).append(total)

    # -- render -----------------------------------------------------------------------------
    def prepass_seed(self, seed) -> int:
        return int(seed) + self.seed

    def ensure_prepass(self, scene, seed=0):
        """Run the prepass unless one for the same scene, settings and seed is cached."""
        key = (id(scene), self.settings(), self.prepass_seed(seed))
        if self._prepass_key == key and self.structure is not None:
            return self.structure, 0.0
        t0 = time.perf_counter()
        structure = self.prepass(scene, self.prepass_seed(seed))
        dr.sync_thread()
        elapsed = time.perf_counter() - t0
        self.structure, self._prepass_key = structure, key
        self._prepass_time = elapsed
        self._prepass_stats = dict(self.prepass_stats(structure))
        return structure, elapsed

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        if self._in_render:  # the C++ overload dispatching back: render directly
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        self._in_render = True
        try:
            _, prepass_seconds = self.ensure_prepass(scene, int(seed))
            self._counters = {}
            t0 = time.perf_counter()
            image = super().render(scene, sensor, seed, spp, develop, evaluate)
            dr.eval(image)
            dr.sync_thread()
            render_seconds = time.perf_counter() - t0
        finally:
            self._in_render = False
        self._finish_stats(sensor, spp, prepass_seconds, render_seconds)
        return image

    def _finish_stats(self, sensor, spp, prepass_seconds, render_seconds):
        stats = {k: 0 for k in STAT_KEYS}
        stats.update(self._prepass_stats)
        for name, parts in self._counters.items():
            stats[name] = int(sum(int(p[0]) if not isinstance(p, (int, float)) else int(p)
                                  for p in parts))
        if not stats.get("viewing_rays"):
            size = sensor.film().crop_size()
            spp = spp or sensor.sampler().sample_count()
            stats["viewing_rays"] = int(size[0]) * int(size[1]) * int(spp)
        stats["prepass_seconds"] = prepass_seconds  # 0.0 when the prepass was reused
        stats["prepass_seconds_last_built"] = self._prepass_time
        stats["render_seconds"] = render_seconds
        self.stats = stats

    def aov_names(self):
        return []

    def to_string(self):
        return f"{type(self).__name__}[max_depth={self.max_depth}, component={self.component}]"


class FarGatherIntegrator(TwoPassIntegrator):
    """An integrator whose gather rays longer than ``r_thresh`` read a radiosity prepass (GSII,
    Zimmerman & Shirley §2.5): reads ``r_thresh`` / ``r_thresh_rel`` and the prepass's budget
    (``max_patches``, ``particles_per_patch``, ``elements_per_patch``, ``vl_threshold``) with the
    subclass's defaults, and resolves ``r_thresh`` for a scene."""

    #: defaults of (max_patches, particles_per_patch, elements_per_patch)
    RADIOSITY_DEFAULTS = (1024, 256, 16)

    def _read_far_gather_props(self, props):
        self.r_thresh_rel = read_float(props, "r_thresh_rel", 0.1, minimum=0.0)
        self.r_thresh_abs = read_float(props, "r_thresh", -1.0) if "r_thresh" in props else None
        if self.r_thresh_abs is not None and self.r_thresh_abs < 0:
            raise ValueError(f"r_thresh={self.r_thresh_abs}: must be >= 0")
        patches, particles, elements = self.RADIOSITY_DEFAULTS
        self.max_patches = read_int(props, "max_patches", patches, minimum=1)
        self.particles_per_patch = read_int(props, "particles_per_patch", particles, minimum=1)
        self.elements_per_patch = read_int(props, "elements_per_patch", elements, minimum=1)
        self.vl_threshold = read_float(props, "vl_threshold", 0.5, minimum=0.0, strict=True)

    @property
    def far_gather_exact(self) -> bool:
        """The radiosity solution holds light of every path length (particles are traced until
        they are absorbed), so reading it is right only for unbounded paths. With a finite
        ``max_depth`` there is no far gather and no virtual luminaire: the integrator path
        traces (with its own direct-light strategy), as ``path`` with that ``max_depth``."""
        return self.max_depth < 0

    @property
    def vl_threshold_used(self) -> float:
        """``vl_threshold``, or ∞ (no virtual luminaires) where the far gather is off."""
        return self.vl_threshold if self.far_gather_exact else math.inf

    def r_thresh(self, scene) -> float:
        """``r_thresh``, else ``r_thresh_rel`` × the scene's bounding-box diagonal; ∞ (every
        gather ray is traced on) with a finite ``max_depth`` (see :attr:`far_gather_exact`)."""
        if not self.far_gather_exact:
            return math.inf
        if self.r_thresh_abs is not None:
            return self.r_thresh_abs
        return self.r_thresh_rel * float(dr.norm(scene.bbox().extents()))
