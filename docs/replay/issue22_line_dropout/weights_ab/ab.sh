#!/usr/bin/env bash
# The replay with the camera-dropout weights against the previous ones (thirty-fourth session): four variants taking turns
# per round, the issue-22 drives and export options; the previous export from the thirty-second session's folder
set -euo pipefail
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
OLD=out/issue22_s32/export_small_v3_swift_eb04782151e4_image_layout_image_half_top_k_100
NEW=out/issue22_s34/export_small_v3_swift_944239bca08a_image_layout_image_half_top_k_100
DATA=out/issue22_s32/synth20 benchmarks/replay_ab.sh out/weights_ab ${1:-2} 1 \
  "full_v1=$OLD,full,on,,int8,,,,,,,,," \
  "pl_v1=$OLD,phase-locked,on,,int8,,,,,1,,16,," \
  "full_drop=$NEW,full,on,,int8,,,,,,,,," \
  "pl_drop=$NEW,phase-locked,on,,int8,,,,,1,,16,,"
.venv/bin/python -m streamdet.benchmarks.replay_table out/weights_ab --baseline full_v1 | tee out/weights_ab/line.md
