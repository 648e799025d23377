"""``python -m mi_twopass bench --prepass`` (mi_twopass/evaluation/prepass_scaling.py): the
studies on tiny settings in fresh processes, a child stopped by its timeout, the generated
scenes, the report's tables and figure, and the command line's options."""
import json

import matplotlib.image
import numpy as np
import pytest

from mi_twopass import cli
from mi_twopass.evaluation import prepass_scaling as ps

SPEC = "radiosity_gather:max_patches=64"


def _tables(text):
    """prepass_scaling.md's tables as {title: [row dict]}."""
    tables, title, rows = {}, None, None
    for line in text.splitlines():
        if line.startswith("## "):
            title, rows = line[3:], []
            tables[title] = rows
        elif line.startswith("| ") and rows is not None:
            rows.append([c.strip() for c in line.strip("|").split(" | ")])
    return {t: [dict(zip(r[0], row)) for row in r[2:]] for t, r in tables.items()}


def test_prepass_scaling_tiny_run(tmp_path):
    out = tmp_path / "prepass"
    lines = []
    data = ps.run_prepass_scaling(ps.DEFAULT_SCENE, ["path", SPEC], sizes=(32, 16),
                                  triangles=(100, 1000), emitters=(1, 4), full_hd=False,
                                  timeout=120, out_dir=str(out), study_res=32, log=lines.append)
    assert lines[0].startswith("prepass scaling: 6 points × (2 integrators + a baseline) = 18")
    assert lines[-1].startswith(f"wrote {out}/prepass_scaling.md")
    for name in ("prepass_scaling.json", "prepass_scaling.md", "prepass_scaling.png"):
        assert (out / name).stat().st_size > 0, name

    saved = json.loads((out / "prepass_scaling.json").read_text())
    assert saved["integrators"] == ["path", SPEC] and saved["sizes"] == [16, 32]
    assert saved["machine"]["cpu"] and saved["variant"] == "llvm_ad_rgb"
    entries = saved["entries"]
    assert len(entries) == 18 == len(data["entries"])
    for e in entries:
        assert e["status"] == "ok", e
        assert e["peak_bytes"] > 0 and e["peak_kib"] > 0 and e["process_seconds"] > 0
        if e["kind"] != "baseline":
            assert e["seconds"] > 0 and e["baseline_bytes"] > 0, e
            assert e["extra_bytes"] == e["peak_bytes"] - e["baseline_bytes"]
    got = {(e["study"], e["x"], e["integrator"]) for e in entries}
    triangles = sorted({e["x"] for e in entries if e["study"] == "triangles"})
    assert 90 <= triangles[0] <= 130 and 900 <= triangles[1] <= 1100
    for study, xs in (("size", [16, 32]), ("triangles", triangles), ("emitters", [1, 4])):
        for x in xs:
            for spec in ("baseline (load only)", "path", SPEC):
                assert (study, x, spec) in got
    by = {(e["study"], e["x"], e["integrator"]): e for e in entries}
    assert by[("size", 16, SPEC)]["size"] == [16, 16]
    assert by[("size", 32, "path")]["spp"] == ps.PATH_SPP
    assert by[("emitters", 4, SPEC)]["emitters"] == 4
    assert by[("triangles", triangles[1], SPEC)]["triangles"] >= triangles[1]
    stats = by[("size", 32, SPEC)]["stats"]
    assert stats["prepass_rays"] > 0 and stats["cache_bytes"] > 0

    tables = _tables((out / "prepass_scaling.md").read_text())
    seconds = next(v for k, v in tables.items() if k.startswith("Prepass seconds vs image"))
    assert [r["integrator \\ film"] for r in seconds] == ["`path` (32 spp render)", f"`{SPEC}`"]
    assert float(seconds[1]["16×16"]) > 0 and float(seconds[1]["32×32"]) > 0
    memory = next(v for k, v in tables.items() if k.startswith("Peak memory, GB (+ over the "
                                                               "baseline), vs emitters"))
    assert [r["integrator \\ emitters"] for r in memory] == [
        "baseline (load only)", "`path` (32 spp render)", f"`{SPEC}`"]
    assert memory[2]["4"].split(" (+")[0] and float(memory[2]["4"].split()[0]) > 0
    assert len(tables) == 6  # seconds and memory per study, no full HD

    image = matplotlib.image.imread(str(out / "prepass_scaling.png"))
    assert image.shape[0] > 500 and image.shape[1] > 500


