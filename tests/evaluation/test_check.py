"""mi_twopass.evaluation.check (the ``check`` report) and scenefile.load_scene's film_res."""
import json
import os

import mitsuba as mi
import numpy as np
import pytest

from mi_twopass.evaluation import check, reference
from mi_twopass.scene.bounds import infinite_light_leaks
from mi_twopass.scenefile import SceneFileError, load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CORNELL = os.path.join(ROOT, "scenes_xml", "cornell_box.xml")


def test_block_means_average_partial_edge_blocks():
    img = np.arange(10 * 9, dtype=np.float64).reshape(10, 9, 1)
    b = check.block_means(img, block=8)
    assert b.shape == (2, 2, 1)
    assert b[0, 0, 0] == img[:8, :8].mean() and b[1, 1, 0] == img[8:, 8:].mean()
    assert b[0, 1, 0] == img[:8, 8:].mean()


def test_block_relmse_ignores_zero_mean_noise_inside_blocks():
    rng = np.random.default_rng(1)
    ref = np.full((16, 16, 3), 0.5)
    signs = np.tile(np.array([[1.0, -1.0], [-1.0, 1.0]]), (8, 8))[..., None]
    noisy = ref + 0.3 * signs * rng.random((1, 1, 3))  # cancels in every 8x8 block
    assert check.block_relmse(noisy, ref) == pytest.approx(0.0, abs=1e-20)
    biased = ref * 1.1
    assert check.block_relmse(biased, ref) == pytest.approx(0.05**2 / (0.25 + 0.01))
    with pytest.raises(ValueError, match="shape"):
        check.block_relmse(ref[:8], ref)


def test_mean_ratio_and_bounds():
    ref = np.full((4, 4, 3), 2.0)
    assert check.mean_ratio(ref * 0.98, ref) == pytest.approx(0.98)
    assert check.mean_ratio(np.zeros_like(ref), np.zeros_like(ref)) == 1.0
    assert check.mean_ratio(ref, np.zeros_like(ref)) == np.inf
    assert not check.is_out(1.005, 1e-3)
    assert check.is_out(1.02, 1e-3) and check.is_out(0.985, 1e-3) and check.is_out(1.0, 4e-3)
    assert check.is_out(float("nan"), 0.0) and check.is_out(1.0, float("nan"))


def test_a_refusing_integrator_is_a_row_not_a_crash(monkeypatch, ref_cache):
    from mi_twopass.integrators import radiosity_gather

    def refuse(self, scene, seed):
        raise ValueError("this scene has no diffuse surface")

    monkeypatch.setattr(radiosity_gather.RadiosityGatherIntegrator, "prepass", refuse)
    result = check.run_check(CORNELL, ["radiosity_gather", "path"], spp=2, film_res=8,
                             ref_spp=16)
    refused, path = result["rows"]
    assert refused.refused == "this scene has no diffuse surface" and refused.seconds is None
    assert path.refused is None and path.mean_ratio > 0
    table = check.format_table(result)
    assert "radiosity_gather                 refused: this scene has no diffuse surface" in table
    assert "8x8" in table


SCENE_WITH_MESH = """<scene version="3.0.0">
  <default name="w" value="40"/>
  <default name="spp" value="2"/>
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
    <film type="hdrfilm"><integer name="width" value="$w"/><integer name="height" value="20"/>
    </film>
  </sensor>
  <shape type="obj"><string name="filename" value="meshes/quad.obj"/>
    <emitter type="area"><rgb name="radiance" value="1"/></emitter></shape>
</scene>
"""

QUAD = "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nf 1 2 3\nf 1 3 4\n"


@pytest.fixture
def scene_with_mesh(tmp_path):
    folder = tmp_path / "scene"
    (folder / "meshes").mkdir(parents=True)
    (folder / "meshes" / "quad.obj").write_text(QUAD)
    (folder / "s.xml").write_text(SCENE_WITH_MESH)
    return str(folder / "s.xml")


