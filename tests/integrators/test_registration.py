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
    """Integrators that do not exist yet are not registered."""
    for name in ("spike_gather", "rex", "radiance_cache"):
        if name not in PLUGINS:
            with pytest.raises(Exception):
                mi.load_dict({"type": name})


def test_variant_switch_reregisters():
    mi.set_variant("scalar_rgb")
    assert mi_twopass.registered_names() == []  # not a JIT variant: nothing registered
    mi.set_variant("llvm_ad_rgb")
    assert mi_twopass.registered_names() == sorted(PLUGINS)
    for name in PLUGINS:
        integrator = mi.load_dict({"type": name})
        # the class was rebuilt for the active variant
        assert isinstance(integrator, mi.SamplingIntegrator)
