"""``radiance_cache``: SH far field + near-field geometry correction.

Arikan, Forsyth & O'Brien 2005, "Radiance Caching and Local Geometry Correction"
(shared/papers/004_*), §4 (far field), §5 (B_C), §7 (BVH), §8.1 (fake GI).
"""
from __future__ import annotations

import numpy as np

import drjit as dr
import mitsuba as mi

from ..prepass.near_field import build_near_field, buried_triangles, split_near_triangles
from ..prepass.radiance_cache import (build_radiance_cache, collect_shading_points,
                                      default_alpha)
from ..prepass.radiosity import receiving_elements, solve_radiosity
from ..scene.patches import build_patches
from .base import TwoPassIntegrator, read_choice, read_float, read_int
from .pathtrace import MAX_DELTA_DEPTH, emission_mis, emitter_sample_mis, first_nondelta_hit

DEBUG_MODES = ("none", "B_D", "B_C", "samples")

#: default alpha as a fraction of the bounding-box diagonal of the camera's shading points.
#: window_interior 64² (diagonal 7.7 m), relMSE at 256 spp against path: 0.0037 at 0.02 and
#: 0.03, 0.0052 at 0.05, 0.0075 at 0.1 (darker as alpha grows: the visibility assumption of
#: B_C, §6); 0.03 needs about half the SH samples of 0.02.
ALPHA_REL = 0.03


class CacheStructure:
    """The prepass output: ``alpha``, ``patches``, ``solution`` (None with fake_gi), ``cache``
    (:class:`~mi_twopass.prepass.radiance_cache.RadianceCache`) and ``near``
    (:class:`~mi_twopass.prepass.near_field.NearField`). A plain class, indexable by name: Dr.Jit
    does not traverse it as loop state."""

    def __init__(self, **parts):
        self.__dict__.update(parts)

    def __getitem__(self, name):
        return self.__dict__[name]


