"""The command line (mi_twopass/cli.py), run in-process on a tiny scene."""
import json
import os
import subprocess
import sys

import numpy as np

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
    """A render split into passes (progress per pass) still averages to the requested spp."""
    res = cli.render_command(tiny_scene_file, str(tmp_path / "a.exr"), "path:max_depth=2",
                             spp=6, defines=["res=8"], out=lambda *_: None)
    assert res["image"].shape == (8, 8, 3)
    assert res["stats"] == {} or isinstance(res["stats"], dict)


def test_missing_scene_is_a_clear_error(tmp_path, capsys):
    out = tmp_path / "x.exr"
    code = cli.main(["render", str(tmp_path / "nope.xml"), "-o", str(out)])
    assert code == 2
    assert "scene file not found" in capsys.readouterr().err
    assert not out.exists()


def test_compare_prints_table_and_writes_plot(tiny_scene_file, tmp_path, ref_cache, capsys):
    outdir = tmp_path / "cmp"
    code = cli.main(["compare", tiny_scene_file, "--integrators", "path,path:max_depth=2",
                     "--budget", "1.5", "-D", "res=8", "--ref-spp", "256", "-o", str(outdir)])
    assert code == 0
    text = capsys.readouterr().out
    assert "equal-time ratio" in text and "path:max_depth=2" in text
    data = json.loads((outdir / "tiny.json").read_text())
    pts = data["curves"]["path"]["points"]
    assert len(pts) >= 2 and [p["spp"] for p in pts][:2] == [1, 2]
    assert all(p["relmse"] > 0 and p["seconds"] > 0 for p in pts)
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
