"""The command line (mi_twopass/cli.py), run in-process on a tiny scene."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from mi_twopass import cli
from mi_twopass.evaluation import images, reference


def test_render_writes_exr_png_and_error(tiny_scene_file, tmp_path, ref_cache, capsys):
    out = str(tmp_path / "o" / "img.exr")
    code = cli.main(["render", tiny_scene_file, "-o", out, "-D", "res=12", "--spp", "8",
                     "--reference", "--ref-spp", "64"])
    assert code == 0
    img = images.read_exr(out)
    assert img.shape == (12, 12, 3) and np.all(np.isfinite(img)) and img.mean() > 0
    assert os.path.getsize(str(tmp_path / "o" / "img.png")) > 0
    text = capsys.readouterr().out
    assert "8 spp" in text and "relMSE" in text


def test_render_in_passes_matches_spp(tiny_scene_file, tmp_path, monkeypatch):
    """A render split into passes averages to the requested spp; a seed per pass."""
    monkeypatch.setattr(cli, "LANES_PER_PASS", 8 * 8 * 2)
    res = cli.render_command(tiny_scene_file, str(tmp_path / "a.exr"), "path:max_depth=2",
                             spp=6, defines=["res=8"], out=lambda *_: None)
    assert res["image"].shape == (8, 8, 3) and res["passes"] == 3
    assert res["prepass_builds"] == 0  # path has no prepass
    one = cli.render_command(tiny_scene_file, str(tmp_path / "b.exr"), "path:max_depth=2",
                             spp=2, defines=["res=8"], out=lambda *_: None)
    assert not np.array_equal(res["image"], one["image"])  # the passes were not all seed 0


def test_passes_share_one_prepass_and_do_not_add_up_its_structure(tiny_scene_file, tmp_path,
                                                                  monkeypatch):
    spec = "radiosity_gather:max_patches=32:particles_per_patch=16:elements_per_patch=4"
    single = cli.render_command(tiny_scene_file, str(tmp_path / "s.exr"), spec, spp=6,
                                defines=["res=8"], out=lambda *_: None)
    assert single["passes"] == 1
    monkeypatch.setattr(cli, "LANES_PER_PASS", 8 * 8 * 2)
    lines = []
    res = cli.render_command(tiny_scene_file, str(tmp_path / "m.exr"), spec, spp=6,
                             defines=["res=8"], out=lines.append)
    assert res["passes"] == 3 and res["prepass_builds"] == 1
    st = res["stats"]
    for key in ("patches", "elements", "prepass_rays", "cache_bytes"):
        assert st[key] == single["stats"][key] > 0, key
    assert st["viewing_rays"] == 8 * 8 * 6 == single["stats"]["viewing_rays"]
    assert st["prepass_seconds"] == st["prepass_seconds_last_built"] > 0
    assert "in 3 passes" in lines[0]
    # the passes differ in their samplers: the average is not one pass's image
    assert np.abs(res["image"] - single["image"]).max() > 0


def _run_cli(argv, capsys):
    code = cli.main(argv)
    captured = capsys.readouterr()
    return code, captured.err


@pytest.mark.parametrize("case", ["malformed", "integrator", "unknown_param", "ill_typed",
                                  "under_file", "negative_spp", "png_output", "bad_int_param"])
def test_mistakes_are_one_error_line(case, tiny_scene_file, tmp_path, capsys):
    bad = tmp_path / "bad.xml"
    bad.write_text('<scene version="3.0.0"><shape type="sphere"></scene>')
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    out = str(tmp_path / "o.exr")
    argv = {
        "malformed": ["render", str(bad), "-o", out],
        "integrator": ["render", tiny_scene_file, "-o", out, "--integrator", "nope"],
        "unknown_param": ["render", tiny_scene_file, "-o", out, "-D", "foo=3"],
        "ill_typed": ["render", tiny_scene_file, "-o", out, "-D", "res=abc"],
        "under_file": ["render", tiny_scene_file, "-o", str(blocker / "o.exr"), "-D", "res=4"],
        "negative_spp": ["render", tiny_scene_file, "-o", out, "--spp", "-1", "-D", "res=4"],
        "png_output": ["render", tiny_scene_file, "-o", str(tmp_path / "x.png"), "-D", "res=4"],
        "bad_int_param": ["render", tiny_scene_file, "-o", out, "--integrator",
                          "radiosity_gather:max_depth=2.5", "-D", "res=4"],
    }[case]
    expected = {
        "malformed": "bad.xml", "integrator": "no integrator named 'nope'",
        "unknown_param": "unknown parameter(s) foo=3", "ill_typed": 'integer value "abc"',
        "under_file": "is a file, not a folder", "negative_spp": "--spp -1: must be >= 1",
        "png_output": "must be an .exr file", "bad_int_param": "max_depth=2.5: expected an integer",
    }[case]
    code, err = _run_cli(argv, capsys)
    assert code == 2
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert expected in err and "Traceback" not in err
    assert not os.path.exists(out) and not (tmp_path / "x.png").exists()


def test_an_integrator_refusing_the_scene_is_one_error_line(tiny_scene_file, tmp_path, capsys,
                                                             monkeypatch):
    from mi_twopass.integrators import radiosity_gather

    def refuse(self, scene, seed):
        raise ValueError("no diffuse surface to put patches on")

    monkeypatch.setattr(radiosity_gather.RadiosityGatherIntegrator, "prepass", refuse)
    code, err = _run_cli(["render", tiny_scene_file, "-o", str(tmp_path / "o.exr"), "-D",
                          "res=4", "--integrator", "radiosity_gather"], capsys)
    assert code == 2 and err.count("\n") == 1
    assert err.startswith("error: radiosity_gather refused ") and "no diffuse surface" in err
    assert not (tmp_path / "o.exr").exists()


def test_mistake_in_a_subprocess_has_no_traceback(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version=")
    r = subprocess.run([sys.executable, "-m", "mi_twopass", "render", str(bad), "-o",
                        str(tmp_path / "o.exr")], capture_output=True, text=True,
                       cwd=os.path.dirname(os.path.dirname(__file__)),
                       env={**os.environ, "MI_TWOPASS_QUIET": "1"})
    assert r.returncode == 2
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr


def test_missing_scene_is_a_clear_error(tmp_path, capsys):
    out = tmp_path / "x.exr"
    code = cli.main(["render", str(tmp_path / "nope.xml"), "-o", str(out)])
    assert code == 2
    assert "scene file not found" in capsys.readouterr().err
    assert not out.exists()


def test_compare_prints_table_and_writes_plot(tiny_scene_file, tmp_path, ref_cache, capsys):
    outdir = tmp_path / "cmp"
    code = cli.main(["compare", tiny_scene_file, "--integrators", "path,path:max_depth=2",
                     "--budget", "1.5", "-D", "res=8", "--ref-spp", "256", "-o", str(outdir),
                     "--repeats", "2"])
    assert code == 0
    text = capsys.readouterr().out
    assert "equal-time ratio" in text and "path:max_depth=2" in text
    data = json.loads((outdir / "tiny.json").read_text())
    pts = data["curves"]["path"]["points"]
    assert len(pts) >= 2 and [p["spp"] for p in pts][:2] == [1, 2]
    assert all(p["relmse"] > 0 and p["seconds"] > 0 for p in pts)
    assert all(len(p["stats"]["repeat_seconds"]) == 2 for p in pts)  # --repeats 2, all short
    assert (outdir / "tiny.png").stat().st_size > 1000


def test_reference_is_cached(tiny_scene_file, ref_cache):
    a = reference.reference_image(tiny_scene_file, {"res": 8}, spp=32)
    files = sorted(os.listdir(ref_cache))
    assert any(f.endswith(".exr") for f in files) and any(f.endswith(".json") for f in files)
    b = reference.reference_image(tiny_scene_file, {"res": 8}, spp=32)
    assert np.array_equal(a, b)
    c = reference.reference_image(tiny_scene_file, {"res": 8}, spp=64)  # other settings: new key
    assert len(os.listdir(ref_cache)) == len(files) + 2
    assert c.shape == a.shape


def test_module_entry_point_help():
    r = subprocess.run([sys.executable, "-m", "mi_twopass", "--help"], capture_output=True,
                       text=True, cwd=os.path.dirname(os.path.dirname(__file__)))
    assert r.returncode == 0 and "render" in r.stdout and "compare" in r.stdout


SCENES = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scenes_xml")
SHARED = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "..",
                      "shared", "scenes")


def test_check_prints_a_table_and_json(tmp_path, ref_cache, capsys):
    js = tmp_path / "r" / "check.json"
    code = cli.main(["check", os.path.join(SCENES, "cornell_box.xml"), "--res", "12", "--spp",
                     "4", "--ref-spp", "32", "--integrators",
                     "path,radiosity_gather:max_patches=32:particles_per_patch=16",
                     "--json", str(js)])
    assert code == 0
    text = capsys.readouterr().out
    assert "mean ratio" in text and "block relMSE" in text and "12x12" in text
    data = json.loads(js.read_text())
    assert [r["integrator"] for r in data["rows"]] == [
        "path", "radiosity_gather:max_patches=32:particles_per_patch=16"]
    for row in data["rows"]:
        assert row["refused"] is None and row["seconds"] > 0
        assert 0.5 < row["mean_ratio"] < 1.5 and row["block_relmse"] >= 0
        assert row["out"] == (abs(row["mean_ratio"] - 1) > 0.01 or row["block_relmse"] > 3e-3)
        assert (" OUT" in [ln for ln in text.splitlines()
                           if ln.startswith(row["integrator"] + " ")][0]) == row["out"]
    assert data["meta"]["width"] == data["meta"]["height"] == 12


def test_check_with_two_renders_prints_the_bias_part_and_writes_it(tmp_path, ref_cache, capsys):
    js = tmp_path / "check2.json"
    code = cli.main(["check", os.path.join(SCENES, "cornell_box.xml"), "--res", "16", "--spp",
                     "4", "--ref-spp", "32", "--renders", "2", "--integrators", "path",
                     "--json", str(js)])
    assert code == 0
    text = capsys.readouterr().out
    assert "bias part" in text and "two renders per row" in text
    row = json.loads(js.read_text())["rows"][0]
    assert row["bias2"] is not None and row["bias2_se"] > 0 and row["ratio_se"] > 0
    assert json.loads(js.read_text())["meta"]["renders"] == 2
    with pytest.raises(SystemExit):  # only 1 or 2
        cli.main(["check", os.path.join(SCENES, "cornell_box.xml"), "--renders", "3"])


@pytest.mark.skipif(not os.path.isfile(os.path.join(SHARED, "veach-bidir", "scene.xml")),
                    reason="the shared scenes are not here")
def test_check_on_a_scene_without_res(tmp_path, ref_cache, capsys):
    """veach-bidir has no $res (1024² by $resx/$resy): --res 32 scales the film, its meshes
    resolve from the scene's own folder, and the scene folder is left untouched."""
    scene = os.path.join(SHARED, "veach-bidir", "scene.xml")
    before = sorted(os.listdir(os.path.dirname(scene)))
    code = cli.main(["check", scene, "--res", "32", "--spp", "4", "--ref-spp", "64",
                     "--integrators", "radiosity_gather,spike_gather",
                     "--json", str(tmp_path / "v.json")])
    assert code == 0
    data = json.loads((tmp_path / "v.json").read_text())
    assert (data["meta"]["width"], data["meta"]["height"]) == (32, 32)
    assert [r["integrator"] for r in data["rows"]] == ["radiosity_gather", "spike_gather"]
    for row in data["rows"]:
        assert row["refused"] or (row["mean_ratio"] > 0 and row["seconds"] > 0)
    assert sorted(os.listdir(os.path.dirname(scene))) == before