def test_film_res_keeps_aspect_and_resolves_relative_paths(scene_with_mesh, tmp_path):
    resolver = mi.file_resolver()
    before = [str(resolver[i]) for i in range(len(resolver))]
    cwd = os.getcwd()
    os.chdir(tmp_path)  # the mesh must resolve from the scene's folder, not from here
    try:
        scene = load_scene(scene_with_mesh, film_res=10)
        assert list(scene.sensors()[0].film().crop_size()) == [10, 5]
        assert len(scene.shapes()) == 1
        scene = load_scene(scene_with_mesh, film_res=12, w=10)  # -D w=10: 10x20 → 6x12
        assert list(scene.sensors()[0].film().crop_size()) == [6, 12]
        scene = load_scene(scene_with_mesh, film_res=12, w=10, spp=3)
        assert scene.sensors()[0].sampler().sample_count() == 3
    finally:
        os.chdir(cwd)
    assert [str(resolver[i]) for i in range(len(resolver))] == before
    assert sorted(os.listdir(os.path.dirname(scene_with_mesh))) == ["meshes", "s.xml"]


def test_film_res_errors_name_the_file(scene_with_mesh, tmp_path):
    with pytest.raises(SceneFileError, match="unknown parameter.*foo=1"):
        load_scene(scene_with_mesh, film_res=8, foo=1)
    with pytest.raises(SceneFileError, match="film_res=0: must be >= 1"):
        load_scene(scene_with_mesh, film_res=0)
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene><sensor>")
    with pytest.raises(SceneFileError, match="bad.xml: malformed XML"):
        load_scene(str(bad), film_res=8)
    with pytest.raises(SceneFileError, match="bad.xml"):
        load_scene(str(bad))


def test_reference_key_includes_film_res(tiny_scene_file, ref_cache):
    k = reference.reference_key(tiny_scene_file, {}, 16)
    assert reference.reference_key(tiny_scene_file, {}, 16, film_res=None) == k
    assert reference.reference_key(tiny_scene_file, {}, 16, film_res=8) != k
    img = reference.reference_image(tiny_scene_file, {}, spp=4, film_res=6)
    assert img.shape == (6, 6, 3)
    assert reference.reference_image(tiny_scene_file, {}, spp=4, film_res=4).shape == (4, 4, 3)


SKY_ROOM = """<scene version="3.0.0">
  <sensor type="perspective">
    <float name="fov" value="70"/>
    <transform name="to_world"><lookat origin="0, 0.2, 0.9" target="0, -0.3, -1" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
  </sensor>
  <bsdf type="diffuse" id="wall"/>
  <emitter type="constant"/>
  <shape type="rectangle"><ref id="wall"/><transform name="to_world"><rotate x="1" angle="-90"/><translate y="-1"/></transform></shape>
  <shape type="rectangle"><ref id="wall"/><transform name="to_world"><rotate x="1" angle="90"/><translate y="1"/></transform></shape>
  <shape type="rectangle"><ref id="wall"/><transform name="to_world"><translate z="-1"/></transform></shape>
  <shape type="rectangle"><ref id="wall"/><transform name="to_world"><rotate y="1" angle="90"/><translate x="-1"/></transform></shape>
  <shape type="rectangle"><ref id="wall"/><transform name="to_world"><rotate y="1" angle="-90"/><translate x="1"/></transform></shape>
  <shape type="rectangle"><ref id="wall"/><transform name="to_world"><scale x="1" y="0.65"/><rotate y="1" angle="180"/><translate y="-0.35" z="1"/></transform></shape>
  <shape type="rectangle"><ref id="wall"/><transform name="to_world"><scale x="1" y="0.15"/><rotate y="1" angle="180"/><translate y="0.85" z="1"/></transform></shape>
  <shape type="sphere"><point name="center" x="0.3" y="-0.65" z="-0.2"/><float name="radius" value="0.35"/><ref id="wall"/></shape>
</scene>
"""


