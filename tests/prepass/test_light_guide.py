"""The light guide: probe yields read back per light-tree node, the floor, the expected rate."""
import numpy as np
import pytest

from mi_twopass.prepass.light_guide import FLOOR, LightGuide


def uniform_probe(grids, lanes=8, seed=0):
    """A probe over uniform trees: emitter e's grid ``grids[e]`` (2^l × 2^l yields, rows iy),
    ``lanes`` photons per leaf whose yields average exactly the grid value (half at 0, half at
    twice it)."""
    em, lev, ix, iy, leaf_lanes, ys = [], [], [], [], [], []
    for e, g in enumerate(grids):
        n = g.shape[0]
        level = int(np.log2(n))
        for y in range(n):
            for x in range(n):
                em.append(e), lev.append(level), ix.append(x), iy.append(y)
                leaf_lanes.append(lanes)
                ys.extend([0.0] * (lanes // 2) + [2 * g[y, x]] * (lanes // 2))
    arr = lambda a: np.asarray(a, np.int64)  # noqa: E731
    return arr(em), arr(lev), arr(ix), arr(iy), arr(leaf_lanes), np.asarray(ys)


def test_node_yield_is_the_mean_over_the_nodes_square_at_any_level():
    g = np.arange(16, dtype=float).reshape(4, 4)  # level 2
    guide = LightGuide.from_probe(1, *uniform_probe([g]), power=np.array([1.0]))
    # at the probe's level: the cell itself
    assert guide.node_yield([0], np.array([2]), np.array([3]), np.array([1])) == \
        pytest.approx(g[1, 3])
    # finer: the cell that holds it
    assert guide.node_yield([0], np.array([4]), np.array([13]), np.array([6])) == \
        pytest.approx(g[1, 3])
    # coarser: the mean over the cells it covers
    assert guide.node_yield([0], np.array([1]), np.array([1]), np.array([0])) == \
        pytest.approx(g[0:2, 2:4].mean())
    assert guide.node_yield([0], np.array([0]), np.array([0]), np.array([0])) == \
        pytest.approx(g.mean())


def test_importance_has_a_floor_and_rates_follow_the_allocation():
    useful = np.array([[0.0, 4.0], [0.0, 0.0]])
    dark = np.zeros((2, 2))
    power = np.array([1.0, 1.0])
    guide = LightGuide.from_probe(2, *uniform_probe([useful, dark]), power=power)
    assert guide.active
    # g = √y; the floor: FLOOR × the photon-weighted mean of √y, Σy / Σ√y = 4 / 2
    assert guide.floor == pytest.approx(FLOOR * 2.0)
    g = guide.importance(np.array([0, 0, 1]), np.array([1, 1, 1]), np.array([1, 0, 0]),
                         np.array([0, 0, 0]))
    assert g == pytest.approx([2.0, 0.25, 0.25])
    # no photon weighs more than 1/FLOOR times those of the cells that shoot most
    assert g.max() / g.min() == pytest.approx(1 / FLOOR)
    # lights share photons by power × mean importance: the dark light keeps the floor
    assert guide.emitter_importance() == pytest.approx([(2.0 + 3 * 0.25) / 4, 0.25])
    # the deposits per photon expected under that allocation; shooting evenly, the useful
    # cell has an eighth of the photons: 0.5 deposits per photon
    assert guide.guided_rate(power) == pytest.approx((2.0 * 4.0 / 4) / (0.6875 + 0.25))
    assert guide.guided_rate(power) > 4 * 0.5


def test_a_probe_that_saw_nothing_leaves_the_allocation_even():
    guide = LightGuide.from_probe(1, *uniform_probe([np.zeros((2, 2))]), power=np.ones(1))
    assert not guide.active
    assert np.all(guide.importance(np.zeros(3, np.int64), np.ones(3, np.int64),
                                   np.arange(3) % 2, np.zeros(3, np.int64)) == 1.0)
    assert guide.guided_rate(np.ones(1)) == 0.0


def test_a_non_uniform_probe_tree_is_refused():
    em, lev, ix, iy, lanes, ys = uniform_probe([np.ones((2, 2))])
    lev[0] = 2
    with pytest.raises(ValueError, match="uniform"):
        LightGuide.from_probe(1, em, lev, ix, iy, lanes, ys, power=np.ones(1))
