"""How a prepass structure holds its Dr.Jit lookup tables: one :class:`Tables`, read by name.

Every structure that the render queries (patches, spike grid and sources, near-field BVH,
radiance cache) keeps the Dr.Jit copies of its arrays in a :class:`Tables` built once, when
the structure is built (or on its first query, for structures that may never be rendered),
outside any symbolic loop.
"""
from __future__ import annotations


class Tables:
    """Named Dr.Jit tables of a structure (arrays, opaque scalars, Python constants), read with
    ``tables["name"]``.

    Deliberately not a dict (nor a dataclass): Dr.Jit traverses those as PyTrees, so a
    structure referenced inside a symbolic loop would turn every table into loop state (and one
    reachable twice, e.g. ``grid.sources`` and ``sources``, into two aliased states). A
    ``Tables`` is opaque to Dr.Jit: its arrays are only ever read by gathers."""

    def __init__(self, **tables):
        self._d = dict(tables)

    def __getitem__(self, name):
        return self._d[name]

    def __contains__(self, name) -> bool:
        return name in self._d

    def values(self):
        """The tables (e.g. for ``dr.eval(*tables.values())`` or a byte count)."""
        return self._d.values()

    def replace(self, name, value) -> None:
        """Swap the existing table ``name`` for ``value``: for a structure whose data change
        after it is built (:meth:`mi_twopass.scene.patches.Patches.uncache`). Only names given
        at construction (``KeyError`` otherwise), so that no table is added lazily, perhaps
        first inside a symbolic loop."""
        if name not in self._d:
            raise KeyError(name)
        self._d[name] = value

    def __repr__(self) -> str:
        return f"Tables({', '.join(self._d)})"