def test_child_past_its_timeout_is_recorded(tmp_path):
    point = {"study": "size", "x": 16, "label": "16 px", "scene": ps.DEFAULT_SCENE,
             "film_res": None, "params": {"res": 16}, "resolver": [], "path_spp": 1}
    result = ps.run_child(ps.child_config(point, SPEC, "prepass"), timeout=0.001)
    assert result["status"] == "timeout" and result["timeout"] == 0.001
    entry = ps.entry_of(point, SPEC, result, {"status": "ok", "peak_kib": 1})
    assert entry["status"] == "timeout" and "peak_bytes" not in entry
    assert ps._cell_seconds(entry).startswith("timeout")


def test_timeout_skips_the_larger_points_of_that_study():
    calls = []

    def runner(config, timeout):
        calls.append((config["mode"], config["film_res"], config["params"].get("res")))
        if config["spec"] == SPEC:
            return {"status": "timeout", "timeout": timeout, "process_seconds": timeout}
        return {"status": "ok", "peak_kib": 1000, "seconds": 0.5, "load_seconds": 0.1,
                "process_seconds": 1.0, "size": [8, 8]}

    points = [{"study": "size", "x": r, "label": f"{r} px", "scene": ps.DEFAULT_SCENE,
               "film_res": None, "params": {"res": r}, "resolver": [], "path_spp": 1}
              for r in (8, 16, 32)]
    entries = ps.measure(points, ["path", SPEC], timeout=5, log=lambda _: None, runner=runner)
    status = [(e["x"], e["integrator"], e["status"]) for e in entries if e["kind"] == "prepass"]
    assert status == [(8, SPEC, "timeout"), (16, SPEC, "skipped"), (32, SPEC, "skipped")]
    assert len(calls) == 3 * 2 + 1  # baselines and path at every size, SPEC once
    path = [e for e in entries if e["integrator"] == "path"]
    assert all(e["extra_bytes"] == 0 and e["peak_bytes"] == 1000 * 1024 for e in path)


def test_generated_scenes(tmp_path):
    import mitsuba as mi

    from mi_twopass.scenefile import load_scene

    verts, faces = ps.sphere_mesh(1000)
    assert 900 <= len(faces) <= 1100 and faces.max() == len(verts) - 1
    p = verts[faces]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert ((normal * (p.mean(axis=1) - [0.3, 0.1, 0.35])).sum(axis=1) > 0).all()  # outward

    resolver = mi.file_resolver()
    saved = [resolver[i] for i in range(len(resolver))]
    resolver.prepend(str(ps.ROOT) + "/scenes_xml")
    try:
        path, n = ps.triangle_scene(str(tmp_path), 100)
        scene = load_scene(path, film_res=8)
        assert n == len(ps.sphere_mesh(100)[1])
        assert sum(s.face_count() for s in scene.shapes() if s.is_mesh()) == 36 + n
        lights = load_scene(ps.emitter_scene(str(tmp_path), 10), film_res=8)
        assert len(lights.emitters()) == 10
        hd, params = ps.sized_scene(ps.DEFAULT_SCENE, str(tmp_path), ps.FULL_HD, {"res": 64})
        assert params == {}  # $res was the film's only use
        film = load_scene(hd).sensors()[0].film()
        assert list(film.size()) == [1920, 1080]
    finally:
        resolver.clear()
        for entry in saved:
            resolver.append(entry)


