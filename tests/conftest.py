"""Shared fixtures. ``import mi_twopass`` first: it configures libLLVM and the variant."""
import os

import pytest

import mi_twopass  # noqa: F401

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = os.path.join(ROOT, "scenes_xml")


@pytest.fixture(autouse=True)
def _llvm_variant():
    """Every test starts on llvm_ad_rgb (a test may switch variants)."""
    import mitsuba as mi

    if mi.variant() != "llvm_ad_rgb":
        mi.set_variant("llvm_ad_rgb")
    yield


@pytest.fixture
def ref_cache(tmp_path, monkeypatch):
    """An empty reference cache per test."""
    d = tmp_path / "refs"
    monkeypatch.setenv("MI_TWOPASS_CACHE", str(d))
    return d


TINY_SCENE = """<scene version="3.0.0">
  <default name="spp" value="4"/>
  <default name="res" value="16"/>
  <integrator type="path"><integer name="max_depth" value="-1"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="60"/>
    <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
    <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="rectangle">
    <transform name="to_world"><scale value="2"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.5, 0.4"/></bsdf>
  </shape>
  <shape type="sphere">
    <point name="center" value="0, 1, 1.5"/><float name="radius" value="0.3"/>
    <emitter type="area"><rgb name="radiance" value="5"/></emitter>
  </shape>
</scene>
"""


@pytest.fixture
def tiny_scene_file(tmp_path):
    """A 16×16 plane under a spherical light, as an XML file."""
    p = tmp_path / "tiny.xml"
    p.write_text(TINY_SCENE)
    return str(p)
