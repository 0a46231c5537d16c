#!/usr/bin/env bash
# Image-lane variants side by side in the replay, taking turns within every round: the drives of DATA (environment;
# the issue-22 ones: benchmarks/replay_prep.sh), streaming mode, int8 image lane + fp32 slices (unless SLICES says), LiDAR-synchronised
# cameras, nuScenes rates (20 Hz x 8 slices unless NUM_SLICES says, 12 Hz cameras). Each run is preceded by the host-speed probe (2048^3
# MatMul GFLOP/s: the shared machine's fast or slow state).
#   DATA=DATASET benchmarks/replay_ab.sh OUT ROUNDS "SCALES" LABEL=EXPORT_DIR,SCHEDULE,TERMS[,CODE[,SLICES[,NICE[,IMAGE_THREADS[,YIELD[,HEAP[,WORKERS[,COALESCE[,QUEUE[,PAIRHOLD[,ISA]]]]]]]]]]]] ...
# e.g. DATA=out/replay_readme/synth20 benchmarks/replay_ab.sh out/ab 2 "1 2" v3_full=exports/v3,full,off \
#        v3_terms=exports/v3,phase-locked,on
# SCHEDULE: full | phase-locked; TERMS: auto | on | off (--camera-terms); CODE (optional): a directory put first on
# PYTHONPATH for that variant, holding another build of the streamdet package (e.g. `git worktree add W REV &&
# pip install --no-deps --no-build-isolation --target CODE W`): an earlier runtime against this one; SLICES
# (optional, default fp32): the slice lane's precision (--precision fp32 | fp16 | int8); NICE (optional, default 0):
# --image-lane-nice; IMAGE_THREADS (optional, default: as the slice lane, 1): --image-lane-threads; YIELD (optional, default 0, phase-locked only):
# --image-lane-yield; HEAP (optional, default freeze): freeze | thaw (--freeze-heap / --no-freeze-heap; thaw: the garbage
# collector's full collections run over the whole heap mid-drive, as in the replays before 2026-12-04's eighteenth session);
# WORKERS (optional, default: the runtime's LaneConfig, 2): --slice-workers; COALESCE (optional, default: the runtime's
# LaneConfig): --coalesce-slices, the most waiting slices of one quadrant one run detects when the lane is behind; QUEUE
# (optional, default: the runtime's LaneConfig, 8): --queue-size, slices waiting before the oldest is dropped; PAIRHOLD
# (optional, default: the runtime's LaneConfig): --pair-hold-load, the slice lane's load above which a quadrant's first slice waits for the next; ISA (optional, default: the CPU's):
# avx2 runs the variant (and its probe) under benchmarks/avx2_only.sh, the AVX2 kernels of an AVX2-only part on this CPU
# (give replay_table --target-ms when variants of both instruction sets share OUT). DELIVERY_MS (environment, default 0): the
# cameras' delivery delay (--camera-delivery-ms); NUM_SLICES (environment, default 8): slices per rotation (--slices); SPLIT (environment, default val): the drives' split played (--split; all: every scene, to compare models rather than schedules). Writes OUT/r<round>_scale<S>_<label>/ (replay.json, report.md),
# OUT/r<round>_scale<S>_<label>.txt, OUT/variants.txt, OUT/probes_gflops.txt, OUT/staleness_cdf.png and OUT/table.md (benchmarks/replay_table.py: one row per
# scale and variant, one value per round in each cell; `python -m streamdet.benchmarks.replay_tail OUT` then says whether a
# variant's slice p99 comes from queueing or from long runs, and `python -m streamdet.benchmarks.replay_table OUT --baseline full
# [--target-ms 100]` counts the rounds meeting issue 22's line against the variant named full). Run it on a quiet machine.
set -euo pipefail
# python -c / -m put the working directory first on sys.path, where a checkout folder named like the package would
# shadow a non-editable install of it (revisions before the package root moved to toplevel/ had one; Python >= 3.11
# honours this, older ones ignore it)
export PYTHONSAFEPATH=1
OUT=${1:?OUT}; ROUNDS=${2:?ROUNDS}; SCALES=${3:?SCALES}; shift 3
[ $# -ge 1 ] || { echo "give at least one LABEL=EXPORT_DIR,SCHEDULE,TERMS[,CODE[,SLICES[,NICE[,IMAGE_THREADS[,YIELD[,HEAP[,WORKERS[,COALESCE[,QUEUE[,PAIRHOLD[,ISA]]]]]]]]]]]]" >&2; exit 2; }
BIN=${BIN:-.venv/bin}
DELIVERY_MS=${DELIVERY_MS:-0}
NUM_SLICES=${NUM_SLICES:-8}
SPLIT=${SPLIT:-val}
: "${DATA:?set DATA to the drives dataset (benchmarks/replay_prep.sh makes the issue-22 one)}"
mkdir -p "$OUT"
# replay_table counts every r<round>_scale<S>_<label> run it finds: an earlier A/B's runs would be counted as rounds of this one
if compgen -G "$OUT/r*_scale*_*" > /dev/null; then
  echo "$OUT already holds runs of an earlier A/B (r*_scale*_*), which its table and line would count as rounds of this one: give a fresh OUT, or move them away" >&2
  exit 2
fi
for V in "$@"; do
  IFS=, read -r EXP SCHEDULE TERMS CODE SLICES NICE ITHREADS YIELD HEAP WORKERS COALESCE QUEUE PAIRHOLD ISA <<< "${V#*=}"
  [ -f "$EXP/manifest.json" ] || { echo "$V: $EXP holds no manifest.json" >&2; exit 2; }
  [ -z "$CODE" ] || [ -d "$CODE/streamdet" ] || { echo "$V: $CODE holds no streamdet package" >&2; exit 2; }
  case "${ISA:-}" in ""|avx2) ;; *) echo "$V: ISA must be avx2 or empty (the CPU's own), got $ISA" >&2; exit 2 ;; esac
