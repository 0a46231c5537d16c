# Sourced by replay_readme.sh and replay_schedules.sh: the held-out dataset and the int8 export both replay from.
# Needs OUT and BIN; sets DATA and EXPORT, making each only when missing (seed 11 is never used in training).
# CHECKPOINT (optional, environment): export that training checkpoint instead of the default model, into
# $OUT/export_<name of the checkpoint's folder>. EXPORT_ARGS (optional, environment): more streamdet-export options,
# space-separated (e.g. "--image-layout image_half --top-k 100"); they name the export folder too.
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
read -r -a MORE_ARGS <<< "${EXPORT_ARGS:-}"
if [ ${#MORE_ARGS[@]} -gt 0 ]; then
  EXPORT="${EXPORT}_$(printf '%s' "${MORE_ARGS[*]}" | tr -cs 'A-Za-z0-9' '_' | sed 's/^_*//; s/_*$//')"
fi
if [ ! -f "$EXPORT/manifest.json" ]; then
  "$BIN/streamdet-export" "${CKPT_ARGS[@]}" "${MORE_ARGS[@]}" --int8 --calibration-data "$DATA" --out "$EXPORT"
fi
