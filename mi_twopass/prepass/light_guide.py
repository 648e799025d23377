"""Photon emission guided by what the eye sees: the light pass's photons shared out by yield.

Heckbert's light quadtree (§3.3.1, §4.1) adapts *where* a light's photons are stratified, but
every leaf still shoots as many photons as the next. A photon that leaves the scene, or whose
light path never reaches a surface the camera sees, costs its rays and fills no bucket the
image reads. This module turns the probe shoot (uniform, 2^16 photons) into
an importance for every leaf: its *yield* y, the deposits its photons left on rexes the eye
sees (the size pass's ``seen``) per photon: the visual importance of Peter & Pietrek
("Importance Driven Construction of Photon Maps", EGWR 1998), measured by the photons
themselves instead of by importons.

The allocation keeps the estimate unbiased without a defensive mixture: the final shoot is
stratified (every leaf, every quadrant of it, shoots ``reps`` ≥ 1 photons of weight
|quadrant| / reps), so *any* positive count per leaf gives an unbiased flux estimate; the
guide only chooses the counts. A leaf's count is proportional to its importance

    g = max(y, FLOOR · ȳ_w),   ȳ_w = Σ p·y² / Σ p·y   (p the light's power, over probe cells)

ȳ_w is the yield of the cells that shoot most photons, so that no photon weighs more than
1/FLOOR times those. (A floor relative to the plain mean ȳ let window_interior's few lucky
photons from cells the probe saw as dark weigh 300× the others: its block relMSE's bias part
went from 3.5e-4 to 4.9e-3.) Across lights the budgets follow power × mean g, which shares the
photons of a scene with many lights out to the ones whose light the image shows.

Status (session 28): opt-in (``rex``'s ``light_guide``). Measured with ``python -m
mi_twopass check SCENE --res 128 --spp 64 --ref-spp 16384 --renders 2 --integrators
rex,rex:light_guide=true`` (the bias part of the 8×8-block relMSE, the default first, then
guided; the bound is 3e-3): zoo 1.2e-4 ± 4.8e-4 and 4.1e-4 ± 5.1e-4 (the same within its
noise), caustic 4.9e-4 and 4.8e-4, mixed_room 1.5e-3 and 2.3e-3, office 2.0e-3 and 2.5e-3,
window_interior 3.5e-4 and 1.45e-3. At 256² the zoo's rex shoots 0.86 M photons instead of
6.3 M (its prepass 1.2 s against 4.7 s in one run beside a CI job). Deposit counts do not
measure the noise of photons of unequal weight, so the budget rule that counts them
(4 × split_limit per bucket) fills buckets less well with the guide on three scenes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: a cell's importance is at least this fraction of the lights' mean yield
FLOOR = 0.125


def _sat(grid):
    n = grid.shape[0]
    sat = np.zeros((n + 1, n + 1))
    sat[1:, 1:] = grid.cumsum(0).cumsum(1)
    return sat


def _block_mean(sat, lp, lev, ix, iy):
    """Mean of a 2^lp-square grid (given by its summed-area table) over light-tree nodes."""
    finer = lev >= lp
    down = np.where(finer, lev - lp, 0)
    up = np.where(finer, 0, lp - lev)
    x0 = np.where(finer, ix >> down, ix << up)
    y0 = np.where(finer, iy >> down, iy << up)
    s = np.left_shift(1, up)
    return (sat[y0 + s, x0 + s] - sat[y0, x0 + s] - sat[y0 + s, x0] + sat[y0, x0]) / (s * s)


@dataclass
class LightGuide:
    """Per emitter, square grids over the light quadtree's adapted 2-D sample at the probe's
    uniform level: the yield y (deposits on seen rexes per photon) and the importance g, kept
    as summed-area tables so that any light-tree node reads its mean in O(1)."""

    level: np.ndarray  # per emitter, the probe grid's level (−1: the emitter shot no photon)
    yields: list  # per emitter, the yield grid (None if level < 0)
    importances: list  # per emitter, the importance grid g (None if level < 0)
    floor: float  # the importance every cell has at least (0: the guide is not active)

    @classmethod
    def from_probe(cls, n_emitters, em, lev, ix, iy, leaf_lanes, lane_yield, power):
        """The guide from a probe shoot over a *uniform* light tree (one level per emitter):
        leaf i of emitter ``em[i]`` at (``lev[i]``, ``ix[i]``, ``iy[i]``) shot ``leaf_lanes[i]``
        photons, consecutive in ``lane_yield`` (each photon's deposits on seen rexes)."""
        level = np.full(n_emitters, -1, np.int64)
        yields = [None] * n_emitters
        starts = np.concatenate([[0], np.cumsum(leaf_lanes)]).astype(np.int64)
        sums = np.add.reduceat(lane_yield.astype(np.float64), starts[:-1]) \
            if len(lane_yield) else np.zeros(len(em))
        sums = np.where(leaf_lanes > 0, sums, 0.0)
        leaf_yield = sums / np.maximum(leaf_lanes, 1)
        for e in np.unique(em):
            mine = em == e
            lv = int(lev[mine].max())
            if (lev[mine] != lv).any():
                raise ValueError("the probe's light tree must be uniform per emitter")
            n = 1 << lv
            grid = np.zeros((n, n))
            grid[iy[mine], ix[mine]] = leaf_yield[mine]
            level[e] = lv
            yields[e] = grid
        # g = y, at least FLOOR × the photon-weighted mean of y (Σ g² / Σ g: the yield of the
        # cells that shoot most photons), so that no photon weighs more than 1/FLOOR times
        # those (√y, Neyman's allocation for a Bernoulli yield, measured the same in check)
        p = np.where(np.isfinite(power) & (power > 0), power, 0.0)
        num = den = 0.0
        for e in np.nonzero((level >= 0) & (p > 0))[0]:
            r = yields[e]
            num += p[e] * (r * r).mean()
            den += p[e] * r.mean()
        floor = FLOOR * num / den if den > 0 else 0.0
        imps = [None if g is None else (np.maximum(g, floor) if floor > 0
                                        else np.ones_like(g)) for g in yields]
        return cls(level, [None if g is None else _sat(g) for g in yields],
                   [None if g is None else _sat(g) for g in imps], floor)

    @property
    def active(self) -> bool:
        """Whether the probe saw any useful photon (else the allocation stays uniform)."""
        return self.floor > 0

    def _nodes(self, tables, em, lev, ix, iy):
        em = np.asarray(em, np.int64)
        lev, ix, iy = (np.asarray(a, np.int64) for a in (lev, ix, iy))
        out = np.zeros(len(em))
        for e in np.unique(em):
            if self.level[e] < 0:
                continue
            mine = np.nonzero(em == e)[0]
            out[mine] = _block_mean(tables[e], int(self.level[e]), lev[mine], ix[mine],
                                    iy[mine])
        return out

    def node_yield(self, em, lev, ix, iy) -> np.ndarray:
        """Mean probe yield over the square of each light-tree node (any level)."""
        return self._nodes(self.yields, em, lev, ix, iy)

    def importance(self, em, lev, ix, iy) -> np.ndarray:
        """Mean importance g over the square of each light-tree node (1 everywhere when the
        guide is not active)."""
        return self._nodes(self.importances, em, lev, ix, iy)

    def emitter_importance(self) -> np.ndarray:
        """Mean g over each emitter's whole sample square (0 for an emitter the probe did not
        shoot)."""
        return np.array([t[-1, -1] / (t.shape[0] - 1) ** 2 if t is not None else 0.0
                         for t in self.importances])

    def guided_rate(self, power) -> float:
        """Deposits on seen rexes per photon expected when the photons are shared out by
        importance (budgets by power × mean g, cells by g within a light)."""
        p = np.where(np.isfinite(power) & (power > 0), power, 0.0)
        num = den = 0.0
        for e in np.nonzero((self.level >= 0) & (p > 0))[0]:
            y = np.diff(np.diff(self.yields[e], axis=0), axis=1)
            g = np.diff(np.diff(self.importances[e], axis=0), axis=1)
            # emitter e's share of the photons ∝ p·mean(g); within it, cell c's ∝ g_c
            num += p[e] * (g * y).mean()
            den += p[e] * g.mean()
        return num / den if den > 0 else 0.0
