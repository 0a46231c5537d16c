#!/usr/bin/env bash
# The camera-dropout weights against the previous ones in the replay on all 8 scenes of the issue-22 drives
# (thirty-fifth session): the thirty-fourth session's comparison (weights_ab in ../issue22_line_dropout/) played only
# the drives' 2 val scenes, too few to resolve a one-point gain. Phase-locked, one slice worker, queue 16 (the
# issue-22 line's variant), int8 image lane and slices, the two variants taking turns each round. The int8 graphs were
# calibrated on the drives' train split, which this plays too (both exports alike).
set -euo pipefail
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
OLD=out/issue22_s32/export_small_v3_swift_eb04782151e4_image_layout_image_half_top_k_100
NEW=out/issue22_s34/export_small_v3_swift_944239bca08a_image_layout_image_half_top_k_100
OUT=${2:-out/weights_all}
SPLIT=all DATA=out/issue22_s32/synth20 benchmarks/replay_ab.sh "$OUT" "${1:-3}" 1 \
  "pl_v1=$OLD,phase-locked,on,,int8,,,,,1,,16,," \
  "pl_drop=$NEW,phase-locked,on,,int8,,,,,1,,16,,"
.venv/bin/python -m streamdet.benchmarks.replay_table "$OUT" --baseline pl_v1 | tee "$OUT/line.md"
