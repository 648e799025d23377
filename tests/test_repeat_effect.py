"""tools/repeat_effect.py: a bench run's cells read from its kept (median) runs and from its
first runs, and the spread of one point's repeats."""
import importlib.util
import os

import pytest

_PATH = os.path.join(os.path.dirname(__file__), "..", "tools", "repeat_effect.py")
_spec = importlib.util.spec_from_file_location("repeat_effect", _PATH)
repeat_effect = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(repeat_effect)


def point(spp, seconds, relmse, repeats=None, errors=None):
    stats = {} if repeats is None else {"repeat_seconds": repeats, "repeat_relmse": errors,
                                        "repeat_kept": repeats.index(seconds)}
    return {"spp": spp, "seconds": seconds, "relmse": relmse, "flip": 0.1, "mse": relmse,
            "stats": stats}


def entry():
    """path reaches 0.01 at 4 s; twopass's 2-spp point was slow in its first run."""
    path = [point(1, 1.0, 0.04), point(2, 2.0, 0.02), point(4, 4.0, 0.01)]
    twopass = [point(1, 0.5, 0.02, [0.5, 0.5, 0.6], [0.02, 0.02, 0.02]),
               point(2, 0.6, 0.005, [0.9, 0.6, 0.55], [0.006, 0.005, 0.005])]
    return {"label": "s (8×8)", "curves": {
        "path": {"label": "path", "points": path},
        "rex": {"label": "rex", "points": [point(1, 0.5, 0.02), point(2, 0.8, 0.005)]},
        "twopass": {"label": "twopass", "points": twopass}}}


def test_first_run_replaces_a_repeated_point_by_its_first_render():
    p = point(2, 0.6, 0.005, [0.9, 0.6, 0.55], [0.006, 0.005, 0.005])
    assert repeat_effect.first_run(p)["seconds"] == 0.9
    assert repeat_effect.first_run(p)["relmse"] == 0.006
    single = point(4, 4.0, 0.01)
    assert repeat_effect.first_run(single) is single


def test_cells_are_read_from_the_kept_runs_and_from_the_first_runs():
    summary = repeat_effect._summary_tool()
    kept = repeat_effect.cells(entry(), lambda p: p, summary)
    first = repeat_effect.cells(entry(), repeat_effect.first_run, summary)
    # kept: 0.02 at 0.5 s → 0.005 at 0.6 s, 0.01 at 0.5·1.2^0.5; rex the same to 0.8 s
    assert kept[0] == pytest.approx(0.5 * 1.2 ** 0.5)
    assert kept[1] == pytest.approx(4.0 / (0.5 * 1.2 ** 0.5))
    assert kept[2] == "best (rex, t(0.01))"
    assert first[0] == pytest.approx(0.5 * 1.8 ** (0.693147 / 1.203973), rel=1e-4)
    assert first[2].endswith("(rex, t(0.01))") and first[2] != "best (rex, t(0.01))"


def test_spread_of_the_repeats():
    run = {"scenes": {"s": entry()}}
    median, largest, off, n = repeat_effect.spread(run)
    assert n == 2
    assert largest == pytest.approx(0.35 / 0.6)  # (0.9 − 0.55) / 0.6
    assert median == pytest.approx((0.1 / 0.5 + 0.35 / 0.6) / 2)
    assert off == pytest.approx(0.5)  # the 2-spp point's first run is 50 % off
