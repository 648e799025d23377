"""The suite's integrator plugins and their registration.

Each plugin module subclasses a Mitsuba class (``mi.SamplingIntegrator``), and Mitsuba's Python
classes belong to one variant. So a plugin module is (re)imported while its variant is active and
ends, as Mitsuba's own integrators do, with ``mi.register_integrator(name, ...)``. When the
variant changes, :func:`register_for_variant` re-imports the modules for the new variant.

Only JIT ``*_rgb`` variants (``llvm_ad_rgb``, ``cuda_ad_rgb``) are supported: the integrators are
wavefront code and use RGB albedo. Under any other variant the plugins are simply not registered.
"""
import importlib
import sys

#: plugin name -> module. Only integrators that exist are listed (no placeholders).
PLUGINS = {
    "radiosity_gather": "mi_twopass.integrators.radiosity_gather",
    "radiance_cache": "mi_twopass.integrators.radiance_cache",
    "rex": "mi_twopass.integrators.rex",
    "spike_gather": "mi_twopass.integrators.spike_gather",
}

#: modules holding variant-bound classes, imported before the plugins, in this order.
_SHARED_MODULES = ("mi_twopass.integrators.base",)

_registered = {}


def supports_variant(variant) -> bool:
    """True for the JIT RGB variants the suite runs on."""
    return bool(variant) and variant.endswith("_rgb") and not variant.startswith("scalar")


def register_for_variant(variant) -> list:
    """Import (or re-import) every plugin module under ``variant`` so it registers itself."""
    if not supports_variant(variant):
        return []
    for name in (*_SHARED_MODULES, *PLUGINS.values()):
        module = sys.modules.get(name)
        if module is None:
            module = importlib.import_module(name)
        elif getattr(module, "_BOUND_VARIANT", None) != variant:
            module = importlib.reload(module)
        module._BOUND_VARIANT = variant
    _registered[variant] = sorted(PLUGINS)
    return _registered[variant]


def registered_names(variant=None) -> list:
    """Plugin names registered for ``variant`` (default: the active one)."""
    import mitsuba as mi

    return list(_registered.get(variant or mi.variant(), []))
