"""``radiance_cache``: SH far field + near-field geometry correction.

Arikan, Forsyth & O'Brien 2005, "Radiance Caching and Local Geometry Correction"
(docs/design.md "Papers"), §4 (far field), §5 (B_C), §7 (BVH), §8.1 (fake GI).
"""
from __future__ import annotations

from dataclasses import replace

import drjit as dr
import mitsuba as mi

from ..prepass.sh_cache import ALPHA_REL, BRIGHT_CONTRAST, NEAR_MERGE_REL, CacheSettings
from ..prepass.pixel_table import PixelTable
from ..prepass.sh_cache import build as build_cache
from ..prepass.sh_cache import refined_count
from ..prepass.spike_grid import SpikeSettings
from .base import (TwoPassIntegrator, read_bool, read_choice, read_float, read_int,
                   read_radiosity_budget)
from .light_samplers import SpikeListSampler
from .pathtrace import (MAX_DELTA_DEPTH, bsdf_step, by_component, first_nondelta_hit,
                        next_hit, path_start)
from .spike_gather import SpikeGatherIntegrator

DEBUG_MODES = ("none", "B_D", "B_C", "samples")
DIRECT_MODES = ("emitter", "spike")

#: accepted range of ``lambda``: 0 (far field alone) … 1 (the physical correction, eq. 2) … this
#: (§8.1, Fig. 12: λ > 1 exaggerates B_C for fake GI); beyond it B_C swamps the image
LAMBDA_MAX = 10.0

#: the cache term's stated bias, as a fraction of the indirect light it replaces (order-2 SH,
#: the coarse radiosity solution, RBF interpolation, the near field's visibility assumption):
#: measured −1 … −10 % (class docstring, "Bias"); tests/integrators/test_radiance_cache*.py
BIAS_BOUND = 0.15


