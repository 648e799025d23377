"""``spike_gather``: radiosity prepass + spike lists on a grid + one explicit and one implicit ray
per gather (Zimmerman & Shirley 1995, docs/design.md "Papers", §2.6, §3 and §4).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..prepass.radiosity import virtual_point_reached
from ..prepass.spike_grid import INVALID, SpikeSettings
from ..prepass.spike_grid import build as build_spike
from ..rays import shadow_ray
from ..scene.emission import has_infinite_emitters
from ..scene.bounds import ray_scale
from .base import (FarGatherIntegrator, needs_memory, read_bool, read_choice, read_float,
                   read_int)
from .light_samplers import SpikeListSampler, receiver
from .pathtrace import (bsdf_step, by_component, first_nondelta_hit, mis_weight, next_hit,
                        path_start)

DEBUG_MODES = ("none", "list_length", "radiosity")

_TINY = 1e-30


class VirtualSample:
    """An explicit sample of a virtual luminaire (:meth:`SpikeGatherIntegrator.sample_virtual`):
    the lanes that ``cast`` a ray, those whose ray ``reached`` the point, its direction ``d``
    and ``radiance_over_pdf``."""

    DRJIT_STRUCT = {"cast": mi.Bool, "reached": mi.Bool, "d": mi.Vector3f,
                    "radiance_over_pdf": mi.Spectrum}

    def __init__(self, cast=None, reached=None, d=None, radiance_over_pdf=None):
        self.cast, self.reached, self.d = cast, reached, d
        self.radiance_over_pdf = radiance_over_pdf


def colour_ramp(t):
    """A blue → cyan → green → yellow → red ramp of ``t`` ∈ [0, 1] (Dr.Jit)."""
    t = dr.clip(t, 0.0, 1.0)

    def ch(c):
        return dr.clip(1.5 - dr.abs(4.0 * t - c), 0.0, 1.0)

    return mi.Spectrum(ch(3.0), ch(2.0), ch(1.0))


class SpikeGatherIntegrator(FarGatherIntegrator):
    r"""
    .. _integrator-spike_gather:

    Spike gather (:monosp:`spike_gather`)
    -------------------------------------

    Zimmerman & Shirley's gather for scenes with many luminaires (§3.3): GSII's radiosity prepass
    (§2.5) plus, in the cells of a regular grid, a *spike list* of the sources that are bright
    and visible there (§3.2, §4). At every non-delta vertex x::

        L(x) = Le(x)                                     [camera rays and delta chains]
             + ONE shadow ray to a source i of x's spike list, chosen with
                   α_i = g_i·L'_i(x) / Σ_j g_j·L'_j(x)   (§4; L' has the geometry term)
             + f(x) · { path-trace recursively          if |y − x| <  r_thresh
                      { B_r(patch(y)) / π               otherwise (unless a listed VL)
             + emission met by the implicit ray y        (the paper: unlisted sources, far y;
                                                          here: every emitter, MIS-weighted)

    Sources are every emitter (area, point, spot, directional, constant, envmap) plus the
    radiosity solution's bright reflectors ("virtual luminaires", VL, GSII's reclassification).
    The lists, their visibility fractions g_i (the paper's self-refining point sampling) and
    the source proxies are built in :mod:`mi_twopass.prepass.spike_grid` (see its docstring for
    I_i, E_i, the bands E_low/E_high, influence regions and the camera-seen cells).

    **List choice (§4, boundary weighting), as a mixture.** The paper picks the list of a
    neighbouring cell for points near a cell boundary. Here x is jittered by up to ±½ cell per
    axis (``jitter``) and the source is drawn from an equal *mixture* of x's own list (a) and
    the jittered point's list (b, where it differs), P(i) = ½α_a(i) + ½α_b(i), both lists
    swept by reservoir sampling. The boundary is still blended as in the paper, but a light
    that x's own cell sees is never dropped because the jitter crossed a wall into a cell that
    does not (the paper's rule, measured on a three-room test scene, halved the efficiency
    through fireflies of such lights and, without ``complete``, lost them). A vertex whose
    cells have no list (not seen by the camera pass: deeper vertices, thin objects) falls back
    to Mitsuba's strategy, a uniformly chosen emitter with MIS (as ``radiosity_gather``), and
    its far gather adds every patch's B_r.

    **Every source is covered (the ``complete`` knob).** The paper counts a listed source only
    explicitly and an unlisted one only through the implicit ray, and only when that ray is
    far (§3.3); near unlisted sources are lost (§5.3's truncation). With ``complete = true``
    (default) the emission of every emitter met by the implicit ray is counted, whatever its
    distance and whether it is listed, weighted by MIS (power heuristic) against the explicit
    strategy's probability of the same direction, P(i)·p_i(ω), recomputed at the hit from the
    lists' sums W kept from the vertex. The explicit choice is a mixture: with probability
    ε = ``defensive`` a uniformly chosen emitter (probability 1 where the lists' weights sum to
    0), else the lists,

        P(i) = ε·[i an emitter]/K + (1 − ε)·(½α_a(i) + ½α_b(i)),

    so every emitter, listed or not, delta or not, has a positive explicit probability wherever
    it can contribute, and the estimator is unbiased however the lists were truncated: a source
    falsely excluded by the point-sampled visibility, or left out by E_low or its influence
    region, becomes noise, not bias. (This deviates from the paper to keep the limit exact.
    Without the defensive term, point lights falsely excluded from the lists of a three-room
    test scene lost 3 % of its image. On ``many_lights.xml`` at 256 spp the mean relMSE of ten
    renders was 0.021 for the pure partition (``mis = false``), 0.016 with MIS and ε = 0,
    0.014–0.017 with ε = 0.05–0.2, 0.014 for the paper's biased estimator; on the three-room
    scene ε = 0.1 doubled the *median* per-pixel variance of the direct light while leaving
    its mean unchanged. The default 0.1 trades between these.)

    ``mis = false`` gives the paper's *partition* instead: listed sources only explicitly,
    unlisted ones only implicitly (with ``complete``, at any distance), and the defensive
    component covers only delta sources (point, spot, directional), which no ray can meet. With
    ``complete = false`` the paper's estimator (§3.3 pseudocode) is reproduced: ε = 0, the
    emission of an unlisted source counts only when the implicit ray is *far* (≥ r_thresh, the
    pseudocode's ``radsimp_color``, or a miss for an environment), near ones are lost; listed
    emitters keep MIS unless ``mis = false``.

    **Virtual luminaires** are counted as in ``radiosity_gather``: explicitly only for
    |y − x| ≥ r_thresh (their L' is 0 where the whole patch is nearer), a far implicit ray that
    lands on a *listed* VL adds nothing, one on an unlisted patch adds its B_r/π. With
    ``r_thresh`` larger than the scene the method is path tracing with many-light sampling,
    which the tests compare with Mitsuba's ``path``.

    **Global (infinite) emitters** (directional, constant, envmap) are ordinary sources with
    E = ∞: candidates in every cell and visibility-tested like the others (rays along the
    emitter's own sampled directions), so the window scene's sun is listed where it shines in
    and excluded where walls block it. Where it is not listed, both are still reached by the
    defensive component (``complete``), the sky by implicit rays too.

    Exactly one explicit (shadow) and one implicit (gather) ray leave every non-delta vertex;
    ``stats`` counts them (``explicit_rays``, ``implicit_rays``) with the prepass's
    ``prepass_rays`` (radiosity + camera pass + ``visibility_rays``), ``spike_list_mean``,
    ``spike_list_max``, ``cells_with_lists``, ``grid_bytes`` and ``cache_bytes`` (grid + lists
    + radiosity solution).

    .. pluginparameters::

     * - grid_res
       - |int|
       - Cells of the spike grid along the longest axis of the scene's bounding box (cubic
         cells; default: 32). Must be > 0.
     * - e_high
       - |float|
       - E_high (W/m²): sources of emittance ≥ e_high are candidates in every cell. Default:
         ``e_high_rel`` × the median emittance Φ/A of the scene's area lights.
     * - e_high_rel
       - |float|
       - Default ``e_high`` relative to the median area-light emittance (default: 4).
     * - e_low
       - |float|
       - E_low (W/m²): sources below it are left to implicit sampling. Default: ``e_low_rel`` ×
         the median area-light emittance.
     * - e_low_rel
       - |float|
       - Default ``e_low`` relative to the median area-light emittance (default: 0.1).
     * - influence
       - |float|
       - Irradiance (W/m²) bounding the influence region of a source with E_low ≤ E < E_high
         and of every VL: it is a candidate in a cell where I_i / d² ≥ influence. Default:
         ``influence_rel`` × the median patch irradiance of the radiosity solution.
     * - influence_rel
       - |float|
       - Default ``influence`` relative to the median patch irradiance (default: 0.01).
     * - visibility_max_rays
       - |int|
       - Most rays of the self-refining visibility estimate per (cell, source) (default: 100,
         the paper's; rounds of 10). Most of them go to pairs that are wholly occluded (the
         rule goes on while one or fewer rays arrive): on ``many_lights.xml`` 20 gave the same
         bias and relMSE with 1.6 M instead of 7.6 M rays (README "Results").
     * - visibility_occluded_rays
       - |int|
       - A pair none of whose first this many rays reached the source is left out of the
         list (g = 0) without the remaining rounds (default: 20; ≥ ``visibility_max_rays``:
         the paper's rule). ``complete=true`` stays unbiased for a source left out.
     * - camera_res
       - |int|
       - Rays along the film's longer side of the camera pass that finds the cells needing a
         list (default: 128). A cell the pass misses has no list and its gathers fall back to
         all emitters: on ``many_lights.xml`` 64² the pixel variance at 128 spp (five renders)
         was 0.025 with 64, 0.015 with 128, 0.013 with 256, for 1500 / 1981 / 2244 lists
         (``tools/spike_noise.py spike_gather:camera_res=64 ...``).
     * - cell_points
       - |int|
       - Visibility sample points kept per cell (camera hits, default: 8).
     * - gather_cells
       - |bool|
       - Also give lists to the cells where near gather rays (shorter than ``r_thresh``) from
         the camera's points land: the recursion gathers explicitly there, and a vertex in a
         cell without a list falls back to choosing among all emitters (default: true; false:
         camera-seen cells only).
     * - jitter
       - |float|
       - Boundary weighting: the second list is the cell of x jittered by up to ±jitter/2
         cells per axis (default: 1, the paper's; 0 uses x's own list only).
     * - complete
       - |bool|
       - true: every emitter met by an implicit ray counts (MIS-weighted), every emitter has
         a defensive explicit probability: unbiased whatever the lists (default). false: the
         paper's estimator, truncated (§5.3).
     * - selection
       - |string|
       - How a listed source is chosen at a shading point x: "cell" (default) ∝ per-cell
         weights g·L' (L' averaged over the cell's visibility points), by a binary search in
         the list's CDF; "point" (the paper's §4) ∝ g·L'(x) estimated at x for every source of
         both lists. Both are unbiased; "cell" costs less per vertex and ignores where in the
         cell x lies (time × error: docs/results/spike-selection-2026-11-25.md).
     * - defensive
       - |float|
       - Probability ε of choosing an emitter uniformly (only delta ones when ``mis`` is
         false) instead of from the lists (``complete`` only; default: 0.1; in [0, 1)).
     * - mis
       - |bool|
       - MIS between the explicit and the implicit strategy (default: true); false: the paper's
         partition (listed sources only explicitly, the others only implicitly).
     * - r_thresh, r_thresh_rel
       -
       - As every far-gather integrator (:class:`~mi_twopass.integrators.base.FarGatherIntegrator`):
         gather rays shorter than ``r_thresh`` trace on (default: 0.05 × the bounding-box
         diagonal of what the camera sees, its rays' first non-delta hits:
         :meth:`~mi_twopass.integrators.base.FarGatherIntegrator.view_diagonal`).
     * - max_patches
       - |int|
       - Patch budget of the radiosity prepass (default: 4096).
     * - particles_per_patch
       - |int|
       - Particles the stochastic radiosity solver shoots per patch (default: 64, a quarter of
         ``radiosity_gather``'s: here the radiosity only feeds far gather rays and the
         reclassified sources; on ``many_lights.xml`` 64² the relMSE at 512 spp was the same
         as with 256, 9.5e-3, and the prepass 0.4 s shorter; ``tools/spike_truncation.py``).
         At least 65536 in all (``prepass.radiosity.MIN_PARTICLES``).
     * - elements_per_patch
       - |int|
       - Receiving elements per radiosity patch, read by far gather rays (as in
         ``radiosity_gather``: a patch's area mean reads dark where gather rays land on its
         lit part; default: 4, i.e. 16 k elements at the default 4096 patches, the element
         count of ``radiosity_gather``'s defaults; 1 turns them off).
     * - vl_threshold
       - |float|
       - Patches with B_r ≥ vl_threshold × max B_r become sources (virtual luminaires; default:
         0.5; a value > 1 disables reclassification).
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
       - "none"; "list_length" colours the first non-delta hit by the length of its cell's
         spike list (blue: short, red: the longest list; black: no list); "radiosity" renders
         the radiosity solution B/π there (the paper's Fig. 7).
    """

    RADIOSITY_DEFAULTS = (4096, 64, 4)

    def _read_props(self, props):
        self.grid_res = read_int(props, "grid_res", 32, minimum=1, maximum=512,
                                 why="cells along the longest axis of the scene's bounding box: "
                                     "a cubic scene would need 512³ = 2^27 cells")
        self.e_high_rel = read_float(props, "e_high_rel", 4.0, minimum=0.0, strict=True)
        self.e_low_rel = read_float(props, "e_low_rel", 0.1, minimum=0.0)
        self.e_high = read_float(props, "e_high", 0.0, minimum=0.0) if "e_high" in props else None
        self.e_low = read_float(props, "e_low", 0.0, minimum=0.0) if "e_low" in props else None
        if self.e_high is None and self.e_low is None and self.e_low_rel > self.e_high_rel:
            raise ValueError(f"e_low_rel={self.e_low_rel}: must be <= e_high_rel="
                             f"{self.e_high_rel}")
        if self.e_high is not None and self.e_low is not None and self.e_low > self.e_high:
            raise ValueError(f"e_low={self.e_low}: must be <= e_high={self.e_high}")
        self.influence_rel = read_float(props, "influence_rel", 0.01, minimum=0.0)
        self.influence = read_float(props, "influence", 0.0, minimum=0.0) \
            if "influence" in props else None
        self.visibility_occluded_rays = read_int(
            props, "visibility_occluded_rays", 20, minimum=10, maximum=10_000,
            why="rays per (cell, source) pair before an unreached source is left out")
        self.visibility_max_rays = read_int(props, "visibility_max_rays", 100, minimum=10,
                                            maximum=10_000, why="rays per (cell, source) pair: "
                                            "the prepass's time grows with it")
        self.camera_res = read_int(props, "camera_res", 128, minimum=1, maximum=4096,
                                   why=lambda v: needs_memory(200, "the camera pass's rays")(v * v))
        self.cell_points = read_int(props, "cell_points", 8, minimum=1, maximum=1024,
                                    why="visibility points per cell: the visibility rays grow "
                                        "with it")
        self.gather_cells = read_bool(props, "gather_cells", True)
        self.jitter = read_float(props, "jitter", 1.0, minimum=0.0)
        self.complete = read_bool(props, "complete", True)
        self.mis = read_bool(props, "mis", True)
        self.selection = read_choice(props, "selection", "cell", SpikeListSampler.SELECTIONS)
        self.defensive = read_float(props, "defensive", 0.1, minimum=0.0)
        if self.defensive >= 1.0:
            raise ValueError(f"defensive={self.defensive}: must be < 1")
        self._read_far_gather_props(props)
        self.debug = read_choice(props, "debug", "none", DEBUG_MODES)

    def settings(self):
        return (self.grid_res, self.e_high_rel, self.e_low_rel, self.e_high, self.e_low,
                self.influence_rel, self.influence, self.visibility_max_rays,
                self.visibility_occluded_rays, self.camera_res,
                self.cell_points, self.radiosity, self.vl_threshold_used, self.vl_contrast,
                self.gather_cells, self.r_thresh_rel, self.r_thresh_abs)

    def spike_settings(self, scene) -> SpikeSettings:
        return SpikeSettings(grid_res=self.grid_res, camera_res=self.camera_res,
                             cell_points=self.cell_points, influence=self.influence,
                             influence_rel=self.influence_rel,
                             visibility_max_rays=self.visibility_max_rays,
                             visibility_occluded_rays=self.visibility_occluded_rays,
                             gather_reach=self.r_thresh(scene) if self.gather_cells else 0.0,
                             vl_threshold=self.vl_threshold_used,
                             vl_contrast=self.vl_contrast, e_high_rel=self.e_high_rel,
                             e_low_rel=self.e_low_rel, E_high=self.e_high, E_low=self.e_low)

    # -- prepass ----------------------------------------------------------------------------
    def prepass(self, scene, seed):
        """GSII steps 1–2 (patches, radiosity), then §3.3 step 3: sources and spike lists
        (:func:`mi_twopass.prepass.spike_grid.build`)."""
        return build_spike(scene, self.spike_settings(scene), self.radiosity, seed,
                           sensor=self.prepass_sensor, memo=self.radiosity_memo)

    def prepass_stats(self, pre):
        st = dict(pre.stats)
        st.update(
            prepass_rays=int(pre.solution.rays) + st["probe_rays"] + st["camera_rays"]
            + st["visibility_rays"],
            grid_bytes=int(pre.grid.nbytes), radiosity_bytes=int(pre.solution.nbytes),
            cache_bytes=int(pre.nbytes))
        return st

    # -- render -----------------------------------------------------------------------------
    def sample(self, scene, sampler, ray, medium=None, active=True):
        if self.debug != "none":
            return self.sample_debug(scene, sampler, ray, active)
        if len(scene.emitters()) == 0:  # no light at all: black, as Mitsuba's path renders it
            return mi.Spectrum(0.0), mi.Bool(True), []
        return self.sample_gather(scene, sampler, ray, active)

    def light_sampler(self, scene) -> SpikeListSampler:
        """The explicit strategy's source choice (§2.6, §4) over this prepass's lists:
        :class:`mi_twopass.integrators.light_samplers.SpikeListSampler`. The defensive
        component covers every emitter where MIS can weight its hits, else only the sources no
        implicit ray can meet (delta)."""
        support = "emitters" if self.complete and self.mis else "delta"
        return SpikeListSampler(self.structure.grid, len(scene.emitters()), self.r_thresh(scene),
                                defensive=self.defensive if self.complete else 0.0,
                                support=support, jitter=self.jitter,
                                selection=self.selection)

    @dr.syntax
    def sample_gather(self, scene, sampler, ray, active):
        """The estimator of the class docstring, one path per lane."""
        pre = self.structure
        sol = pre.solution
        r_thresh = mi.Float(self.r_thresh(scene))
        scale, max_depth, want_direct, want_indirect, ctx, lights = \
            self.loop_constants(scene, ray_scale(scene))
        complete, use_mis = self.complete, self.mis
        emitters = scene.emitters_dr()

        # n_nondelta: non-delta vertices before the current hit
        ray, L, beta, eta, depth, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, \
            prev_lights, active, n_implicit, n_explicit = path_start(ray, active, lights)
        n_fallback = mi.UInt32(0)  # explicit gathers at vertices whose cells have no list

        while dr.hint(active, label="spike_gather"):
            si, gather_ray, n_implicit = next_hit(scene, ray, depth, prev_bsdf_delta, active,
                                                  n_implicit)
            from_list = gather_ray & prev_lights.has_list

            # -- Emission met by this ray: MIS against the previous vertex's choice, or the
            #    paper's partition by its lists.
            ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
            Le = ds.emitter.eval(si, active)
            hit_sid = lights.source_of_emitter(ds.emitter, gather_ray)
            P_hit, listed = lights.pmf_listed(prev_lights, hit_sid, gather_ray)
            pdf_dir = ds.emitter.pdf_direction(prev_si, ds, gather_ray)
            w_mis = mis_weight(prev_bsdf_pdf, P_hit * pdf_dir)
            if use_mis:
                w_listed = w_mis
            else:
                w_listed = mi.Float(0.0)
            if complete and use_mis:  # every emitter has an explicit strategy: MIS throughout
                w_unlisted = w_listed
            elif complete:  # the partition: implicit only
                w_unlisted = mi.Float(1.0)
            else:  # the paper: only far implicit rays gather (a miss has t = inf)
                w_unlisted = dr.select(si.t >= r_thresh, 1.0, 0.0)
            # without a list the previous vertex sampled an emitter uniformly, with MIS
            w_emit = dr.select(prev_bsdf_delta, 1.0,
                               dr.select(~from_list, w_mis,
                                         dr.select(listed, w_listed, w_unlisted)))
            Le = beta * w_emit * Le
            L += by_component(Le, n_nondelta <= 1, want_direct, want_indirect)

            # -- Far gather ray: B_r/pi of the patch hit ends the path, unless it is a VL of
            #    the lists used (then it was sampled explicitly).
            far = gather_ray & si.is_valid() & (si.t >= r_thresh)
            hit_receiver = sol.receiver_at(si, far)  # looked up once for both questions
            far &= sol.receiver_cached(hit_receiver, far)
            if want_indirect:
                vl_listed = self.listed_virtual(lights, prev_lights, si, far & from_list)
                # the receiving element hit (the patch's value without elements)
                L += beta * sol.receiver_reflected_radiance(hit_receiver, far & ~vl_listed,
                                                            si.p)

            active_next = active & si.is_valid() & ~far & (depth + 1 < max_depth)
            bsdf = si.bsdf(ray)
            first_vertex = n_nondelta == 0
            smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            active_em = active_next & smooth
            n_r, two = receiver(si, bsdf)

            # -- Explicit gather: one source of the spike lists (section 4), or an emitter
            #    uniformly where the cell has no list.
            sid, P_sel, here = lights.sample(si, n_r, two, sampler, active_em)
            u_pos = sampler.next_2d()
            chosen = active_em & (sid != INVALID) & (P_sel > 0)
            is_vl = lights.is_patch(sid, chosen) if self.has_virtual else mi.Bool(False)
            sample_em = chosen & ~is_vl
            use_fb = sample_em & ~here.has_list

            emitter = dr.gather(mi.EmitterPtr, emitters, lights.emitter_index(sid, sample_em),
                                sample_em)
            ds_l, spec_l = emitter.sample_direction(si, u_pos, sample_em)
            is_em = sample_em & (ds_l.pdf > 0)

            vl = self.sample_virtual(scene, si, sid, u_pos, is_vl, r_thresh, scale)
            is_vl = vl.reached

            # emitters: a shadow ray; reclassified patches: the ray of sample_virtual
            cast = is_em | vl.cast
            shadow = shadow_ray(si, ds_l, scale, has_infinite_emitters(scene))
            visible = (is_em & ~scene.ray_test(shadow, is_em)) | is_vl
            n_explicit += dr.select(cast, 1, 0)
            n_fallback += dr.select(use_fb & is_em, 1, 0)

            wo = si.to_local(dr.select(is_vl, vl.d, ds_l.d))
            f, bsdf_pdf = bsdf.eval_pdf(ctx, si, wo, visible)
            w_em = mis_weight(P_sel * ds_l.pdf, bsdf_pdf)
            if not use_mis:  # the paper's partition for listed sources (fallback keeps MIS)
                w_em = dr.select(use_fb, w_em, 1.0)
            w_em = dr.select(ds_l.delta, 1.0, w_em)
            contrib_em = spec_l * (w_em / dr.maximum(P_sel, _TINY))
            contrib_vl = vl.radiance_over_pdf / dr.maximum(P_sel, _TINY)
            Ld = beta * f * dr.select(is_vl, contrib_vl, contrib_em)
            Ld = dr.select(visible & dr.all(dr.isfinite(Ld)), Ld, 0.0)
            L += by_component(Ld, is_em & first_vertex, want_direct, want_indirect)

            # -- Implicit gather ray, sampled from the BSDF.
            prev_lights = here
            ray, beta, eta, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, depth, active = \
                bsdf_step(bsdf, ctx, si, sampler, active_next, scale, beta, eta, n_nondelta, depth,
                          self.rr_depth)

        self.count_after((L,), implicit_rays=n_implicit, explicit_rays=n_explicit,
                         fallback_gathers=n_fallback)
        return L, mi.Bool(True), []

    @property
    def has_virtual(self) -> bool:
        """Does the prepass have virtual luminaires. Without, their code is left out of the
        render kernel: its masked gathers, surface interaction and patch lookups cost every
        lane, used or not (about a quarter of a sample on many_lights at 128²,
        tools/render_cost.py)."""
        return self.structure.sources.patch_count > 0

    def listed_virtual(self, lights, ctx, si, active):
        """Lanes whose far gather ray met a virtual luminaire of the lists of ``ctx`` (the
        vertex it left): that light was sampled explicitly there, so the far gather adds
        nothing."""
        if not self.has_virtual:
            return mi.Bool(False)
        pre = self.structure
        pid = pre.solution.patches.lookup(si, active)
        return lights.listed(ctx, pre.sources.source_of_patch(pid, active), active)

    def sample_virtual(self, scene, si, sid, u, active, r_thresh, scale) -> VirtualSample:
        """The explicit sample of source ``sid`` where it is a virtual luminaire (``active``):
        a point y on its patch (uniform by area, from ``u``), and whether the ray towards it
        first meets the patch where the radiosity is cached
        (:func:`~mi_twopass.prepass.radiosity.virtual_point_reached`) at |y − x| ≥ r_thresh.
        The radiance over the area density, B_r/π · cos_y / (|y − x|² · pdf_A), is what the
        caller divides by the source's probability."""
        if not self.has_virtual:
            return VirtualSample(mi.Bool(False), mi.Bool(False), mi.Vector3f(0.0),
                                 mi.Spectrum(0.0))
        pre = self.structure
        sol = pre.solution
        pid = pre.sources.gather("patch_id", sid, active)
        p_y, n_y, pdf_a = sol.patches.sample_points(pid, u, active)
        d_y = p_y - si.p
        dist2 = dr.squared_norm(d_y)
        dist = dr.sqrt(dist2)
        w_y = d_y / dr.maximum(dist, _TINY)
        cos_y = dr.dot(n_y, -w_y)
        cast = active & (dist >= r_thresh) & (pdf_a > 0) & (cos_y > 0) & (dist2 > 0)
        reached = virtual_point_reached(scene, sol, si, w_y, pid, dist, scale, cast)
        value = sol.patch_reflected_radiance(pid, cast) * (
            cos_y / dr.maximum(dist2 * pdf_a, _TINY))
        return VirtualSample(cast, reached, w_y, value)

    def sample_debug(self, scene, sampler, ray, active):
        """Debug views at the first non-delta hit (delta surfaces followed as a path)."""
        pre = self.structure
        sol, grid = pre.solution, pre.grid
        longest = float(max(int(pre.grid.lengths.max()) if pre.grid.count else 0, 1))
        si, _, beta, _, stop = first_nondelta_hit(scene, sampler, ray, active)
        if self.debug == "radiosity":
            value = sol.radiosity(si, stop) * (1.0 / dr.pi)
        else:
            lid = grid.list_at(si.p, stop)
            _, count = grid.list_range(lid, stop)
            value = dr.select(lid != INVALID, colour_ramp(mi.Float(count) / longest), 0.0)
        return dr.select(stop, beta * value, 0.0), mi.Bool(True), []

    def to_string(self):
        return (f"SpikeGatherIntegrator[grid_res={self.grid_res}, complete={self.complete}, "
                f"mis={self.mis}, max_depth={self.max_depth}, component={self.component}]")


mi.register_integrator("spike_gather", lambda props: SpikeGatherIntegrator(props))
