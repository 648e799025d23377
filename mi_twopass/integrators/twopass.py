"""``twopass``: per scene and camera, the composition of the suite's techniques that pays.

The cost model and the table of compositions are in :mod:`mi_twopass.compose.cost`, the pilot
in :mod:`mi_twopass.compose.pilot`, the choice that runs them in
:mod:`mi_twopass.compose.choose`; this module wires them to Mitsuba's render call.
"""
from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi

from ..compose import cost
from ..compose.choose import choose, path_without_pilot, probe_gate
from ..compose.pilot import PilotSettings
from ..prepass.radiosity import SolveMemo
from ..prepass.rex_textures import ProbeMemo
from .base import TwoPassIntegrator, read_choice, read_float, read_int
from .component_path import ComponentPathIntegrator
from .pathtrace import first_nondelta_hit

AUTO = "auto"
DEBUG_MODES = ("none", "direct_technique", "indirect_technique")

#: debug="direct_technique" / "indirect_technique": the colour of the structure that serves the
#: direct / the indirect light at the first non-delta vertex (grey: none, emitter sampling or
#: path tracing there)
TECHNIQUE_COLOURS = {
    "path": (0.5, 0.5, 0.5),
    "spike": (0.9, 0.45, 0.0),       # a spike list in the vertex's cell (direct light)
    "radiosity": (0.0, 0.35, 0.9),   # the radiosity far field caches the surface
    "cache": (0.0, 0.75, 0.2),       # the radiance cache reads the surface
    "rex": (0.85, 0.0, 0.75),        # the surface carries rexes
}