def test_full_hd_table_and_bars(tmp_path):
    def entry(spec, kind, peak_gb, seconds, **extra):
        return {"study": "full_hd", "x": 1920 * 1080, "label": "1920×1080", "integrator": spec,
                "kind": kind, "status": "ok", "peak_bytes": int(peak_gb * 1e9),
                "baseline_bytes": int(0.15e9), "extra_bytes": int(peak_gb * 1e9 - 0.15e9),
                "seconds": seconds, "load_seconds": 0.01, "size": [1920, 1080], **extra}

    entries = [entry("baseline (load only)", "baseline", 0.15, None),
               entry("path", "render", 0.23, 7.7, spp=1),
               entry("rex", "prepass", 3.5, 94.0, stats={"cache_bytes": 123}),
               {"study": "full_hd", "x": 1920 * 1080, "label": "1920×1080",
                "integrator": "spike_gather", "kind": "prepass", "status": "timeout",
                "timeout": 300.0}]
    data = {"entries": entries, "integrators": ["path", "rex", "spike_gather"],
            "scene": ps.DEFAULT_SCENE, "study_res": 128, "header": "header", "title": "t"}
    rows = _tables(ps.format_report(data))
    (hd,) = [v for k, v in rows.items() if k.startswith("1920×1080")]
    assert [r["integrator"] for r in hd] == ["baseline (load only)", "`path` (1 spp render)",
                                             "`rex`", "`spike_gather`"]
    assert hd[1]["≤ 2 GB"] == "yes" and hd[2]["≤ 2 GB"] == "**no**"
    assert hd[2]["peak GB"] == "3.5" and hd[2]["cache bytes"] == "123 bytes"
    assert hd[3]["seconds"].startswith("timeout")
    ps.write_plot(data, str(tmp_path / "p.png"))
    assert (tmp_path / "p.png").stat().st_size > 0


def test_cli_prepass_options(monkeypatch, tmp_path, capsys):
    got = {}
    monkeypatch.setattr(ps, "run_prepass_scaling", lambda scene, specs, **kw: got.update(
        scene=scene, specs=specs, **kw))
    out = tmp_path / "o"
    assert cli.main(["bench", "--prepass", "--quick", "--integrators", SPEC, "--emitters",
                     "4,1", "--timeout", "9", "-o", str(out)]) == 0
    assert got["scene"] == ps.DEFAULT_SCENE and got["specs"] == ["path", SPEC]
    assert got["sizes"] == list(ps.QUICK_SIZES) and got["emitters"] == [1, 4]
    assert got["triangles"] == list(ps.QUICK_TRIANGLES) and got["timeout"] == 9
    assert got["full_hd"] is True and got["out_dir"] == str(out)
    assert cli.main(["bench", "--prepass", "--scene", ps.DEFAULT_SCENE, "--sizes", "8", "-o",
                     str(out)]) == 0
    assert got["sizes"] == [8] and got["full_hd"] is True
    assert cli.main(["bench", "--prepass", "--no-full-hd", "-o", str(out)]) == 0
    assert got["full_hd"] is False and got["sizes"] == list(ps.DEFAULT_SIZES)
    assert got["triangles"] == list(ps.DEFAULT_TRIANGLES)


@pytest.mark.parametrize("argv, message", [
    (["--prepass", "--cold"], "choose one"),
    (["--prepass", "--sizes", "0"], "--sizes 0"),
    (["--prepass", "--sizes", "a"], "expected an integer"),
    (["--prepass", "--timeout", "0"], "--timeout 0"),
    (["--prepass", "--res", "64"], "not with --prepass"),
    (["--prepass", "--corpus"], "not with --prepass"),
    (["--sizes", "64"], "--sizes: only with --prepass"),
    (["--no-full-hd"], "only with --prepass"),
    (["--quick"], "--quick: only with --prepass"),
])
def test_cli_prepass_mistakes(argv, message, tmp_path, capsys):
    out = tmp_path / "never"
    assert cli.main(["bench", *argv, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err, err
    assert not out.exists()


def test_estimate():
    parts = ps.estimate_parts()
    assert parts["processes"] == 13 * 7
    assert parts["total"] == pytest.approx(parts["start"] + sum(parts[s] for s in ps.STUDIES))
    assert ps.estimate_seconds(full_hd=False) < parts["total"]
    assert f"{parts['total']:.0f} s" in ps.estimate_text()
    assert ps.estimate_parts(timeout=1)["size"] == 0  # every process capped by the timeout
