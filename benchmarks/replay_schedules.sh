#!/usr/bin/env bash
# Issue 22's figures: the image lane's two schedules (LaneConfig.schedule "full" and "phase-locked") on the same
# drives, streaming mode, int8 image lane + fp32 slices, nuScenes rates (20 Hz LiDAR x 8 slices, 12 Hz cameras).
# Reuses the dataset and export of benchmarks/replay_readme.sh (made here the same way when missing):
#   benchmarks/replay_schedules.sh [OUT_DIR [SCALES [TRIGGERS]]]   (default out/replay_readme, scales "1 2",
#   camera trigger models "lidar-synced simultaneous": replay/triggers.py)
# Per trigger model, schedule and time scale it writes replay_<trigger>_<schedule>_scale<S>.{txt,json} and the details
# under <trigger>_<schedule>_scale<S>/replay.json; the report's "image lane" table holds the staleness added by processing
# (p50 / p95 / p99 / max), the image age and the image lane's CPU ms per LiDAR rotation. Run it on a quiet machine
# (timings on a shared machine vary 2-8x); uptime before and after is kept beside the reports.
set -euo pipefail
OUT=${1:-out/replay_readme}
SCALES=${2:-"1 2"}
TRIGGERS=${3:-"lidar-synced simultaneous"}
BIN=${BIN:-.venv/bin}
source "$(dirname "$0")/replay_prep.sh"  # DATA, EXPORT
uptime > "$OUT/schedules_uptime_before.txt"
for SCALE in $SCALES; do
  for TRIGGER in $TRIGGERS; do
    for SCHEDULE in full phase-locked; do
      NAME="${TRIGGER}_${SCHEDULE}_scale$SCALE"
      "$BIN/streamdet-replay" --data "$DATA" --split val --export-dir "$EXPORT" --precision fp32 --image-precision int8 \
        --lidar-hz 20 --slices 8 --camera-hz 12 --camera-trigger "$TRIGGER" --mode streaming --schedule "$SCHEDULE" \
        --time-scale "$SCALE" --json "$OUT/replay_$NAME.json" --out "$OUT/$NAME" | tee "$OUT/replay_$NAME.txt"
    done
  done
done
uptime > "$OUT/schedules_uptime_after.txt"
# offline: four per-quadrant updates give the full update's BEV and detections on the val scenes (no clock involved)
"$BIN/python" -m streamdet.benchmarks.quadrant_parity --data "$DATA" --export-dir "$EXPORT" --image-precision int8 \
  | tee "$OUT/quadrant_parity.txt"
# the schedules around modelled stage times (no CPU contention) and the staleness floor; the lifter's gather forms
"$BIN/python" -m streamdet.benchmarks.schedule_model --export-dir "$EXPORT" | tee "$OUT/schedule_model.txt"
"$BIN/python" -m streamdet.benchmarks.lut_gather --export-dir "$EXPORT" | tee "$OUT/lut_gather.txt"
echo "wrote $OUT/replay_*_{full,phase-locked}_scale*.txt"
