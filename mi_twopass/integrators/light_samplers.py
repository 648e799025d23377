"""Direct light behind one interface: which source a shading point samples, and with what
probability.

A light sampler is pbrt-v4's ``LightSampler`` (``Sample`` / ``PMF``) in Dr.Jit form. At a
non-delta vertex x an integrator asks it for one source,

    (i, P(i | x), ctx) = sampler.sample(si, n, two_sided, sampler_, active),

takes a point or direction on that source (its own density p_i(ω)), and keeps ``ctx`` (what
the choice depended on at x) in its loop state. When the BSDF-sampled ray leaving x meets an
emitter j, the explicit strategy's density of that direction is P(j | x) · p_j(ω), with
P(j | x) = ``sampler.pmf(ctx, j)``; MIS weights the two strategies with it (Veach 1997,
§9.2.4). Source ids of emitters are their indices in ``scene.emitters()``.

The samplers of the suite:

* :class:`EmitterSampler`: Mitsuba's own choice (``Scene::sample_emitter``: uniform, or by
  the emitters' ``sampling_weight``); no context.
* :class:`SpikeListSampler`: Zimmerman & Shirley's spike lists (§2.6, §4): a source of the
  lists of x's cell and of a jittered neighbour cell, ∝ g_i · L'_i(x), with a defensive
  uniform component; the context holds the two lists and their normalisations.
* :class:`mi_twopass.prepass.radiosity.VirtualLuminaires`: GSII's reclassified bright patches,
  power-proportional, context-free (its sources are patch ids, sampled by area).

:func:`sample_emitter_mis` and :func:`emission_mis` are the two halves of the direct-light
estimate for any sampler whose sources are emitters; :class:`EmitterSampler` overrides both
with Mitsuba's fused calls (``Scene::sample_emitter_direction`` / ``pdf_emitter_direction``),
which compute the same values. An integrator that holds a light sampler therefore renders with
any of them without a loop of its own.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..host_arrays import jit
from ..prepass.spike_grid import INVALID
from ..rays import shadow_ray
from ..scene.emission import has_infinite_emitters
from .pathtrace import emission_mis as scene_emission_mis
from .pathtrace import emitter_sample_mis as scene_emitter_sample_mis
from .pathtrace import mis_weight

_TINY = 1e-30


class SpikeContext:
    """What a spike-list choice at x depended on, kept as loop state until the next hit:
    the lists ``list_a`` / ``list_b`` (``INVALID``: none; no list at all means the uniform
    fallback), their normalisations ``scale_a`` / ``scale_b`` (m_c / W_c), the defensive
    weight ``eps``, and x's position ``p``, receiver normal ``n`` and ``two_sided`` flag (the
    arguments of L'_i(x))."""

    DRJIT_STRUCT = {"list_a": mi.UInt32, "list_b": mi.UInt32, "scale_a": mi.Float,
                    "scale_b": mi.Float, "eps": mi.Float, "p": mi.Point3f, "n": mi.Vector3f,
                    "two_sided": mi.Bool}

    def __init__(self, list_a=None, list_b=None, scale_a=None, scale_b=None, eps=None, p=None,
                 n=None, two_sided=None):
        self.list_a = mi.UInt32(INVALID) if list_a is None else list_a
        self.list_b = mi.UInt32(INVALID) if list_b is None else list_b
        self.scale_a = mi.Float(0.0) if scale_a is None else scale_a
        self.scale_b = mi.Float(0.0) if scale_b is None else scale_b
        self.eps = mi.Float(0.0) if eps is None else eps
        self.p = mi.Point3f(0.0) if p is None else p
        self.n = mi.Vector3f(0.0) if n is None else n
        self.two_sided = mi.Bool(False) if two_sided is None else two_sided

    @property
    def has_list(self):
        """Lanes whose choice came from the lists (else from the uniform fallback)."""
        return self.list_a != INVALID


