# Sourced by replay_readme.sh and replay_schedules.sh: the held-out dataset and the int8 export both replay from.
# Needs OUT and BIN; sets DATA and EXPORT, making each only when missing (seed 11 is never used in training).
# CHECKPOINT (optional, environment): export that training checkpoint instead of the default model, into
# $OUT/export_<checkpoint's file name>_<first 12 hex digits of its sha256>. EXPORT_ARGS (optional, environment): more streamdet-export options,
# space-separated (e.g. "--image-layout image_half --top-k 100"); they name the export folder too.
mkdir -p "$OUT"
# 12 Hz cameras at the LiDAR's crossings, as nuScenes records them (synth20, without them, held key-frame images)
DATA="$OUT/synth20_cam12"
if [ ! -f "$DATA/trajectories.npz" ]; then
  "$BIN/streamdet-synth" --out "$DATA" --scenes 8 --seed 11 --resolution 480x270 --sweeps-per-sample 10 --camera-hz 12 --overwrite
fi
# an export is named by its checkpoint's file name and hash, so that an export of other weights is never reused (two
# checkpoints of one folder, or earlier weights under the same name); hashed by Python: no sha256sum on every system
sha12() { "$BIN/python" -c 'import hashlib, sys; print(hashlib.sha256(open(sys.argv[1], "rb").read()).hexdigest()[:12])' "$1"; }
if [ -n "${CHECKPOINT:-}" ]; then
  EXPORT="$OUT/export_$(basename "$CHECKPOINT" .pt)_$(sha12 "$CHECKPOINT")"
  CKPT_ARGS=(--checkpoint "$CHECKPOINT")
else
  EXPORT="$OUT/export_shipped_$(sha12 models/weights/small.pt)"
  CKPT_ARGS=()
fi
read -r -a MORE_ARGS <<< "${EXPORT_ARGS:-}"
if [ ${#MORE_ARGS[@]} -gt 0 ]; then
  EXPORT="${EXPORT}_$(printf '%s' "${MORE_ARGS[*]}" | tr -cs 'A-Za-z0-9' '_' | sed 's/^_*//; s/_*$//')"
fi
if [ ! -f "$EXPORT/manifest.json" ]; then
  "$BIN/streamdet-export" "${CKPT_ARGS[@]}" "${MORE_ARGS[@]}" --int8 --calibration-data "$DATA" --out "$EXPORT"
fi
