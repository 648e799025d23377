"""``rex``: bidirectional ray tracing with adaptive radiosity textures (Heckbert 1990).

Heckbert, "Adaptive Radiosity Textures for Bidirectional Ray Tracing", SIGGRAPH 1990
(docs/design.md "Papers"): §3.4 (size, light and eye passes), §4 (implementation). The prepass
(size pass, light pass, rex build) lives in :mod:`mi_twopass.prepass.rex_textures`; this module is the
plugin and its eye pass.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .. import units
from ..prepass.rex_textures import (BUCKET_PIXELS, KIND_NONE, MAX_LEVEL, NO_SHAPE, SPLIT_LIMIT,
                                    RexSettings, check_no_media)
from ..prepass.rex_textures import build as build_rexes
from ..prepass.sharp_light import SharpLight
from ..prepass.sharp_light import measure as measure_sharp_light
from ..rays import spawn_ray
from .base import TwoPassIntegrator, read_bool, read_choice, read_float, read_int
from .pathtrace import (by_component, next_hit, path_start, russian_roulette,
                        trace_until)

DEBUG_MODES = ("none", "leaves", "edges", "buckets")
DIRECT_MODES = ("rex", "shadow")

#: bounds of a budget from ``photons_per_pixel``
MIN_PHOTONS = 1 << 16
MAX_PIXEL_PHOTONS = 1 << 22


class RexIntegrator(TwoPassIntegrator):
    r"""
    .. _integrator-rex:

    Adaptive radiosity textures (:monosp:`rex`)
    --------------------------------------------

    Heckbert's three-pass bidirectional ray tracer (SIGGRAPH 1990). Every Lambertian surface
    (``diffuse``, and ``twosided`` / ``blendbsdf`` made only of it) carries *rexes*: adaptive
    quadtree histograms over its parameter square (one per analytic shape over its (u, v); one
    per triangle of a mesh, over its barycentrics; one per side of a two-sided BSDF) that
    collect the flux of photons shot from the lights::

        size pass   eye rays (through specular/glossy bounces) record each diffuse surface's
                    pixel preimage size in (u, v): the finest bucket worth keeping there
        light pass  photons leave every light through an adaptive light quadtree, follow
                    specular bounces (Fresnel-weighted, TransportMode.Importance), deposit their
                    flux at every diffuse hit and continue diffusely (Russian roulette)
        rex build   buckets split while they hold more than split_limit photons (past the
                    size-pass cap, only with 4× more per level); E = ΣΦ / area, reflected
                    radiance ρ·E/π
        eye pass    L = Le + ρ(x)·E(x)/π at the first diffuse hit x reached through specular
                    bounces (glossy vertices are path traced with emitter sampling and MIS)

    **Paths.** The light pass continues photons diffusely after each deposit (the simple
    alternative to the paper's §4 progressive shooting from bright rexes), so the rexes hold all
    of L(S|D)*D: the image covers L(S*D)*S*E and converges to Mitsuba's ``path`` as the photon
    count grows and the buckets shrink. Its bias is the blur of a bucket: irradiance averaged
    over a bucket and interpolated bilinearly between bucket centres (measured on a 16×16
    Cornell box with 4M photons: ≤ 1.2 % on 4×4-pixel blocks, < 0.5 % on most; on
    ``caustic.xml`` at 64×64 the relMSE floor is ≈ 0.004 at 4M photons, mostly the one-bucket
    blur of the caustic's edges). On an image *mean* the blur largely cancels: we state 1 % at
    65536 photons on 16×16 images (``tests/integrators/test_rex_correctness.py`` allows that
    much beyond the noise; measured there within it), +1.1 % on veach-bidir at 32×24 with the
    default photons, +0.5 % at 1M. A finite ``max_depth`` means what it means for ``path`` (at most
    max_depth segments; 1: emitters seen directly; 0: black): a bucket keeps one irradiance per
    eye depth d < min(max_depth − 1, 8), from the photons of at most max_depth − 2 − d
    bounces; rex surfaces deeper on the eye path are path traced.

    **Size-pass cap.** The cap stops splitting where a finer bucket would be smaller than
    ``bucket_pixels`` on screen, but it is soft: past it a bucket still splits when it holds
    more than split_limit·4^(levels past the cap) photons. A hard cap kept surfaces that are a
    dot on screen, or that no size-pass ray met, at one bucket whatever the photon count; the
    camera then saw the bucket's average where it saw only part of it (the rim of a lamp shade
    in veach-bidir, its bulb alone: 1.26× ``path``, no better with 4× the photons).

    **Light quadtree.** Per light, a quadtree over one 2-D factor of ``Emitter.sample_ray``'s
    primary samples — the emission direction of point, spot and area lights and of
    environments, the beam cross-section of a directional light — refined level by level from
    jittered pilot rays where neighbouring nodes reach a different surface or specular chain or
    land more than ``light_split_dist`` apart, and only where the eye sees one of the two hits
    (silhouettes, shadow and caustic edges); a restricted quadtree, as in the paper. It is 2-D,
    not the 4-D tree §3.3.1 asks for area lights: the position on an area light (and on the
    environment's bounding disk) is stratified, not adapted. The tree grows to a sixteenth of the
    photon budget (at most 2^18 leaves); every leaf then shoots fresh photons, the same number
    in each quadrant (the tree depends only on the pilot rays, so the estimate stays unbiased:
    a test checks the flux through a square against I·Ω). The adaptation buys little here:
    ``python -m mi_twopass check scenes_xml/caustic.xml --res 256 --spp 128 --ref-spp 1024
    --integrators rex,rex:light_levels=0`` gave block relMSE 9.0e-4 with ``light_levels`` 3
    and 8.0e-4 with 0 (image means 1.0016 and 1.0017).

    **Histogram redistribution (§4.1).** Instead of clearing and reshooting at each level, the
    final shoot keeps its photon records and the quadtrees are built from them, so every bucket
    holds exactly the photons that fell in it (the paper's §5 suggestion). Buckets partly buried
    under closed objects (a box on a floor) divide by their open area only (4 probe points per
    leaf), so no dark seam runs along contact lines. Only the back of a one-sided surface
    buries a point: a two-sided or transmissive surface's normal says nothing about inside and
    outside (veach-bidir's room of two-sided walls with outward normals read as "inside", and
    was 1.8× too bright). Rexes do not interpolate across mesh triangles and are not
    2:1-balanced (the bilinear lookup handles leaves of any size).

    **Direct light.** ``direct="rex"`` reads direct light from the rexes too (a pure
    two-pass image); ``direct="shadow"`` computes it with shadow rays (Mitsuba's emitter sampling
    plus one BSDF-sampled ray, MIS), and the rexes hold indirect and caustic light only (photons
    from their second vertex on). "shadow" is the default, by measurement on
    ``scenes_xml/caustic.xml`` at 64×64 with the default 1M photons (relMSE against a 65536-spp
    ``path``, mean of 3 seeds, times with the prepass, on 2 shared CPU cores): "rex" stalls at
    ≈ 0.034 (photon noise and blur of the sharp direct light and shadows; 64 spp, 1.6 s), while
    "shadow" reaches 0.0087 at 256 spp (1.9 s) and 0.0068 at 1024 spp (2.7 s), where ``path``
    at equal time has ≈ 0.018 and ≈ 0.013. With 4M photons "shadow" reaches 0.0041 (9.5 s): at
    long times path tracing, unbiased, wins.

    **Photon budget: what the image needs.** Unless ``photons`` (or ``photons_per_pixel``) is
    given, the budget is the larger of two counts, both divided by the deposits a photon leaves
    on rexes the eye sees (a probe shoot of 65536 photons measures them):

    - *noise*: the size pass records, for one eye sample per pixel, the rex it reads, its
      bucket at the cap, the specular chain's throughput and what the pixel takes from
      elsewhere (emitted light; direct light where shadow rays compute it, one emitter sample).
      With the probe's deposits per size cell (Σw, Σw², each photon weighted as the light
      guide will shoot it) that predicts the 8×8-block relMSE the rexes' photon noise leaves
      in the image, ∝ 1/photons (``rex_textures.predicted_noise``: buckets sharing pixels
      share their error, blocks over (mean² + ε) as ``check`` reads them). The budget holds it
      to a third of ``check``'s bound (3e-3). Against the noise ``check --renders 2`` measured
      it read 0.5–2.4× (window_interior to tut-cbox), and 0.7–0.9× against the photon noise
      of renders in the test that pins it;
    - *resolution*, for *sharp* light only: the probe's deposits of photons that came from
      the light through delta bounces only (a caustic, a sun patch through a glass pane,
      direct light kept in the rexes). Where the image's rex light is sharp, 4 × split_limit
      photons per bucket the image needs (the size pass counts, for every pixel that sees a
      rex through specular and glossy bounces, (pixel side / bucket side at its cap)², ¼–1
      bucket per visible pixel with ``bucket_pixels`` = 2), so that buckets split down to the
      pixel footprint: with fewer, a sharp caustic blurs in coarse buckets, which the noise
      model does not see (``caustic.xml`` read 0.17× its prediction); in proportion to the
      sharp share below a third of the image's rex light; none where the light is smooth.
      Smooth light's error is the noise: with the photons forced to 1, ½, ¼ and ⅛ of session
      29's budget, ``check``'s bias part on window_interior and many_lights (no sharp light)
      grew as 1/photons, near the model's prediction, and on ``caustic.xml`` (8.6 % sharp)
      faster, its blur (``rex_textures.SHARP_FULL``). A sun patch through a pane at 32²
      (``tests/compose/test_unsampled.py``) read 1.15× its light with a quarter of the
      photons, 1.06× with all of them.

    Where pixels read more than 1 % of the image's radiance from whole rexes (rexes no larger
    than their pixel: veach-bidir's lamp at 128², 3.2 %), the floor is the rule of sessions
    12–28, 4 × split_limit photons per bucket: those reads converge only as photons split such
    rexes past their cap, and veach-bidir's image mean read +0.98 % of the reference with the
    noise budget alone against +0.64 % with that floor. The budget lies within [2^16, 2^24]
    photons and keeps the records below 8M (memory). Photons at 128² / 256²
    (``stats["photons"]``, session 30, ``tools/rex_budget.py``): the Cornell box 0.065M (the
    floor) / 0.13M, the office 0.34M / 1.44M, veach-bidir 0.60M / 1.08M, window_interior
    0.94M / 3.9M, ``caustic.xml`` (0.16 deposits a photon; 8.6 % of its image's rex light
    sharp) 2.1M / 8.0M. A scene seen mostly through non-Lambertian surfaces needs few.
    Session 28's rule (4 × split_limit per bucket everywhere) gave the
    office's ceiling-lit walls 7e-4 of ``check``'s bias part and the Cornell box 6e-5: the
    image's need differs tenfold between scenes at one fill, which the noise model measures.

    **Light guide.** Most photons of an open scene or of a sky outside a window never reach a
    surface the camera sees (window_interior: 1.25 % deposits on seen rexes per photon in the
    probe). The probe's deposits per photon y, per cell of each light's quadtree square, set
    how many photons each leaf shoots: in proportion to its area × √y (Neyman's allocation,
    the fewest photons for a given variance of the seen deposits), at least an eighth of the
    photon-weighted mean of √y; each light's budget follows its power × its mean √y. The
    estimate stays unbiased: every leaf still shoots ≥ 1 photon per quadrant, weighted by its
    own count. The automatic budget divides the need by the seen deposits per photon the
    probe's cells predict for that allocation (within 1–5 % of what the final shoot deposits
    on six scenes). ``check`` at 128 px, 64 spp against 16384
    spp, two renders, bias parts without and with the guide: office 2.0e-3 → 7.2e-4,
    veach-bidir 2.4e-3 → 1.5e-3, window_interior 3.5e-4 → 1.9e-4, mixed_room 1.5e-3 → 1.4e-3,
    the others the same within their noise; with session 28's fill per bucket, the zoo's
    rex shot 1.23 M photons at 256² instead of 6.3 M, mixed_room's 5.56 M instead of 16.8 M
    (:mod:`mi_twopass.prepass.light_guide` has the commands and the rules tried first). The
    noise model weighs each probe deposit by the weight the guide gives its photon.

    **Cost.** Photons cost about one ray per bounce. The emission samples are made in Dr.Jit
    (no per-photon numpy), the light quadtree has at most 2^18 leaves, and the rex build sorts
    the records once by a Morton key so that each level costs its nodes, not its photons.
    Measured on two CPU cores with ``python -m mi_twopass bench --prepass --quick
    --integrators rex`` (the prepass alone, warm kernel cache; session 18): 0.71 s on the
    Cornell box at 128² (9.7 s with 256 photons per pixel), 3.1 s at 256² (12.7 s), 5.4 s at
    1920×1080 (14.7 s; peak memory 1.4 GB, was 3.8 GB). The records (26 bytes per deposit)
    are freed after the build; the rexes take 8 + 24 bytes per node and depth class
    (``cache_bytes``).

    **Emission and scale.** Area lights emit from ``sample_position`` with cosine-weighted
    directions, infinite emitters (constant, envmap, sunsky, directional) from a disk facing
    their ``sample_direction`` on the sphere around the geometry's own bounds (Mitsuba 3.9's
    ``scene.bbox()`` leaves out rectangles it merged into one mesh: a room of rectangles
    sharing a BSDF had photons start inside it, 1.98× ``path``), the rest from Mitsuba's
    ``sample_ray``. A photon's weight at a non-delta bounce is the BSDF evaluated with the new
    direction on the eye side (the adjoint of what ``path`` integrates), exact for BSDFs that
    are not symmetric too (normal and bump maps: the shading-normal correction with the
    surface's own normal left photons off a normal-mapped wall 4.5 % too bright), over the
    sample's own density; a sample Mitsuba's sampling discards (weight 0: a rough dielectric's
    microfacet event that lands on the other side) ends the photon, as it ends Mitsuba's own
    paths (``photon_scatter_weight``). The rays rex
    spawns (photons, eye continuations, shadow rays) are offset relative to the scene's size
    (:mod:`mi_twopass.rays`), not by Mitsuba's absolute ≥ 89 µm: the image of a 0.2 mm
    Cornell box is that of the 2 m one (Mitsuba's own ``path`` gives 0.90× of it), shadows of
    occluders closer than 89 µm included. When ``scene.bbox()`` misses
    merged rectangles and an infinite emitter is present, Mitsuba's emitter sampling also ends
    shadow rays short of distant walls (``path`` leaks as well); the prepass warns then.

    **Limits.** Non-Lambertian surfaces (glossy, delta, mixed lobes, bumpmap and normalmap,
    which tilt the shading normal) and instanced shapes carry no rex: the eye pass path-traces
    them (emitter sampling, BSDF sampling, MIS) and the photons bounce off them. Participating
    media are refused with a ValueError at prepass time (use ``volpath``). A finely tessellated
    mesh gets one rex per triangle, so each collects few photons and the image is mottled where
    indirect light dominates (``window_interior.xml``: many more photons, or a larger
    ``split_limit``, are needed there). The size pass ignores the focusing of curved mirrors
    and lenses (their buckets may split finer than needed).

    .. pluginparameters::

     * - photons
       - |int|
       - Photons shot in the light pass (shared among the lights by power). Default: what the
         image needs (above, "Photon budget").
     * - photons_per_pixel
       - |float|
       - If given (> 0) and ``photons`` is not: ``photons_per_pixel`` × the first sensor's
         pixel count, within [2^16, 2^22] (the budget rule before 2026-11-25 was 256).
     * - split_limit
       - |int|
       - A rex bucket holding more photons than this splits into four (default: 32; the paper
         asks for at least 10 photons per bucket). It also sets the automatic photon budget
         (4 × split_limit photons per visible bucket): with 16, the office's rexes left a
         block relMSE of 1.8–3.3e-3 over four builds at 128² (``check --renders 2``, the
         bound 3e-3), with 32 0.7–1.2e-3 over three.
     * - max_level
       - |int|
       - Deepest rex level, whatever the size pass says (default: 14, at most 20).
     * - bucket_pixels
       - |float|
       - Size-pass cap: the smallest bucket is at most this many pixels wide on screen, more
         than half of it (default: 2; it also sets the automatic photon budget: half of it,
         4× the photons).
     * - direct
       - |string|
       - "shadow" (default): direct light by shadow rays with MIS, rexes hold the rest;
         "rex": everything from the rexes.
     * - light_levels
       - |int|
       - Adaptive levels of the light quadtrees below their uniform base level (default: 3;
         0 = stratified emission only).
     * - light_split_dist
       - |float|
       - Neighbouring light rays landing farther apart than this fraction of the scene's
         bounding-box diagonal (of its shapes' own bounds) split their node (default: 0.05).
     * - light_guide
       - |bool|
       - Share the photons out among the lights and their light-quadtree leaves by the
         deposits on rexes the eye sees that the probe shoot measured per photon, and
         measure the automatic budget on that allocation ("Light guide" above; default:
         true). false: by power, evenly over the leaves (the rule before session 28).
     * - max_depth, rr_depth, seed, component
       -
       - As every mi_twopass integrator: path length (-1: unbounded; finite: at most max_depth
         segments in all, as ``path``), Russian roulette start (eye and photon paths),
         prepass seed offset, "all" / "direct" / "indirect" (direct: emission and direct light
         at the first non-specular vertex).
     * - debug
       - |string|
       - "none"; "leaves" a random colour per rex leaf (the paper's Fig. 11); "edges" the rex
         radiance with bucket boundaries in black; "buckets" the piecewise-constant rex radiance
         without interpolation (Figs. 7–9).

    ``integrator.stats`` adds to the suite's columns: ``light_rays`` (pilot + photon rays),
    ``pilot_rays``, ``photons``, ``light_hit_percent`` (final photons whose first ray hits the
    scene), ``light_tree_leaves``, ``light_tree_max_level``, ``rex_leaves``, ``rex_nodes``,
    ``rex_max_depth``, ``rexes``, ``size_rays``, ``exposure_rays``, ``eye_rays`` (camera,
    continuation and shadow rays of the eye pass), ``size_seconds``, ``light_seconds``,
    ``rex_build_seconds``, ``cache_bytes`` and ``plan_reused`` (inside ``twopass``: the size
    pass and probe shoot were read from another build of the same prepass, and ``size_rays``
    is then 0).

    Every emitter Mitsuba can ``sample_ray`` (or, infinite, ``sample_direction``) is handled
    (point, spot, area, directional, constant, envmap, sunsky, ...); a scene without emitters
    renders black.
    """

    def _read_props(self, props):
        self.photons = read_int(props, "photons", -1, minimum=-1)
        if self.photons == 0:
            raise ValueError("photons=0: must be >= 1 (or -1 for the default)")
        self.photons_per_pixel = read_float(props, "photons_per_pixel", 0.0, minimum=0.0)
        self.split_limit = read_int(props, "split_limit", SPLIT_LIMIT, minimum=1)
        self.max_level = read_int(props, "max_level", 14, minimum=0)
        if self.max_level > MAX_LEVEL:
            raise ValueError(f"max_level={self.max_level}: must be <= {MAX_LEVEL}")
        self.bucket_pixels = read_float(props, "bucket_pixels", BUCKET_PIXELS, minimum=0.0,
                                        strict=True)
        self.direct = read_choice(props, "direct", "shadow", DIRECT_MODES)
        self.light_levels = read_int(props, "light_levels", 3, minimum=0)
        self.light_split_dist = read_float(props, "light_split_dist", 0.05, minimum=0.0)
        self.light_guide = read_bool(props, "light_guide", True)
        self.debug = read_choice(props, "debug", "none", DEBUG_MODES)

    def settings(self):
        return (self.photons, self.photons_per_pixel, self.split_limit, self.max_level,
                self.bucket_pixels, self.direct, self.light_levels, self.light_split_dist,
                self.light_guide, self.max_depth, self.rr_depth)

    # -- prepass ----------------------------------------------------------------------------
    def settings_photons(self, scene) -> int:
        """``photons``, else ``photons_per_pixel`` × the first sensor's pixels (within
        [2^16, 2^22]), else 0: the prepass then shoots what the image needs."""
        if self.photons > 0:
            return self.photons
        if self.photons_per_pixel <= 0:
            return 0
        sensors = scene.sensors()
        pixels = 256 * 256
        if len(sensors):
            size = sensors[0].film().crop_size()
            pixels = int(size[0]) * int(size[1])
        return int(min(MAX_PIXEL_PHOTONS,
                       max(MIN_PHOTONS, round(self.photons_per_pixel * pixels))))

    def photon_budget(self, scene, seed=0, sensor=None) -> int:
        """The photons the prepass will shoot: ``photons`` where it is set, else the image's
        need, measured by a size pass and a probe shoot (:meth:`sharp_light`)."""
        settings = self.rex_settings(scene)
        if settings.photons > 0:
            return int(settings.photons)
        return self.sharp_light(scene, seed, sensor).photons

    def sharp_light(self, scene, seed=0, sensor=None) -> SharpLight:
        """The size pass and probe shoot read for twopass's cost model: the photons the image
        needs and path's predicted variance on sharp light
        (:func:`~mi_twopass.prepass.sharp_light.measure`); remembered for the scene, sensor,
        settings and seed it was measured for. Refuses a scene with media as the prepass
        does."""
        if sensor is None and len(scene.sensors()):
            sensor = scene.sensors()[0]
        key = self.prepass_key(scene, sensor, seed)
        memo = getattr(self, "_sharp_memo", None)
        if memo is None or memo[0] is not scene or memo[1] != key:
            check_no_media(scene)
            found = measure_sharp_light(scene, self.rex_settings(scene),
                                        self.prepass_seed(seed), sensor, self.probe_memo)
            self._sharp_memo = memo = (scene, key, found)
        return memo[2]

    def rex_settings(self, scene) -> RexSettings:
        return RexSettings(photons=self.settings_photons(scene), split_limit=self.split_limit,
                           max_level=self.max_level, bucket_pixels=self.bucket_pixels,
                           direct=self.direct, max_depth=self.max_depth, rr_depth=self.rr_depth,
                           light_levels=self.light_levels,
                           light_split_dist=self.light_split_dist,
                           light_guide=self.light_guide)

    def prepass(self, scene, seed):
        """Size pass, light pass and rex build (§3.4):
        :func:`mi_twopass.prepass.rex_textures.build`."""
        return build_rexes(scene, self.rex_settings(scene), seed, sensor=self.prepass_sensor,
                           memo=self.probe_memo)

    def prepass_stats(self, pre):
        stats = dict(pre.stats)
        stats["cache_bytes"] = int(pre.nbytes)
        return stats

    # -- eye pass ---------------------------------------------------------------------------
    def sample(self, scene, sampler, ray, medium=None, active=True):
        if self.max_depth == 0:  # as Mitsuba's path: a path of no segment carries no light
            return mi.Spectrum(0.0), mi.Bool(True), []
        if self.debug != "none":
            return self.sample_debug(scene, sampler, ray, active)
        return self.sample_eye(scene, sampler, ray, active)

    @dr.syntax
    def sample_eye(self, scene, sampler, ray, active):
        """Eye pass (§3.4.3): specular chains from the eye, rex radiance at the first diffuse hit.

        Delta vertices are followed; other non-rex vertices (glossy, mixed, textured normals,
        instances) are path traced with emitter sampling and MIS; at a rex vertex x the path
        ends with ρ(x)·E(x)/π, plus (with ``direct="shadow"``) emitter sampling and one BSDF
        ray that only looks for emitters. Under a finite max_depth the rex read at eye depth d
        holds only photons that keep the whole path within max_depth segments (its depth
        class); vertices deeper than the classes are path traced."""
        pre = self.structure
        tables, rexes = pre.tables, pre.rexes
        # tables.scale: a ray offset's length (mi_twopass.rays)
        scale, max_depth, want_direct, want_indirect, ctx, lights = \
            self.loop_constants(scene, tables.scale)
        shadow = self.direct == "shadow"
        finite = self.max_depth > 0
        classes = rexes.classes

        # n_nondelta: non-delta vertices before the current hit
        ray, L, beta, eta, depth, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, \
            prev_lights, active, n_implicit, n_explicit = path_start(ray, active, lights)
        after_rex = mi.Bool(False)  # the MIS ray of a rex vertex: only emitters count
        n_traced = mi.UInt32(0)  # camera and continuation rays (eye_rays with the shadow rays)

        while dr.hint(active, label="rex_eye"):
            si, gather_ray, n_implicit = next_hit(scene, ray, depth, prev_bsdf_delta, active,
                                                  n_implicit)
            n_traced += dr.select(active, 1, 0)

            L += self.emission_met(scene, lights, si, beta, n_nondelta,
                                   (prev_si, prev_bsdf_pdf, prev_bsdf_delta, prev_lights), active)

            valid = active & si.is_valid() & ~after_rex
            shape = tables.shape_index(si, valid)
            kind = dr.gather(mi.UInt32, tables.d_kind, shape, valid & (shape != NO_SHAPE))
            on_rex_surface = valid & (shape != NO_SHAPE) & (kind != KIND_NONE)
            if finite:
                on_rex_surface &= depth < classes
            rex, uv, at_rex = tables.locate(si, on_rex_surface)
            first = n_nondelta == 0
            bsdf = si.bsdf(ray)

            # The rex: ρ·E/π with E from the photons (§3.4.3).
            w_d = 0.0
            if not shadow:
                w_d = dr.select(first, 1.0 if want_direct else 0.0, 1.0 if want_indirect else 0.0)
            w_i = 1.0 if want_indirect else 0.0
            E, _, _ = rexes.irradiance(rex, uv, at_rex, w_direct=w_d, w_indirect=w_i,
                                       cls=depth if finite else 0)
            rho = bsdf.eval_diffuse_reflectance(si, at_rex)
            L += dr.select(at_rex, beta * units.reflected_radiance(rho, E), 0.0)

            # Emitter sampling at glossy vertices, and at rex vertices for direct="shadow".
            smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            glossy = valid & ~on_rex_surface & smooth
            can_go = depth + 1 < max_depth
            Ld, cast, here = lights.sample_emitter_mis(scene, si, bsdf, ctx, sampler,
                                                       (glossy | (at_rex & shadow)) & can_go,
                                                       scale)
            n_explicit += dr.select(cast, mi.UInt32(1), mi.UInt32(0))
            L += by_component(beta * Ld, first, want_direct, want_indirect)

            # Continue through specular/glossy vertices; a rex vertex sends its MIS ray only.
            through = valid & ~on_rex_surface
            mis_ray = at_rex & shadow
            go = (through | mis_ray) & can_go
            bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(go), sampler.next_2d(go), go)
            is_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            n_nondelta += dr.select(go & ~is_delta, mi.UInt32(1), mi.UInt32(0))
            ray = spawn_ray(si, si.to_world(bs.wo), scale)
            beta = dr.select(go, beta * bsdf_weight, beta)
            eta = dr.select(go, eta * bs.eta, eta)
            prev_si = dr.detach(si, True)
            prev_bsdf_pdf = bs.pdf
            prev_bsdf_delta = is_delta
            after_rex = mis_ray
            prev_lights = here
            depth += 1

            # Russian roulette on long specular/glossy chains (as Mitsuba's path).
            beta, survive = russian_roulette(beta, eta, through & (depth >= self.rr_depth),
                                             sampler.next_1d())
            active = go & survive & (dr.max(beta) != 0.0) & (bs.pdf > 0)

        self.count_after((L,), implicit_rays=n_implicit, explicit_rays=n_explicit,
                         eye_rays=n_traced + n_explicit)
        return L, mi.Bool(True), []

    def sample_debug(self, scene, sampler, ray, active):
        """Debug views of the rexes at the first rex hit (other surfaces followed by BSDF
        sampling, :func:`mi_twopass.integrators.pathtrace.trace_until`)."""
        pre = self.structure
        tables, rexes = pre.tables, pre.rexes

        def at_rex(si, bsdf, hit):
            return tables.locate(si, hit)[2]

        si, ray, beta, _, found = trace_until(scene, sampler, ray, active, at_rex)
        rex, uv, found = tables.locate(si, found)
        value = self.debug_value(rexes, si, si.bsdf(ray), rex, uv, found)
        return dr.select(found, beta * value, 0.0), mi.Bool(True), []

    def debug_value(self, rexes, si, bsdf, rex, uv, at_rex):
        """The debug view's colour at a rex hit (leaf colour, or bucket radiance ± edges)."""
        E, node, level = rexes.irradiance(rex, uv, at_rex, smooth=False)
        if self.debug == "leaves":
            hsh = node * mi.UInt32(2654435761)
            return mi.Spectrum(mi.Float((hsh >> 8) & 255), mi.Float((hsh >> 16) & 255),
                               mi.Float((hsh >> 24) & 255)) / 255.0
        value = units.reflected_radiance(bsdf.eval_diffuse_reflectance(si, at_rex), E)
        if self.debug == "edges":
            n = mi.Float(mi.UInt32(1) << level)
            fu, fv = uv.x * n, uv.y * n
            du = dr.minimum(fu - dr.floor(fu), dr.ceil(fu) - fu)
            dv = dr.minimum(fv - dr.floor(fv), dr.ceil(fv) - fv)
            value = dr.select(dr.minimum(du, dv) < 0.06, 0.0, value)
        return value

    def to_string(self):
        return (f"RexIntegrator[photons={self.photons}, split_limit={self.split_limit}, "
                f"direct={self.direct}, max_depth={self.max_depth}, component={self.component}]")


mi.register_integrator("rex", lambda props: RexIntegrator(props))
