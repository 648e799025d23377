"""``python -m mi_twopass bench --sweep`` (mi_twopass/evaluation/sweep.py): the files and the
table of a sweep over two tiny sizes, its options' mistakes, and its rules' arithmetic."""
import json

import matplotlib.image
import pytest

from mi_twopass import cli
from mi_twopass.evaluation import sweep
from mi_twopass.evaluation.harness import Curve, Point


def _table(text):
    """sweep.md's table as [row dict]."""
    lines = [ln for ln in text.splitlines() if ln.startswith("| ")]
    split = [[c.strip() for c in ln.strip("|").split(" | ")] for ln in lines]
    return [dict(zip(split[0], r)) for r in split[2:]]


def test_sweep_writes_table_figure_and_json(tiny_scene_file, tmp_path, ref_cache, capsys):
    out = tmp_path / "sweep"
    spec = "radiosity_gather:max_patches=64"
    argv = ["bench", "--sweep", "16,8", tiny_scene_file, "--integrators", spec,
            "--budget", "8", "--ref-spp", "64", "-o", str(out)]
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    progress = [ln for ln in printed.splitlines() if ln.startswith("[")]
    assert len(progress) == 4 and progress[0].startswith("[1/4] tiny 8")  # small sizes first
    assert "floor relMSE" in printed
    for name in ("sweep.json", "sweep.md", "sweep.png", "sweep.log"):
        assert (out / name).stat().st_size > 0, name
    assert len(list(ref_cache.glob("*.exr"))) == 2  # one reference per size, in the cache

    rows = _table((out / "sweep.md").read_text())
    assert list(rows[0]) == list(sweep.COLUMNS)
    assert [(r["scene"], r["size"], r["integrator"]) for r in rows] == [
        ("tiny", "8×8", "`path`"), ("tiny", "8×8", f"`{spec}`"),
        ("tiny", "16×16", "`path`"), ("tiny", "16×16", f"`{spec}`")]
    for r in rows:
        assert int(r["pixels"]) == int(r["size"].split("×")[0]) ** 2
        if r["integrator"] == "`path`":
            assert r["speed-up"] == "1.00" and r["from"] in ("t(0.01)", "equal-time")
    # --budget and --ref-spp are given at 128 px and scaled by side / 128 and 128 / side
    assert [r["budget s"] for r in rows[::2]] == ["0.5", "1"]
    assert [r["ref spp"] for r in rows[::2]] == ["1024", "512"]

    data = json.loads((out / "sweep.json").read_text())
    assert data["sizes"] == [8, 16] and data["budget_at_128"] == 8
    assert data["ref_spp_at_128"] == 64 and data["integrators"] == {"tiny": ["path", spec]}
    assert [(p["res"], p["size"], p["ref_spp"]) for p in data["points"]] == [
        (8, [8, 8], 1024), (16, [16, 16], 512)]
    for p in data["points"]:
        assert p["ref_floor"] > 0 and p["reference_seconds"] > 0
        assert set(p["curves"]) == {"path", spec}
        assert all(pt["relmse"] > 0 for c in p["curves"].values() for pt in c["points"])
    assert len(data["rows"]) == 4 and data["machine"]["cpu"] and data["variant"]
    assert data["complete"] is True
    assert "took" in (out / "sweep.md").read_text().splitlines()[0]

    # a sweep stopped after its first size leaves that size's table, marked partial
    part = tmp_path / "part"
    part.mkdir()
    sweep.write_report(str(part), dict(data), data["points"][:1], ["tiny"], 3.0, done=False)
    first = (part / "sweep.md").read_text().splitlines()[0]
    assert "partial: sizes 8 of 8,16" in first
    assert len(_table((part / "sweep.md").read_text())) == 2

    image = matplotlib.image.imread(str(out / "sweep.png"))
    assert image.shape[1] > image.shape[0]  # the plot and its legend beside it


