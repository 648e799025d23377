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

import hashlib
import math
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from ..prepass.radiosity import VL_CONTRAST, RadiositySettings
from ..scene.bounds import scene_diagonal
from ..scene.view import collect_shading_points, view_diagonal
from .light_samplers import EmitterSampler
from .pathtrace import by_component

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


def _show(value) -> str:
    """A parameter value as an error message shows it (``2.5``, ``1e+12``, ``'abc'``)."""
    if isinstance(value, float):
        return format(value, ".6g")
    if isinstance(value, str):
        return repr(value)
    return str(value)


def _show_bound(bound) -> str:
    """``16777216`` → ``2^24``; other bounds as they are."""
    if isinstance(bound, int) and bound >= 1024 and bound & (bound - 1) == 0:
        return f"2^{bound.bit_length() - 1}"
    return _show(bound)


def human_bytes(n: float) -> str:
    """``3.2e9`` → ``"3.2 GB"`` (powers of 1000, as a message for people)."""
    for unit in ("bytes", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.3g} {unit}"
        n /= 1000.0
    return f"{n:.3g} TB"  # pragma: no cover


def needs_memory(bytes_each: float, what: str):
    """A ``why`` for the readers' ``maximum``: says what the bound protects, for the value read.

    ``needs_memory(64, "the particle records")`` gives, for 1e12, "the particle records would
    need 64 TB"."""
    return lambda value: f"{what} would need {human_bytes(float(value) * bytes_each)}"


def _check_range(name, value, minimum, maximum, strict, why, shown=None):
    """Raise a ValueError naming ``name`` (shown as ``shown``, default the value) when
    ``value`` is below ``minimum`` (or equal, ``strict``) or above ``maximum``."""
    shown = _show(value) if shown is None else shown
    if minimum is not None and (value < minimum or (strict and value == minimum)):
        cmp = ">" if strict else ">="
        raise ValueError(f"{name}={shown}: must be {cmp} {_show(minimum)}")
    if maximum is not None and value > maximum:
        reason = why(value) if callable(why) else why
        raise ValueError(f"{name}={shown}: at most {_show_bound(maximum)}"
                         + (f" ({reason})" if reason else ""))


def _from_string(raw: str, convert):
    """The value a string property spells, ``convert(raw.strip())`` (``int`` or ``float``), or
    None where ``convert`` refuses it (the readers then name the parameter)."""
    try:
        return convert(raw.strip())
    except ValueError:
        return None


def read_choice(props, name, default, choices):
    """Read a string property and check it is one of ``choices``."""
    value = props.get(name, default)
    if value not in choices:
        raise ValueError(f"{name}={value!r}: expected one of {', '.join(choices)}")
    return value


def read_int(props, name, default, minimum=None, maximum=None, why=None):
    """Read an integer property, checked to lie in [``minimum``, ``maximum``].

    Accepts Mitsuba's integer properties, floats with an integral value (``1e6``) and strings of
    an integer; refuses anything else (``max_depth=2.5: expected an integer``), booleans
    included. ``maximum`` bounds counts that size memory or time; ``why`` (a string, or a
    function of the value such as :func:`needs_memory`) says what the bound protects and is
    part of the message."""
    raw = props.get(name, default)
    value = None
    if isinstance(raw, bool):
        value = None
    elif isinstance(raw, int):
        value = int(raw)
    elif isinstance(raw, float):
        if math.isfinite(raw) and raw == int(raw):
            value = int(raw)
    elif isinstance(raw, str):
        value = _from_string(raw, int)
    if value is None:
        raise ValueError(f"{name}={_show(raw)}: expected an integer")
    _check_range(name, value, minimum, maximum, False, why, _show(raw))
    return value


