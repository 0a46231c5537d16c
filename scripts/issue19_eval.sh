#!/usr/bin/env bash
# Scores one training run of the camera-lane comparison (issue 19, docs/training/issue19_plan.md): exports it,
# evaluates it at 1, 8 and 32 slices with --save-results (the input of `streamdet-eval --compare`), and for a fused
# model runs the image-use gate (every camera zeroed; (5 deg, 50 cm) extrinsic noise).
#
#   scripts/issue19_eval.sh RUN_DIR VAL_DATA OUT_DIR [MAX_SAMPLES]
#
# RUN_DIR: a finished `streamdet-train` folder (model.pt); VAL_DATA: the evaluation world (all of its samples are
# scored: `--split all`); OUT_DIR/export, OUT_DIR/res_<n>/ (per slice count), OUT_DIR/gate_*.json.
# Then, per seed and slice count: streamdet-eval --compare A/res_8 B/res_8 --bootstrap 1000 --json cmp.json
set -euo pipefail
if [ $# -lt 3 ]; then
    echo "usage: $0 RUN_DIR VAL_DATA OUT_DIR [MAX_SAMPLES]" >&2
    exit 2
fi
run=$1; val=$2; out=$3; max=${4:-}
[ -f "$run/model.pt" ] || { echo "$0: $run/model.pt not found (is the run finished?)" >&2; exit 1; }
[ -d "$val" ] || { echo "$0: no dataset at $val" >&2; exit 1; }
limit=()
[ -n "$max" ] && limit=(--max-samples "$max")
mkdir -p "$out"

streamdet-export --checkpoint "$run/model.pt" --out "$out/export"
for n in 1 8 32; do
    echo "== $run: $n slices"
    streamdet-eval --data "$val" --split all --export-dir "$out/export" --slices "$n" "${limit[@]}" \
        --save-results "$out/res_$n" --json "$out/eval_$n.json"
done
if grep -q '"use_image": true' "$out/export/manifest.json"; then
    echo "== $run: image-use gate"
    streamdet-study drop-camera --export-dir "$out/export" --data "$val" --split all "${limit[@]}" --slices 8 \
        --no-cameras --json "$out/gate_drop_cameras.json"
    streamdet-study calib-noise --export-dir "$out/export" --data "$val" --split all "${limit[@]}" --slices 8 \
        --level 5,50 --json "$out/gate_calib_noise.json"
fi
echo "wrote $out"