class RadianceCacheIntegrator(TwoPassIntegrator):
    r"""
    .. _integrator-radiance_cache:

    Radiance cache (:monosp:`radiance_cache`)
    ------------------------------------------

    A radiosity prepass (the coarse global solution), a sparse field of order-2 spherical
    harmonics of the *indirect* incident radiance fitted at clusters of the camera's shading
    points (§4.1), and at render time, at the first non-delta hit (delta surfaces are followed as
    a path)::

        L(x) = Le(x) + direct(x) [Mitsuba emitter sampling + one BSDF ray, MIS]
                     + ρ(x)/π · (B_D(x) + λ · B_C(x))

        B_D = ⟨max(N·ω, 0)⟩ · ⟨L_F⟩                  (eq. 3, RBF-interpolated cluster SH)
        B_C = Σ_{triangles t, centroid within α} (R_t − π L_F(D_t)) · F(x → t)   (eq. 5, irradiance)
            (near_far="mean": R_t − B_D, the paper's eq. 6)

    with R_t the *reflected* radiosity of the triangle's patch and F the point-to-triangle form
    factor: exact (Lambert's formula, finite at corners) for BVH leaves, one disk per BVH node
    farther than 4 × its bounding radius (§7). The far field holds indirect light only (gather
    rays read B_r/π; rays that hit within α are left out of the fit), so direct light is counted
    once, by emitter sampling. ``alpha → 0`` removes B_C; ``alpha`` larger than the scene gives
    B_D ≈ 0 and a visibility-free one-bounce gather from the radiosity solution.

    The near-field triangles are the radiosity patches' triangles, split lazily (§5) by
    longest-edge bisection until smaller than α wherever a camera shading point may lie within α
    of them (:func:`~mi_twopass.prepass.near_field.split_near_triangles`); triangles inside a
    closed solid (faces of overlapping boxes) are left out, since no point sees them
    (:func:`~mi_twopass.prepass.near_field.buried_triangles`). The sum B_D + λ B_C is clamped at
    0 (irradiance; B_C can over-correct where the visibility assumption fails).

    The RBF interpolation visits only the clusters listed in the lane's cell of a uniform grid
    (those whose support touches the cell); the BVH walk skips nodes with no triangle centroid
    within α and nodes whose box lies on or below the tangent plane, and starts from its cell's
    list of subtrees (:class:`~mi_twopass.prepass.near_field.NodeCells`, built in the prepass for
    the cells around the shading points), which sums the same nodes as a walk from the root.

    Simplifications: ρ is the BSDF's diffuse reflectance (``eval_diffuse_reflectance``) at every
    non-delta gather vertex, glossy ones included; clusters split on size alone (not on the lazy
    "gather rays hit inside the sphere" criterion); shading points come from the first sensor.

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
       - Weight λ of the near-field correction B_C (default: 1; 0 gives the far field alone).
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
     * - max_patches
       - |int|
       - Patch budget of the radiosity prepass; the patches' triangles are the near-field
         triangles (default: 2048).
     * - particles_per_patch
       - |int|
       - Particles the radiosity solver shoots per patch (default: 256).
     * - elements_per_patch
       - |int|
       - Receiving elements per radiosity patch (as in ``radiosity_gather``); the SH gather
         rays read the element they hit (default: 1, patch means). On window_interior 64² at
         256 spp, 8 moved the image mean from 0.989 to 1.001 of the reference but left relMSE
         where it was (2.9e-3 vs 3.0e-3) for 0.35 s more prepass (``tools/radiosity_bias.py
         scenes_xml/window_interior.xml radiance_cache radiance_cache:elements_per_patch=8``).
     * - max_points
       - |int|
       - Shading points collected from the camera's view (default: 4096).
     * - max_clusters
       - |int|
       - Most SH samples (clusters) (default: 1024).
     * - rays_per_cluster
       - |int|
       - Gather rays per SH sample (default: 128).
     * - max_near_triangles
       - |int|
       - Budget of the lazy split (§5): splitting stops (longest edges first) when the near
         field would hold more triangles (default: 131072; stat ``split_complete``).
     * - near_cell_rel
       - |float|
       - Cell size of the walk's start lists, in units of α (default: 1).
     * - max_depth, rr_depth, seed, component
       - 
       - As every mi_twopass integrator. ``component``: "direct" = emission + direct light,
         "indirect" = the ρ/π (B_D + λ B_C) term.
     * - debug
       - |string|
       - "none"; "B_D" renders B_D/π, "B_C" renders λ·B_C/π (signed) at the first non-delta hit;
         "samples" marks the SH sample positions (cluster centres) in white over B_D/π.

    After a render, ``stats`` adds: ``ART`` (render seconds), ``NRT`` (rays traced for GI: the
    SH gather rays plus the radiosity particles' rays), ``NFGS`` (number of SH samples =
    clusters), ``CS`` (cache bytes: SH field + BVH + start lists), ``bvh_visits`` (BVH nodes
    visited), ``near_triangles`` (after the lazy split), ``split_complete``.
    FGO (time over a direct-only render) needs a second render: :func:`fgo`
    (``tools/radiance_cache_table.py`` prints the Table 1 columns).
    """

    def _read_props(self, props):
        self.alpha_rel = read_float(props, "alpha_rel", ALPHA_REL, minimum=0.0, strict=True)
        self.alpha_abs = read_float(props, "alpha", 1.0, minimum=0.0, strict=True) \
            if "alpha" in props else None
        self.lam = read_float(props, "lambda", 1.0)
        self.fake_gi = bool(props.get("fake_gi", False))
        self.ambient = read_float(props, "ambient", 0.1, minimum=0.0)
        self.max_patches = read_int(props, "max_patches", 2048, minimum=1)
        self.particles_per_patch = read_int(props, "particles_per_patch", 256, minimum=1)
        self.max_points = read_int(props, "max_points", 4096, minimum=1)
        self.elements_per_patch = read_int(props, "elements_per_patch", 1, minimum=1)
        self.max_clusters = read_int(props, "max_clusters", 1024, minimum=1)
        self.rays_per_cluster = read_int(props, "rays_per_cluster", 128, minimum=1)
        self.max_near_triangles = read_int(props, "max_near_triangles", 1 << 17, minimum=1)
        self.cell_rel = read_float(props, "near_cell_rel", 1.0, minimum=0.0, strict=True)
        self.debug = read_choice(props, "debug", "none", DEBUG_MODES)
        self.near_far = read_choice(props, "near_far", "direction", ("direction", "mean"))

    def settings(self):
        return (self.alpha_rel, self.alpha_abs, self.fake_gi, self.ambient, self.max_patches,
                self.particles_per_patch, self.elements_per_patch, self.max_points,
                self.max_clusters, self.rays_per_cluster, self.max_near_triangles, self.cell_rel)

    def alpha(self, scene, points=None) -> float:
        """``alpha``, else ``alpha_rel`` × the bounding-box diagonal of the camera's shading
        ``points`` (:func:`~mi_twopass.prepass.radiance_cache.default_alpha`; the scene's
        bounding-box diagonal without points)."""
        if self.alpha_abs is not None:
            return self.alpha_abs
        scene_diag = max(float(dr.norm(scene.bbox().extents())), 1e-30)
        return default_alpha(np.zeros((0, 3)) if points is None else points, self.alpha_rel,
                             scene_diag)

    # -- prepass ----------------------------------------------------------------------------
    def prepass(self, scene, seed):
        """Shading points, coarse solution (radiosity), SH far field (§4.1), near-field BVH
        (§7)."""
        sensor = scene.sensors()[0] if len(scene.sensors()) else None
        points = collect_shading_points(scene, sensor, self.max_points, seed) \
            if sensor is not None else None
        alpha = self.alpha(scene, None if points is None else points[0])
        patches = build_patches(scene, max_patches=self.max_patches, seed=seed)
        if self.fake_gi:
            solution = None
            tri_B = np.zeros((len(patches.tri_patch), 3))
        else:
            elements = receiving_elements(scene, self.max_patches, self.elements_per_patch, seed)
            solution = solve_radiosity(scene, patches,
                                       n_particles=max(1, self.particles_per_patch * patches.count),
                                       seed=seed, elements=elements)
            tri_B = np.asarray(solution.B_reflected)[np.asarray(patches.tri_patch)]
        diffuse = np.asarray(patches.is_diffuse)[np.asarray(patches.tri_patch)]
        tri_B = np.where(diffuse[:, None], tri_B, 0.0)
        cache = build_radiance_cache(scene, solution, alpha, sensor=sensor, shading_points=points,
                                     max_points=self.max_points, max_clusters=self.max_clusters,
                                     rays_per_cluster=self.rays_per_cluster, seed=seed,
                                     ambient=self.ambient if self.fake_gi else 0.0,
                                     fake_gi=self.fake_gi or sensor is None)
        # §5: triangles near the camera's shading points split lazily until smaller than alpha
        verts, tri_n, tri_B, split_complete = split_near_triangles(
            patches.tri_vertices, patches.tri_normal, tri_B,
            np.zeros((0, 3)) if points is None else points[0], alpha,
            max_triangles=self.max_near_triangles)
        seen = ~buried_triangles(scene, verts, tri_n)  # inside a solid: never visible (§5)
        near = build_near_field(verts[seen], tri_n[seen], tri_B[seen],
                                points=None if points is None else points[0], alpha=alpha,
                                cell_size=self.cell_rel * alpha)
        return CacheStructure(alpha=alpha, patches=patches, solution=solution, cache=cache,
                              near=near, split_complete=split_complete)

    def prepass_stats(self, s):
        radiosity_rays = int(s["solution"].rays) if s["solution"] is not None else 0
        cache, near = s["cache"], s["near"]
        sol_bytes = int(s["solution"].nbytes) if s["solution"] is not None else 0
        cs = int(cache.nbytes + near.nbytes)
        return {"prepass_rays": radiosity_rays + cache.rays + cache.shading_rays,
                "NRT": radiosity_rays + cache.rays, "sh_gather_rays": cache.rays,
                "NFGS": cache.count, "shading_points": int(len(cache.points)),
                "patches": int(s["patches"].count), "bvh_nodes": near.node_count,
                "near_triangles": int(len(near.verts)), "split_complete": s["split_complete"],
                "CS": cs, "cache_bytes": cs + sol_bytes, "alpha": s["alpha"]}

    def _finish_stats(self, sensor, spp, prepass_seconds, render_seconds):
        super()._finish_stats(sensor, spp, prepass_seconds, render_seconds)
        self.stats["ART"] = render_seconds

    # -- render-time irradiance -------------------------------------------------------------
    def irradiance_terms(self, si, n, active):
        """(B_D, λ·B_C, BVH visits) at ``si`` with viewer-facing normal ``n``."""
        s = self.structure
        L_F = s["cache"].coefficients(si.p, active)
        B_D = s["cache"].far_field(si.p, n, active, coeffs=L_F)
        if self.lam == 0.0:
            return B_D, mi.Color3f(0.0), mi.UInt32(0)
        B_C, visits = s["near"].correction(si.p, n, B_D, s["alpha"], active,
                                           L_F=L_F if self.near_far == "direction" else None)
        return B_D, self.lam * dr.select(active, B_C, 0.0), dr.select(active, visits, 0)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        return self.sample_cache(scene, sampler, ray, active)

    def sample_cache(self, scene, sampler, ray, active):
        """The estimator of the class docstring (or a debug view), one path per lane: a delta
        chain (:func:`~mi_twopass.integrators.pathtrace.first_nondelta_hit`), then straight-line
        code at the gather vertex."""
        want_direct = self.component in ("all", "direct") and self.debug == "none"
        want_indirect = self.component in ("all", "indirect") or self.debug != "none"
        ctx = mi.BSDFContext()
        max_delta = MAX_DELTA_DEPTH if self.max_depth < 0 else min(self.max_depth, MAX_DELTA_DEPTH)
        si, ray, beta, Le, gather = first_nondelta_hit(scene, sampler, ray, active, max_delta)
        L = Le if want_direct else mi.Spectrum(0.0)
        bsdf = si.bsdf(ray)

        # Direct light at the gather vertex: Mitsuba's emitter sampling ...
        Ld, active_em = emitter_sample_mis(scene, si, bsdf, ctx, sampler.next_2d(), gather)
        # ... and one BSDF ray that picks up emission, both MIS-weighted (power heuristic).
        bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), gather)
        active_bsdf = gather & (bs.pdf > 0) & want_direct
        si_b = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), active_bsdf)
        is_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        Le_b = emission_mis(scene, si_b, si, bs.pdf, is_delta, active_bsdf)
        if want_direct:
            L += beta * Ld
            L += dr.select(active_bsdf, beta * bsdf_weight * Le_b, 0.0)
        self.count("explicit_rays", active_em)
        self.count("implicit_rays", active_bsdf)

        # Indirect light from the cache: ρ/π (B_D + λ B_C) (eq. 2).
        n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
        B_D, B_C, visits = self.irradiance_terms(si, n, gather)
        self.count("bvh_visits", visits)
        if self.debug == "B_D":
            L += dr.select(gather, beta * B_D / dr.pi, 0.0)
        elif self.debug == "B_C":
            L += dr.select(gather, beta * B_C / dr.pi, 0.0)
        elif self.debug == "samples":
            L += dr.select(gather, beta * dr.select(self.near_sample(si.p, gather),
                                                   mi.Color3f(1.0), B_D / dr.pi), 0.0)
        elif want_indirect:
            rho = bsdf.eval_diffuse_reflectance(si, gather)
            # irradiance is never negative: where B_C over-corrects (the visibility assumption,
            # §6) the sum is clamped at 0
            L += dr.select(gather, beta * rho / dr.pi * dr.maximum(B_D + B_C, 0.0), 0.0)
        return L, mi.Bool(True), []

    def near_sample(self, p, active):
        """Debug "samples": within 0.2 α of an SH sample position (a cluster centre)."""
        cache = self.structure["cache"]
        if cache.count == 0:
            return mi.Bool(False)
        return cache.near_centre(p, 0.2 * self.structure["alpha"], active)