done
uptime > "$OUT/uptime_before.txt"
: > "$OUT/variants.txt"
touch "$OUT/probes_gflops.txt"
for ROUND in $(seq 1 "$ROUNDS"); do
  for SCALE in $SCALES; do
    for V in "$@"; do
      LABEL=${V%%=*}
      IFS=, read -r EXP SCHEDULE TERMS CODE SLICES NICE ITHREADS YIELD HEAP WORKERS COALESCE QUEUE PAIRHOLD ISA <<< "${V#*=}"
      NAME="r${ROUND}_scale${SCALE}_$LABEL"
      MASK=()
      [ -z "$ISA" ] || MASK=("$(dirname "$0")/avx2_only.sh")
      echo "$NAME $("${MASK[@]}" "$BIN/python" -c 'from streamdet.benchmarks.probe import measure_peak; print(max(measure_peak(2).run_gflops_per_s))')" \
        >> "$OUT/probes_gflops.txt"
      RUNENV=()
      EXTRA=()
      [ -z "$ITHREADS" ] || EXTRA=(--image-lane-threads "$ITHREADS")
      [ -z "$YIELD" ] || EXTRA+=(--image-lane-yield "$YIELD")  # only when asked: an earlier CODE build lacks the option
      [ -z "$WORKERS" ] || EXTRA+=(--slice-workers "$WORKERS")
      [ -z "$COALESCE" ] || EXTRA+=(--coalesce-slices "$COALESCE")  # only when asked, as YIELD
      [ -z "$QUEUE" ] || EXTRA+=(--queue-size "$QUEUE")
      [ -z "$PAIRHOLD" ] || EXTRA+=(--pair-hold-load "$PAIRHOLD")  # only when asked, as YIELD
      case "${HEAP:-}" in
        ""|freeze) ;;
        thaw) EXTRA+=(--no-freeze-heap) ;;
        *) echo "$V: HEAP must be freeze or thaw, got $HEAP" >&2; exit 2 ;;
      esac
      [ -z "$CODE" ] || RUNENV=(PYTHONPATH="$(realpath "$CODE")${PYTHONPATH:+:$PYTHONPATH}")
      [ "$ROUND" != 1 ] || [ "$SCALE" != "${SCALES%% *}" ] || echo "$LABEL: $EXP $SCHEDULE terms=$TERMS code=${CODE:-this checkout} slices=${SLICES:-fp32} nice=${NICE:-0} image_threads=${ITHREADS:-1} yield=${YIELD:-0} heap=${HEAP:-freeze} slice_workers=${WORKERS:-default} coalesce=${COALESCE:-default} queue=${QUEUE:-default} pair_hold=${PAIRHOLD:-default} isa=${ISA:-cpu} slices_per_rotation=$NUM_SLICES split=$SPLIT" >> "$OUT/variants.txt"
      "${MASK[@]}" env "${RUNENV[@]}" "$BIN/streamdet-replay" --data "$DATA" --split "$SPLIT" --export-dir "$EXP" --precision "${SLICES:-fp32}" --image-precision int8 \
        --lidar-hz 20 --slices "$NUM_SLICES" --camera-hz 12 --camera-trigger lidar-synced --camera-delivery-ms "$DELIVERY_MS" \
        --mode streaming --schedule "$SCHEDULE" --camera-terms "$TERMS" --image-lane-nice "${NICE:-0}" --time-scale "$SCALE" "${EXTRA[@]}" --out "$OUT/$NAME" \
        > "$OUT/$NAME.txt"
      grep -A2 "staleness added p50" "$OUT/$NAME.txt" | tail -1 | sed "s/^/$NAME /"
    done
  done
done
uptime > "$OUT/uptime_after.txt"
"$BIN/python" -m streamdet.benchmarks.replay_table "$OUT" > "$OUT/table.md"
"$BIN/python" -m streamdet.benchmarks.replay_table "$OUT" --plot "$OUT/staleness_cdf.png" > /dev/null \
  || echo "no staleness_cdf.png (matplotlib missing?)" >&2
echo "wrote $OUT/table.md and $OUT/staleness_cdf.png"
