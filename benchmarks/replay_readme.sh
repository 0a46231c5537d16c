#!/usr/bin/env bash
# The figures of the README's "Streaming in real time" section and docs/replay.md, from scratch:
#   1. held-out synthetic scenes at nuScenes rates (seed 11, never seen in training; 20 Hz LiDAR, 8 scenes, val = 2),
#   2. the shipped model exported with int8 graphs, calibrated on that dataset's train split,
#   3. streamdet-replay of the val scenes in all three modes (int8 image lane + fp32 slices) at time scales 1, 2, 4,
#      all six cameras triggered at once (--camera-trigger simultaneous: the README's figures were measured so),
#   4. the player's own CPU with a no-op detector.
# Run it from the repository root on a quiet machine (timings on a shared machine vary 2-8x):
#   benchmarks/replay_readme.sh [OUT_DIR [DOCS_DIR]]   (default out/replay_readme; about 10 minutes on 2 cores)
# With DOCS_DIR (e.g. docs/replay) the picture, the three reports and the player cost are also copied there
# (replay_timeline.png, replay_scale{1,2,4}.txt, player_cost.txt) for the README and docs/replay.md to quote.
set -euo pipefail
OUT=${1:-out/replay_readme}
DOCS=${2:-}
BIN=${BIN:-.venv/bin}
source "$(dirname "$0")/replay_prep.sh"  # DATA, EXPORT
# the CPUs this process may use (affinity and cgroup quota: streamdet.core.cpu.usable_cpus; nproc is not on macOS)
"$BIN/python" -c 'from streamdet.core.cpu import usable_cpus; print(usable_cpus())' > "$OUT/nproc.txt"
uptime > "$OUT/uptime_before.txt"
for SCALE in 1 2 4; do
  PLOT=()
  if [ "$SCALE" = 1 ]; then PLOT=(--plot "$OUT/replay_timeline.png"); fi
  "$BIN/streamdet-replay" --data "$DATA" --split val --export-dir "$EXPORT" --precision fp32 --image-precision int8 \
    --lidar-hz 20 --slices 8 --camera-hz 12 --camera-trigger simultaneous --mode all --time-scale "$SCALE" \
    --json "$OUT/replay_scale$SCALE.json" --out "$OUT/scale$SCALE" "${PLOT[@]}" | tee "$OUT/replay_scale$SCALE.txt"
done
"$BIN/python" -m streamdet.replay.cost --seconds 10 | tee "$OUT/player_cost.txt"
uptime > "$OUT/uptime_after.txt"
if [ -n "$DOCS" ]; then
  mkdir -p "$DOCS"
  cp "$OUT/replay_timeline.png" "$OUT/player_cost.txt" "$DOCS/"
  for SCALE in 1 2 4; do cp "$OUT/replay_scale$SCALE.txt" "$DOCS/"; done
fi
echo "wrote $OUT (tables: replay_scale*.txt, picture: replay_timeline.png, player cost: player_cost.txt)"