def test_sweep_defaults_and_mistakes(tiny_scene_file, tmp_path, capsys):
    args = cli.build_parser().parse_args(["bench", "--sweep"])
    assert sweep.parse_sizes(args.sweep) == list(sweep.DEFAULT_SIZES)
    assert cli.build_parser().parse_args(["bench"]).sweep is None  # bench unchanged
    assert [sweep.default_specs(s) for s in sweep.DEFAULT_SCENES] == [
        ["path", "spike_gather", "twopass"], ["path", "rex", "twopass"],
        ["path", "radiance_cache", "twopass"]]
    assert sweep.default_specs(tiny_scene_file) == ["path", "twopass"]
    out = tmp_path / "never"
    for argv, message in ((["--sweep", "64,abc"], "'abc' is not a film size"),
                          (["--sweep", "64", "--res", "32"], "not with --sweep"),
                          (["--sweep", "64", "-D", "res=32"], "-D res: not with --sweep"),
                          (["--sweep", "64", "--cold"], "choose one"),
                          (["--spp", "4"], "only with --cold")):
        code = cli.main(["bench", tiny_scene_file, *argv, "-o", str(out)])
        err = capsys.readouterr().err
        assert code == 2 and err.startswith("error: ") and message in err, (argv, err)
    assert not out.exists()


def test_rules_and_floor_arithmetic():
    assert sweep.parse_sizes("256, 64,64") == [64, 256]
    with pytest.raises(ValueError):
        sweep.parse_sizes("0")
    assert sweep.point_budget(10, 128) == 10 and sweep.point_budget(10, 1024) == 80
    assert sweep.reference_spp(2048, 128) == 2048 and sweep.reference_spp(2048, 1024) == 256
    assert sweep.reference_spp(2048, 64) == 4096 and sweep.reference_spp(64, 1 << 14) == 16
    assert sweep.max_spp(1024 * 1024) == sweep.MAX_LANES >> 20
    assert sweep.max_spp(sweep.MAX_LANES * 4) == 1

    # path with true relMSE 0.8 / spp against a reference of 256 spp: floor 0.8 / 256
    ref_spp = 256
    path = [Point(s, 0.1 * s, 0.8 / s + 0.8 / ref_spp, 0.1, 0.1) for s in (1, 2, 4, 8, 16)]
    floor = sweep.reference_floor(path, ref_spp)
    assert floor == pytest.approx(0.8 / ref_spp)
    assert sweep.reference_floor([], ref_spp) is None
    # a method 4× better than path at equal time: the raw ratio is pulled towards 1 by the
    # floor, the floor-removed one is 4
    method = [Point(s, 0.4 * s, 0.05 / s + floor, 0.1, 0.1) for s in (1, 2)]
    t, base, own, extrapolated = sweep.equal_time_errors(method, path)
    assert t == pytest.approx(0.8) and base / own < 4 and not extrapolated
    assert sweep.floor_removed_ratio(method, path, floor) == pytest.approx(4.0)

    # a method whose first point comes after path's last: path extrapolated as 1/time
    # above the floor (0.8 / 16 + floor at 1.6 s, so 0.8 / 32 + floor at 3.2 s)
    slow = [Point(1, 3.2, 0.01 + floor, 0.1, 0.1)]
    t, base, own, extrapolated = sweep.equal_time_errors(slow, path, floor)
    assert extrapolated and t == 3.2 and base == pytest.approx(0.8 / 32 + floor)
    row = sweep.sweep_row("s", 8, (8, 8), "m", Curve("m", slow, {"equal_time_ratio": None}),
                          Curve("path", path), 1.0, ref_spp, floor)
    assert row["equal_time_ratio"] == pytest.approx(base / own)
    assert row["plotted_from"] == "equal-time≈" and "≈" in sweep.format_row(row)
    assert row["floor_removed_ratio"] == pytest.approx(2.5)

    est = sweep.estimate_seconds(9, sweep.DEFAULT_SIZES, sweep.DEFAULT_BUDGET,
                                 sweep.DEFAULT_REF_SPP, 3)
    assert 40 * 60 < est < 50 * 60  # the help text's 45 min
    row = {"speedup": None, "equal_time_ratio": 1.5}
    assert sweep.plotted_speedup(row) == (1.5, "equal-time")
    assert sweep.plotted_speedup({"speedup": 2.0, "equal_time_ratio": 1.5}) == (2.0, "t(0.01)")
