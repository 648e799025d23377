"""The suite's integrator plugins and their registration.

Each plugin module subclasses a Mitsuba class (``mi.SamplingIntegrator``), and Mitsuba's Python
classes belong to one variant. So a plugin module is (re)imported while its variant is active and
ends, as Mitsuba's own integrators do, with ``mi.register_integrator(name, ...)``. When the
variant changes, :func:`register_for_variant` re-imports the modules for the new variant.

Only JIT ``*_rgb`` variants (``llvm_ad_rgb``, ``cuda_ad_rgb``) are supported: the integrators are
wavefront code and use RGB albedo. Under any other variant (``scalar_rgb``, ``llvm_ad_mono``,
the spectral ones) every plugin name is registered as a stub whose constructor raises
:class:`UnsupportedVariantError` naming the supported variants, so that loading
``{'type': 'rex'}`` there says why instead of Mitsuba's "Plugin not found".
"""
import importlib
import sys

#: plugin name -> module. Only integrators that exist are listed (no placeholders).
PLUGINS = {
    "radiosity_gather": "mi_twopass.integrators.radiosity_gather",
    "radiance_cache": "mi_twopass.integrators.radiance_cache",
    "rex": "mi_twopass.integrators.rex",
    "spike_gather": "mi_twopass.integrators.spike_gather",
    "twopass": "mi_twopass.integrators.twopass",
}

#: modules holding variant-bound classes, imported before the plugins, in this order.
_SHARED_MODULES = ("mi_twopass.integrators.base", "mi_twopass.integrators.component_path")

_registered = {}
#: variants under which the stubs are registered
_stubbed = set()


class UnsupportedVariantError(NotImplementedError):
    """A mi_twopass integrator was loaded under a variant it does not run on."""


def supports_variant(variant) -> bool:
    """True for the JIT RGB variants the suite runs on."""
    return bool(variant) and variant.endswith("_rgb") and not variant.startswith("scalar")


def supported_variants() -> list:
    """The variants of the installed Mitsuba the suite runs on (``llvm_ad_rgb``,
    ``cuda_ad_rgb``)."""
    import mitsuba as mi

    return [v for v in mi.variants() if supports_variant(v)]


def unsupported_message(name, variant) -> str:
    """Why plugin ``name`` cannot be loaded under ``variant``, and what to do instead."""
    supported = ", ".join(supported_variants()) or "llvm_ad_rgb, cuda_ad_rgb"
    return (f"integrator '{name}' (mi_twopass) does not run under the variant '{variant}': "
            f"it needs a JIT RGB variant ({supported}); call mi.set_variant('llvm_ad_rgb') "
            "before loading the scene")


def _register_stubs(variant) -> None:
    """Register every plugin name under the unsupported ``variant`` as a constructor that
    raises :class:`UnsupportedVariantError` (once per variant)."""
    import mitsuba as mi

    if variant in _stubbed or not hasattr(mi, "register_integrator"):
        return

    def stub(name):
        def construct(props):
            raise UnsupportedVariantError(unsupported_message(name, variant))
        return construct

    for name in PLUGINS:
        mi.register_integrator(name, stub(name))
    _stubbed.add(variant)


def register_for_variant(variant) -> list:
    """Import (or re-import) every plugin module under ``variant`` so it registers itself;
    under a variant the suite does not support, register the stubs instead (returns [])."""
    if not variant:
        return []
    if not supports_variant(variant):
        _register_stubs(variant)
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
