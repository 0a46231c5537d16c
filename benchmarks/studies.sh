#!/usr/bin/env bash
# The four robustness studies of the paper's Sec. IV (docs/studies/RESULTS.md) on the shipped models:
# models/weights/small.pt (fused) and models/weights/small_lidar_only.pt (its LiDAR-only baseline).
#
#   benchmarks/studies.sh VAL_DATA OUT_DIR [HIRES_DATA]
#
# VAL_DATA: the evaluation world (issue 19: streamdet-synth --out val60w4 --scenes 60 --seed 8 --resolution 480x270,
# every sample is unseen, so --split all). HIRES_DATA: a 1600x900 set for the resolution study; made here when absent
# (streamdet-synth --scenes 3 --seed 123 --resolution 1600x900). Each study runs its fp32 graphs with one
# onnxruntime thread; two studies run at a time (one per core). Writes OUT_DIR/{slices,drop_camera,calib_noise,
# resolution}.{json,png} and the exports under OUT_DIR/exports.
set -euo pipefail
if [ $# -lt 2 ]; then
    echo "usage: $0 VAL_DATA OUT_DIR [HIRES_DATA]" >&2
    exit 2
fi
val=$1; out=$2; hires=${3:-$out/val1600}
here=$(cd "$(dirname "$0")/.." && pwd)
[ -d "$val" ] || { echo "$0: no dataset at $val" >&2; exit 1; }
mkdir -p "$out/exports"
E=$out/exports/fused; B=$out/exports/lidar_only
streamdet-export --checkpoint "$here/models/weights/small.pt" --out "$E"
streamdet-export --checkpoint "$here/models/weights/small_lidar_only.pt" --out "$B"
[ -d "$hires/v1.0-synth" ] || streamdet-synth --out "$hires" --scenes 3 --seed 123 --resolution 1600x900

common=(--export-dir "$E" --data "$val" --split all)
streamdet-study slices "${common[@]}" --max-samples 60 --baseline-export-dir "$B" \
    --json "$out/slices.json" --plot "$out/slices.png" &
pid=$!
streamdet-study drop-camera "${common[@]}" --max-samples 60 --camera CAM_BACK --camera CAM_FRONT --no-cameras \
    --json "$out/drop_camera.json" --plot "$out/drop_camera.png"
wait "$pid"  # a plain `wait` would hide the background study's failure
streamdet-study calib-noise "${common[@]}" --max-samples 20 --seeds 3 \
    --json "$out/calib_noise.json" --plot "$out/calib_noise.png" &
pid=$!
streamdet-study resolution --export-dir "$E" --data "$hires" --split all --max-samples 15 \
    --resolution 1600x900 --resolution 1200x675 --resolution 800x450 --resolution 384x216 \
    --json "$out/resolution.json" --plot "$out/resolution.png"
wait "$pid"
echo "wrote $out"