def emitter_index_table(scene):
    """``(table, n)``: Dr.Jit table from an emitter's registry id (``dr.reinterpret_array`` of
    an ``mi.EmitterPtr``) to its index in ``scene.emitters()``, ``INVALID`` elsewhere."""
    emitters = scene.emitters()
    if not emitters:
        return mi.UInt32([INVALID]), 0
    regs = np.array(dr.reinterpret_array(mi.UInt32, scene.emitters_dr()), dtype=np.int64)
    table = np.full(int(regs.max()) + 1, INVALID, dtype=np.uint32)
    table[regs] = np.arange(len(emitters), dtype=np.uint32)
    return jit(mi.UInt32, table), len(emitters)


class LightSampler:
    """The interface (see the module docstring). Subclasses implement :meth:`start`,
    :meth:`sample`, :meth:`pmf`, :meth:`source_of_emitter` and :meth:`emitter_index`."""

    def start(self):
        """The context before the first vertex (loop state's initial value)."""
        raise NotImplementedError

    def sample(self, si, n, two_sided, sampler, active):
        """``(source, P(source | x), ctx)`` for one explicit sample at ``si`` (receiver
        normal ``n``, |cos| where ``two_sided``); ``source`` is ``INVALID`` where there is
        nothing to sample."""
        raise NotImplementedError

    def pmf(self, ctx, source, active):
        """P(source | x) of :meth:`sample` at the vertex whose context is ``ctx``."""
        raise NotImplementedError

    def source_of_emitter(self, emitter, active):
        """The source id of an ``mi.EmitterPtr`` (``INVALID`` for a null pointer)."""
        raise NotImplementedError

    def emitter_index(self, source, active):
        """Index in ``scene.emitters()`` of an emitter source."""
        raise NotImplementedError

    def is_emitter(self, source, active):
        """The lanes whose ``source`` is an emitter (other sources, e.g. virtual luminaires,
        are sampled by their integrator)."""
        return mi.Bool(active) & (source != INVALID)

    def sample_emitter_mis(self, scene, si, bsdf, bsdf_ctx, sampler, active, scale=1.0):
        """``(f·Le·w/(P·p), cast, ctx)``: :func:`sample_emitter_mis` with this sampler."""
        return sample_emitter_mis(self, scene, si, bsdf, bsdf_ctx, sampler, active, scale)

    def emission_mis(self, scene, ctx, si, prev_si, prev_bsdf_pdf, prev_bsdf_delta, active):
        """Le at ``si`` MIS-weighted against this sampler's choice at ``prev_si``:
        :func:`emission_mis`."""
        return emission_mis(self, scene, ctx, si, prev_si, prev_bsdf_pdf, prev_bsdf_delta,
                            active)


class EmitterSampler(LightSampler):
    """Mitsuba's emitter choice, ``Scene::sample_emitter`` (uniform over ``scene.emitters()``
    unless emitters carry a ``sampling_weight``); P does not depend on x, so the context is
    empty. Its direct-light halves are Mitsuba's fused calls (the values of the generic ones,
    fewer operations)."""

    def __init__(self, scene):
        self.scene = scene
        self.index_table, self.count = emitter_index_table(scene)

    def start(self):
        return ()

    def sample(self, si, n, two_sided, sampler, active):
        active = mi.Bool(active) & (self.count > 0)
        index, _, _ = self.scene.sample_emitter(sampler.next_1d(active), active)
        P = self.scene.pdf_emitter(index, active)
        return dr.select(active, index, INVALID), dr.select(active, P, 0.0), ()

    def pmf(self, ctx, source, active):
        active = mi.Bool(active) & (source != INVALID)
        return dr.select(active, self.scene.pdf_emitter(source, active), 0.0)

    def source_of_emitter(self, emitter, active):
        rid = dr.reinterpret_array(mi.UInt32, emitter)
        ok = mi.Bool(active) & (rid < dr.width(self.index_table))
        return dr.select(ok, dr.gather(mi.UInt32, self.index_table, rid, ok), INVALID)

    def emitter_index(self, source, active):
        return source

    def sample_emitter_mis(self, scene, si, bsdf, bsdf_ctx, sampler, active, scale=1.0):
        Ld, cast = scene_emitter_sample_mis(scene, si, bsdf, bsdf_ctx, sampler.next_2d(), active,
                                            scale)
        return Ld, cast, ()

    def emission_mis(self, scene, ctx, si, prev_si, prev_bsdf_pdf, prev_bsdf_delta, active):
        return scene_emission_mis(scene, si, prev_si, prev_bsdf_pdf, prev_bsdf_delta, active)