def read_bool(props, name, default):
    """Read a boolean property: a bool, or the strings "true" / "false" (any case); anything
    else (``1``, ``"yes"``) is refused, so that the string "false" never reads as true."""
    value = props.get(name, default)
    if isinstance(value, str):
        if value.strip().lower() not in ("true", "false"):
            raise ValueError(f"{name}={value!r}: expected true or false")
        return value.strip().lower() == "true"
    if not isinstance(value, bool):
        raise ValueError(f"{name}={_show(value)}: expected true or false")
    return value


def read_float(props, name, default, minimum=None, strict=False, maximum=None, why=None):
    """Read a finite float property in [``minimum``, ``maximum``] (``strict``: > ``minimum``).

    Accepts Mitsuba's float and integer properties and strings of a number; refuses booleans,
    other strings, NaN and infinities, naming the parameter."""
    raw = props.get(name, default)
    value = None
    if isinstance(raw, (int, float)) and not isinstance(raw, bool):
        value = float(raw)
    elif isinstance(raw, str):
        value = _from_string(raw, float)
    if value is None:
        raise ValueError(f"{name}={_show(raw)}: expected a number")
    if not math.isfinite(value):
        raise ValueError(f"{name}={_show(value)}: must be finite")
    _check_range(name, value, minimum, maximum, strict, why)
    return value


# -- what a prepass depends on --------------------------------------------------------------
def _plain_value(value):
    """A traversed parameter as a Dr.Jit array where it is one (a transform: its matrix)."""
    if hasattr(value, "matrix") and not dr.is_array_v(value):  # (Affine)Transform4f, ...
        return value.matrix
    return value


def _value_bytes(value) -> bytes:
    """Bytes that change when a traversed parameter's value changes (arrays: their contents)."""
    if isinstance(value, (bool, int, float, str)) or value is None:
        return repr(value).encode()
    value = _plain_value(value)
    if dr.is_array_v(value):
        array = np.asarray(dr.detach(value))
        return str((array.dtype, array.shape)).encode() + array.tobytes()
    return f"{type(value).__name__}:{value!r}".encode()


#: the 32-bit scalar types whose arrays the fingerprint reads as UInt32 words
_WORD_TYPES = (dr.VarType.Float32, dr.VarType.UInt32, dr.VarType.Int32)


def _device_words(value):
    """A JIT array parameter of 32-bit scalars as ``(header, flat UInt32 array)`` to copy to
    the host; None for any other value."""
    value = _plain_value(value)
    if not (dr.is_array_v(value) and dr.is_jit_v(value)) or dr.type_v(value) not in _WORD_TYPES:
        return None
    flat = dr.ravel(dr.detach(value))
    if dr.is_tensor_v(flat):
        flat = flat.array
    words = flat if dr.type_v(flat) == dr.VarType.UInt32 else dr.reinterpret_array(
        dr.uint32_array_t(type(flat)), flat)
    return str((type(value).__name__, dr.shape(value))).encode(), words


def parameter_fingerprint(obj, skip_camera=False) -> str:
    """SHA-1 over ``mi.traverse(obj)``: every key and its value's bytes.

    Two calls agree exactly when no traversed parameter (emitter radiance, BSDF albedo,
    vertex positions, transforms, the film size and camera pose...) changed in between. With
    ``skip_camera`` the parameters of sensors, films, samplers and reconstruction filters are
    left out (for prepasses that do not look through the camera). Cost: one host copy and hash
    of every parameter array, ~1–2 ms per MB (README "Using it"), plus Python per parameter.
    Each 32-bit JIT array is copied on its own (:func:`_device_words`: its reinterpretation
    as UInt32 is one small kernel, the same for every array). Until session 23 they were
    concatenated on the device and copied in one transfer: the concatenation is one kernel
    with an input per array, compiled anew for every scene; with 1000 area lights (4000
    parameters) it took 14 s, against 0.1 s copied one by one (on many_lights.xml, 494
    parameters, 15–27 ms both ways; a one-off timing script)."""
    camera_types = (mi.Sensor, mi.Film, mi.Sampler, mi.ReconstructionFilter)
    params = mi.traverse(obj)
    h = hashlib.sha1()
    for key in params.keys():
        node = params.properties[key][2]
        if skip_camera and isinstance(node, camera_types):
            continue
        value = params[key]
        h.update(key.encode())
        h.update(b"\0")
        words = _device_words(value)
        if words is not None and dr.width(words[1]) > 0:
            h.update(words[0])
            h.update(np.asarray(words[1]).tobytes())
        else:
            h.update(_value_bytes(value))
        h.update(b"\1")
    return h.hexdigest()


