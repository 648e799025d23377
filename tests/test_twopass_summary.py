"""tools/twopass_summary.py: issue 14's figure, twopass against the best single integrator, read
by t(0.01) where both reach relMSE 0.01 and by equal-time ratios otherwise."""
import importlib.util
import os

_PATH = os.path.join(os.path.dirname(__file__), "..", "tools", "twopass_summary.py")
_spec = importlib.util.spec_from_file_location("twopass_summary", _PATH)
twopass_summary = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(twopass_summary)
versus_best = twopass_summary.versus_best


def row(name, t=None, et=None):
    return {"integrator": name, "time_to_target": t, "equal_time_ratio": et}


def test_by_time_to_target_against_the_fastest_that_reaches_it():
    cands = [row("rex", 0.32, 1.1), row("radiosity_gather", 1.5, 1.9), row("spike_gather", None, 9)]
    assert versus_best(cands, row("twopass", 0.46, 1.3)) == "1.44 (rex, t(0.01))"
    assert versus_best(cands, row("twopass", 0.30, 1.3)) == "best (rex, t(0.01))"


def test_by_equal_time_where_twopass_or_no_single_integrator_reaches_it():
    cands = [row("rex", None, 5.19), row("radiance_cache", None, 0.94)]
    assert versus_best(cands, row("twopass", None, 3.43)) == "1.51 (rex, equal-time)"
    reached = [row("rex", 0.3, 5.19)]
    assert versus_best(reached, row("twopass", None, 6.0)) == "best (rex, equal-time)"
    assert versus_best(cands, None) == "—"
    assert versus_best([], row("twopass", None, 3.0)) == "—"
