"""Per-vertex pieces of a path tracer shared by the integrators' gather loops.

Each is the step Mitsuba's own ``path`` integrator takes at a vertex, as a plain function of
Dr.Jit values (no Python branching on them), so that it can sit inside a ``@dr.syntax`` symbolic
loop: the emission met by a BSDF-sampled ray, MIS-weighted against emitter sampling; one emitter
sample with MIS; Russian roulette; and the split of a contribution into the ``direct`` and
``indirect`` components. Veach's power heuristic (Veach 1997, §9.2.4) weights both strategies.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..rays import shadow_ray, spawn_ray
from ..scene.emission import has_infinite_emitters


def path_start(ray, active, lights):
    """The loop state of a path at its camera ray, in the order the gather loops unpack it:
    ``(ray, L, β, η, depth, non-delta vertices so far, previous interaction, its BSDF pdf,
    whether its BSDF sample was delta, the light sampler's context there, active lanes,
    implicit rays, explicit rays)``; the camera counts as a delta vertex (emission seen directly
    gets MIS weight 1), ``lights`` (:mod:`mi_twopass.integrators.light_samplers`) gives its
    context's start and the two ray counters (``STAT_KEYS``) start at zero."""
    return (mi.Ray3f(ray), mi.Spectrum(0.0), mi.Spectrum(1.0), mi.Float(1.0), mi.UInt32(0),
            mi.UInt32(0), dr.zeros(mi.SurfaceInteraction3f), mi.Float(1.0), mi.Bool(True),
            lights.start(), mi.Bool(active), mi.UInt32(0), mi.UInt32(0))


def next_hit(scene, ray, depth, prev_bsdf_delta, active, n_implicit):
    """The hit of a path's next ray, whether that ray is an implicit (gather) ray, sampled from
    the BSDF of a non-delta vertex (the camera ray and rays leaving delta vertices are not;
    docs/design.md, "Stats"), and the implicit-ray counter with it counted:
    ``(si, gather_ray, n_implicit)``. Camera rays (depth 0) are traced as coherent."""
    si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=depth == 0)
    gather_ray = active & ~prev_bsdf_delta
    return si, gather_ray, n_implicit + dr.select(gather_ray, 1, 0)


def mis_weight(pdf_a, pdf_b):
    """Power heuristic (β = 2): w_a = p_a² / (p_a² + p_b²); 0 where it is not finite
    (both pdfs 0, or an infinite pdf at a grazing or coincident sample), as Mitsuba's own."""
    a2 = dr.square(pdf_a)
    w = a2 / (a2 + dr.square(pdf_b))
    return dr.detach(dr.select(dr.isfinite(w), w, 0.0))


def emission_mis(scene, si, prev_si, prev_bsdf_pdf, prev_bsdf_delta, active):
    """Radiance Le(y → x) emitted at the hit ``si`` of a BSDF-sampled ray from ``prev_si``,
    weighted by MIS against the emitter sampling done at ``prev_si``:
    w = p_bsdf² / (p_bsdf² + p_em²), 1 after a delta BSDF sample (no emitter strategy there)."""
    ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
    em_pdf = scene.pdf_emitter_direction(prev_si, ds, active & ~prev_bsdf_delta)
    w = dr.select(prev_bsdf_delta, 1.0, mis_weight(prev_bsdf_pdf, em_pdf))
    return w * ds.emitter.eval(si, active)


def emitter_sample_mis(scene, si, bsdf, ctx, u, active, scale=1.0):
    """One emitter sample at ``si`` (Mitsuba's ``sample_emitter_direction``) and its shadow ray:
    ``(f·Le·w_MIS/p, cast)``: the BSDF-weighted contribution (β not included) and the lanes that
    traced a shadow ray (occluded ones included: the ray statistics count them). MIS weight
    p_em² / (p_em² + p_bsdf²), 1 for delta emitters. The shadow ray's offset is relative to
    ``scale`` (:func:`mi_twopass.rays.shadow_ray`; 1: Mitsuba's own)."""
    ds, em_weight = scene.sample_emitter_direction(si, u, False, active)
    cast = active & (ds.pdf != 0.0) & dr.any(em_weight != 0.0)
    visible = cast & ~scene.ray_test(
        shadow_ray(si, ds, scale, has_infinite_emitters(scene)), cast)
    bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), visible)
    w = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, bsdf_pdf))
    return dr.select(visible, w * bsdf_val * em_weight, 0.0), cast


def by_component(value, is_direct, want_direct: bool, want_indirect: bool):
    """``value`` where its component (direct where ``is_direct``, else indirect) is wanted,
    else 0; ``want_*`` are Python booleans (the integrator's ``component``)."""
    return dr.select(is_direct, value if want_direct else 0.0, value if want_indirect else 0.0)


def russian_roulette(beta, eta, rr_active, u):
    """Mitsuba's Russian roulette: survive with q = min(max(β)·η², 0.95) where ``rr_active``,
    dividing β by q. Returns ``(beta, survive)``."""
    q = dr.minimum(dr.max(beta) * dr.square(eta), 0.95)
    beta = dr.select(rr_active, beta * dr.rcp(dr.maximum(q, 1e-30)), beta)
    return beta, ~rr_active | (u < q)


