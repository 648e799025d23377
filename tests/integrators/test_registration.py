"""`import mi_twopass` registers every plugin of the suite, for every JIT *_rgb variant."""
import mitsuba as mi
import pytest

import mi_twopass
from mi_twopass.integrators import PLUGINS

SCENE_WITH = """<scene version="3.0.0">
  <integrator type="{name}"/>
  <sensor type="perspective">
    <film type="hdrfilm"><integer name="width" value="4"/><integer name="height" value="4"/></film>
  </sensor>
  <shape type="rectangle"><bsdf type="diffuse"/></shape>
</scene>"""


def test_every_plugin_is_listed_and_registered():
    assert sorted(PLUGINS) == mi_twopass.registered_names()
    assert "radiosity_gather" in PLUGINS


@pytest.mark.parametrize("name", sorted(PLUGINS))
def test_load_file_and_load_dict(name, tmp_path):
    p = tmp_path / "s.xml"
    p.write_text(SCENE_WITH.format(name=name))
    scene = mi.load_file(str(p))
    assert isinstance(scene.integrator(), mi.SamplingIntegrator)
    assert type(scene.integrator()).__module__ == PLUGINS[name]
    assert isinstance(mi.load_dict({"type": name}), mi.SamplingIntegrator)


def test_no_placeholder_names():
    """Only integrators that exist are registered: every listed plugin implements its own
    prepass and estimator, and a name that is not listed is not found."""
    from mi_twopass.integrators.base import TwoPassIntegrator

    for name in PLUGINS:
        cls = type(mi.load_dict({"type": name}))
        assert cls.prepass is not TwoPassIntegrator.prepass, name
        assert cls.sample is not mi.SamplingIntegrator.sample, name
    with pytest.raises(RuntimeError, match="not found"):
        mi.load_dict({"type": "mi_twopass_placeholder"})


UNSUPPORTED = [v for v in ("scalar_rgb", "llvm_ad_mono", "scalar_spectral", "llvm_ad_spectral")
               if v in mi.variants()]


@pytest.mark.skipif(not UNSUPPORTED, reason="no unsupported variant in this Mitsuba build")
@pytest.mark.parametrize("variant", UNSUPPORTED)
def test_unsupported_variant_says_which_variants_work(variant):
    try:
        mi.set_variant(variant)
        for name in PLUGINS:
            with pytest.raises(RuntimeError, match=rf"UnsupportedVariantError: integrator "
                                                   rf"'{name}' \(mi_twopass\) does not run "
                                                   rf"under the variant '{variant}'") as e:
                mi.load_dict({"type": name})
            msg = str(e.value)
            assert "not found" not in msg
            assert f"integrator '{name}'" in msg and f"variant '{variant}'" in msg
            assert "llvm_ad_rgb" in msg and "UnsupportedVariantError" in msg
    finally:
        mi.set_variant("llvm_ad_rgb")
    assert isinstance(mi.load_dict({"type": "rex"}), mi.SamplingIntegrator)


def test_variant_switch_reregisters():
    mi.set_variant("scalar_rgb")
    assert mi_twopass.registered_names() == []  # not a JIT variant: nothing registered
    mi.set_variant("llvm_ad_rgb")
    assert mi_twopass.registered_names() == sorted(PLUGINS)
    for name in PLUGINS:
        integrator = mi.load_dict({"type": name})
        # the class was rebuilt for the active variant
        assert isinstance(integrator, mi.SamplingIntegrator)
