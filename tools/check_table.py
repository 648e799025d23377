"""The README's `check` table from the JSON reports of ``python -m mi_twopass check --json``.

    .venv/bin/python tools/check_table.py out/check/*.json

One row per report (scene), one column per integrator in the order of the first report. A cell
is *mean ratio / block relMSE* for a report of one render per row; for ``--renders 2`` it is
*mean ratio ± its standard error / bias part ± its standard error*. **Bold**: OUT;
*(noise)* after a bold cell: OUT but noise-limited (check's ``noise_limited``); "refused" where
the integrator refused the scene.
"""
import argparse
import json

from mi_twopass.scenefile import scene_label


def cell(row: dict) -> str:
    """One integrator's cell (module docstring)."""
    if row.get("refused"):
        what = "medium" if "medi" in row["refused"] else row["refused"][:40]
        return f"refused ({what})"
    if row.get("bias2") is not None:
        se = row.get("ratio_se")  # reports before session 12's last check change lack it
        text = (f"{row['mean_ratio']:.3f}" + (f" ± {se:.3f}" if se is not None else "")
                + f" / {row['bias2']:+.1e} ± {row['bias2_se']:.0e}")
    else:
        text = f"{row['mean_ratio']:.3f} / {row['block_relmse']:.1e}"
    if row["out"]:
        text = f"**{text}**" + (" *(noise)*" if row.get("noise_limited") else "")
    return text


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+", help="check --json files")
    args = ap.parse_args(argv)
    reports = [json.load(open(p)) for p in args.reports]
    names = [r["integrator"] for r in reports[0]["rows"]]
    print("| scene | " + " | ".join(f"`{n}`" for n in names) + " |")
    print("| --- |" + " --- |" * len(names))
    for rep in reports:
        rows = {r["integrator"]: r for r in rep["rows"]}
        cells = [cell(rows[n]) if n in rows else "—" for n in names]
        print(f"| {scene_label(rep['meta']['scene'])} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
