"""``python -m mi_twopass bench`` (mi_twopass/evaluation/bench.py): the report's files and
numbers on a tiny scene, its mistakes as one ``error:`` line, and the table's arithmetic."""
import json
import math

import matplotlib.image
import pytest

from mi_twopass import cli
from mi_twopass.evaluation import bench
from mi_twopass.evaluation.harness import Point


def _load_tool(name):
    """A script of tools/ as a module."""
    import importlib.util
    import os

    path = os.path.join(os.path.dirname(__file__), "..", "..", "tools", f"{name}.py")
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _table(text):
    """results.md's table as (header cells, [row cells])."""
    lines = [ln for ln in text.splitlines() if ln.startswith("| ")]
    split = [[c.strip() for c in ln.strip("|").split(" | ")] for ln in lines]
    return split[0], split[2:]


def test_bench_writes_table_plots_images_and_json(tiny_scene_file, tmp_path, ref_cache,
                                                  capsys):
    out = tmp_path / "bench"
    argv = ["bench", tiny_scene_file, "--res", "16", "--integrators",
            "path,radiosity_gather:max_patches=64", "--budget", "1", "--ref-spp", "64",
            "-o", str(out)]
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    progress = [ln for ln in printed.splitlines() if ln.startswith("[")]
    assert len(progress) == 2 and progress[0].startswith("[1/2] tiny")
    assert "radiosity_gather:max_patches=64" in progress[1]
    for name in ("bench.json", "bench.log", "results.md", "tiny.json", "tiny.png",
                 "tiny_images.png"):
        assert (out / name).stat().st_size > 0, name
    assert list(ref_cache.glob("*.exr"))  # the reference went to MI_TWOPASS_CACHE

    text = (out / "results.md").read_text()
    first = text.splitlines()[0]
    data = json.loads((out / "bench.json").read_text())
    assert data["machine"]["cpu"] in first and data["date"] in first
    assert "python -m mi_twopass bench " + tiny_scene_file in first  # the exact command
    header, rows = _table(text)
    assert header == list(bench.COLUMNS)
    assert [(r[0], r[1]) for r in rows] == [("tiny (16×16)", "`path`"),
                                            ("tiny (16×16)", "`radiosity_gather:max_patches=64`")]
    path, rad = (dict(zip(header, r)) for r in rows)
    assert path["speed-up vs path"] == "1.00" and path["equal-time ratio"] == "1.00"
    assert path["equal-spp ratio"] == "1.00"
    assert path["prepass share"] == "—" and path["rays / viewing ray"] == "—"
    assert rad["prepass share"].endswith(" %") and 0 < float(rad["prepass share"][:-2]) <= 100
    assert float(rad["rays / viewing ray"]) > 1  # gather and shadow rays beside the camera's
    assert "spp)" in rad["relMSE @ max spp"]
    for row in (path, rad):
        assert row["t(relMSE 0.01) s"] == "not reached" or float(row["t(relMSE 0.01) s"]) > 0

    m = data["machine"]
    assert m["cpu"] and m["cores"] >= 1 and m["usable_cores"] >= 1
    assert data["date"] and data["command"].startswith("python -m mi_twopass bench ")
    assert data["variant"] == "llvm_ad_rgb" and data["mitsuba"] and data["drjit"]
    assert data["budget"] == 1.0 and data["ref_spp"] == 64
    assert data["complete"] is True and m["gpu"] is None  # llvm: no GPU named
    assert "took" in first and "partial" not in first

    # tools/bench_retable.py: the same rows from bench.json, summarised again
    retable = _load_tool("bench_retable")
    again = tmp_path / "again.md"
    retable.main([str(out / "bench.json"), "-o", str(again)])
    header2, rows2 = _table(again.read_text())
    assert header2 == header and [r[:2] for r in rows2] == [r[:2] for r in rows]
    assert data["git_commit"] is None or data["git_commit"] in again.read_text()

    # a run stopped after its first of two scenes leaves a table that says it is partial
    part = tmp_path / "part"
    part.mkdir()
    bench.write_report(str(part), dict(data), dict(data["scenes"]), 12.0, n_scenes=2)
    assert "partial: 1 of 2 scenes" in (part / "results.md").read_text().splitlines()[0]
    assert json.loads((part / "bench.json").read_text())["complete"] is False
    assert list(data["scenes"]) == ["tiny"]  # scenes given: the corpus is not added
    scene = data["scenes"]["tiny"]
    assert scene["params"] == {"res": 16} and scene["size"] == [16, 16]
    curves = scene["curves"]
    assert list(curves) == ["path", "radiosity_gather:max_patches=64"]
    pts = curves["radiosity_gather:max_patches=64"]["points"]
    assert [p["spp"] for p in pts] == [2**k for k in range(len(pts))]
    assert all(p["seconds"] > 0 and p["relmse"] > 0 and p["stats"]["prepass_seconds"] > 0
               for p in pts)
    # by default a point under a second is three runs, and the point is the median one
    assert data["repeats"] == 3 and data["repeat_below"] == 1.0
    assert "median of 3" in first
    for p in pts:
        times = p["stats"]["repeat_seconds"]
        assert len(times) == 3 and p["seconds"] == sorted(times)[1]
        assert p["seconds"] == times[p["stats"]["repeat_kept"]]
        assert p["relmse"] == pytest.approx(p["stats"]["repeat_relmse"][p["stats"]["repeat_kept"]])
    assert scene["rows"][0]["speedup"] in (None, 1.0)
    share = pts[-1]["stats"]["prepass_seconds"] / pts[-1]["seconds"]
    assert scene["rows"][1]["prepass_share"] == pytest.approx(share)
    per_scene = json.loads((out / "tiny.json").read_text())  # compare's format
    assert set(per_scene["curves"]) == set(curves)

    strip = matplotlib.image.imread(str(out / "tiny_images.png"))
    assert strip.shape[1] > strip.shape[0]  # three columns side by side, two rows