class TwoPassChooser(TwoPassIntegrator):
    r"""
    .. _integrator-twopass:

    Two-pass composition (:monosp:`twopass`)
    -----------------------------------------

    The integrator to use on a scene nobody checked: it measures the suite's techniques on
    this scene and camera and renders with the composition that is predicted to reach the
    lowest error for its time, building only the structures that may pay (the table of
    compositions and the cost model: :mod:`mi_twopass.compose.cost`)::

        0. no pilot (path renders) where its samples would be more than 15 % of the
           render's (in proportion to ``pilot_budget``) or no prepass's least cost fits
           path's predicted render time (the most the first candidate may spend):
           :func:`mi_twopass.compose.cost.pilot_too_dear`,
           :func:`~mi_twopass.compose.cost.none_fit`;
           on a GPU, where the pilot and the prepasses are host work that path samples'
           time does not predict, the same two tests in seconds, against path's render
           timed at 1 spp (``path_probe``:
           :func:`~mi_twopass.compose.cost.too_dear_in_seconds`)
        1. pilot path trace (``pilot_pixels`` pixels × 144 samples, fewer pixels where that
           would pass 5 % of the render's samples, at least 256:
           :func:`mi_twopass.compose.pilot.pixel_count`; Mitsuba's path estimator)
           with its light split into direct, caustic (L S+ D ...) and other indirect parts,
           each part's relative variance measured; where the caustic part is below 20 %
           of the whole and some surface is specular, rex's size pass and probe shoot
           predict path's variance on light through delta bounces (rare bright samples a
           pilot misses: :mod:`mi_twopass.prepass.sharp_light`), and the caustic part is
           the larger of the two (``twopass_caustic_prediction``)
        2. for each composition the forced choices allow, by its best case (path's variance
           less the parts it serves, at path's cost, no prepass): skip it when the best case
           cannot beat the best measured so far by 1.25×, once the pilot and the prepasses
           so far leave no room for its prepass in its budget (for the first one built, half
           its best case's break-even prepass time, between ``pilot_budget`` and all of
           path's predicted render time: :func:`mi_twopass.compose.cost.prepass_budget`;
           for the others ``pilot_budget``), or where the scene gives it nothing (one
           emitter for spike lists, no Lambertian surface, a finite max_depth for a far
           field); else build its prepass and pilot it on the same pixels. Rexes may be
           built first with as few as 1/16 of the image's photon need; once piloted, their
           budget is at least half the prepass their measured score breaks even at
           (:func:`mi_twopass.compose.cost.measured_room`). They are built a second time
           with up to 4× the photons (or half the need, where that is more) that budget
           pays for, and that build renders; the pair measures the photons' own noise,
           counted in the score. They are built again where they have fewer than half the
           need (their buckets blur beyond check's bound) or their noise is above half of
           check's bound, with the photons that do, if the budget pays for them; else a
           rex below half the need is dropped, and one above it kept within the bound and
           dropped beyond it (:func:`mi_twopass.compose.choose.fit_frozen`)
        3. take the candidate of least predicted relMSE × seconds, (S + N·t) × (v/N + b²),
           N the render's samples per pixel, S the seconds the pilot and the prepasses have
           taken (spent whichever renders), b² its squared relative bias against the path
           pilot, pixel by pixel; path's v is measured against the other pilots' pixel
           means, which its own fireflies do not inflate
        4. where it reads a cache and a bias too small for its pilot to see could still make
           it lose to the runner-up, test it against path again with more samples per pixel
           (within 5 % of path's predicted render time) and choose again
           (:func:`mi_twopass.compose.choose.check_bias`); render with the winner

    Every composition is one of the suite's estimators (or ``path``), each consistent or
    within its own stated bias bound, so every part of path space is estimated exactly once
    (caustics=off: path traced, not dropped). With max_depth = 0 the image is black and
    nothing is built.

    **Light path cannot sample.** Light a point, spot or directional light sends through
    specular surfaces onto diffuse ones (a sun behind a window pane) is missing from ``path``
    at any sample count, so from its pilot and from every composition but rexes. Once the
    pilot has run, it is light-traced to the camera (:mod:`mi_twopass.compose.unsampled`,
    a few ms) and its share of the image, a lower bound, is ``twopass_path_unsampled_share``.
    Where that is at least 1 % and the composition chosen is not rexes, twopass warns. It
    does not switch to rexes by itself (its bias test measures against path, which lacks
    that light); ``caustics="rex"`` renders it.

    ``integrator.stats`` holds the chosen estimator's statistics and ``twopass_choice`` (the
    composition), ``twopass_reason`` (the predicted figures that decided), ``twopass_candidates``
    (per candidate built: prepass seconds, seconds per spp, relative variance, bias², score),
    ``twopass_skipped`` (per composition not built: why), ``twopass_best_case`` (per
    composition with a prepass: the score it could at best reach, relMSE × seconds, from the
    path pilot's parts; the order in which they were considered), ``twopass_bias_checks`` (per
    candidate tested again: samples per pixel, b², its standard error, outcome),
    ``twopass_probe`` (path's render time as probed: fixed part, seconds per spp, the
    render's; None where not probed), ``twopass_path_unsampled_share`` (above),
    ``twopass_caustic_prediction`` (path's caustic variance as photons predicted it and as the
    pilot measured it, and sharp light's share of the image; None where not asked),
    ``pilot_seconds`` (the probe, the pilot and the tests) and
    ``prepass_seconds`` (the pilot and every prepass built, the chosen one's included).

    .. pluginparameters::

     * - direct
       - |string|
       - "auto" (default), "emitter" (Mitsuba's emitter sampling with MIS) or "spike"
         (spike lists: ``spike_gather``'s, or with indirect="cache" ``radiance_cache``'s
         ``direct="spike"``).
     * - indirect
       - |string|
       - "auto" (default), "path" (traced), "radiosity" (GSII far gather), "cache" (the
         radiance cache's SH field) or "rex" (photon rexes, with caustics="rex").
     * - caustics
       - |string|
       - "auto" (default), "off" (caustic paths traced by BSDF sampling) or "rex".
     * - pilot_pixels
       - |int|
       - Pixels of the pilot (default: 1024; the whole film if smaller; fewer, down to 256,
         where 144 samples of each would pass 5 % of the render's samples).
     * - pilot_budget
       - |float|
       - The least share of the time ``path`` is predicted to need for the render that the
         pilot and the prepasses may spend, a candidate's own prepass included (default:
         0.25; a candidate whose best case is far ahead of path may spend more, up to that
         whole time; 0: path only, unless a choice is forced). The pilot starts only where
         its samples are at most 0.6 × this share of the render's (15 % at the default).
     * - path_probe
       - |string|
       - "auto" (default: on the CUDA backend only), "on" or "off": time ``path``'s render of
         the film at 1 spp before the pilot, and skip the pilot where it and the least
         prepass (0.15 s) do not fit the time path is predicted to take
         (:func:`mi_twopass.compose.cost.probe_wanted`).
     * - debug
       - |string|
       - "none"; "direct_technique" colours the first non-delta hit orange where a spike list
         serves its direct light (grey: emitter sampling); "indirect_technique" colours it by
         the structure that serves its indirect light (blue: the radiosity far field; green:
         the radiance cache; magenta: rexes; grey: path traced).
     * - max_depth, rr_depth, seed, component
       -
       - As every mi_twopass integrator; passed to the chosen estimator.
    """

    def _read_props(self, props):
        forced = {}
        for key, choices in (("direct", cost.DIRECT), ("indirect", cost.INDIRECT),
                             ("caustics", cost.CAUSTICS)):
            value = read_choice(props, key, AUTO, (AUTO, *choices))
            forced[key] = None if value == AUTO else value
        self.forced = forced
        self.allowed = cost.matching(**forced)  # a combination no row has fails at load
        self.pilot_settings = PilotSettings(
            pixels=read_int(props, "pilot_pixels", 1024, minimum=16, maximum=65536,
                            why="pilot pixels: each costs 144 samples per candidate"))
        self.pilot_budget = read_float(props, "pilot_budget", cost.PILOT_BUDGET, minimum=0.0)
        self.path_probe = read_choice(props, "path_probe", AUTO, (AUTO, "on", "off"))
        self.debug = read_choice(props, "debug", "none", DEBUG_MODES)
        self._candidates = {}  # plugin name+props -> integrator, kept so prepasses are reused
        # radiosity solves the candidates share within one prepass (radiosity.build's memo)
        self._radiosity_memo = SolveMemo()
        # rex size passes and probe shoots they share within one prepass (rex_textures.build's)
        self._probe_memo = ProbeMemo()
        self._render_spp = 0
        self._early = None  # (key, Choice) of the last early_path that found path
        self._probed = None  # path's render probe made by early_path, for choose
        #: samples per pixel of the whole image when a caller renders it in several passes
        #: (``python -m mi_twopass render`` does): the choice is made for the whole, not a pass
        self.planned_spp = 0

    def settings(self):
        return (tuple(sorted(self.forced.items(), key=lambda kv: kv[0])), self.pilot_settings,
                self.pilot_budget, self.path_probe, self._render_spp)

    # -- candidates -------------------------------------------------------------------------
    def _common_props(self) -> dict:
        return {"max_depth": self.max_depth, "rr_depth": self.rr_depth, "seed": self.seed,
                "component": self.component}

    def candidate(self, c: cost.Composition, photons: int = 0, twin: bool = False,
                  seed_offset: int = 0):
        """The integrator of composition ``c`` (built once per twopass object; ``photons`` > 0:
        its rexes with that many photons instead of the image's need; ``twin``: a new one,
        not kept, for a second build of the same prepass with another seed; ``seed_offset``:
        its prepass seed offset by that much, so that its build is independent of one without
        while the render's seed still finds it)."""
        key = (c.plugin, c.props, photons, seed_offset)
        if twin and c.plugin != "path":
            extra = {"photons": int(photons)} if photons > 0 else {}
            return self._sharing(mi.load_dict({"type": c.plugin, **self._common_props(),
                                               **dict(c.props), **extra}))
        if key not in self._candidates:
            if c.plugin == "path":
                props = mi.Properties()
                for k, v in self._common_props().items():
                    props[k] = v
                self._candidates[key] = ComponentPathIntegrator(props)
            else:
                extra = {"photons": int(photons)} if photons > 0 else {}
                props = self._common_props()
                props["seed"] = (int(props["seed"]) + int(seed_offset)) % (1 << 31)
                self._candidates[key] = self._sharing(mi.load_dict(
                    {"type": c.plugin, **props, **dict(c.props), **extra}))
        return self._candidates[key]

    def _sharing(self, integ):
        """``integ`` given the memos the candidates of one prepass share: radiosity solves
        (``SolveMemo``) and rex plans (``ProbeMemo``)."""
        integ.radiosity_memo = self._radiosity_memo
        integ.probe_memo = self._probe_memo
        return integ

    # -- prepass: pilot, then the structures that pay ---------------------------------------
    def prepass(self, scene, seed):
        """The pilot and the structures that may pay: :func:`mi_twopass.compose.choose.choose`.
        The candidates share their radiosity solves within it (one solve where spike_gather,
        radiosity_gather and radiance_cache ask for the same budget: the row of spike lists
        with the radiance cache asks for spike_gather's, ``cost.CACHE_RADIOSITY``) and their
        rex plans (one size pass and probe shoot for the photon need, a cut build, its twin and
        its rebuild: ``rex_textures.ProbeMemo``)."""
        self._radiosity_memo.clear()
        self._probe_memo.clear()
        try:
            return choose(scene, self.prepass_sensor, seed, self._render_spp, self.allowed,
                          self.candidate, self.pilot_settings, self.pilot_budget,
                          self.max_depth, self.path_probe, self._probed)
        finally:  # the chosen candidate keeps its own structure
            self._radiosity_memo.clear()
            self._probe_memo.clear()

    def early_path(self, scene, sensor, seed):
        """``(Choice of path, seconds)`` where the gates that count samples rule out the pilot
        (:func:`mi_twopass.compose.choose.path_without_pilot`), else ``(None, 0.0)``: asked
        before :meth:`ensure_prepass`, whose key fingerprints every scene parameter (9 ms on
        two CPU cores and 13 ms on an H200 for many_lights.xml's 494, most of twopass's cost
        over path's where it renders path), for a structure that holds nothing to reuse. The
        sample gates read the film's size, the samples per pixel and the settings only, so
        their answer is kept for those (seconds 0.0 when reused). Where they leave the pilot
        open and path's render is probed (on a GPU,
        :func:`~mi_twopass.compose.choose.probe_gate`), the gates in its seconds are asked
        too; their answer is not kept, and the probe goes on to
        :func:`~mi_twopass.compose.choose.choose`. The cached prepass is forgotten, as a new
        one would replace it."""
        key = (tuple(int(v) for v in sensor.film().crop_size()), self.settings(), seed)
        if self._early is not None and self._early[0] == key:
            choice = self._early[1]
            self.structure, self._prepass_key = choice, None
            self._prepass_stats = dict(self.prepass_stats(choice))
            self._prepass_time = choice.seconds["pilot"]
            return choice, 0.0
        t0 = time.perf_counter()
        spp = max(self._render_spp or sensor.sampler().sample_count(), 1)
        choice = path_without_pilot(sensor, seed, spp, self.allowed, self.candidate,
                                    self.pilot_settings, self.pilot_budget)
        if choice is None:  # on a GPU, path's render probed: its gates, and the probe kept
            choice, self._probed = probe_gate(scene, sensor, seed, spp, self.allowed,
                                              self.candidate, self.pilot_settings,
                                              self.pilot_budget, self.path_probe)
            if choice is None:
                return None, 0.0
            key = None  # the probe's answer depends on the scene: not kept
        seconds = time.perf_counter() - t0
        choice.seconds["pilot"] = seconds
        self.structure, self._prepass_key = choice, None
        self._prepass_scene, self._prepass_sensor_obj = scene, sensor
        self._prepass_time = seconds
        self._prepass_stats = dict(self.prepass_stats(choice))
        self._early = (key, choice) if key is not None else None
        return choice, seconds

    def prepass_stats(self, choice):
        d = choice.decision
        return {
            "twopass_choice": d.chosen.name,
            "twopass_reason": d.reason(),
            "twopass_candidates": {
                n: {"prepass_seconds": m.prepass_seconds, "seconds_per_spp": m.seconds_per_spp,
                    "relative_variance": m.variance, "bias2": m.bias2,
                    "bias2_standard_error": m.bias_se, "frozen": m.frozen,
                    "mean_ratio": m.mean_ratio,
                    "score": m.score(d.spp)}
                for n, m in d.measured.items()},
            "twopass_skipped": dict(d.skipped),
            "twopass_best_case": dict(d.best_case),
            "twopass_fitted": {n: {"light_paths": f[0], "image_needs": f[1]}
                               for n, f in d.fitted.items()},
            "twopass_frozen": {n: [{"light_paths": k, "block_relmse": f.block,
                                    "block_standard_error": f.block_se, "pixel_relmse": f.pixel}
                                   for k, f in history]
                               for n, history in d.frozen.items()},
            "twopass_bias_checks": {n: [{"samples_per_pixel": k, "bias2": b2,
                                         "standard_error": se, "outcome": why}
                                        for k, b2, se, why in checks]
                                    for n, checks in d.bias_checks.items()},
            "twopass_probe": None if d.probe is None else {
                "fixed_seconds": d.probe.fixed, "seconds_per_spp": d.probe.per_spp,
                "render_seconds": d.probe.seconds(d.spp)},
            "twopass_path_unsampled_share": d.unsampled,
            "twopass_caustic_prediction": d.caustic_prediction,
            "pilot_seconds": choice.seconds["pilot"],
        }

    # -- render -----------------------------------------------------------------------------
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        if self._in_render:  # the C++ render of a debug view dispatching back
            return TwoPassIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)
        if self.max_depth == 0:
            return self._render_black(scene, sensor, seed, spp, develop, evaluate)
        self._render_spp = int(self.planned_spp or spp)
        if self.debug != "none":  # the base class's render, with sample_technique
            return TwoPassIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)
        choice, seconds = self.early_path(scene, sensor, seed)
        if choice is None:
            try:
                choice, seconds = self.ensure_prepass(scene, seed, sensor)
            finally:
                self._probed = None  # handed to choose, or stale where the prepass was reused
        chosen = choice.integrator
        chosen.sample_seed_offset = self.sample_seed_offset
        image = chosen.render(scene, sensor, seed, spp, develop, evaluate)
        stats = dict(chosen.stats)
        stats.update(self._prepass_stats)
        stats["prepass_seconds"] = seconds  # pilot + every prepass built (0.0 when reused)
        stats["prepass_seconds_last_built"] = self._prepass_time
        self.structure_stat_keys = frozenset(self._prepass_stats) | chosen.structure_stat_keys
        self.stats = stats
        return image

    def sample(self, scene, sampler, ray, medium=None, active=True):
        if self.debug != "none":
            return self.sample_technique(scene, sampler, ray, active)
        return self.structure.integrator.sample(scene, sampler, ray, medium, active)

    def sample_technique(self, scene, sampler, ray, active):
        """The debug views: at the first non-delta vertex, the colour of the structure that
        serves its direct ("direct_technique") or indirect ("indirect_technique") light
        (:data:`TECHNIQUE_COLOURS`), grey where none does."""
        choice = self.structure
        si, _, _, _, found = first_nondelta_hit(scene, sampler, ray, active)
        colour = mi.Color3f(*TECHNIQUE_COLOURS["path"])
        parts = self.served_parts(choice.integrator, choice.decision.chosen, si, found)
        wanted = ("spike",) if self.debug == "direct_technique" else ("radiosity", "cache", "rex")
        for part in wanted:
            if part in parts:
                colour = dr.select(parts[part], mi.Color3f(*TECHNIQUE_COLOURS[part]), colour)
        return dr.select(found, colour, 0.0), mi.Bool(True), []

    @staticmethod
    def served_parts(integ, c, si, active) -> dict:
        """{structure: lanes whose hit ``si`` it serves} for composition ``c``."""
        s = integ.structure
        parts = {}
        if s is None:
            return parts
        if c.direct == "spike" and s.grid is not None:
            from ..prepass.spike_grid import INVALID
            parts["spike"] = active & (s.grid.list_at(si.p, active) != INVALID)
        if c.indirect == "radiosity":
            parts["radiosity"] = active & s.solution.cached_at(si, active)
        if c.indirect == "cache":
            parts["cache"] = active & s.cached.at(si, active)
        if c.caustics == "rex":
            from ..prepass.rex_textures import KIND_NONE, NO_SHAPE
            shape = s.tables.shape_index(si, active)
            kind = dr.gather(mi.UInt32, s.tables.d_kind, shape, active & (shape != NO_SHAPE))
            parts["rex"] = active & (shape != NO_SHAPE) & (kind != KIND_NONE)
        return parts

    def to_string(self):
        chosen = self.structure.decision.chosen.name if self.structure is not None else "?"
        return (f"TwoPassChooser[{chosen}, max_depth={self.max_depth}, "
                f"component={self.component}]")


mi.register_integrator("twopass", lambda props: TwoPassChooser(props))