class SpikeListSampler(LightSampler):
    """Zimmerman & Shirley's selection (§2.6, §4) from a spike-list grid
    (:class:`mi_twopass.prepass.spike_grid.SpikeGrid`): at x, the lists of x's cell (a) and
    of the cell of x jittered by up to ±``jitter``/2 cell (b); one source from the mixture
    ε·uniform(support) + m_a·(g·L' in a)/W_a + m_b·(g·L' in b)/W_b
    (:meth:`~mi_twopass.prepass.spike_grid.SpikeGrid.sample`). Where x's cells have no list,
    an emitter uniformly (P = 1/N, the *fallback*). Sources may be emitters or virtual
    luminaires (patches): :meth:`is_patch` tells them apart.

    ``support``: the defensive component's sources, "emitters" (every emitter, so that each
    has an explicit strategy and MIS can weight all their hits) or "delta" (only sources no
    ray can hit); ``defensive``: its weight ε; ``r_thresh``: the gather reach L' is clamped
    with.

    ``selection``: "point" (the paper's) weighs each listed source by g·L'_i(x) at the
    shading point, a sweep over both lists per vertex; "cell" by fixed per-cell weights
    (:func:`~mi_twopass.prepass.spike_grid.cell_weights`: L' averaged over the cell's
    visibility points), drawn by a binary search in the list's CDF, and P(i | x) is a table
    read: cheaper per vertex, blind to where in the cell x lies."""

    SELECTIONS = ("point", "cell")

    def __init__(self, grid, n_emitters, r_thresh, defensive=0.1, support="emitters",
                 jitter=1.0, selection="point"):
        if selection not in self.SELECTIONS:
            raise ValueError(f"selection={selection!r}: expected one of {self.SELECTIONS}")
        self.selection = selection
        self.grid = grid
        self.sources = grid.sources
        self.n_emitters = int(n_emitters)
        self.r_thresh = r_thresh
        self.defensive = float(defensive)
        self.support = support
        self.jitter = float(jitter)
        _, n_support, self.in_support = grid.support_tables(support)
        self.inv_n_support = 1.0 / max(n_support, 1)
        self.inv_n_emitters = 1.0 / max(self.n_emitters, 1)

    def start(self):
        return SpikeContext()

    def sample(self, si, n, two_sided, sampler, active):
        """Draws 6 numbers from ``sampler``, in this order: the jitter (2D + 1D), the two
        reservoir passes, the mixture (which also picks the fallback emitter)."""
        grid = self.grid
        active = mi.Bool(active)
        u_j = sampler.next_2d()
        u_jz = sampler.next_1d()
        lid_a, lid_b = grid.choose_lists(si.p, mi.Point3f(u_j.x, u_j.y, u_jz), active,
                                         self.jitter)
        has_list = active & (lid_a != INVALID)
        u_a = sampler.next_1d()
        u_b = sampler.next_1d()
        u_mix = sampler.next_1d()
        P = None
        if self.selection == "cell":
            sid, scale_a, scale_b, eps = self._cell_sample(lid_a, lid_b, u_a, u_mix, has_list)
        else:
            sid, P, scale_a, scale_b, eps = grid.sample(
                lid_a, lid_b, si.p, n, two_sided, u_a, u_b, u_mix, self.r_thresh,
                self.defensive, has_list, self.support)
        # no list: an emitter uniformly (source ids of emitters are their indices)
        fallback = active & ~has_list & (self.n_emitters > 0)
        fb = dr.minimum(mi.UInt32(u_mix * self.n_emitters), max(self.n_emitters - 1, 0))
        sid = dr.select(has_list, sid, dr.select(fallback, fb, INVALID))
        ctx = SpikeContext(dr.select(has_list, lid_a, INVALID),
                           dr.select(has_list, lid_b, INVALID),
                           dr.select(has_list, scale_a, 0.0), dr.select(has_list, scale_b, 0.0),
                           dr.select(has_list, eps, 0.0), mi.Point3f(si.p), mi.Vector3f(n),
                           mi.Bool(two_sided))
        if P is None:  # the cell selection's P: two table reads (pmf)
            P = self.pmf(ctx, sid, active & (sid != INVALID))
        else:
            P = dr.select(has_list, P, dr.select(fallback, self.inv_n_emitters, 0.0))
        return sid, P, ctx

    def _cell_sample(self, lid_a, lid_b, u, u_mix, active):
        """The per-cell selection: the defensive component with ε, else list a or b (equally
        among those with weight), then a source by the list's CDF. Returns ``(sid, m_a, m_b,
        ε)`` (the context's scales are the mixture weights here)."""
        grid = self.grid
        eps, m_a, m_b = grid.cell_mixture(lid_a, lid_b, self.defensive, self.support)
        pick_def = active & (u_mix < eps)
        pick_b = active & ~pick_def & (u_mix >= eps + m_a) & (m_b > 0)
        pick_a = active & ~pick_def & ~pick_b & (m_a > 0)
        from_list = pick_a | pick_b
        sid, _ = grid.cell_pick(dr.select(pick_b, lid_b, lid_a), u, from_list)
        sid = dr.select(from_list, sid, INVALID)
        ids, K, _ = grid.support_tables(self.support)
        if K > 0:
            k = mi.UInt32(dr.minimum(u_mix / dr.maximum(eps, _TINY) * K, K - 1))
            sid = dr.select(pick_def, dr.gather(mi.UInt32, ids, k, pick_def), sid)
        return sid, m_a, m_b, eps

    def pmf_listed(self, ctx, source, active):
        """``(P(source | x), listed)``: :meth:`pmf`, and whether ``source`` is in one of the
        context's lists (the paper's partition needs it)."""
        active = mi.Bool(active)
        from_list = active & ctx.has_list
        if self.selection == "cell":
            listed_a, e_a = self.grid.entry_of(ctx.list_a, source, from_list)
            listed_b, e_b = self.grid.entry_of(ctx.list_b, source, from_list)
            prob = self.grid._tables["cell_prob"]
            P_list = ctx.scale_a * dr.gather(mi.Float, prob, e_a, listed_a) \
                + ctx.scale_b * dr.gather(mi.Float, prob, e_b, listed_b)
            listed = listed_a | listed_b
        else:
            listed_a, g_a = self.grid.contains(ctx.list_a, source, from_list)
            listed_b, g_b = self.grid.contains(ctx.list_b, source, from_list)
            listed = listed_a | listed_b
            Lp = self.sources.estimate(source, ctx.p, ctx.n, ctx.two_sided, self.r_thresh,
                                       listed)
            P_list = (ctx.scale_a * g_a + ctx.scale_b * g_b) * Lp
        in_support = dr.gather(mi.Bool, self.in_support, source,
                               from_list & (source != INVALID))
        P_list += dr.select(in_support, ctx.eps * self.inv_n_support, 0.0)
        is_emitter = (source != INVALID) & (source < self.n_emitters)
        P_fallback = dr.select(is_emitter, self.inv_n_emitters, 0.0)
        P = dr.select(from_list, P_list, dr.select(active, P_fallback, 0.0))
        return P, listed

    def pmf(self, ctx, source, active):
        return self.pmf_listed(ctx, source, active)[0]

    def listed(self, ctx, source, active):
        """Is ``source`` in one of the context's lists."""
        active = mi.Bool(active) & ctx.has_list
        return self.grid.contains(ctx.list_a, source, active)[0] \
            | self.grid.contains(ctx.list_b, source, active)[0]

    def is_patch(self, source, active):
        """Is ``source`` a virtual luminaire (a patch), not an emitter."""
        active = mi.Bool(active) & (source != INVALID)
        return active & self.sources.gather("is_patch", source, active)

    def is_emitter(self, source, active):
        active = mi.Bool(active) & (source != INVALID)
        return active & ~self.is_patch(source, active)

    def source_of_emitter(self, emitter, active):
        return self.sources.source_of_emitter(emitter, active)

    def emitter_index(self, source, active):
        return self.sources.gather("emitter_index", source, active)