def _as_int(seed) -> int:
    """A render seed as a Python int (``mi.render`` may pass a one-element ``mi.UInt32``)."""
    if dr.is_array_v(seed):
        if dr.width(seed) != 1:
            raise ValueError(f"seed: expected one value, got an array of {dr.width(seed)}")
        return int(dr.detach(seed)[0])
    return int(seed)


#: parameters a prepass may not exceed, with what the bound protects (see the readers)
MAX_DEPTH_LIMIT = (1 << 31) - 1
MAX_SEED = (1 << 31) - 1
#: patches: ~6 kB each at the peak of ``build_patches`` (measured on office.xml, 32 k patches)
MAX_PATCHES = 1 << 20
BYTES_PER_PATCH_BUILD = 6000
#: receiving elements in all (elements_per_patch × max_patches): ~3 kB each while built
MAX_ELEMENTS = 1 << 22
BYTES_PER_ELEMENT_BUILD = 3000
#: particles per patch: memory is bounded by batches, this bounds the prepass's time
MAX_PARTICLES_PER_PATCH = 1 << 24


class NotDifferentiableError(NotImplementedError):
    """``dr.backward`` / ``dr.forward`` through a render of a mi_twopass integrator."""


class TwoPassIntegrator(mi.SamplingIntegrator):
    """Base class: common parameters, prepass caching, stats.

    Common XML parameters (every integrator of the suite):

    .. list-table::
       * - max_depth
         - int, default -1
         - Longest path (-1: unbounded, as Mitsuba's ``path``; 0: a black image, no prepass).
       * - rr_depth
         - int, default 5
         - Depth at which Russian roulette starts on continued paths.
       * - seed
         - int, default 0
         - Added to the render's seed for every random number of the prepass.
       * - component
         - string, default "all"
         - "direct" (emission + direct light) / "indirect" (everything else) / "all".

    Prepass reuse: a render reuses the last prepass when the scene is the same object, no
    parameter of ``mi.traverse(scene)`` changed (:func:`parameter_fingerprint`: emitters, BSDFs,
    geometry, transforms, and, where ``PREPASS_USES_CAMERA``, the sensors and films), the
    render's sensor is the same with the same parameters (``PREPASS_USES_CAMERA``),
    :meth:`settings` are equal and the prepass seed is the same; otherwise it runs the prepass
    again. The integrator holds the scene and sensor of its last prepass (Mitsuba objects have
    no weak references), so a new scene can never take a freed scene's identity.

    Not differentiable: the forward render of a scene with grad-enabled parameters works (the
    detached values are rendered), but ``dr.backward`` / ``dr.forward`` through it raise
    :class:`NotDifferentiableError` (use Mitsuba's ``prb``).
    """

    #: the prepass looks through the camera (film size, pose): sensor parameters join its key.
    #: Subclasses whose prepass ignores the camera set False (fewer rebuilds).
    PREPASS_USES_CAMERA = True
    #: radiosity solves this prepass may share with others of the same scene and camera (the
    #: ``SolveMemo`` twopass gives its candidates, :func:`mi_twopass.prepass.radiosity.build`)
    radiosity_memo = None
    #: the rex size pass and probe shoot this prepass may share with others of the same scene
    #: and camera (the ``ProbeMemo`` twopass gives its candidates,
    #: :func:`mi_twopass.prepass.rex_textures.build`)
    probe_memo = None

    def __init__(self, props):
        super().__init__(props)
        self.max_depth = read_int(props, "max_depth", -1, minimum=-1, maximum=MAX_DEPTH_LIMIT,
                                  why="a 32-bit path depth; -1 is unbounded")
        self.rr_depth = read_int(props, "rr_depth", 5, minimum=1, maximum=MAX_DEPTH_LIMIT,
                                 why="a 32-bit path depth")
        self.seed = read_int(props, "seed", 0, minimum=0, maximum=MAX_SEED,
                             why="seeds are 32-bit")
        self.component = read_choice(props, "component", "all", COMPONENTS)
        self.structure = None
        #: added to the render's seed for the samplers only, never for the prepass: a render
        #: split into passes gives each pass its own offset and they share one prepass
        self.sample_seed_offset = 0
        #: the sensor of the render whose prepass runs (``None`` outside ``ensure_prepass``)
        self.prepass_sensor = None
        self._prepass_key = None
        self._prepass_scene = None
        self._prepass_sensor_obj = None
        self._prepass_time = 0.0
        self._prepass_stats = {}
        self._in_render = False
        self._counters = {}
        self.stats = {k: 0 for k in STAT_KEYS}
        #: keys of ``stats`` that describe the prepass's structure (patch counts, bytes...):
        #: a render split into passes must not add them up
        self.structure_stat_keys = frozenset()
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

    def loop_constants(self, scene, scale: float) -> tuple:
        """What every gather loop reads and never changes: ``(scale, max_depth, want_direct,
        want_indirect, bsdf_ctx, lights)``. ``scale`` (the scene's ray-offset length,
        :mod:`mi_twopass.rays`) is made opaque, so that one compiled kernel serves every
        scene; the depth bound and the components are Python values the loop is traced with;
        ``lights`` is the integrator's :meth:`light_sampler` for ``scene``."""
        return (dr.opaque(mi.Float, scale), self.depth_bound, self.want_direct,
                self.want_indirect, mi.BSDFContext(), self.light_sampler(scene))

    def emission_met(self, scene, lights, si, beta, n_nondelta, prev, active):
        """β·Le(y → x)·w_MIS: the emission met at ``si`` by the path's last ray, weighted by
        ``lights`` against its choice at the vertex the ray left, ``prev = (prev_si,
        prev_bsdf_pdf, prev_bsdf_delta, prev_lights)`` (:meth:`LightSampler.emission_mis`), and
        kept where its component is rendered: direct where met from the first non-delta vertex
        (``n_nondelta ≤ 1``, :func:`~mi_twopass.integrators.pathtrace.by_component`)."""
        prev_si, prev_bsdf_pdf, prev_bsdf_delta, prev_lights = prev
        Le = lights.emission_mis(scene, prev_lights, si, prev_si, prev_bsdf_pdf, prev_bsdf_delta,
                                 active)
        return by_component(beta * Le, n_nondelta <= 1, self.want_direct, self.want_indirect)

    # -- to override ------------------------------------------------------------------------
    def light_sampler(self, scene):
        """The explicit strategy's choice of a source
        (:mod:`mi_twopass.integrators.light_samplers`): Mitsuba's own emitter choice unless an
        integrator has a structure for it."""
        return EmitterSampler(scene)

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

    def count_after(self, results, **counters):
        """Evaluate a gather loop's ``results`` together with its ray ``counters`` (name →
        per-lane UInt32 or mask) and add the counters to :attr:`stats` (:meth:`count`).

        The counters are reductions: evaluated alone they would run the loop once for
        themselves and once more for the image. Scheduled with the results, one kernel computes
        both (``tests/integrators/test_api.py::test_a_render_traces_its_paths_once``)."""
        dr.schedule(*results, *counters.values())
        for name, value in counters.items():
            self.count(name, value)

    # -- render -----------------------------------------------------------------------------
    def prepass_seed(self, seed) -> int:
        """The prepass's seed for a render's ``seed``: the render's seed plus ``seed``."""
        return _as_int(seed) + self.seed

    def prepass_key(self, scene, sensor, seed) -> tuple:
        """What the prepass depends on, besides the identity of the scene and sensor objects:
        the scene's parameter fingerprint (sensors included where ``PREPASS_USES_CAMERA``),
        the render sensor's fingerprint (idem), :meth:`settings` and the prepass seed."""
        camera = self.PREPASS_USES_CAMERA
        scene_fp = parameter_fingerprint(scene, skip_camera=not camera)
        sensor_fp = parameter_fingerprint(sensor) if camera and sensor is not None else None
        return (scene_fp, sensor_fp, self.settings(), self.prepass_seed(seed))

    def ensure_prepass(self, scene, seed=0, sensor=None):
        """Run the prepass unless the cached one was built for this scene object and sensor
        with the same parameters, settings and seed (:meth:`prepass_key`). Returns
        (structure, seconds spent: 0.0 when reused)."""
        if sensor is None and len(scene.sensors()):
            sensor = scene.sensors()[0]
        key = self.prepass_key(scene, sensor, seed)
        same_objects = self._prepass_scene is scene and (
            not self.PREPASS_USES_CAMERA or self._prepass_sensor_obj is sensor)
        if same_objects and self._prepass_key == key and self.structure is not None:
            return self.structure, 0.0
        t0 = time.perf_counter()
        self.prepass_sensor = sensor
        try:
            self.before_prepass(scene, self.prepass_seed(seed))
            structure = self.prepass(scene, self.prepass_seed(seed))
        finally:
            self.prepass_sensor = None
        dr.sync_thread()
        elapsed = time.perf_counter() - t0
        self.structure, self._prepass_key = structure, key
        self._prepass_scene, self._prepass_sensor_obj = scene, sensor
        self._prepass_time = elapsed
        self._prepass_stats = dict(self.prepass_stats(structure))
        return structure, elapsed

    def before_prepass(self, scene, seed) -> None:
        """Called by :meth:`ensure_prepass` just before :meth:`prepass`, with
        ``prepass_sensor`` set: what the prepass and the render both read (nothing here)."""

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        if self._in_render:  # the C++ overload dispatching back: render directly
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        sampler_seed = seed + self.sample_seed_offset if self.sample_seed_offset else seed
        if self.max_depth == 0:
            return self._render_black(scene, sensor, sampler_seed, spp, develop, evaluate)
        self._in_render = True
        try:
            _, prepass_seconds = self.ensure_prepass(scene, seed, sensor)
            self._counters = {}
            t0 = time.perf_counter()
            image = super().render(scene, sensor, sampler_seed, spp, develop, evaluate)
            dr.eval(image)
            dr.sync_thread()
            render_seconds = time.perf_counter() - t0
        finally:
            self._in_render = False
        self._finish_stats(sensor, spp, prepass_seconds, render_seconds)
        return image

    def _render_black(self, scene, sensor, seed, spp, develop, evaluate):
        """``max_depth = 0``: what Mitsuba's ``path`` renders (black, alpha 0, the film's
        size and channels), without a prepass."""
        black = mi.load_dict({"type": "path", "max_depth": 0})
        return self._render_with_plugin(black, scene, sensor, seed, spp, develop, evaluate)

    def _render_with_plugin(self, plugin, scene, sensor, seed, spp, develop, evaluate):
        """The image of one of Mitsuba's own integrators rendering in this one's place (no
        prepass, no ray counters), with this integrator's :attr:`stats` for it."""
        t0 = time.perf_counter()
        image = plugin.render(scene, sensor, seed, spp, develop, evaluate)
        dr.eval(image)
        dr.sync_thread()
        self._counters = {}
        self._prepass_stats = {}
        self._finish_stats(sensor, spp, 0.0, time.perf_counter() - t0)
        return image

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        """Not available: see :class:`NotDifferentiableError`."""
        raise NotDifferentiableError(self._not_differentiable())

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        """Not available: see :class:`NotDifferentiableError`."""
        raise NotDifferentiableError(self._not_differentiable())

    def _not_differentiable(self) -> str:
        return (f"{type(self).__name__} is not differentiable: its prepass and gather are not "
                "traced by Dr.Jit's AD, so it cannot give gradients of scene parameters "
                "(the forward render uses their detached values). Use Mitsuba's 'prb' "
                "integrator for dr.backward / dr.forward.")

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
        self.structure_stat_keys = frozenset(self._prepass_stats) | {
            "prepass_rays", "cache_bytes", "prepass_seconds_last_built"}
        self.stats = stats

    def aov_names(self):
        return []

    def to_string(self):
        return f"{type(self).__name__}[max_depth={self.max_depth}, component={self.component}]"


