#!/usr/bin/env bash
# The GPU report of issue 15 in one command, for a machine with an NVIDIA GPU and no network:
# every integrator on cuda_ad_rgb (tools/gpu_check.py, with tracebacks), the bench on cuda_ad_rgb
# over the corpus and the scenes given, and optionally the resolution sweep; each step under its
# own time limit, and each writes its table as it goes, so a step cut short still reports.
#
#   bash tools/gpu_run.sh [SCENE.xml ...]
#
# Needs, in the repository root: .whl/ with Python wheels for the GPU machine's Python (mitsuba
# 3.9.1 with its cuda_ad_rgb module, drjit 1.5.0, OpenEXR, flip-evaluator; the rest is assumed
# installed: numpy, matplotlib, tqdm), unless they are importable already:
# `python tools/gpu_wheels.py` fetches and repacks them (38.6 MB). Scenes outside the checkout
# (../shared/scenes) must be copied into it, e.g. into .gpu_scenes/; list .whl and .gpu_scenes
# in .git/info/exclude and in the device call's carry. Writes into $OUT
# (default out/gpu): gpu.txt, check.log, bench.log, bench_data.tgz (results.md, bench.json,
# per-scene JSON and plots), the image strips in two tars (a file may be at most 16 MiB), and
# with a sweep sweep.log and sweep.tgz.
# Environment: CHECK (1: run the check, default), CHECK_TIMEOUT (s, default 120), CORPUS (1:
# bench every scenes_xml scene before those given, default), BENCH_TIMEOUT (s, default 330),
# BUDGET (s per integrator and scene, default 2), RES (default 256), REF_SPP (default 2048),
# SWEEP_SIZES (e.g. 256,512: run `bench --sweep` on its default scenes; default none),
# SWEEP_BUDGET and SWEEP_REF_SPP (given at 128², default 1 and 8192), SWEEP_TIMEOUT (s, default
# 270), VARIANT (default cuda_ad_rgb), MI_TWOPASS_GIT_COMMIT (the commit the copy holds),
# INTEGRATORS (the bench's --integrators, default all), PROBE (1: tools/probe_check.py over the
# corpus and the scenes given before the bench, writing probe.log; default 0), PROBE_SPP
# (default 8,64), PROBE_SETTINGS (twopass's path_probe columns, default auto), PROBE_TIMEOUT
# (s, default 150).
set -u
cd "$(dirname "$0")/.."
OUT=${OUT:-out/gpu}
mkdir -p "$OUT"
if ls .whl/*.whl >/dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site:$PWD
else
    export PYTHONPATH=$PWD
fi
export MI_TWOPASS_VARIANT=${VARIANT:-cuda_ad_rgb} MI_TWOPASS_CACHE=${MI_TWOPASS_CACHE:-/tmp/refcache}
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$OUT/gpu.txt"

if [ "${CHECK:-1}" = 1 ]; then
    timeout "${CHECK_TIMEOUT:-120}" python3 tools/gpu_check.py scenes_xml/cornell_box.xml \
        scenes_xml/caustic.xml scenes_xml/many_lights.xml --res 128 --spp 16 2>&1 \
        | tee "$OUT/check.log"
fi

if [ "${PROBE:-0}" = 1 ]; then
    timeout "${PROBE_TIMEOUT:-150}" python3 tools/probe_check.py scenes_xml/*.xml "$@" \
        --res "${RES:-256}" --spp "${PROBE_SPP:-8,64}" --repeats 2 \
        --settings "${PROBE_SETTINGS:-auto}" 2>&1 | tee "$OUT/probe.log"
fi

scenes=()
if [ "${CORPUS:-1}" = 1 ]; then
    scenes=(scenes_xml/many_lights.xml scenes_xml/caustic.xml scenes_xml/window_interior.xml
            scenes_xml/office.xml scenes_xml/cornell_box.xml scenes_xml/furnace.xml
            scenes_xml/mixed_room.xml)
fi
scenes+=("$@")
BENCH=/tmp/gpubench
rm -rf "$BENCH"
timeout "${BENCH_TIMEOUT:-330}" python3 -m mi_twopass bench --variant "$MI_TWOPASS_VARIANT" \
    --res "${RES:-256}" --ref-spp "${REF_SPP:-2048}" --budget "${BUDGET:-2}" -o "$BENCH" \
    ${INTEGRATORS:+--integrators "$INTEGRATORS"} \
    "${scenes[@]}" 2>&1 | tee "$OUT/bench.log"

tar czf "$OUT/bench_data.tgz" -C "$BENCH" --exclude='*_images.png' .
(cd "$BENCH" && ls *_images.png 2>/dev/null | sort > /tmp/strips.txt)
n=$(wc -l < /tmp/strips.txt)
if [ "$n" -gt 0 ]; then
    head -n $(((n + 1) / 2)) /tmp/strips.txt | tar cf "$OUT/images_1.tar" -C "$BENCH" -T -
    tail -n +$(((n + 1) / 2 + 1)) /tmp/strips.txt | tar cf "$OUT/images_2.tar" -C "$BENCH" -T -
fi
if [ -n "${SWEEP_SIZES:-}" ]; then
    SWEEP=/tmp/gpusweep
    rm -rf "$SWEEP"
    timeout "${SWEEP_TIMEOUT:-270}" python3 -m mi_twopass bench --variant "$MI_TWOPASS_VARIANT" \
        --sweep "$SWEEP_SIZES" --budget "${SWEEP_BUDGET:-1}" --ref-spp "${SWEEP_REF_SPP:-8192}" \
        -o "$SWEEP" 2>&1 | tee "$OUT/sweep.log"
    tar czf "$OUT/sweep.tgz" -C "$SWEEP" .
fi
ls -la "$OUT"
