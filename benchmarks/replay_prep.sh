# Sourced by replay_readme.sh and replay_schedules.sh: the held-out dataset and the int8 export both replay from.
# Needs OUT and BIN; sets DATA and EXPORT, making each only when missing (seed 11 is never used in training).
# CHECKPOINT (optional, environment): export that training checkpoint instead of the default model, into
# $OUT/export_<name of the checkpoint's folder>.
mkdir -p "$OUT"
DATA="$OUT/synth20"
if [ ! -f "$DATA/trajectories.npz" ]; then
  "$BIN/streamdet-synth" --out "$DATA" --scenes 8 --seed 11 --resolution 480x270 --sweeps-per-sample 10 --overwrite
fi
if [ -n "${CHECKPOINT:-}" ]; then
  EXPORT="$OUT/export_$(basename "$(dirname "$CHECKPOINT")")"
  CKPT_ARGS=(--checkpoint "$CHECKPOINT")
else
  # the shipped model, named by its file's hash so that an export of earlier weights is never reused
  EXPORT="$OUT/export_shipped_$(sha256sum models/weights/small.pt | cut -c1-12)"
  CKPT_ARGS=()
fi
if [ ! -f "$EXPORT/manifest.json" ]; then
  "$BIN/streamdet-export" "${CKPT_ARGS[@]}" --int8 --calibration-data "$DATA" --out "$EXPORT"
fi