#: the default r_thresh as a fraction of the diagonal of what the camera sees
#: (:meth:`FarGatherIntegrator.view_diagonal`). 0.1 until session 17, when that diagonal
#: replaced the scene's: with 0.05, at 256² (docs/results/far-gather-view-2026-11-27,
#: ``bench`` with ``r_thresh_rel=0.05`` beside the default), radiosity_gather's equal-time ratio
#: against ``path`` went 4.16 → 5.34 on window_interior, 3.68 → 4.84 on the office (time to
#: relMSE 0.01 1.26 → 1.00 s, 4.11 → 5.19×), 1.20 → 1.92 on many_lights, 6.47 → 7.06 on
#: mixed_room and 2.36 → 2.83 on the Cornell box; spike_gather's 3.48 → 4.21, 8.24 → 9.23
#: and 2.05 → 2.37 on the last three. The relMSE at 512 spp was the same or lower everywhere,
#: and ``check --renders 2`` at 128 px found the same bias parts on all nine scenes of
#: scenes_xml/ and ../shared/scenes. 0.2 was worse (office 2.35×).
R_THRESH_REL = 0.05


class FarGatherIntegrator(TwoPassIntegrator):
    """An integrator whose gather rays longer than ``r_thresh`` read a radiosity prepass (GSII,
    Zimmerman & Shirley §2.5): reads ``r_thresh`` / ``r_thresh_rel`` and the prepass's budget
    (``max_patches``, ``particles_per_patch``, ``elements_per_patch``, ``vl_threshold``,
    ``vl_contrast``) with the
    subclass's defaults, and resolves ``r_thresh`` for a scene.

    Its XML parameters, beside the budget's (each subclass's manual gives those defaults):

    .. list-table::
       * - r_thresh
         - float
         - Gather-ray length below which the path is traced on (scene units). Default:
           ``r_thresh_rel`` × the diagonal of what the camera sees (:meth:`view_diagonal`).
       * - r_thresh_rel
         - float, default ``R_THRESH_REL`` (0.05)
         - Default ``r_thresh`` as a fraction of that diagonal.
    """

    #: camera rays whose first non-delta hits give the view's extent (:meth:`view_diagonal`)
    VIEW_POINTS = 4096

    #: defaults of (max_patches, particles_per_patch, elements_per_patch)
    RADIOSITY_DEFAULTS = (1024, 256, 16)

    def _read_far_gather_props(self, props):
        self.r_thresh_rel = read_float(props, "r_thresh_rel", R_THRESH_REL, minimum=0.0)
        self.r_thresh_abs = read_float(props, "r_thresh", 0.0, minimum=0.0) \
            if "r_thresh" in props else None
        self.radiosity = read_radiosity_budget(props, *self.RADIOSITY_DEFAULTS)
        self.vl_threshold = read_float(props, "vl_threshold", 0.5, minimum=0.0, strict=True)
        self.vl_contrast = read_float(props, "vl_contrast", VL_CONTRAST, minimum=0.0)
        self._view_diagonal = None  # set by before_prepass for the scene and camera built for

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

    def view_diagonal(self, scene) -> float:
        """The diagonal of the bounding box of the first non-delta hits of ``VIEW_POINTS``
        camera rays of ``prepass_sensor`` (:func:`mi_twopass.scene.view.collect_shading_points`),
        else (no sensor, no hit) of the scene's geometry.

        The scale of the gather: r_thresh separates the near light that is path traced from the
        far light read from the radiosity elements. Scaled by the scene's bounds (before
        2026-11-27), a room seen through its own walls got the r_thresh of the street or ground
        plane around it (scenes_xml/window_interior.xml: 2.08 m in a 6 m room; 0.77 m at the same
        fraction of the view, 0.39 m with :data:`R_THRESH_REL`) and traced on most of its
        gather rays. At 256², two bench runs each side
        (docs/results/far-gather-view-2026-11-27): time to relMSE 0.01 on window_interior,
        radiosity_gather 1.49–1.67 → 1.21–1.24 s and spike_gather 1.45–1.57 → 1.08–1.27 s
        (`path`: 4.1–4.4 s), with the bias parts of ``check`` unchanged."""
        fallback = scene_diagonal(scene)
        sensor = self.prepass_sensor
        if sensor is None:
            return fallback
        # one jitter for every seed: r_thresh is a literal of the render's kernels, and a value
        # that followed the seed compiled them again for every render seed (the office at
        # 256²: spike_gather's time to relMSE 0.01 0.64 → 0.96 s in the bench)
        points, _, _ = collect_shading_points(scene, sensor, self.VIEW_POINTS, seed=0,
                                              lambertian_only=False)
        return view_diagonal(points, fallback)

    def before_prepass(self, scene, seed) -> None:
        self._view_diagonal = self.view_diagonal(scene) if self.far_gather_exact else None

    def r_thresh(self, scene) -> float:
        """``r_thresh``, else ``r_thresh_rel`` × the diagonal of what the camera sees
        (:meth:`view_diagonal`, measured for the last prepass; the scene's bounds' before any);
        ∞ (every gather ray is traced on) with a finite ``max_depth`` (see
        :attr:`far_gather_exact`)."""
        if not self.far_gather_exact:
            return math.inf
        if self.r_thresh_abs is not None:
            return self.r_thresh_abs
        diagonal = self._view_diagonal if self._view_diagonal is not None \
            else scene_diagonal(scene)
        return self.r_thresh_rel * diagonal


def read_radiosity_budget(props, max_patches=1024, particles_per_patch=256,
                          elements_per_patch=16) -> RadiositySettings:
    """Read and bound ``max_patches``, ``particles_per_patch`` and ``elements_per_patch`` (the
    radiosity prepass's budget, shared by every integrator that runs it), once, in one place."""
    patches = read_int(props, "max_patches", max_patches, minimum=1, maximum=MAX_PATCHES,
                       why=needs_memory(BYTES_PER_PATCH_BUILD, "building the patches"))
    particles = read_int(
        props, "particles_per_patch", particles_per_patch, minimum=1,
        maximum=MAX_PARTICLES_PER_PATCH,
        why=lambda v: f"{float(v) * patches:.3g} particles for max_patches={patches}: "
                      "hours of prepass")
    elements = read_int(props, "elements_per_patch", elements_per_patch, minimum=1,
                        maximum=MAX_ELEMENTS // patches,
                        why=lambda v: f"{v} × max_patches={patches} receiving elements; "
                                      + needs_memory(BYTES_PER_ELEMENT_BUILD,
                                                     "building them")(v * patches))
    return RadiositySettings(max_patches=patches, particles_per_patch=particles,
                             elements_per_patch=elements)