def fgo(scene, spp=4, seed=0, **props):
    """Arikan et al. Table 1 FGO: the time of a ``radiance_cache`` image over the time of the same
    image without global illumination (``component="direct"``: the same camera rays, emitter
    sample and BSDF ray, no cache term). Both are rendered once untimed first (kernel
    compilation); then the direct image is timed with its (unused) prepass already built, and
    ``radiance_cache`` with a fresh integrator, so its prepass is paid and counted.

    → ``(fgo, stats)``; ``stats`` also holds ``FGO_render`` (render seconds alone over the direct
    image's: the per-sample overhead of the cache lookup) and ``direct_seconds``."""
    direct = mi.load_dict({"type": "radiance_cache", "component": "direct", "lambda": 0.0,
                           "fake_gi": True, **props})
    mi.render(scene, integrator=direct, spp=spp, seed=seed)  # prepass + compile, untimed
    mi.render(scene, integrator=mi.load_dict({"type": "radiance_cache", **props}), spp=spp,
              seed=seed)  # compile, untimed
    img = mi.render(scene, integrator=direct, spp=spp, seed=seed)
    t_direct = direct.stats["render_seconds"]
    rc = mi.load_dict({"type": "radiance_cache", **props})
    img = mi.render(scene, integrator=rc, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    stats = dict(rc.stats)
    t_rc = stats["prepass_seconds"] + stats["render_seconds"]
    stats["direct_seconds"] = t_direct
    stats["FGO_render"] = stats["render_seconds"] / max(t_direct, 1e-9)
    stats["FGO"] = t_rc / max(t_direct, 1e-9)
    return stats["FGO"], stats


mi.register_integrator("radiance_cache", lambda props: RadianceCacheIntegrator(props))
