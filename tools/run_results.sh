#!/usr/bin/env bash
# The speed-vs-error runs quoted in README "Results" (each writes out/results/<scene>.png/.json).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
BUDGET=${BUDGET:-12}
run() { "$PY" -m mi_twopass compare --budget "$BUDGET" -o out/results "$@"; }
run scenes_xml/cornell_box.xml     -D res=128 --integrators path,radiosity_gather,radiosity_gather:r_thresh=0
run scenes_xml/office.xml          -D res=128 --integrators path,radiosity_gather,radiosity_gather:r_thresh=0
run scenes_xml/caustic.xml         -D res=64  --integrators path,rex --ref-spp 65536
run scenes_xml/window_interior.xml -D res=64  --integrators path,radiance_cache,radiance_cache:alpha_rel=0.03
run scenes_xml/many_lights.xml   -D res=64  --integrators path,spike_gather,spike_gather:visibility_max_rays=20,radiosity_gather --ref-spp 16384 --budget 30
"$PY" tools/spike_truncation.py scenes_xml/many_lights.xml -D res=64 --spp 1024 --seeds 4 -o out/results/spike_truncation.json
