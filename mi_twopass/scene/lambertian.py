"""Which surfaces a cache may stand for: Lambertian reflection, one rule for every integrator.

A radiosity patch (radiosity_gather, spike_gather), an SH cache point (radiance_cache) and a rex
bucket (rex) all replace the light a surface reflects by ρ(x)·E(x)/π: the outgoing radiance of
a Lambertian reflector lit by irradiance E *in its shading frame*. That holds for ``diffuse``
and for ``twosided`` / ``blendbsdf`` made only of diffuse BSDFs, and for nothing else:

* a glossy, delta, transmissive or null lobe (plastic, principled, conductors, dielectrics,
  mask, a blend with a conductor) makes the radiance view-dependent or lets light through;
* ``bumpmap`` and ``normalmap`` around a diffuse BSDF have exactly a diffuse BSDF's flags, but
  shade in a tilted frame: the light they reflect depends on the texel's normal, and their
  reflectance seen by light tracing (the radiosity and photon passes) is not what ``path``
  transports (shading normals are not reciprocal). Cached, they were 10 % too bright.

Given only flags (a Python int or per-lane ``mi.UInt32``), :func:`lambertian_flags` is the
flag test alone: necessary, not sufficient. Per lane, :class:`LambertianShapes` answers for the
shape that was hit from a table built with :func:`is_lambertian` per shape.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

#: lobes that no cache represents
_NOT_LAMBERTIAN = int(mi.BSDFFlags.Glossy | mi.BSDFFlags.Delta | mi.BSDFFlags.DiffuseTransmission
                      | mi.BSDFFlags.Null)
_DIFFUSE_REFLECTION = int(mi.BSDFFlags.DiffuseReflection)

#: plugins (C++ class names) that are Lambertian given Lambertian children: 0 = a leaf, 2 = a
#: combination of its children. Plugins not named here (bumpmap, normalmap, plugins we do not
#: know) are not Lambertian.
_LAMBERTIAN_PLUGINS = {"SmoothDiffuse": 0, "TwoSidedBRDF": 2, "BlendBSDF": 2}


def lambertian_flags(flags):
    """The flag test: a diffuse-reflection lobe and no glossy, delta, transmission or null lobe.
    ``flags``: a Python int (returns bool) or per-lane flags (returns ``mi.Bool``)."""
    if isinstance(flags, (int, np.integer, mi.BSDFFlags)):
        flags = int(flags)
        return bool(flags & _DIFFUSE_REFLECTION) and not flags & _NOT_LAMBERTIAN
    flags = mi.UInt32(flags)
    return ((flags & _DIFFUSE_REFLECTION) != 0) & ((flags & _NOT_LAMBERTIAN) == 0)


class _BSDFChildren(mi.TraversalCallback):
    """Collects the BSDFs a BSDF holds (``twosided``'s two sides, ``blendbsdf``'s pair)."""

    def __init__(self):
        super().__init__()
        self.children = []

    def put(self, name, value, flags, cpptype=None):
        if isinstance(value, mi.BSDF):
            self.children.append(value)


def _plugin_is_lambertian(bsdf) -> bool:
    kind = _LAMBERTIAN_PLUGINS.get(bsdf.class_name())
    if kind is None:
        return False
    if kind == 0:
        return True
    cb = _BSDFChildren()
    bsdf.traverse(cb)
    return len(cb.children) > 0 and all(_plugin_is_lambertian(c) for c in cb.children)


def is_lambertian(bsdf) -> bool:
    """Whether a BSDF (object) is Lambertian reflection, one- or two-sided: its flags pass
    :func:`lambertian_flags` and it is ``diffuse`` or a ``twosided`` / ``blendbsdf`` of such.
    Given flags (an int), the flag test alone. ``None`` (no BSDF) is not Lambertian."""
    if bsdf is None:
        return False
    if isinstance(bsdf, (int, np.integer, mi.BSDFFlags)):
        return lambertian_flags(bsdf)
    return lambertian_flags(int(bsdf.flags())) and _plugin_is_lambertian(bsdf)


def shape_registry_ids(scene) -> np.ndarray:
    """Per shape of ``scene.shapes()``: the id that ``dr.reinterpret_array(mi.UInt32, si.shape)``
    gives at a hit on it."""
    if not len(scene.shapes()):
        return np.zeros(0, np.int64)
    return np.asarray(dr.reinterpret_array(mi.UInt32, scene.shapes_dr()), dtype=np.int64)


class LambertianShapes:
    """Per-lane answer of :func:`is_lambertian` for the shape a ray hit: a table indexed by the
    shape's registry id, with one sentinel entry (False) for every id it does not list (shapes
    inside instanced shape groups, which the caches do not model)."""

    def __init__(self, scene):
        ids = shape_registry_ids(scene)
        self.n_ids = int(ids.max()) + 1 if ids.size else 1
        table = np.zeros(self.n_ids + 1, bool)
        table[ids] = [is_lambertian(s.bsdf()) for s in scene.shapes()]
        self.per_shape = table[ids]
        self.d_table = mi.Bool(table)

    @property
    def nbytes(self) -> int:
        return int(self.n_ids + 1)

    def at(self, si, active=True):
        """``mi.Bool`` per lane: the hit is valid and its shape is Lambertian."""
        ok = mi.Bool(active) & si.is_valid()
        sid = dr.minimum(dr.reinterpret_array(mi.UInt32, si.shape), self.n_ids)
        return ok & dr.gather(mi.Bool, self.d_table, sid, ok)
