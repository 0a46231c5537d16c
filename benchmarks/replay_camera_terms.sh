#!/usr/bin/env bash
# Issue 22: the phase-locked image lane with and without per-camera lifts (DetectorConfig.camera_terms), beside the
# full schedule, on the drives and int8 export of benchmarks/replay_readme.sh (made here when missing): time scales
# 1 and 2, ROUNDS rounds taking turns (benchmarks/replay_ab.sh: probe before each run, OUT/table.md).
#   benchmarks/replay_camera_terms.sh [OUT_DIR [ROUNDS]]   (default out/replay_readme/terms, 2 rounds: about 15 minutes)
# Run it on a quiet machine. Results: docs/replay.md, "Per-camera lifts in the runtime".
set -euo pipefail
OUT=${1:-out/replay_readme/terms}
ROUNDS=${2:-2}
BIN=${BIN:-.venv/bin}
source "$(dirname "$0")/replay_prep.sh"  # DATA, EXPORT
export DATA
exec "$(dirname "$0")/replay_ab.sh" "$OUT" "$ROUNDS" "1 2" full="$EXPORT",full,off \
  phase-locked="$EXPORT",phase-locked,off phase-locked+terms="$EXPORT",phase-locked,on
