"""``python -m mi_twopass bench --cold`` (mi_twopass/evaluation/cold_start.py): path's first
render on the tiny scene in fresh processes, cold and warm, and the options' mistakes."""
import json

import pytest

from mi_twopass import cli
from mi_twopass.evaluation import cold_start


def test_cold_start_writes_table_and_json(tiny_scene_file, tmp_path, capsys):
    out = tmp_path / "cold"
    argv = ["bench", "--cold", tiny_scene_file, "--integrators", "path", "--res", "8",
            "--spp", "4", "-o", str(out)]
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    assert "[1/1] path" in printed and "kernels compiled" in printed
    lines = [ln for ln in (out / "cold.md").read_text().splitlines() if ln.startswith("| ")]
    cells = [[c.strip() for c in ln.strip("|").split(" | ")] for ln in lines]
    assert cells[0] == list(cold_start.COLUMNS) and len(cells) == 3  # header, rule, path
    row = dict(zip(cells[0], cells[2]))
    assert row["integrator"] == "`path`"
    assert float(row["cold s"]) > 0 and float(row["warm s"]) > 0

    data = json.loads((out / "cold.json").read_text())
    assert data["integrators"] == ["path"] and data["spp"] == 4 and data["res"] == 8
    (r,) = data["rows"]
    assert r["cold_seconds"] > 0 and r["warm_seconds"] > 0
    for key in ("compiled_cold", "launches", "unique"):
        assert isinstance(r[key], int) and r[key] >= 1, key
    assert r["compiled_cold"] <= r["launches"] and isinstance(r["compiled_warm"], int)
    run = data["runs"]["path"]
    assert run["config"]["params"] == {"res": 8} and run["cache_bytes"] > 0
    assert len(run["warm"]) == cold_start.WARM_RUNS
    cold = run["cold"]
    assert cold["size"] == [8, 8] and cold["render_kernels"]["from_disk"] == 0
    assert cold["process_seconds"] > cold["render_seconds"]
    # the warm process found kernels in the cache the cold one filled
    assert run["warm"][-1]["render_kernels"]["from_disk"] >= 1


@pytest.mark.parametrize("argv, message", [
    (["--cold", "--budget", "5"], "not with --cold"),
    (["--cold", "--corpus"], "not with --cold"),
    (["--cold", "--spp", "0"], "--spp 0: must be >= 1"),
])
def test_cold_start_mistakes(argv, message, tiny_scene_file, tmp_path, capsys):
    out = tmp_path / "never"
    assert cli.main(["bench", tiny_scene_file, *argv, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err, err
    assert not out.exists()


def test_cold_start_defaults_and_counts():
    import drjit as dr

    args = cli.build_parser().parse_args(["bench", "--cold"])
    assert args.cold and args.spp is None and args.scenes == []
    assert cold_start.DEFAULT_SCENE.endswith("scenes_xml/cornell_box.xml")
    history = [
        {"type": dr.KernelType.JIT, "hash": "a", "cache_hit": 0, "cache_disk": 0,
         "backend_time": 12.0, "codegen_time": 0.5},
        {"type": dr.KernelType.JIT, "hash": "a", "cache_hit": 1, "cache_disk": 0,
         "backend_time": 0.0, "codegen_time": 0.5},
        {"type": dr.KernelType.JIT, "hash": "b", "cache_hit": 1, "cache_disk": 1,
         "backend_time": 0.0, "codegen_time": 0.5},
        {"type": dr.KernelType.Memset},
    ]
    counts = cold_start.kernel_counts(history)
    assert counts == {"launches": 3, "unique": 2, "compiled": 1, "from_disk": 1,
                      "in_memory": 1, "backend_ms": 12.0, "codegen_ms": 1.5,
                      "other_launches": 1}
