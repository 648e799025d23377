#!/usr/bin/env bash
# Every number quoted in README "Results": the harness runs (out/results/<scene>.png/.json, and
# out/results/128/ for the 128² runs), the Table-1 columns and spike_gather's truncation table;
# each command's printout is kept in out/results/<name>.txt.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
BUDGET=${BUDGET:-12}
OUT=out/results
mkdir -p "$OUT"
export MI_TWOPASS_QUIET=1
run() { local name=$1; shift; "$PY" -m mi_twopass compare --budget "$BUDGET" -o "$OUT" "$@" | tee "$OUT/$name.txt"; }
run cornell_box        scenes_xml/cornell_box.xml     -D res=128 --integrators path,radiosity_gather,radiosity_gather:r_thresh=0
run office             scenes_xml/office.xml          -D res=128 --integrators path,radiosity_gather,radiosity_gather:r_thresh=0
run caustic            scenes_xml/caustic.xml         -D res=64  --integrators path,rex --ref-spp 65536
run window_interior    scenes_xml/window_interior.xml -D res=64  --integrators path,radiance_cache,radiance_cache:max_near_triangles=1
run window_interior128 scenes_xml/window_interior.xml -D res=128 --integrators path,radiance_cache -o "$OUT/128"
run many_lights        scenes_xml/many_lights.xml     -D res=64  --integrators path,spike_gather,spike_gather:visibility_max_rays=20,radiosity_gather --ref-spp 16384 --budget 30
run many_lights128     scenes_xml/many_lights.xml     -D res=128 --integrators path,spike_gather,spike_gather:visibility_max_rays=20 --ref-spp 16384 --budget 30 -o "$OUT/128"
"$PY" tools/spike_truncation.py scenes_xml/many_lights.xml -D res=64 --spp 1024 --seeds 4 \
    -o "$OUT/spike_truncation.json" | tee "$OUT/spike_truncation.txt"
"$PY" tools/radiance_cache_table.py scenes_xml/window_interior.xml -D res=64 --spp 16,64,256 --repeat 3 \
    | tee "$OUT/radiance_cache_table.txt"
for spec in "cornell_box radiosity_gather" "caustic rex" "many_lights spike_gather" "window_interior radiance_cache"; do
  set -- $spec
  "$PY" tools/table1.py "scenes_xml/$1.xml" "$2" -D res=64 --spp 16 > "$OUT/table1_$1_$2.json"
done
"$PY" tools/equal_time_figure.py scenes_xml/many_lights.xml --seconds 2 \
    --integrators spike_gather:visibility_max_rays=20,spike_gather -D res=128 --ref-spp 16384 \
    -o docs/results/many_lights_equal_time.png
"$PY" tools/equal_time_figure.py scenes_xml/window_interior.xml --seconds 1 \
    --integrators radiance_cache -D res=128 -o docs/results/window_interior_equal_time.png
"$PY" tools/results_table.py "$OUT"/cornell_box.json "$OUT"/office.json "$OUT"/caustic.json \
    "$OUT"/many_lights.json "$OUT"/128/many_lights.json "$OUT"/window_interior.json \
    "$OUT"/128/window_interior.json | tee "$OUT/results_table.md"