def sample_emitter_mis(lights: LightSampler, scene, si, bsdf, bsdf_ctx, sampler, active,
                       scale=1.0):
    """One explicit sample of direct light at ``si`` with ``lights``: source i with
    probability P(i | x), a direction toward it by the emitter's own density p_i(ω), a shadow
    ray, and the MIS weight (P·p_i)² / ((P·p_i)² + p_bsdf²) (1 for delta emitters). Returns
    ``(f·Le·w/(P·p_i), cast, ctx)``: β not included; ``cast`` the lanes that traced a shadow
    ray; ``ctx`` for :func:`emission_mis` at the next hit. Sources that are not emitters
    contribute 0 (an integrator with virtual luminaires samples those itself)."""
    active = mi.Bool(active)
    n, two_sided = receiver(si, bsdf)
    sid, P, ctx = lights.sample(si, n, two_sided, sampler, active)
    u_dir = sampler.next_2d()
    ok = lights.is_emitter(sid, active & (P > 0))
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), lights.emitter_index(sid, ok), ok)
    ds, spec = emitter.sample_direction(si, u_dir, ok)
    cast = ok & (ds.pdf != 0.0) & dr.any(spec != 0.0)
    visible = cast & ~scene.ray_test(
        shadow_ray(si, ds, scale, has_infinite_emitters(scene)), cast)
    f, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, si.to_local(ds.d), visible)
    w = dr.select(ds.delta, 1.0, mis_weight(P * ds.pdf, bsdf_pdf))
    Ld = f * spec * (w / dr.maximum(P, _TINY))
    return dr.select(visible & dr.all(dr.isfinite(Ld)), Ld, 0.0), cast, ctx


