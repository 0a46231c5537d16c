#!/usr/bin/env bash
# Issue 22: the lighter image lane (preset small_v3_lite, CHECKPOINT) against the shipped small_v3, each under the
# full schedule and the phase-locked one with per-camera lifts, on the drives of benchmarks/replay_readme.sh, time
# scales 1 and 2, ROUNDS rounds taking turns (benchmarks/replay_ab.sh: int8 image lane + fp32 slices, probe before
# each run, OUT/table.md). Both exports are made here when missing (int8, calibrated on the drives' dataset).
#   CHECKPOINT=RUN/model.pt benchmarks/replay_lite_lane.sh [OUT_DIR [ROUNDS]]   (default out/replay_readme, 2 rounds)
# Run it on a quiet machine. Results: docs/replay.md, "A lighter image lane".
set -euo pipefail
OUT=${1:-out/replay_readme}
ROUNDS=${2:-2}
BIN=${BIN:-.venv/bin}
: "${CHECKPOINT:?set CHECKPOINT to a small_v3_lite training checkpoint (model.pt)}"
source "$(dirname "$0")/replay_prep.sh"  # DATA, EXPORT of CHECKPOINT
LITE=$EXPORT
LITE_CHECKPOINT=$CHECKPOINT
unset CHECKPOINT
source "$(dirname "$0")/replay_prep.sh"  # EXPORT of the shipped model
SHIPPED=$EXPORT
echo "lite: $LITE_CHECKPOINT -> $LITE; shipped: $SHIPPED" > "$OUT/lite_lane_exports.txt"
export DATA
exec "$(dirname "$0")/replay_ab.sh" "$OUT/lite_lane" "$ROUNDS" "1 2" v3_full="$SHIPPED",full,off \
  v3_phase_terms="$SHIPPED",phase-locked,on lite_full="$LITE",full,off lite_phase_terms="$LITE",phase-locked,on
