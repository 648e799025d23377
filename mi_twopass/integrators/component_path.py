"""A path tracer that keeps three parts of the light apart: direct, caustic, other indirect.

``twopass`` (:mod:`mi_twopass.integrators.twopass`) runs it as its pilot and as its "path"
composition. It is Mitsuba's ``path`` estimator (emitter sampling and BSDF sampling with the
power heuristic, Russian roulette from ``rr_depth``, the same ``max_depth``), built from the
per-vertex steps of :mod:`mi_twopass.integrators.pathtrace`, with each contribution filed
under the part of path space it belongs to (Heckbert's regular-expression notation, eye side
on the right)::

    direct     L (S*) D? (S*) E     emission seen through delta vertices, and light reaching the
                                    first non-delta vertex along one segment (emitter sampling,
                                    or a BSDF ray meeting an emitter)
    caustic    L S+ D (S|D)* E      emission met by a ray that left a delta vertex after at least
                                    one non-delta vertex: no emitter sample reaches it, only BSDF
                                    sampling does (the paths Heckbert's rexes are made for)
    indirect   the rest             light that reached a non-delta vertex after another one,
                                    without a delta vertex just before the emitter

The three add up to ``path``'s estimate, lane by lane; their separate variances are what
``twopass``'s cost model reads (:mod:`mi_twopass.compose.cost`).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..scene.bounds import ray_scale
from ..scene.emission import has_infinite_emitters
from .base import TwoPassIntegrator
from .pathtrace import bsdf_step, next_hit, path_start


class ComponentPathIntegrator(TwoPassIntegrator):
    """Mitsuba's ``path`` estimator with its contributions split into direct / caustic /
    indirect (module docstring). No prepass. Not registered as a plugin: ``twopass`` builds it.

    ``sample`` returns the parts ``component`` asks for ("all": their sum, the same estimate as
    ``path``; "direct": the direct part; "indirect": caustic + indirect)."""

    PREPASS_USES_CAMERA = False

    def mitsuba_path_is_the_same(self, scene) -> bool:
        """Whether Mitsuba's own ``path`` plugin renders this estimator's "all": every
        component, Mitsuba's ray offsets (a scene of a metre and more:
        :func:`~mi_twopass.scene.bounds.ray_scale` is 1, :mod:`mi_twopass.rays`) and no
        infinite emitter (whose shadow rays :func:`mi_twopass.rays.shadow_ray` carries past
        the scene's box, where Mitsuba's stop). Its render then traces the same paths with no
        split into parts (which only twopass's pilot reads) and no ray counters."""
        return (self.component == "all" and ray_scale(scene) == 1.0
                and not has_infinite_emitters(scene))

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        """Rendered by Mitsuba's ``path`` where that is the same estimator
        (:meth:`mitsuba_path_is_the_same`): twopass renders path where no structure pays, and
        there it now costs what ``path`` costs (the furnace at 256², 4 spp: median 0.0638 s
        against path's 0.0584 s through this class's loop, ``tools/repeat_timing.py``)."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        if self._in_render or self.max_depth == 0 or not self.mitsuba_path_is_the_same(scene):
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        plugin = getattr(self, "_mitsuba_path", None)
        if plugin is None:
            plugin = self._mitsuba_path = mi.load_dict(
                {"type": "path", "max_depth": self.max_depth, "rr_depth": self.rr_depth})
        image = self._render_with_plugin(plugin, scene, sensor, seed + self.sample_seed_offset,
                                         spp, develop, evaluate)
        for key in ("implicit_rays", "explicit_rays"):  # not counted by Mitsuba's plugin
            self.stats.pop(key, None)
        return image

    def sample(self, scene, sampler, ray, medium=None, active=True):
        if self.max_depth == 0:
            return mi.Spectrum(0.0), mi.Bool(True), []
        direct, caustic, indirect, caustic_first = self.sample_components(scene, sampler, ray,
                                                                          active)
        # ``component`` splits as every integrator of the suite does (pathtrace.by_component):
        # emission met from the first non-delta vertex is direct, delta vertices between or not
        if self.component == "direct":
            L = direct + caustic_first
        elif self.component == "indirect":
            L = caustic - caustic_first + indirect
        else:
            L = direct + caustic + indirect
        return L, mi.Bool(True), []

    @dr.syntax
    def sample_components(self, scene, sampler, ray, active=True):
        """``(direct, caustic, indirect, caustic_first)`` radiance along ``ray``, one path per
        lane; ``caustic_first`` is the part of ``caustic`` met from the first non-delta vertex
        (what ``component="direct"`` counts as direct)."""
        scale, max_depth, _, _, ctx, lights = \
            self.loop_constants(scene, ray_scale(scene))
        ray, _, beta, eta, depth, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, \
            prev_lights, active, n_implicit, n_explicit = path_start(ray, active, lights)
        direct, caustic, indirect, caustic_first = (mi.Spectrum(0.0) for _ in range(4))

        while dr.hint(active, label="component_path"):
            si, gather_ray, n_implicit = next_hit(scene, ray, depth, prev_bsdf_delta, active,
                                                  n_implicit)
            Le = beta * lights.emission_mis(scene, prev_lights, si, prev_si, prev_bsdf_pdf,
                                            prev_bsdf_delta, active)
            is_caustic = prev_bsdf_delta & (n_nondelta >= 1)
            caustic += dr.select(is_caustic, Le, 0.0)
            caustic_first += dr.select(is_caustic & (n_nondelta == 1), Le, 0.0)
            direct += dr.select(~is_caustic & (n_nondelta <= 1), Le, 0.0)
            indirect += dr.select(~is_caustic & (n_nondelta > 1), Le, 0.0)

            active_next = active & si.is_valid() & (depth + 1 < max_depth)
            bsdf = si.bsdf(ray)
            smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            Ld, cast, here = lights.sample_emitter_mis(scene, si, bsdf, ctx, sampler,
                                                       active_next & smooth, scale)
            n_explicit += dr.select(cast, 1, 0)
            Ld = beta * Ld
            first_vertex = n_nondelta == 0
            direct += dr.select(first_vertex, Ld, 0.0)
            indirect += dr.select(first_vertex, 0.0, Ld)

            prev_lights = here
            ray, beta, eta, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, depth, active = \
                bsdf_step(bsdf, ctx, si, sampler, active_next, scale, beta, eta, n_nondelta, depth,
                          self.rr_depth)

        self.count_after((direct, caustic, indirect, caustic_first), implicit_rays=n_implicit,
                         explicit_rays=n_explicit)
        return direct, caustic, indirect, caustic_first

    def to_string(self):
        return (f"ComponentPathIntegrator[max_depth={self.max_depth}, "
                f"component={self.component}]")