def emission_mis(lights: LightSampler, scene, ctx, si, prev_si, prev_bsdf_pdf, prev_bsdf_delta,
                 active):
    """Radiance Le(y → x) emitted at the hit ``si`` of the BSDF-sampled ray from ``prev_si``,
    weighted against the explicit strategy at ``prev_si`` (context ``ctx``):
    w = p_bsdf² / (p_bsdf² + (P(j | x)·p_j(ω))²), 1 after a delta BSDF sample."""
    ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
    Le = ds.emitter.eval(si, active)
    weigh = mi.Bool(active) & ~prev_bsdf_delta
    sid = lights.source_of_emitter(ds.emitter, weigh)
    P = lights.pmf(ctx, sid, weigh)
    p_dir = ds.emitter.pdf_direction(prev_si, ds, weigh)
    w = dr.select(prev_bsdf_delta, 1.0, mis_weight(prev_bsdf_pdf, P * p_dir))
    return w * Le


def receiver(si, bsdf):
    """The receiver normal L'_i(x) is evaluated with (the shading normal on ``wi``'s side) and
    whether |cos| applies (BSDFs that transmit)."""
    side = dr.select(mi.Frame3f.cos_theta(si.wi) >= 0, 1.0, -1.0)
    two_sided = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission)
    return mi.Vector3f(si.sh_frame.n) * side, two_sided


__all__ = ["LightSampler", "EmitterSampler", "SpikeListSampler", "SpikeContext",
           "emitter_index_table", "sample_emitter_mis", "emission_mis", "receiver"]