def test_an_integrator_refusing_a_scene_is_a_row_and_the_run_goes_on(
        tiny_scene_file, tmp_path, ref_cache, capsys, monkeypatch):
    from mi_twopass.integrators import radiosity_gather

    def refuse(self, scene, seed):
        raise ValueError("no diffuse surface to put patches on")

    monkeypatch.setattr(radiosity_gather.RadiosityGatherIntegrator, "prepass", refuse)
    out = tmp_path / "b"
    assert cli.main(["bench", tiny_scene_file, "--res", "8", "--integrators",
                     "radiosity_gather,path:max_depth=2", "--budget", "0.3", "--ref-spp", "16",
                     "-o", str(out)]) == 0
    header, rows = _table((out / "results.md").read_text())
    cells = {r[1]: r for r in rows}
    assert list(cells) == ["`radiosity_gather`", "`path:max_depth=2`"]  # no path added
    assert cells["`radiosity_gather`"][2] == "refused: no diffuse surface to put patches on"
    assert cells["`path:max_depth=2`"][3] in ("1.00", "—")
    assert (out / "tiny_images.png").stat().st_size > 0
    assert "refused" in capsys.readouterr().out


@pytest.mark.parametrize("case", ["integrator", "missing_scene", "budget", "malformed",
                                  "repeats", "repeats_sweep"])
