"""``radiosity_gather``: radiosity prepass + per-pixel gather (Rushmeier's implicit gather, GSII).

Zimmerman & Shirley 1995 (docs/design.md "Papers"), §2.3 (implicit gather) and §2.5 (GSII).
"""
from __future__ import annotations

import os
from dataclasses import replace

import drjit as dr
import mitsuba as mi

from ..prepass.radiosity import RadiositySettings, virtual_point_reached
from ..prepass.radiosity import build as build_radiosity
from ..scene.bounds import ray_scale
from ..scenefile import SceneFileError
from .base import FarGatherIntegrator, read_choice
from .pathtrace import (bsdf_step, by_component, first_nondelta_hit, next_hit,
                        path_start)

DEBUG_MODES = ("none", "radiosity", "patches", "virtual")


class RadiosityGatherIntegrator(FarGatherIntegrator):
    r"""
    .. _integrator-radiosity_gather:

    Radiosity gather (:monosp:`radiosity_gather`)
    ----------------------------------------------

    A radiosity prepass over diffuse patches of the scene (or of a simplified "massing" scene),
    then a path tracer that stops at the first *gather ray* longer than ``r_thresh`` and adds the
    reflected radiosity of the patch it hits (Zimmerman & Shirley §2.5, GSII)::

        L(x) = Le(x) + direct(x) [emitter sampling, MIS]
                     + virtual luminaires: bright patches sampled explicitly (GSII's reclassification)
                     + f(x) · { path-trace recursively        if |y − x| <  r_thresh
                              { B_r(patch(y)) / π             otherwise

    The r_thresh rule applies at every non-delta vertex, as in the paper's pseudocode (§2.5):
    ``r_thresh = 0`` is the pure two-pass method (Rushmeier's implicit gather, §2.3) and an
    ``r_thresh`` larger than the scene is path tracing. Delta (specular) vertices are followed
    as in Mitsuba's ``path``; glossy and specular surfaces carry no patch radiosity, so a gather
    ray that lands on one continues as a path. Neither do receivers (elements, else patches) that
    geometry cuts or that are lit unevenly (their flux off centre or on the faces turned to a
    light: :func:`mi_twopass.prepass.radiosity.receiver_spread`): their mean is no stand-in for
    the light where gather rays land, so those rays trace on too. Only the *reflected* part B_r
    of a patch is gathered: emission is added by the emitter-hit term with MIS, never twice.

    Virtual luminaires (GSII, "bright reflecting zones"): patches whose reflected radiosity is at
    least ``vl_threshold`` × the brightest patch's are sampled explicitly, one shadow ray per
    vertex, with probability ∝ B_r · area. A pair (x, y) is counted explicitly only when
    |y − x| ≥ r_thresh and y lies where the radiosity is cached, and a far gather ray that lands
    on a virtual luminaire adds nothing, so the two estimators partition the far field and
    nothing is counted twice (:func:`mi_twopass.prepass.radiosity.virtual_point_reached`); near
    pairs stay path-traced, so the r_thresh → ∞ limit is still path tracing.

    .. pluginparameters::

     * - r_thresh, r_thresh_rel
       -
       - As every far-gather integrator (:class:`~mi_twopass.integrators.base.FarGatherIntegrator`):
         gather rays shorter than ``r_thresh`` trace on (default: 0.05 × the bounding-box
         diagonal of what the camera sees, its rays' first non-delta hits:
         :meth:`~mi_twopass.integrators.base.FarGatherIntegrator.view_diagonal`).
     * - max_patches
       - |int|
       - Patch budget of the prepass (default: 1024; on the Cornell box 4096 patches lowered
         the error at 1024 spp by < 10 % and cost 4× the prepass time).
     * - particles_per_patch
       - |int|
       - Particles the stochastic radiosity solver shoots per patch (default: 256). At least
         65536 in all (``prepass.radiosity.MIN_PARTICLES``), however few the patches. Where a
         sun, sky or point light is guided by the camera (``prepass.emission_guide``), up to
         8× more, until the flux the camera reads has a predicted noise of 0.25 %.
     * - elements_per_patch
       - |int|
       - Receiving elements per patch (Cohen et al. 1986 substructuring; default: 16, i.e.
         elements of a quarter of the patch edge). The particles deposit in patches and in
         elements; a far gather ray reads the element it hits. A patch's area mean reads dark
         where gather rays land (irradiance and hit density covary inside a patch), by an
         amount proportional to the edge length; 1 turns elements off.
     * - prepass_scene
       - |string|
       - Scene file of a simplified ("massing") scene to run the prepass on and to trace far
         gather rays in (GSII). Default: the rendered scene itself.
     * - vl_threshold
       - |float|
       - Reclassify patches with B_r ≥ vl_threshold × max B_r as virtual luminaires
         (default: 0.5; a value > 1 disables reclassification).
     * - vl_contrast
       - |float|
       - ... and only those with B_r ≥ vl_contrast × the area-weighted mean B_r of the cached
         patches, and none where together they carry under 2 % of the cached patches'
         reflected power (default: 4; 0: GSII's rule alone, whose count follows the noise of
         the brightest patch: :func:`mi_twopass.prepass.radiosity.reclassified_patches`).
     * - max_depth, rr_depth, seed, component
       - 
       - As every mi_twopass integrator: path length (-1: unbounded), Russian roulette start,
         prepass seed offset, "all" / "direct" / "indirect".
     * - debug
       - |string|
       - "none"; "radiosity" renders the radiosity solution B/π at the first non-delta hit (the
         paper's Fig. 7); "patches" a colour per patch; "virtual" marks virtual luminaires.
    """

    #: the camera guides the particles of suns, skies and point lights
    #: (:func:`mi_twopass.prepass.radiosity.guide_emission`)
    PREPASS_USES_CAMERA = True

    def _read_props(self, props):
        self._read_far_gather_props(props)
        self.debug = read_choice(props, "debug", "none", DEBUG_MODES)
        self.prepass_scene_path = props.get("prepass_scene", "")
        if self.prepass_scene_path and not os.path.isfile(self.prepass_scene_path):
            raise SceneFileError(f"prepass_scene: file not found: {self.prepass_scene_path}")

    def settings(self):
        return (self.radiosity_settings,)

    @property
    def radiosity_settings(self) -> RadiositySettings:
        """The budget read at load, with GSII's virtual-luminaire threshold (∞ where the far
        gather is off) and the simplified prepass scene."""
        return replace(self.radiosity, vl_threshold=self.vl_threshold_used,
                       vl_contrast=self.vl_contrast, prepass_scene=self.prepass_scene_path)

    # -- prepass ----------------------------------------------------------------------------
    def prepass(self, scene, seed):
        """GSII steps 1–2 (:func:`mi_twopass.prepass.radiosity.build`)."""
        return build_radiosity(scene, self.radiosity_settings, seed,
                               sensor=self.prepass_sensor, memo=self.radiosity_memo)

    def prepass_stats(self, pre):
        st = pre.stats
        return {**st, "prepass_rays": st["radiosity_rays"] + st["probe_rays"],
                "cache_bytes": pre.nbytes}

    # -- gather -----------------------------------------------------------------------------
    def far_reflected(self, ray, si, gather_ray, r_thresh):
        """(B_r/π of the patch a far gather ray sees, far mask) — GSII §2.5.

        A gather ray is *far* when it travels at least ``r_thresh`` and lands on a diffuse
        patch; with a ``prepass_scene`` the ray is traced again in the massing model and reads
        its patches. Virtual luminaires give 0: they are sampled explicitly. The value is the
        element's (``elements_per_patch``; the patch's without elements): see
        :func:`mi_twopass.prepass.radiosity.solve_radiosity` for why a patch mean is biased."""
        pre = self.structure
        sol = pre.solution
        far = gather_ray & si.is_valid() & (si.t >= r_thresh)
        receiver = sol.receiver_at(si, far)  # looked up once for both questions
        far &= sol.receiver_cached(receiver, far)
        pid = receiver
        if sol.elements is not None and pre.virtual.count:  # only virtual luminaires need it
            pid = sol.patches.lookup(si, far)
        if pre.simplified:
            si = pre.scene.ray_intersect(ray, far)
            pid = sol.patches.lookup(si, far & si.is_valid())
            receiver = sol.receiver_at(si, far & si.is_valid())
        counted = far & ~pre.virtual.contains(pid, far) if pre.virtual.count else far
        if sol.elements is None:
            return sol.patch_reflected_radiance(pid, counted), far
        return sol.receiver_reflected_radiance(receiver, counted, si.p), far

    def sample_virtual(self, scene, sampler, si, bsdf, ctx, r_thresh, active, scale=1.0):
        """One explicit sample of a virtual luminaire: f · (B_r/π) · G / pdf, for |y−x| ≥ r_thresh."""
        vl = self.structure.virtual
        if vl.count == 0:
            return mi.Spectrum(0.0), mi.Bool(False)
        sol = self.structure.solution
        pid = vl.sample(sampler.next_1d(active), active)
        p, n, pdf_area = sol.patches.sample_points(pid, sampler.next_2d(active), active)
        d = p - si.p
        dist2 = dr.squared_norm(d)
        dist = dr.sqrt(dist2)
        wo_world = d / dr.maximum(dist, 1e-30)
        # ``n`` is the normal of the patch's own side: a patch emits B_r/π into that side only
        # (the back of a two-sided surface is its own patch); a point behind it gets nothing,
        # however unoccluded the shadow ray (it ends on the surface from behind)
        cos_y = dr.dot(n, -wo_world)
        ok = active & (dist >= r_thresh) & (pdf_area > 0) & (dist2 > 0) & (cos_y > 0)
        # in the scene the patches belong to (the simplified prepass_scene, GSII)
        visible = virtual_point_reached(self.structure.scene, sol, si, wo_world, pid, dist,
                                        scale, ok)
        wo = si.to_local(wo_world)
        f = bsdf.eval(ctx, si, wo, visible)
        pmf = vl.pmf(pid, visible)
        Lr = sol.patch_reflected_radiance(pid, visible)
        G = cos_y / dr.maximum(dist2, 1e-30)
        contrib = f * Lr * G / dr.maximum(pmf * pdf_area, 1e-30)
        return dr.select(visible, contrib, 0.0), ok

    def sample(self, scene, sampler, ray, medium=None, active=True):
        if self.debug != "none":
            return self.sample_debug(scene, sampler, ray, active)
        return self.sample_gather(scene, sampler, ray, active)

    @dr.syntax
    def sample_gather(self, scene, sampler, ray, active):
        """The GSII estimator of the class docstring, one path per lane."""
        r_thresh = mi.Float(self.r_thresh(scene))
        scale, max_depth, want_direct, want_indirect, ctx, lights = \
            self.loop_constants(scene, ray_scale(scene))

        # n_nondelta: non-delta vertices before the current hit
        ray, L, beta, eta, depth, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, \
            prev_lights, active, n_implicit, n_explicit = path_start(ray, active, lights)

        while dr.hint(active, label="radiosity_gather"):
            si, gather_ray, n_implicit = next_hit(scene, ray, depth, prev_bsdf_delta, active,
                                                  n_implicit)

            L += self.emission_met(scene, lights, si, beta, n_nondelta,
                                   (prev_si, prev_bsdf_pdf, prev_bsdf_delta, prev_lights), active)

            # Far gather ray: reflected radiosity of the patch it hits ends the path (§2.5).
            L_far, far = self.far_reflected(ray, si, gather_ray, r_thresh)
            if want_indirect:
                L += beta * L_far

            active_next = active & si.is_valid() & ~far & (depth + 1 < max_depth)
            bsdf = si.bsdf(ray)
            first_vertex = n_nondelta == 0
            smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)

            # Explicit gather from the emitters (Mitsuba's emitter sampling, MIS).
            Ld, cast, here = lights.sample_emitter_mis(scene, si, bsdf, ctx, sampler,
                                                       active_next & smooth, scale)
            n_explicit += dr.select(cast, 1, 0)
            L += by_component(beta * Ld, first_vertex, want_direct, want_indirect)

            # Explicit gather from virtual luminaires (GSII reclassified bright reflectors).
            if want_indirect:
                Lv, vl_ray = self.sample_virtual(scene, sampler, si, bsdf, ctx, r_thresh,
                                                 active_next & smooth, scale)
                L += beta * Lv
                n_explicit += dr.select(vl_ray, 1, 0)

            # Implicit gather ray, sampled from the BSDF.
            prev_lights = here
            ray, beta, eta, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, depth, active = \
                bsdf_step(bsdf, ctx, si, sampler, active_next, scale, beta, eta, n_nondelta, depth,
                          self.rr_depth)

        self.count_after((L,), implicit_rays=n_implicit, explicit_rays=n_explicit)
        return L, mi.Bool(True), []

    def sample_debug(self, scene, sampler, ray, active):
        """Debug views at the first non-delta hit (delta surfaces followed as a path)."""
        sol = self.structure.solution
        si, _, beta, _, stop = first_nondelta_hit(scene, sampler, ray, active)
        pid = sol.patches.lookup(si, stop)
        if self.debug == "radiosity":
            value = sol.radiosity(si, stop) * (1.0 / dr.pi)
        elif self.debug == "patches":
            h = pid * mi.UInt32(2654435761)
            value = mi.Spectrum(mi.Float(h & 255), mi.Float((h >> 8) & 255),
                                mi.Float((h >> 16) & 255)) / 255.0
        else:  # virtual luminaires in white over a dim radiosity view
            is_vl = self.structure.virtual.contains(pid, stop)
            value = dr.select(is_vl, mi.Spectrum(1.0), 0.25 * sol.radiosity(si, stop) / dr.pi)
        return dr.select(stop, beta * value, 0.0), mi.Bool(True), []


mi.register_integrator("radiosity_gather", lambda props: RadiosityGatherIntegrator(props))
