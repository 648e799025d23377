"""mi_twopass.tables: the one holder of a structure's Dr.Jit tables."""
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import pytest

from mi_twopass.tables import Tables


@dataclass
class _Holder:
    """A prepass structure as the package writes them: a dataclass holding its tables."""
    tables: object


def test_tables_returns_what_it_was_given():
    a, b = mi.Float([1.0, 2.0, 3.0]), mi.UInt32([4, 5])
    t = Tables(a=a, b=b, n=3)
    assert t["a"] is a and t["b"] is b and t["n"] == 3
    assert "a" in t and "c" not in t
    assert list(t.values()) == [a, b, 3]
    with pytest.raises(KeyError):
        t["c"]


def test_replace_swaps_an_existing_table_only():
    t = Tables(a=mi.Float([1.0]))
    c = mi.Float([2.0])
    t.replace("a", c)
    assert t["a"] is c
    with pytest.raises(KeyError):
        t.replace("b", c)  # no table is added after construction


def test_tables_are_not_traversed_by_drjit():
    # What a symbolic loop collects as state from a structure it closes over: a dict (or a
    # dataclass) of tables would list every array; a Tables lists none.
    a = mi.Float([1.0, 2.0, 3.0])
    assert dr.detail.collect_indices(_Holder({"a": a}))  # the control: a dict is traversed
    assert dr.detail.collect_indices(_Holder(Tables(a=a))) == []
    assert dr.detail.collect_indices(Tables(a=a)) == []
    assert not dr.is_struct_v(Tables)


@dr.syntax
def _sum_table(holder, n):
    i, total = mi.UInt32(0), mi.Float(0.0)
    while i < n:
        total += dr.gather(mi.Float, holder.tables["a"], i)
        i += 1
    return total


def test_a_symbolic_loop_reads_a_held_table():
    h = _Holder(Tables(a=mi.Float([1.0, 2.0, 3.0])))
    assert dr.allclose(_sum_table(h, mi.UInt32([1, 3])), [1.0, 6.0])


def test_spike_grid_reexports_tables():
    from mi_twopass.prepass import spike_grid

    assert spike_grid.Tables is Tables
