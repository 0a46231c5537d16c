#!/usr/bin/env bash
# phase-locked (1 worker, q16) replays taking turns: glibc malloc defaults vs large mmap threshold + no trim
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
OUT=${1:-out/malloc_ab}
E=out/issue22_s35/export_small_v3_swift_944239bca08a_image_layout_image_half_top_k_100
for r in 1 2 3 4; do
  for v in default heap; do
    ENVS=()
    [ $v = heap ] && ENVS=(MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=1073741824 MALLOC_TOP_PAD_=268435456)
    mkdir -p $OUT/r${r}_scale1_$v
    env "${ENVS[@]}" .venv/bin/streamdet-replay --data out/issue22_s35/synth20 --split val --export-dir $E --precision int8 --image-precision int8 \
      --lidar-hz 20 --slices 8 --camera-hz 12 --camera-trigger lidar-synced --mode streaming --schedule phase-locked --camera-terms on \
      --slice-workers 1 --queue-size 16 --out $OUT/r${r}_scale1_$v > $OUT/r${r}_$v.txt 2>&1
  done
done
.venv/bin/python -m streamdet.benchmarks.replay_tail $OUT