def test_a_sky_in_a_room_of_merged_walls_gets_an_unmerged_reference(tmp_path, ref_cache):
    """Mitsuba merges the room's rectangles into a mesh scene.bbox() leaves out, and its path
    lets the sky through the walls there (shadow rays end 2R from the shading point): the
    reference is rendered on the scene loaded with optimize=False, under its own key."""
    p = tmp_path / "sky_room.xml"
    p.write_text(SKY_ROOM)
    merged = load_scene(str(p))
    assert infinite_light_leaks(merged)
    img = reference.reference_image(str(p), {}, spp=64)
    unmerged = reference.render_path(load_scene(str(p), optimize=False), 64)
    leaky = reference.render_path(merged, 64)
    # not bit for bit: Mitsuba's parallel loading may order the shapes differently from one
    # load to the next (docs/design.md, "Vectorisation"), which changes the samples drawn
    assert leaky.mean() > 1.2 * unmerged.mean()  # the leak the reference avoids
    assert abs(img.mean() - unmerged.mean()) < 0.2 * (leaky.mean() - unmerged.mean())
    meta = [json.loads(f.read_text()) for f in ref_cache.glob("*.json")]
    assert [m["unmerged"] for m in meta] == [True]


def test_out_rows_say_noise_limited_where_path_itself_is_out():
    path = check.CheckRow("path", mean_ratio=0.985, block_relmse=6e-3, out=True)
    biased = check.CheckRow("spike_gather", mean_ratio=0.984, block_relmse=3.4e-3, out=True)
    fine = check.CheckRow("radiosity_gather", mean_ratio=1.0, block_relmse=1e-4, out=False)
    refused = check.CheckRow("rex", refused="no media")
    rows = [path, biased, fine, refused]
    check.mark_noise_limited(rows)
    assert biased.noise_limited and not fine.noise_limited and not path.noise_limited
    assert not refused.noise_limited
    for r in (path, biased, fine):
        r.seconds = 1.0
    assert check.format_row(biased).endswith("OUT (path is OUT too: noise-limited at this spp)")
    assert check.format_row(path).endswith("  OUT")
    # path in bounds: an OUT row is just OUT
    path.out = False
    check.mark_noise_limited(rows)
    assert not biased.noise_limited and check.format_row(biased).endswith("  OUT")
    # no path row: nothing is marked
    check.mark_noise_limited([biased])
    assert not biased.noise_limited


def test_path_out_names_the_spp_at_which_a_bias_could_be_told_from_noise():
    # path's row on caustic.xml at 128 px, 64 spp against 1024 spp (session 11's check)
    path = check.CheckRow("path", seconds=0.1, mean_ratio=1.005, block_relmse=7.62e-3, out=True)
    rows = [path, check.CheckRow("rex", seconds=1.0, mean_ratio=1.004, block_relmse=1e-3)]
    more = check.spp_to_see_bias(rows, 64, 1024)
    assert more > 64 and more & (more - 1) == 0
    # path's noise c (1/s + 1/r) predicted at that spp with its reference 16x as long: at
    # most a quarter of the bound there, more than that at half the spp
    c = 7.62e-3 / (1 / 64 + 1 / 1024)

    def predicted(s):
        return c * (1 / s + 1 / (check.REF_SPP_FACTOR * s))

    assert predicted(more) <= check.NOISE_SHARE * check.BLOCK_RELMSE_MAX < predicted(more / 2)
    result = {"meta": {"scene": "s.xml", "params": {}, "width": 128, "height": 128, "spp": 64,
                       "ref_spp": 1024, "ratio_tolerance": check.RATIO_TOLERANCE,
                       "block_relmse_max": check.BLOCK_RELMSE_MAX, "block": check.BLOCK},
              "rows": rows}
    assert f"--spp {more} --ref-spp {16 * more}" in check.format_table(result)
    # a mean ratio far off asks for more samples than the block relMSE alone
    path.mean_ratio = 1.02
    assert check.spp_to_see_bias(rows, 64, 1024) > more
    # path in bounds, or no path row: nothing to ask for
    path.out = False
    assert check.spp_to_see_bias(rows, 64, 1024) is None
    assert "rerun" not in check.format_table(result)
    assert check.spp_to_see_bias(rows[1:], 64, 1024) is None


