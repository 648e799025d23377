"""One results.md from the bench.json of one or more `python -m mi_twopass bench` runs, with the
curves summarised again by the current harness (:func:`mi_twopass.evaluation.harness.summarise`).

    python tools/bench_retable.py RUN1/bench.json [RUN2/bench.json ...] -o results.md

For runs made on a machine that is gone (a GPU lent for a session) whose table a later fix of the
summaries changes, and to put two partial runs of the same command into one table. The header
names each run's date, machine, commit and command; the curves themselves are not changed.
"""
import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mi_twopass.evaluation import harness  # noqa: E402
from mi_twopass.evaluation.bench import (_duration, failed_row, format_results,  # noqa: E402
                                         machine_label, table_row)


def curves_of(entry: dict) -> dict:
    """{spec: Curve} from a scene entry of bench.json, summarised again."""
    curves = {spec: harness.Curve(c["label"], [harness.Point(**p) for p in c["points"]])
              for spec, c in entry["curves"].items()}
    baseline = next((k for k in curves if k.split(":")[0] == "path"), "path")
    harness.summarise(curves, baseline=baseline)
    return curves, baseline


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", metavar="bench.json")
    ap.add_argument("-o", "--output", default="results.md")
    args = ap.parse_args(argv)
    rows, noise, headers = [], {}, []
    for path in args.runs:
        with open(path) as f:
            run = json.load(f)
        state = "complete" if run.get("complete", True) else "stopped early"
        headers.append(
            f"{run['date']} on {machine_label(run['machine'])}, {run['variant']}, commit "
            f"{run['git_commit']}, {len(run['scenes'])} scenes in "
            f"{_duration(run['wall_seconds'])} ({state}): `{run['command']}`")
        for entry in run["scenes"].values():
            curves, baseline = curves_of(entry)
            for spec in run["integrators"]:
                if spec in curves:
                    rows.append(table_row(entry["label"], curves[spec], curves.get(baseline)))
                elif spec in entry.get("failed", {}):
                    rows.append(failed_row(entry["label"], spec, entry["failed"][spec]))
            noise[entry["label"]] = (entry["reference_relmse"], entry["ref_spp"])
    header = ("Bench runs, summaries recomputed by tools/bench_retable.py:\n\n" +
              "\n".join(f"- {h}" for h in headers))
    with open(args.output, "w") as f:
        f.write(format_results(rows, header, noise))
    print(f"wrote {args.output}: {len(rows)} rows from {len(args.runs)} runs")


if __name__ == "__main__":
    main()