def test_mistakes_are_one_error_line(case, tiny_scene_file, tmp_path, capsys):
    bad = tmp_path / "bad.xml"
    bad.write_text('<scene version="3.0.0"><shape type="sphere"></scene>')
    out = tmp_path / "never"
    argv = {
        "integrator": [tiny_scene_file, "--integrators", "path,nope"],
        "missing_scene": [tiny_scene_file, str(tmp_path / "nope.xml")],
        "budget": [tiny_scene_file, "--budget", "0"],
        "malformed": [tiny_scene_file, str(bad)],
        "repeats": [tiny_scene_file, "--repeats", "0"],
        "repeats_sweep": [tiny_scene_file, "--sweep", "16", "--repeats", "3"],
    }[case]
    code = cli.main(["bench", *argv, "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert {"integrator": "no integrator named 'nope'",
            "missing_scene": "scene file not found",
            "budget": "--budget 0.0: must be > 0",
            "malformed": "malformed XML",
            "repeats": "--repeats 0: must be > 0",
            "repeats_sweep": "--repeats: only for the bench's curves"}[case] in err
    assert not out.exists()  # nothing rendered, nothing written


def test_defaults_cover_the_corpus_and_the_suite_within_half_an_hour():
    from mi_twopass.integrators import PLUGINS

    assert bench.suite_integrators() == ["path", *PLUGINS]
    scenes = bench.corpus_scenes()
    assert len(scenes) >= 6 and all(s.endswith(".xml") for s in scenes)
    assert all(bench.has_res_parameter(s) for s in scenes)  # --res goes in as -D res=PX
    assert bench.estimate_seconds(len(scenes), 6, bench.DEFAULT_BUDGET) < 30 * 60
    args = cli.build_parser().parse_args(["bench"])
    assert args.scenes == [] and args.budget is None and args.res is None


def test_table_arithmetic():
    def pts(spps, errors, stats=None):
        return [Point(s, 0.1 * s, e, 0.1, e, dict(stats or {})) for s, e in zip(spps, errors)]

    path = pts([1, 2, 4, 8], [0.8, 0.4, 0.2, 0.1])
    # inside path's range: exact or log-log interpolated; beyond it: as 1/spp
    assert bench.path_relmse_at_spp(path, 4) == (0.2, False)
    assert bench.path_relmse_at_spp(path, 16) == (pytest.approx(0.05), True)
    value, extrapolated = bench.path_relmse_at_spp(pts([1, 4], [0.8, 0.2]), 2)
    assert value == pytest.approx(0.4) and not extrapolated
    ratio, extrapolated = bench.equal_spp_ratio(path, pts([1, 2, 4], [0.2, 0.1, 0.05]))
    assert ratio == pytest.approx(4.0) and not extrapolated

    p = Point(4, 2.0, 0.1, 0.1, 0.1, {"prepass_seconds": 0.5, "viewing_rays": 100,
                                      "implicit_rays": 150, "explicit_rays": 50})
    assert bench.prepass_share(p) == pytest.approx(0.25)
    assert bench.rays_per_viewing_ray(p) == pytest.approx(3.0)
    bare = Point(4, 2.0, 0.1, 0.1, 0.1, {})
    assert bench.prepass_share(bare) is None and bench.rays_per_viewing_ray(bare) is None

    row = bench.failed_row("s (8×8)", "rex", "refused: no caustic | at all")
    line = bench.format_row(row)
    assert line.count(" | ") == len(bench.COLUMNS) - 1  # the | of the message escaped
    assert bench.scene_names(["a/scene.xml", "b/scene.xml", "c/cbox.xml"]) == [
        "a_scene", "b_scene", "cbox"]
    assert not math.isnan(bench.auto_exposure([[[0.0, 0.0, 0.0]]]))


def test_reference_noise_is_read_off_paths_curve_and_marked_where_it_eats_the_target():
    def pts(spps, errors):
        return [Point(s, 0.1 * s, e, 0.1, e, {}) for s, e in zip(spps, errors)]

    # path against a reference of the same estimator: relMSE = c (1/spp + 1/ref_spp)
    c, ref = 12.5, 2048
    curve = pts([8, 16, 32, 64, 128], [c * (1 / s + 1 / ref) for s in (8, 16, 32, 64, 128)])
    assert bench.reference_relmse(curve, ref) == pytest.approx(c / ref)
    # one firefly-struck point does not move the median
    curve[2] = Point(32, 3.2, 50.0, 0.1, 50.0, {})
    assert bench.reference_relmse(curve, ref) == pytest.approx(c / ref)
    assert bench.reference_relmse([], ref) is None

    notes = "\n".join(bench.reference_notes({"a (256×256)": (c / 2048, 2048),
                                             "b (256×256)": (c / 8192, 8192),
                                             "c (8×8)": (None, 64)}))
    a_line = next(ln for ln in notes.splitlines() if ln.startswith("- a"))
    b_line = next(ln for ln in notes.splitlines() if ln.startswith("- b"))
    assert "61 %" in a_line and "reference-limited" in a_line  # 6.1e-3 of 0.01
    assert "15 %" in b_line and "reference-limited" not in b_line
    assert "- c" not in notes