class RadianceCacheIntegrator(TwoPassIntegrator):
    r"""
    .. _integrator-radiance_cache:

    Radiance cache (:monosp:`radiance_cache`)
    ------------------------------------------

    A radiosity prepass (the coarse global solution), a sparse field of order-2 spherical
    harmonics of the *indirect* incident radiance fitted at clusters of the camera's shading
    points (§4.1), and at render time Mitsuba's ``path`` estimator (light sampling and BSDF
    sampling with MIS, Russian roulette; the light's emitter chosen from Zimmerman & Shirley's
    spike lists where the scene has more than one, ``direct``) in which one vertex per path
    reads the cache instead of tracing on: the *cache vertex*, the first purely diffuse surface
    reached from the camera through delta (specular) vertices only, where the shading points
    are::

        L(x) = Le(x) + direct(x) [spike lists (or emitter sampling) + one BSDF ray, MIS]
                     + ρ(x)/π · (B_D(x) + λ · B_C(x))      light reflected by cached surfaces
                     + f·cos/p · L(y), y the BSDF ray's hit, when y is not cached (path traced;
                       past y a ray that lands ≥ alpha away on a cached surface z reads
                       B_r(z)/π of the coarse solution and ends, GSII's far gather)

        B_D = ⟨max(N·ω, 0)⟩ · ⟨L_F⟩                  (eq. 3, RBF-interpolated cluster SH)
        B_C = Σ_{triangles t, centroid within α} (R_t − π L_F(D_t)) · F(x → t)   (eq. 5, irradiance)
            (near_far="mean": R_t − B_D, the paper's eq. 6)

    **What the cache holds.** ρ/π·E describes the outgoing radiance of a *purely diffuse*
    reflector only, and a radiosity B_r/π the light leaving one only. So a surface is *cached*
    where its BSDF has a diffuse-reflection lobe and nothing else (no glossy, delta,
    transmission or null lobe: not ``plastic``, ``blendbsdf``, ``roughconductor``,
    ``thindielectric``, ``mask``) and its receiver of the radiosity solution (the receiving
    element, with elements) on the side hit is diffuse, not cut by geometry, not unevenly lit
    (unless flat, exposed and so refined into cells read at the point hit:
    :mod:`~mi_twopass.prepass.element_grid`) and not a bright reflector
    (:class:`~mi_twopass.prepass.sh_cache.CachedReceivers`). The SH gather rays
    read B_r/π only on cached surfaces (0 elsewhere), the near-field triangles of other
    surfaces have R_t = 0, so ρ/π (B_D + λ B_C) estimates the light that reaches x *from cached
    surfaces* and nothing else. The rest is path traced, never read from the cache: a vertex
    that is not purely diffuse (a glossy, mixed or transmissive camera hit) continues as in
    ``path``; at the cache vertex, the BSDF ray (also the MIS partner of emitter sampling) ends
    on a cached surface (after its emission is counted) and otherwise carries the path on from
    there, except on a bright reflector at least ``alpha`` away, which it reads from the coarse
    solution (``bright_contrast``). Past that surface a ray that lands at least ``alpha`` away
    on a cached surface or a bright reflector reads the surface's reflected radiosity B_r/π
    from the coarse solution and ends there (GSII's far gather, as in ``radiosity_gather``);
    until session 20 such paths ran on to Russian
    roulette (window_interior at 256², 16 spp: render 0.396 → 0.350 s, the indirect light's
    relvar at 128 px 0.0168 → 0.0098, ``tools/variance_parts.py``). This is how light that
    reaches x through specular chains (L S+ D: a lamp behind a window pane, caustics of glass
    and metal, the glossy floor's reflection) is counted, once:
    the radiosity solution holds such light only after a diffuse bounce at another surface
    (its particles follow every BSDF), which B_r of that surface carries to x as ordinary
    indirect light. The back of a one-sided diffuse surface is black, as its BSDF is.

    **max_depth.** The cache holds light of every path length, so with a finite ``max_depth``
    no vertex reads it and the estimator *is* ``path`` (paths of at most ``max_depth``
    segments; 0 black, 1 emitters seen directly), without a prepass.

    **Bias.** The cache term is biased (order-2 SH, the coarse radiosity solution, RBF
    interpolation between clusters, B_C's visibility assumption, the regularised fit of few
    gather rays), and so is the coarse solution's B_r/π read past an uncached surface (a
    receiver's mean, at least alpha away: the light of the third diffuse vertex on); the
    stated bound is :data:`BIAS_BOUND` = 15 % of the indirect light (``path``
    − ``path(max_depth=2)``). Measured (16² px, image means against ``path``): −1 … −4 %
    with the defaults (a closed room, a box lit by a 5 mm sphere, a bulb in a lamp shade);
    −2 … −10 % with small prepasses (256 patches, 64 clusters of 64 gather rays: the Tikhonov
    fit of few rays shrinks toward 0); on tut-cbox, veach-bidir and staircase2 (32² px)
    within ±2 % of the whole image, within the noise. Everything else is unbiased: a scene
    the camera sees no purely diffuse surface in is rendered as ``path``.

    **Scale.** Every offset is relative to the scene's size: rays leave a surface by Mitsuba's
    RayEpsilon × (min(1, bbox diagonal) + |p|) (:func:`mi_twopass.rays.spawn_offset`;
    Mitsuba's own is absolute below 1 m), shadow rays included, so a scene scaled by 1e-4 or 1e4 renders the same image.

    **Infinite emitters in a box that misses shapes.** Mitsuba 3.9.1 gives the mesh it merges
    from shapes sharing a BSDF an invalid ``bbox()``, and a sky, sun or envmap's own
    ``sample_ray`` then starts from the bounding sphere of the other shapes only (a room of
    merged walls: flux ~1e-7 of the true one, or particles starting inside the room). The
    radiosity prepass builds those rays around the geometry's own bounds
    (:func:`mi_twopass.scene.emission.emitter_rays`, as rex's photons), so the cache is built
    there too (until session 8 the integrator warned and rendered ``path``).

    **Media.** The estimator transports light between surfaces only: a scene with a
    participating medium fails at the prepass with a ValueError that names it (render it with
    ``volpath``), unless ``ignore_media`` is set (then media are ignored, as ``path`` does).

    R_t is the *reflected* radiosity of the triangle's receiver and F the point-to-triangle form
    factor: exact (Lambert's formula, finite at corners) for BVH leaves, one disk per BVH node
    farther than 4 × its bounding radius (§7). The far field holds indirect light only (gather
    rays read B_r/π, near hits included: B_C cancels the fit's value in the directions of a
    point's near triangles), so direct light is counted
    once, by emitter sampling. ``alpha → 0`` removes B_C; with ``alpha`` larger than a closed
    scene the near triangles cover every direction, and B_D + B_C is a visibility-free
    one-bounce gather from the radiosity solution.

    The near-field triangles are the cached patches' triangles, with the cached elements' of cut
    or unevenly lit patches (:class:`~mi_twopass.prepass.sh_cache.CachedReceivers`), split
    lazily (§5) by
    longest-edge bisection until smaller than α wherever a camera shading point may lie within α
    of them (:func:`~mi_twopass.prepass.near_field.split_near_triangles`); triangles inside a
    closed solid (faces of overlapping boxes) are left out, since no point sees them
    (:func:`~mi_twopass.prepass.near_field.buried_triangles`). The sum B_D + λ B_C is clamped at
    0 (irradiance; B_C can over-correct where the visibility assumption fails).

    The RBF interpolation visits only the clusters listed in the lane's cell of a uniform grid
    (those whose support touches the cell); the BVH walk skips nodes with no triangle centroid
    within α and nodes whose box lies on or below the tangent plane. Around the shading points
    a read does not walk it: its cell lists the triangles a point of the cell may count
    (:class:`~mi_twopass.prepass.near_field.LeafCells`, built in the prepass for the cells around
    the shading points), and it sums their exact form factors, as the walk from the root does
    with no disks.

    **One evaluation per pixel.** A camera ray's own first hit (no specular vertex before it)
    reads E = max(B_D + λ B_C, 0) interpolated from the pixel centres around its film position
    (:class:`~mi_twopass.prepass.pixel_table.PixelTable`, built at the end of the prepass:
    E at each pixel centre's first hit), over the centres that lie on its surface within
    alpha/4 of it; elsewhere (beside creases and contacts, behind specular vertices) E is
    evaluated per sample. At 16 spp that is about 1 evaluation per pixel, not 16
    (window_interior at 256², 16 spp: 96.6 % of the reads, render 0.40 → 0.29 s,
    ``tools/render_cost.py``). ρ is read per sample.

    Simplifications: ρ/π is the BSDF's value toward the normal at the cache vertex (textures
    included); B_D uses the geometric normal (a shading normal that differs is ignored);
    clusters split on size alone (not on the lazy "gather rays hit inside the sphere"
    criterion); shading points come from the render's sensor (the first without one); only
    the first purely diffuse vertex reached through delta vertices reads the cache (the
    shading points are there), later ones (behind a glossy bounce) are path traced.

    .. pluginparameters::

     * - alpha
       - |float|
       - Near-field radius and cluster size (scene units). Default ``alpha_rel`` × the
         bounding-box diagonal of the camera's shading points (what the camera sees, §6; the
         scene's bounding-box diagonal when there is no sensor).
     * - alpha_rel
       - |float|
       - Default ``alpha`` as a fraction of that diagonal (default: 0.03).
     * - lambda
       - |float|
       - Weight λ of the near-field correction B_C, in [0, 10] (default: 1, the physical
         correction; 0 gives the far field alone; > 1 exaggerates B_C, §8.1 Fig. 12).
     * - fake_gi
       - |bool|
       - §8.1: no global solution; B_D = π · ``ambient`` and every triangle's radiosity 0, so B_C
         darkens where nearby geometry occupies the hemisphere (default: false).
     * - ambient
       - |float|
       - Constant ambient radiance of ``fake_gi`` (default: 0.1).
     * - near_far
       - |string|
       - What a near triangle's radiosity R_t is compared with: "direction" (default) the far
         field in the triangle's direction, π·L_F(D_t) (eq. 5, footnote 1: no constant-L_F
         assumption); "mean" the paper's eq. 6, B_D for every triangle.
     * - direct
       - |string|
       - How direct(x) chooses its emitter: "spike" (default) Zimmerman & Shirley's spike
         lists of the emitters (built on the coarse solution, as ``spike_gather``'s without
         virtual luminaires: the cache holds the reflected light) where the scene has two or
         more emitters, Mitsuba's emitter sampling where it has one (no lists are built);
         "emitter" Mitsuba's emitter sampling always. Either is unbiased (MIS with the BSDF
         ray throughout). The spike lists are the default since session 25: at 256², 2048-spp
         references, they took the time to relMSE 0.01 from 4.62× ``path``'s speed to 5.51×
         on window_interior and from 3.03× to 4.89× on the office, and the equal-time ratio
         from 4.12 to 6.03 on mixed_room, 1.24 to 1.63 on many_lights, 0.75 to 0.88 on the
         caustic and 1.69 to 2.75 on veach-bidir (docs/results/radiance-cache-spike-2026-11-28).
     * - max_patches
       - |int|
       - Patch budget of the radiosity prepass; the cached patches' triangles are the
         near-field triangles, with the elements' where a patch is cut (default: 2048; 4096
         where the spike lists are built, see below).
     * - particles_per_patch
       - |int|
       - Particles the radiosity solver shoots per patch (default: 256; 64 where the spike
         lists are built). At least 65536 in all (``prepass.radiosity.MIN_PARTICLES``),
         however few the patches. Where ``direct="spike"`` builds spike lists (more than one
         emitter) and neither budget is set, the solve is spike_gather's (4096 patches × 64
         particles, the same 262,144 particles as 1024 × 256, half the 2048 × 256 of the
         single-emitter default), as twopass's row of spike lists with the cache has had since
         session 26. At 256², 2048-spp references, 25 s budgets, from 2048 × 256 to that:
         time to relMSE 0.01 window_interior 4.79× → 5.52× ``path``, office 3.76× → 5.62×;
         equal-time ratio mixed_room 6.51 → 7.74, many_lights 3.07 → 4.67; ``check`` at
         128², 64 spp, 16384-spp references, two renders: every bias part within one standard
         error of the old one (docs/results/prepass-points-2026-11-29).
     * - elements_per_patch
       - |int|
       - Receiving elements per radiosity patch (as in ``radiosity_gather``); the SH gather
         rays read the element they hit (default: 4; 1: patch means). A patch's mean is not
         the radiosity where a cluster's gather rays hit it (they find the patch by solid
         angle, not by area): with patch means the image was 0.8 % dark on window_interior
         and 0.55 % on mixed_room. ``check SCENE --res 128 --spp 256 --ref-spp 16384
         --renders 2``, image mean over path's, 1 → 4 elements: window_interior 0.9922 →
         0.9980 (16: 0.9985), mixed_room 0.9945 → 0.9996, office 0.9929 → 0.9941, Cornell
         box, tut-cbox and veach-bidir unchanged within ±0.001; the prepass at 256² costs
         25–35 % more (window_interior 0.82 → 1.10 s, mixed_room 0.84 → 1.05 s: ``bench
         --prepass --quick --scene SCENE --sizes 256 --no-full-hd --integrators
         radiance_cache:elements_per_patch=1,radiance_cache``).
     * - max_points
       - |int|
       - Shading points collected from the camera's view (default: 4096).
     * - max_clusters
       - |int|
       - Most SH samples (clusters) (default: 1024). Where that many clusters within ``alpha``
         cannot cover the shading points, ``alpha`` grows until they can
         (:func:`~mi_twopass.prepass.sh_cache.fit_clusters`; stat ``alpha``): a far field
         stands for a cluster only if the near field reaches as far as the cluster.
     * - parallax
       - |float|
       - κ ≥ 0: clusters are also held within κ / g of each shading point, g the mean of
         [t > alpha] / t over 16 rays from it (t the distance to the geometry hit): the
         translational gradient of Ward et al.'s irradiance cache, so κ bounds the mean angle
         by which the far geometry shifts across a cluster
         (:func:`~mi_twopass.prepass.sh_cache.parallax_limits`). Default 0: clusters within
         alpha only. Where geometry lies just beyond alpha (a floor under a metal plate 0.65 m
         up, alpha 0.67 m), clusters of size alpha blur its occlusion into bands of +20 % and
         −12 % of the image there; 0.1 (with ``max_clusters`` 4096) took them to +6–8 % and −1 %,
         and the bias part (``tools/bias_map.py``, 256², 2 × 256 spp) down by 9–39 % on five
         of six scenes (veach-bidir, noise-bound, +1 %). It costs 1.6–2.4× the clusters,
         +0.05–0.07 s of prepass and about 10 % more render time per sample on the office and
         window_interior (docs/results/mis-plates-2026-11-28). Raise ``max_clusters`` with it,
         or alpha grows.
     * - rays_per_cluster
       - |int|
       - Gather rays per SH sample (default: 128).
     * - bright_contrast
       - |float|
       - Receivers (patches, and elements on their own) whose reflected radiosity is at least
         this many times the cached ones' area-weighted mean (and together carry ≥ 2 % of the
         reflected power) are not cached: the far and near fields read nothing there; a ray
         past the cache vertex that meets them at least alpha away reads their B_r/π from the
         coarse solution and ends, a nearer one traces on (default: 4, the contrast of
         GSII's virtual luminaires; ≥ 1). An order-2 SH field cannot hold a reflector that
         much brighter than the rest (a lamp shade's inside): cached, it made ±20–50 % blotches that moved
         with the prepass seed (:func:`~mi_twopass.prepass.sh_cache.bright_receivers`).
     * - max_near_triangles
       - |int|
       - Budget of the lazy split (§5): splitting stops (longest edges first) when the near
         field would hold more triangles (default: 131072; stat ``split_complete``).
     * - near_cell_rel
       - |float|
       - Cell size of the near field's leaf lists, in units of α (default: 0.5): a cache
         read in a listed cell sums its cell's triangles instead of walking the BVH; smaller
         cells list fewer triangles each but cost more prepass and memory.
     * - near_merge_rel
       - |float|
       - Near-field triangles whose longest edge is below this many α are merged by vertex
         clustering at cells of that side (default: 0.25; 0: never;
         :mod:`~mi_twopass.prepass.near_merge`): a mesh of millions of triangles far smaller
         than α costs the near field what the surface needs at α, not per triangle (stat
         ``near_merged``: the triangles it took away).
     * - pixel_table
       - |bool|
       - Evaluate E once per pixel centre and interpolate it for the camera rays' own hits
         (see above; default: true). false: E at every sample, as before session 21 (an
         orthographic or other camera that cannot project points onto its film always does).
     * - ignore_media
       - |bool|
       - Render a scene with participating media as ``path`` does, ignoring them (default:
         false: such a scene fails at the prepass, naming the medium).
     * - max_depth, rr_depth, seed, component
       - 
       - As every mi_twopass integrator. ``max_depth`` ≥ 0 renders ``path`` (see above).
         ``component``: "direct" = emission + direct light at the first non-delta vertex,
         "indirect" = the rest (the cache term and the paths traced on).
     * - debug
       - |string|
       - "none"; "B_D" renders B_D/π, "B_C" renders λ·B_C/π (signed) at the first non-delta hit;
         "samples" marks the SH sample positions (cluster centres) in white over B_D/π.

    After a render, ``stats`` adds: ``cache_reads`` (cache vertices), ``table_reads`` (those
    served by the pixel table), ``uncovered_reads`` (diffuse camera-chain vertices the far field
    does not hold, traced on), ``pixel_table`` (pixel centres with a value), ``solution_reads``
    (rays past an uncached surface that ended on the coarse solution), ``ART`` (render seconds),
    ``NRT`` (rays traced for GI: the SH gather rays plus the radiosity particles' rays),
    ``NFGS`` (number of SH samples = clusters), ``CS`` (cache bytes: SH field + BVH + start
    lists), ``bvh_visits`` (BVH nodes visited), ``near_triangles`` (after the lazy split),
    ``near_merged`` (triangles the vertex clustering of small ones took away),
    ``split_complete``, ``refined_elements`` (unevenly lit elements read cell by cell:
    :mod:`~mi_twopass.prepass.element_grid`).
    FGO (time over a direct-only render) needs a second render:
    :func:`mi_twopass.evaluation.table1.fgo`
    (``tools/radiance_cache_table.py`` prints the Table 1 columns).
    """

    def _read_props(self, props):
        self.alpha_rel = read_float(props, "alpha_rel", ALPHA_REL, minimum=0.0, strict=True)
        self.alpha_abs = read_float(props, "alpha", 1.0, minimum=0.0, strict=True) \
            if "alpha" in props else None
        #: λ, the near-field correction's weight (XML ``lambda``: a Python keyword)
        self.near_weight = read_float(props, "lambda", 1.0)
        if not 0.0 <= self.near_weight <= LAMBDA_MAX:
            raise ValueError(f"lambda={self.near_weight:.6g}: must be in [0, {LAMBDA_MAX:g}] "
                             "(0: far field alone, 1: the physical near-field correction, "
                             "> 1: exaggerated for fake GI, §8.1)")
        self.fake_gi = read_bool(props, "fake_gi", False)
        self.ignore_media = read_bool(props, "ignore_media", False)
        self.ambient = read_float(props, "ambient", 0.1, minimum=0.0)
        self.radiosity = read_radiosity_budget(props, max_patches=2048, particles_per_patch=256,
                                               elements_per_patch=4)
        #: the XML sets the solve's budget: no other budget where spike lists are built
        self.budget_given = "max_patches" in props or "particles_per_patch" in props
        self.max_points = read_int(props, "max_points", 4096, minimum=1)
        self.max_clusters = read_int(props, "max_clusters", 1024, minimum=1)
        self.parallax = read_float(props, "parallax", 0.0, minimum=0.0)
        self.rays_per_cluster = read_int(props, "rays_per_cluster", 128, minimum=1)
        self.max_near_triangles = read_int(props, "max_near_triangles", 1 << 17, minimum=1)
        self.near_cell_rel = read_float(props, "near_cell_rel", 0.5, minimum=0.0, strict=True)
        self.near_merge_rel = read_float(props, "near_merge_rel", NEAR_MERGE_REL, minimum=0.0)
        self.debug = read_choice(props, "debug", "none", DEBUG_MODES)
        self.near_far = read_choice(props, "near_far", "direction", ("direction", "mean"))
        self.direct = read_choice(props, "direct", "spike", DIRECT_MODES)
        self.bright_contrast = read_float(props, "bright_contrast", BRIGHT_CONTRAST,
                                          minimum=1.0)
        self.pixel_table = read_bool(props, "pixel_table", True)

    def settings(self):
        return (self.alpha_rel, self.alpha_abs, self.fake_gi, self.ambient, self.radiosity,
                self.max_points, self.max_clusters, self.parallax,
                self.rays_per_cluster,
                self.max_near_triangles, self.near_cell_rel, self.near_merge_rel, self.direct,
                self.bright_contrast, self.pixel_table, self.near_weight, self.near_far)

    def builds_spike_lists(self, scene) -> bool:
        """``direct="spike"`` on a scene of more than one emitter (with one, a spike list is
        emitter sampling: none is built, :func:`~mi_twopass.prepass.sh_cache.build`)."""
        return self.direct == "spike" and len(scene.emitters()) > 1

    def radiosity_settings(self, scene):
        """The radiosity solve's budget for ``scene``: the XML's (or the defaults), except
        where spike lists are built and the XML sets no budget: spike_gather's patches and
        particles (``SpikeGatherIntegrator.RADIOSITY_DEFAULTS``, the manual's
        ``particles_per_patch``), so that a scene of many lights pays half the particles."""
        if self.budget_given or not self.builds_spike_lists(scene):
            return self.radiosity
        patches, particles, _ = SpikeGatherIntegrator.RADIOSITY_DEFAULTS
        return replace(self.radiosity, max_patches=patches, particles_per_patch=particles)

    def cache_settings(self, scene) -> CacheSettings:
        """Everything the prepass of ``scene`` reads, from the XML properties (checked at
        load) and, for the solve's budget, the scene's emitters (:meth:`radiosity_settings`)."""
        return CacheSettings(alpha_rel=self.alpha_rel, alpha=self.alpha_abs,
                             fake_gi=self.fake_gi, ambient=self.ambient,
                             radiosity=self.radiosity_settings(scene),
                             max_points=self.max_points, max_clusters=self.max_clusters,
                             parallax=self.parallax,
                             rays_per_cluster=self.rays_per_cluster,
                             bright_contrast=self.bright_contrast,
                             max_near_triangles=self.max_near_triangles,
                             near_cell_rel=self.near_cell_rel,
                             near_merge_rel=self.near_merge_rel, ignore_media=self.ignore_media,
                             path_only=not self.reads_cache and self.debug == "none",
                             debug_view=self.debug != "none",
                             spike=SpikeSettings() if self.direct == "spike" else None)

    def light_sampler(self, scene):
        """The direct light's source choice: the spike lists of the prepass with
        ``direct="spike"`` (:class:`~mi_twopass.integrators.light_samplers.SpikeListSampler`,
        a defensive 10 % over every emitter, so MIS weighs every hit), else Mitsuba's."""
        s = self.structure
        if s is None or s.grid is None:
            return super().light_sampler(scene)
        return SpikeListSampler(s.grid, len(scene.emitters()), r_thresh=0.0, defensive=0.1,
                                support="emitters", selection="cell")

    # -- prepass ----------------------------------------------------------------------------
    def prepass(self, scene, seed):
        """Shading points, coarse solution, SH far field, near field
        (:func:`mi_twopass.prepass.sh_cache.build`)."""
        s = build_cache(scene, self.cache_settings(scene), seed, sensor=self.prepass_sensor,
                        memo=self.radiosity_memo)
        sensor = self.prepass_sensor
        if self.pixel_table and self.debug == "none" and s.cache is not None \
                and sensor is not None and self.reads_cache:
            s.pixels = PixelTable.build(
                scene, sensor, lambda si, n, active: self.irradiance(s, si, n, active)[::2],
                s.lambertian.at, s.alpha)
        return s

    def prepass_stats(self, s):
        lists = {}
        if s.spike is not None:
            st = s.spike.stats
            lists = {"spike_lists": int(s.spike.grid.count),
                     "spike_visibility_rays": int(st.get("visibility_rays", 0)),
                     "spike_camera_rays": int(st.get("camera_rays", 0)),
                     "spike_bytes": int(s.spike.grid.nbytes)}
        return {**self._cache_stats(s), **lists}

    def _cache_stats(self, s):
        if s.cache is None:
            return {"prepass_rays": 0, "NRT": 0, "NFGS": 0, "CS": 0, "cache_bytes": s.nbytes,
                    "alpha": 0.0}
        radiosity_rays = int(s.solution.rays) if s.solution is not None else 0
        cache, near = s.cache, s.near
        cs = int(cache.nbytes + near.nbytes)
        return {"prepass_rays": radiosity_rays + cache.rays + cache.shading_rays,
                "NRT": radiosity_rays + cache.rays, "sh_gather_rays": cache.rays,
                "NFGS": cache.count, "shading_points": int(len(cache.points)),
                "patches": int(s.patches.count), "bvh_nodes": near.node_count,
                "near_triangles": int(len(near.verts)), "near_merged": s.near_merged,
                "split_complete": s.split_complete,
                "CS": cs, "cache_bytes": s.nbytes, "alpha": s.alpha,
                "pixel_table": s.pixels.count if s.pixels is not None else 0,
                "refined_elements": refined_count(s.solution)}

    def _finish_stats(self, sensor, spp, prepass_seconds, render_seconds):
        super()._finish_stats(sensor, spp, prepass_seconds, render_seconds)
        self.stats["ART"] = render_seconds

    # -- render-time irradiance -------------------------------------------------------------
    def irradiance_terms(self, si, n, active, s=None):
        """(B_D, λ·B_C, BVH visits, covered) at ``si`` with viewer-facing normal ``n`` (``s``:
        the prepass, default the integrator's); ``covered``: the far field holds the point
        (clusters of its orientation near it, :meth:`RadianceCache.coefficients`)."""
        s = self.structure if s is None else s
        L_F, covered = s.cache.coefficients(si.p, active, n, coverage=True)
        B_D = s.cache.far_field(si.p, n, active, coeffs=L_F)
        if self.near_weight == 0.0:
            return B_D, mi.Color3f(0.0), mi.UInt32(0), covered
        B_C, visits = s.near.correction(si.p, n, B_D, s.alpha, active,
                                           L_F=L_F if self.near_far == "direction" else None)
        return B_D, self.near_weight * dr.select(active, B_C, 0.0), dr.select(active, visits, 0), \
            covered

    def sample(self, scene, sampler, ray, medium=None, active=True):
        if self.debug != "none":
            return self.sample_debug(scene, sampler, ray, active)
        if self.max_depth == 0:  # as path: no segment, no light
            return mi.Spectrum(0.0), mi.Bool(True), []
        return self.sample_path(scene, sampler, ray, active)

    @property
    def reads_cache(self) -> bool:
        """The cache term is used: ``max_depth = -1`` (the cache holds light of every path
        length, so a path of bounded length may not end in it) and ``component`` wants it."""
        return self.max_depth < 0 and self.want_indirect

    @dr.syntax
    def sample_path(self, scene, sampler, ray, active):
        """The estimator of the class docstring, one path per lane: Mitsuba's ``path`` (emitter
        sampling and BSDF sampling with MIS, Russian roulette), except that at the first
        purely diffuse vertex reached from the camera through delta vertices only (where the
        cache's shading points are) the light reflected by *diffuse* surfaces comes from the
        cache, ρ/π (B_D + λ B_C), and the BSDF ray there goes on only if it meets a surface
        that is not purely diffuse (whose outgoing light the cache does not hold)."""
        s = self.structure
        # the ray offset's length: see mi_twopass.rays.spawn_offset
        scale, max_depth, want_direct, want_indirect, ctx, lights = \
            self.loop_constants(scene, min(1.0, s.scale))
        reads_cache = self.reads_cache and s.cache is not None

        ray, L, beta, eta, depth, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, \
            prev_lights, active, n_implicit, n_explicit = path_start(ray, active, lights)
        camera_chain = mi.Bool(True)  # only delta vertices so far: a diffuse hit reads the cache
        after_cache = mi.Bool(False)  # the previous vertex read the cache
        past_cache = mi.Bool(False)  # an earlier vertex did, and the path went on from there
        far_reads = reads_cache and s.solution is not None
        alpha = dr.opaque(mi.Float, s.alpha)  # follows the prepass: a literal compiled per seed
        n_cache = mi.UInt32(0)
        n_table = mi.UInt32(0)
        uncovered = mi.UInt32(0)
        n_solution = mi.UInt32(0)
        visits = mi.UInt32(0)

        while dr.hint(active, label="radiance_cache"):
            si, gather_ray, n_implicit = next_hit(scene, ray, depth, prev_bsdf_delta, active,
                                                  n_implicit)

            L += self.emission_met(scene, lights, si, beta, n_nondelta,
                                   (prev_si, prev_bsdf_pdf, prev_bsdf_delta, prev_lights), active)

            bsdf = si.bsdf(ray)
            flags = bsdf.flags()
            diffuse = s.lambertian.at(si, active)
            # The BSDF ray of a cache vertex that meets a diffuse surface with a radiosity patch
            # ends here: the light that surface reflects is the cache term (its emission was
            # just counted). Elsewhere (glossy, glass, a shape without patches) it goes on.
            in_cache = mi.Bool(False)
            if reads_cache:
                cached_hit, receiver = s.cached.receiver_at(si, (after_cache | past_cache)
                                                            & diffuse)
                in_cache = cached_hit & after_cache
                # Past the cache vertex's successor, a ray that lands at least alpha away on
                # a cached surface reads that surface's reflected light from the coarse
                # solution and ends, as GSII's far gather ray (radiosity_gather): before,
                # such paths ran on to Russian roulette (window_interior: the 17 % of paths
                # whose cache-vertex BSDF ray met an uncached element took 5.5 loop
                # iterations against 1.9)
                if far_reads:
                    # A bright reflector the cache leaves out (a lamp's shade, the wall
                    # beside a small light) reads the coarse solution too, from the cache
                    # vertex's own BSDF ray on, where it lands at least alpha away: traced on,
                    # its emitter sample toward the light beside it carried 1/r² from a
                    # surface the ray meets rarely (many_lights at 256²: samples of 900 where
                    # the pixel's mean is 0.46, relMSE 1.7e-2 at 256 spp, 8.7e-3 for
                    # spike_gather, whose far gather reads such patches beyond r_thresh)
                    bright = s.cached.bright_at(receiver, (after_cache | past_cache) & diffuse
                                                & ~cached_hit)
                    far = ((cached_hit & past_cache) | bright) & (si.t >= alpha)
                    L += beta * s.solution.receiver_reflected_radiance(receiver, far, si.p)
                    in_cache |= far
                    n_solution += dr.select(far, 1, 0)
            active_next = active & si.is_valid() & ~in_cache & (depth + 1 < max_depth)
            smooth = mi.has_flag(flags, mi.BSDFFlags.Smooth)
            first_vertex = n_nondelta == 0
            if not want_indirect:  # "direct": nothing past the first non-delta vertex's light
                active_next &= first_vertex | ~smooth

            # Emitter sampling (MIS), at every non-delta vertex as in path.
            Ld, cast, here = lights.sample_emitter_mis(scene, si, bsdf, ctx, sampler,
                                                       active_next & smooth, scale)
            n_explicit += dr.select(cast, 1, 0)
            L += by_component(beta * Ld, first_vertex, want_direct, want_indirect)

            # The cache: light reflected by diffuse surfaces toward this diffuse vertex. A
            # symbolic branch: past the first non-delta vertex no lane reads it, and a packet of
            # lanes none of which reads skips the SH interpolation and the near field (masked,
            # they ran at every bounce: window_interior at 256², 16 spp, 0.477 -> 0.443 s,
            # the office 0.525 -> 0.499 s, tools/render_cost.py)
            read = active_next & camera_chain & diffuse & reads_cache
            if reads_cache:
                camera_hit = depth == 0
                Lc, v, served, covered = dr.if_stmt(
                    (si, ray, read, camera_hit), read,
                    lambda si, ray, read, camera_hit: self.cache_term(si, ray, bsdf, ctx, read,
                                                                      camera_hit),
                    lambda si, ray, read, camera_hit: (mi.Color3f(0.0), mi.UInt32(0),
                                                       mi.Bool(False), mi.Bool(False)))
                # a vertex the far field does not hold (no cluster of its orientation near
                # it) is not a cache vertex: its path goes on as at a surface not cached
                uncovered += dr.select(read & ~covered, 1, 0)
                read &= covered
                L += beta * Lc
                n_cache += dr.select(read, 1, 0)
                n_table += dr.select(served, 1, 0)
                visits += v

            prev_lights = here
            camera_chain &= ~smooth
            past_cache |= after_cache
            after_cache = read
            # BSDF sampling.
            ray, beta, eta, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, depth, active = \
                bsdf_step(bsdf, ctx, si, sampler, active_next, scale, beta, eta, n_nondelta, depth,
                          self.rr_depth)

        self.count_after((L,), implicit_rays=n_implicit, explicit_rays=n_explicit,
                         cache_reads=n_cache, table_reads=n_table, solution_reads=n_solution,
                         uncovered_reads=uncovered,
                         bvh_visits=visits)
        return L, mi.Bool(True), []

    def irradiance(self, s, si, n, active):
        """The cache's irradiance max(B_D + λ B_C, 0) (never negative: where B_C
        over-corrects, §6, the sum is clamped; 0 where the far field does not hold the
        point), the BVH nodes visited and where it holds it → ``(E, visits, covered)``."""
        B_D, B_C, visits, covered = self.irradiance_terms(si, n, active, s)
        return dr.select(covered, dr.maximum(B_D + B_C, 0.0), 0.0), visits, covered

    @staticmethod
    def viewer_normal(si, ray):
        """The geometric normal on the side the ray arrives from (the shading points' side)."""
        return dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)

    def cache_term(self, si, ray, bsdf, ctx, active, camera_hit):
        """ρ/π · E at a purely diffuse vertex, E = max(B_D + λ B_C, 0) (:meth:`irradiance`).
        ρ/π is the BSDF's value toward the normal on the viewer's side, so the back of a
        one-sided diffuse surface is black, as its BSDF is, and textures are read at ``si``.
        Where the vertex is the camera ray's own hit (``camera_hit``) and the prepass has a
        :class:`~mi_twopass.prepass.pixel_table.PixelTable`, E is interpolated from its pixel
        centres where they lie on the vertex's surface; a symbolic branch evaluates it
        everywhere else. → ``(value, BVH nodes visited, read from the table, covered)``;
        ``covered`` False where the far field does not hold the vertex (value 0): the caller
        traces the path on there as at a surface the cache does not hold."""
        s = self.structure
        n = self.viewer_normal(si, ray)
        if s.pixels is not None:
            E, served = s.pixels.lookup(si.p, n, active & camera_hit)
            need = active & ~served
            E_here, visits, covered = dr.if_stmt(
                (si, n, need), need,
                lambda si, n, need: self.irradiance(s, si, n, need),
                lambda si, n, need: (mi.Color3f(0.0), mi.UInt32(0), mi.Bool(False)))
            E = dr.select(served, E, E_here)
            covered = served | covered
        else:
            E, visits, covered = self.irradiance(s, si, n, active)
            served = mi.Bool(False)
        up = mi.Vector3f(0.0, 0.0, dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0))
        f = bsdf.eval(ctx, si, up, active)  # = ρ/π · |cos| with cos = 1
        return dr.select(active & covered, f * E, 0.0), visits, served, active & covered

    def sample_debug(self, scene, sampler, ray, active):
        """Debug views at the first non-delta hit (delta surfaces followed as a path)."""
        max_delta = MAX_DELTA_DEPTH if self.max_depth < 0 else min(self.max_depth, MAX_DELTA_DEPTH)
        si, ray, beta, _, gather = first_nondelta_hit(scene, sampler, ray, active, max_delta)
        B_D, B_C, visits, _ = self.irradiance_terms(si, self.viewer_normal(si, ray), gather)
        self.count("bvh_visits", visits)
        if self.debug == "B_D":
            value = B_D / dr.pi
        elif self.debug == "B_C":
            value = B_C / dr.pi
        else:  # "samples"
            value = dr.select(self.near_sample(si.p, gather), mi.Color3f(1.0), B_D / dr.pi)
        return dr.select(gather, beta * value, 0.0), mi.Bool(True), []

    def near_sample(self, p, active):
        """Debug "samples": within 0.2 α of an SH sample position (a cluster centre)."""
        cache = self.structure.cache
        if cache.count == 0:
            return mi.Bool(False)
        return cache.near_centre(p, 0.2 * self.structure.alpha, active)


mi.register_integrator("radiance_cache", lambda props: RadianceCacheIntegrator(props))
