#!/usr/bin/env bash
# Issue 22 with the flat lifter: the image lane's schedules on the same drives, taking turns within every round,
# streaming mode, int8 image lane + fp32 slices, nuScenes rates (20 Hz LiDAR x 8 slices, 12 Hz cameras):
#   volume_full  the shipped small model (volume lifter) exported as when issue 22 was filed (--lut-layout slots),
#                full schedule: "today's full"
#   flat_full    CHECKPOINT (a flat-lifter model, models/flat_lifter.py) in the default export, full schedule
#   flat_phase   the same export, phase-locked schedule
#   CHECKPOINT=RUN/model.pt benchmarks/replay_lifters.sh [OUT_DIR [ROUNDS [SCALES [TRIGGERS]]]]
# (default out/replay_readme, 2 rounds, scales "1 2", triggers "lidar-synced simultaneous"). Writes
# OUT/lifters/<trigger>_scale<S>_<config>_r<round>.{txt,json}, then the offline parity of the two schedules on the
# flat export. Run it on a quiet machine: nothing else running (timings on a shared machine vary 2-8x).
set -euo pipefail
OUT=${1:-out/replay_readme}
ROUNDS=${2:-2}
SCALES=${3:-"1 2"}
TRIGGERS=${4:-"lidar-synced simultaneous"}
BIN=${BIN:-.venv/bin}
: "${CHECKPOINT:?set CHECKPOINT to a flat-lifter training checkpoint (model.pt)}"
source "$(dirname "$0")/replay_prep.sh"  # DATA, EXPORT (of CHECKPOINT)
FLAT=$EXPORT
VOLUME="$OUT/export_small_slots"
if [ ! -f "$VOLUME/manifest.json" ]; then
  "$BIN/streamdet-export" --int8 --calibration-data "$DATA" --lut-layout slots --out "$VOLUME"
fi
mkdir -p "$OUT/lifters"
uptime > "$OUT/lifters/uptime_before.txt"
for ROUND in $(seq 1 "$ROUNDS"); do
  for SCALE in $SCALES; do
    for TRIGGER in $TRIGGERS; do
      for CONFIG in volume_full flat_full flat_phase; do
        case $CONFIG in
          volume_full) EXP=$VOLUME SCHEDULE=full ;;
          flat_full) EXP=$FLAT SCHEDULE=full ;;
          flat_phase) EXP=$FLAT SCHEDULE=phase-locked ;;
        esac
        NAME="${TRIGGER}_scale${SCALE}_${CONFIG}_r$ROUND"
        "$BIN/streamdet-replay" --data "$DATA" --split val --export-dir "$EXP" --precision fp32 --image-precision int8 \
          --lidar-hz 20 --slices 8 --camera-hz 12 --camera-trigger "$TRIGGER" --mode streaming --schedule "$SCHEDULE" \
          --time-scale "$SCALE" --json "$OUT/lifters/$NAME.json" --out "$OUT/lifters/$NAME" > "$OUT/lifters/$NAME.txt"
        grep -A3 "staleness added" "$OUT/lifters/$NAME.txt" | tail -1 | sed "s/^/$NAME /"
      done
    done
  done
done
uptime > "$OUT/lifters/uptime_after.txt"
# the modelled schedules and the staleness floor take stage times: pass the flat export's quiet means from the
# reports' stage tables, e.g. python -m streamdet.benchmarks.schedule_model --export-dir EXPORT --encode-ms E --lift-ms L --slice-ms S
"$BIN/python" -m streamdet.benchmarks.quadrant_parity --data "$DATA" --export-dir "$FLAT" --image-precision int8 \
  | tee "$OUT/lifters/quadrant_parity_flat.txt"
echo "wrote $OUT/lifters/"