def bsdf_continue(bsdf, ctx, si, sampler, active, scale, beta, eta, n_nondelta):
    """The path's next segment, sampled from the BSDF at ``si`` (Mitsuba's ``path`` step, the
    gather loops' implicit ray), and the path state after it: ``(ray, β·f·cos/p, η·η_bs,
    non-delta vertices (+1 where ``active`` sampled a non-delta lobe), prev_si, prev_bsdf_pdf,
    prev_bsdf_delta, bs)``, in :func:`path_start`'s order. The ray leaves with a scene-relative
    offset (:func:`mi_twopass.rays.spawn_ray`); ``prev_si`` is the detached interaction that
    the next vertex's MIS weight refers to."""
    bs, weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active)
    is_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    ray = spawn_ray(si, si.to_world(bs.wo), scale)
    n_nondelta = n_nondelta + dr.select(active & ~is_delta, 1, 0)
    return (ray, beta * weight, eta * bs.eta, n_nondelta, dr.detach(si, True), bs.pdf, is_delta,
            bs)


def roulette_step(beta, eta, depth, rr_depth, u, active, bs):
    """Russian roulette from ``rr_depth`` on (:func:`russian_roulette`), then which lanes go on:
    ``(beta, active)``, ended where roulette stopped the path, its throughput is 0 or the BSDF
    sample failed."""
    beta, survive = russian_roulette(beta, eta, depth >= rr_depth, u)
    return beta, active & survive & (dr.max(beta) != 0.0) & (bs.pdf > 0)


def bsdf_step(bsdf, ctx, si, sampler, active, scale, beta, eta, n_nondelta, depth, rr_depth):
    """A gather loop's implicit ray, as Mitsuba's ``path`` takes it: :func:`bsdf_continue`,
    the depth counted where ``si`` is a hit, then :func:`roulette_step` from ``rr_depth`` on.
    Returns ``(ray, beta, eta, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, depth,
    active)``."""
    ray, beta, eta, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, bs = bsdf_continue(
        bsdf, ctx, si, sampler, active, scale, beta, eta, n_nondelta)
    depth = dr.select(si.is_valid(), depth + 1, depth)
    beta, active = roulette_step(beta, eta, depth, rr_depth, sampler.next_1d(), active, bs)
    return ray, beta, eta, n_nondelta, prev_si, prev_bsdf_pdf, prev_bsdf_delta, depth, active


#: delta bounces followed before the first non-delta vertex
MAX_DELTA_DEPTH = 64


@dr.syntax
def trace_until(scene, sampler, ray, active, stop, max_depth=MAX_DELTA_DEPTH):
    """Follow BSDF-sampled bounces from ``ray`` to the first hit where ``stop(si, bsdf, hit)``
    holds. Returns ``(si, ray, beta, Le, found)``: that interaction and the ray that reached
    it, the throughput of the chain before it, the emission met on the way (unweighted: the
    chain's vertices have no emitter sampling) and the lanes that found one within
    ``max_depth`` vertices."""
    ctx = mi.BSDFContext()
    ray = mi.Ray3f(ray)
    beta = mi.Spectrum(1.0)
    Le = mi.Spectrum(0.0)
    depth = mi.UInt32(0)
    found = mi.Bool(False)
    si = dr.zeros(mi.SurfaceInteraction3f)
    active = mi.Bool(active)
    max_depth = int(max_depth)
    while dr.hint(active, label="trace_until"):
        si_cur = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=depth == 0)
        Le += beta * si_cur.emitter(scene).eval(si_cur, active)
        bsdf = si_cur.bsdf(ray)
        hit = active & si_cur.is_valid()
        stops = hit & stop(si_cur, bsdf, hit)
        here = stops & (depth + 1 < max_depth)
        si[here] = si_cur
        found |= here
        go = hit & ~stops
        bs, w = bsdf.sample(ctx, si_cur, sampler.next_1d(), sampler.next_2d(), go)
        go &= bs.pdf > 0
        ray[go] = si_cur.spawn_ray(si_cur.to_world(bs.wo))
        beta[go] *= w
        depth += 1
        active = go & (depth < max_depth) & (dr.max(beta) != 0.0)
    return si, ray, beta, Le, found


def is_smooth(si, bsdf, hit):
    """A vertex with a non-delta lobe (where emitter sampling and gathers happen)."""
    return mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)


def first_nondelta_hit(scene, sampler, ray, active, max_depth=MAX_DELTA_DEPTH):
    """Follow delta (specular) bounces from ``ray`` to the first hit on a non-delta (smooth)
    surface, as Mitsuba's ``path`` would: :func:`trace_until` stopping at smooth BSDFs (the
    emission met on the way has MIS weight 1: no other strategy reaches it). Integrators'
    debug views and radiance_cache's gather vertex start here."""
    return trace_until(scene, sampler, ray, active, is_smooth, max_depth)


__all__ = ["trace_until", "is_smooth", "first_nondelta_hit", "path_start", "next_hit",
           "mis_weight", "emission_mis", "emitter_sample_mis",
           "by_component", "russian_roulette", "bsdf_continue", "roulette_step", "bsdf_step"]