def test_block_bias2_keeps_the_bias_and_drops_the_renders_noise():
    rng = np.random.default_rng(1)
    ref = np.full((256, 256, 3), 0.5)
    ref[:128] = 2.0  # two regions, a bias in one of them

    def render(bias):
        noise = rng.normal(0.0, 0.3, ref.shape) * ref  # per pixel relative noise
        return ref * (1.0 + bias) + noise

    biased = np.zeros(ref.shape[:2] + (1,))
    biased[:128] = 0.05  # +5 % where the light is
    a, b = render(biased), render(biased)
    est, se = check.block_bias2(a, b, ref)
    # what the bias alone contributes: half of the blocks have (0.05 r)² / (r² + eps)
    want = 0.5 * np.mean(0.05**2 * 4.0 / (4.0 + check.RELMSE_EPS))
    assert abs(est - want) < 3 * se and se < 0.3 * want
    # one render's block relMSE holds its noise too: (0.3 r)² / 64 per block, above it
    assert check.block_relmse(a, ref) > 2 * want
    est0, se0 = check.block_bias2(render(0.0), render(0.0), ref)
    assert abs(est0) < 3 * se0
    with pytest.raises(ValueError, match="shapes differ"):
        check.block_bias2(a, b[:32], ref)
    # the mean ratio's standard error: the noise of the mean of two renders' image means
    sigma = np.sqrt(np.mean((0.3 * ref) ** 2))  # per pixel and channel, all independent
    want_se = sigma / np.sqrt(2 * ref.size) / ref.mean()
    assert check.ratio_se(render(0.0), render(0.0), ref) == pytest.approx(want_se, rel=0.15)


def test_two_renders_per_row_find_a_bias_that_noise_would_hide(ref_cache):
    """path:max_depth=2 leaves out the light of longer paths: its bias part stands out of its
    noise; path's own is the reference's noise, near 0."""
    result = check.run_check(CORNELL, ["path", "path:max_depth=2"], spp=16, film_res=32,
                             ref_spp=1024, renders=2)
    path, short = result["rows"]
    assert path.bias2 is not None and short.bias2 is not None
    assert abs(path.bias2) < 3 * path.bias2_se + 1e-4 and path.bias2 < path.block_relmse
    assert short.bias2 > 3 * short.bias2_se and short.bias2 > check.BLOCK_RELMSE_MAX
    assert short.out and path.bias2 < check.BLOCK_RELMSE_MAX
    table = check.format_table(result)
    assert "bias part" in table and "two renders per row" in table and "OUT" in table
    assert result["meta"]["renders"] == 2
    with pytest.raises(ValueError, match="renders=3"):
        check.check_integrator(None, "path", None, 1, renders=3)
    # a row of two renders is judged by its own standard errors, whatever path's row says
    assert short.ratio_se > 0 and path.ratio_se > 0
    path.out = True
    check.mark_noise_limited([path, short])
    assert not short.noise_limited and not check.within_noise(short)
    assert check.within_noise(path) and path.noise_limited
    assert check.format_row(path).endswith("noise-limited at this spp)")


def test_the_second_render_keeps_the_prepass_so_its_noise_counts_as_bias(monkeypatch,
                                                                          ref_cache):
    """A prepass's own noise is an error no number of samples removes from a user's image:
    the second render reads the first one's prepass (built once), with other samples."""
    from mi_twopass.integrators import radiosity_gather

    built, sampler_seeds = [], []
    cls = radiosity_gather.RadiosityGatherIntegrator
    prepass, sample = cls.prepass, cls.sample

    def counted(self, scene, seed):
        built.append(seed)
        return prepass(self, scene, seed)

    def seen(self, scene, sampler, *args, **kwargs):
        sampler_seeds.append(self.sample_seed_offset)
        return sample(self, scene, sampler, *args, **kwargs)

    monkeypatch.setattr(cls, "prepass", counted)
    monkeypatch.setattr(cls, "sample", seen)
    spec = "radiosity_gather:max_patches=16:particles_per_patch=64"
    result = check.run_check(CORNELL, [spec], spp=4, film_res=16, ref_spp=64, renders=2)
    row = result["rows"][0]
    assert len(built) == 1 and row.bias2 is not None
    assert sampler_seeds == [0, check.SECOND_RENDER_STRIDE]
