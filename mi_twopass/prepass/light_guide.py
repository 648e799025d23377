"""Photon emission guided by what the eye sees: the light pass's photons shared out by yield.

Heckbert's light quadtree (§3.3.1, §4.1) adapts *where* a light's photons are stratified, but
every leaf still shoots as many photons as the next. A photon that leaves the scene, or whose
light path never reaches a surface the camera sees, costs its rays and fills no bucket the
image reads. This module turns the probe shoot (uniform, 2^16 photons) into
an importance for every leaf: its *yield* y, the deposits its photons left on rexes the eye
sees (the size pass's ``seen``) per photon: the visual importance of Peter & Pietrek
("Importance Driven Construction of Photon Maps", EGWR 1998), measured by the photons
themselves instead of by importons.

The radiosity prepass has its own guide for the same idea (:mod:`mi_twopass.prepass.emission_guide`:
cells of the emitters' primary sample space, 4-D for a sky, drawn from a fitted density mixed
with Mitsuba's own, scored by camera importance). rex keeps Heckbert's light quadtree, whose
leaves stratify each light, so this guide sets every leaf's photon count instead of drawing
cells; it shares that module's Neyman rule (density ∝ √ of the mean squared score), not its
code.

The allocation keeps the estimate unbiased without a defensive mixture: the final shoot is
stratified (every leaf, every quadrant of it, shoots ``reps`` ≥ 1 photons of weight
|quadrant| / reps), so *any* positive count per leaf gives an unbiased flux estimate; the
guide only chooses the counts. A leaf of area a (in the light's sample square) gets photons in
proportion to a·g, its importance

    g = max(√y, FLOOR · ḡ_w),   ḡ_w = Σ p·y / Σ p·√y   (p the light's power, over probe cells)

a·√y is Neyman's allocation: with n_c photons of weight a_c/n_c and y_c seen deposits each, the
variance of the seen flux is ∝ Σ a_c² y_c / n_c, least for n_c ∝ a_c √y_c. ḡ_w is the √y of
the cells that shoot most photons, so that no photon weighs more than 1/FLOOR times those.
Across lights the budgets follow power × mean g.

Measured with ``python -m mi_twopass check SCENE --res 128 --spp 64 --ref-spp 16384 --renders
2 --integrators rex:light_guide=false,rex`` (the bias part of the 8×8-block relMSE, the bound
3e-3; session 28, each pair in one sitting except the first five, whose light_guide=false rows
came from an earlier run of the same command): office 2.0e-3 → 7.2e-4, window_interior 3.5e-4
→ 1.9e-4, mixed_room 1.5e-3 → 1.4e-3, zoo 1.2e-4 → 2.6e-4 (± 5e-4 both), caustic 4.9e-4 →
4.3e-4, veach-bidir 2.4e-3 → 1.5e-3, Cornell box 8.0e-5 → 6.0e-5, furnace 1.2e-4 → 6.0e-5,
tut-cbox 5.6e-5 → 6.0e-5, many_lights −3.2e-4 → −3.9e-4 (± 4.5e-4 both).

Rules tried first and not kept (same command):
- g = y with its floor at FLOOR × the plain mean of y, and leaves' counts ∝ g alone (not
  × area, so the light tree's fine leaves kept their extra photons): window_interior's bias
  part 4.9e-3, out of bounds (a few photons from cells the probe saw as dark weighed 300× the
  others);
- g = y with the photon-weighted floor, counts ∝ g: window_interior 1.45e-3, mixed_room
  2.3e-3, office 2.5e-3 (the weights' spread: the seen deposits' effective count
  (Σw)²/Σw² per deposit was 0.05 of the count on window_interior, 0.19 evenly, 0.45 with
  this rule).
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


@dataclass
class LightGuide:
    """Per emitter, square grids over the light quadtree's adapted 2-D sample at the probe's
    uniform level: the yield y (deposits on seen rexes per photon) and the importance g, kept
    as summed-area tables so that any light-tree node reads its mean in O(1)."""

    level: np.ndarray  # per emitter, the probe grid's level (−1: the emitter shot no photon)
    yields: list  # per emitter, the yield grid (None if level < 0)
    importances: list  # per emitter, the importance grid g (None if level < 0)
    floor: float  # the importance every cell has at least (0: the guide is not active)
    #: per emitter, the records (all deposits) per photon, as summed-area tables (None: not
    #: measured)
    deposits: list | None = None

    @classmethod
    def from_probe(cls, n_emitters, em, lev, ix, iy, leaf_lanes, lane_yield, power,
                   lane_records=None):
        """The guide from a probe shoot over a *uniform* light tree (one level per emitter):
        leaf i of emitter ``em[i]`` at (``lev[i]``, ``ix[i]``, ``iy[i]``) shot ``leaf_lanes[i]``
        photons, consecutive in ``lane_yield`` (each photon's deposits on seen rexes) and in
        ``lane_records`` (each photon's deposits anywhere; optional)."""
        level = np.full(n_emitters, -1, np.int64)
        starts = np.concatenate([[0], np.cumsum(leaf_lanes)]).astype(np.int64)

        def grids(per_lane):
            sums = np.add.reduceat(per_lane.astype(np.float64), starts[:-1]) \
                if len(per_lane) else np.zeros(len(em))
            per_leaf = np.where(leaf_lanes > 0, sums, 0.0) / np.maximum(leaf_lanes, 1)
            out = [None] * n_emitters
            for e in np.unique(em):
                mine = em == e
                lv = int(lev[mine].max())
                if (lev[mine] != lv).any():
                    raise ValueError("the probe's light tree must be uniform per emitter")
                n = 1 << lv
                grid = np.zeros((n, n))
                grid[iy[mine], ix[mine]] = per_leaf[mine]
                level[e] = lv
                out[e] = grid
            return out
        yields = grids(lane_yield)
        deposits = grids(lane_records) if lane_records is not None else None
        # g = √y, at least FLOOR × the photon-weighted mean of √y (Σ g² / Σ g: that of the
        # cells that shoot most photons), so that no photon weighs more than 1/FLOOR times
        # those
        p = np.where(np.isfinite(power) & (power > 0), power, 0.0)
        num = den = 0.0
        for e in np.nonzero((level >= 0) & (p > 0))[0]:
            r = np.sqrt(yields[e])
            num += p[e] * (r * r).mean()
            den += p[e] * r.mean()
        floor = FLOOR * num / den if den > 0 else 0.0
        imps = [None if g is None else (np.maximum(np.sqrt(g), floor) if floor > 0
                                        else np.ones_like(g)) for g in yields]
        return cls(level, [None if g is None else _sat(g) for g in yields],
                   [None if g is None else _sat(g) for g in imps], floor,
                   None if deposits is None else
                   [None if g is None else _sat(g) for g in deposits])

    @property
    def active(self) -> bool:
        """Whether the probe saw any useful photon (else the allocation stays uniform)."""
        return self.floor > 0

    def _nodes(self, tables, em, lev, ix, iy):
        """Mean of each emitter's grid (``tables``: its summed-area tables) over the nodes'
        squares, all emitters at once (one flat array of the tables, no loop over lights)."""
        em = np.asarray(em, np.int64)
        lev, ix, iy = (np.asarray(a, np.int64) for a in (lev, ix, iy))
        side = np.array([0 if t is None else t.shape[0] for t in tables], np.int64)  # 2^l + 1
        start = np.concatenate([[0], np.cumsum(side * side)[:-1]])
        flat = np.concatenate([t.ravel() for t in tables if t is not None] or [np.zeros(1)])
        lp = np.maximum(self.level[em], 0)
        finer = lev >= lp
        down = np.where(finer, lev - lp, 0)
        up = np.where(finer, 0, lp - lev)
        x0 = np.where(finer, ix >> down, ix << up)
        y0 = np.where(finer, iy >> down, iy << up)
        s = np.left_shift(1, up)
        w, base = np.maximum(side[em], 1), start[em]

        def at(y, x):
            return flat[np.minimum(base + y * w + x, len(flat) - 1)]
        total = at(y0 + s, x0 + s) - at(y0, x0 + s) - at(y0 + s, x0) + at(y0, x0)
        return np.where(self.level[em] >= 0, total / (s * s), 0.0)

    def node_yield(self, em, lev, ix, iy) -> np.ndarray:
        """Mean probe yield over the square of each light-tree node (any level)."""
        return self._nodes(self.yields, em, lev, ix, iy)

    def node_deposits(self, em, lev, ix, iy):
        """Mean records (all deposits) per probe photon over the square of each light-tree
        node; None where the probe did not count them."""
        return None if self.deposits is None else self._nodes(self.deposits, em, lev, ix, iy)

    def importance(self, em, lev, ix, iy) -> np.ndarray:
        """Mean importance g over the square of each light-tree node (1 everywhere when the
        guide is not active)."""
        return self._nodes(self.importances, em, lev, ix, iy)

    def emitter_importance(self) -> np.ndarray:
        """Mean g over each emitter's whole sample square (0 for an emitter the probe did not
        shoot)."""
        return np.array([t[-1, -1] / (t.shape[0] - 1) ** 2 if t is not None else 0.0
                         for t in self.importances])

    def weight_scale(self, em, lev, ix, iy, power) -> np.ndarray:
        """Per probe photon (its emitter and probe-grid cell), the weight a photon from there
        has in the guided shoot over its weight in an even shoot of as many photons: the
        cell's photons are Σp·ḡ / (Σp · g) times fewer (budgets ∝ power × mean g, cells ∝
        g), each as much heavier, so its deposits' Σw² grows by that factor."""
        p = np.where(np.isfinite(power) & (power > 0), power, 0.0)
        shot = (self.level >= 0) & (p > 0)
        mean_g = self.emitter_importance()
        ratio = float(np.sum(p[shot] * mean_g[shot]) / np.sum(p[shot])) if shot.any() else 1.0
        g = self.importance(em, lev, ix, iy)
        return np.where(g > 0, ratio / np.where(g > 0, g, 1.0), 0.0)

    def guided_rate(self, power) -> float:
        """Deposits on seen rexes per photon expected when the photons are shared out by
        importance (budgets by power × mean g, cells by g within a light: the probe's cells
        are of equal area)."""
        p = np.where(np.isfinite(power) & (power > 0), power, 0.0)
        num = den = 0.0
        for e in np.nonzero((self.level >= 0) & (p > 0))[0]:
            y = np.diff(np.diff(self.yields[e], axis=0), axis=1)
            g = np.diff(np.diff(self.importances[e], axis=0), axis=1)
            # emitter e's share of the photons ∝ p·mean(g); within it, cell c's ∝ g_c
            num += p[e] * (g * y).mean()
            den += p[e] * g.mean()
        return num / den if den > 0 else 0.0
