#!/usr/bin/env bash
# ready lifts in the replay: the issue-22 line's variants, the build before (b2ce1b7) against this one, taking turns
set -euo pipefail
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
EXPORT=out/issue22_s32/export_small_v3_swift_eb04782151e4_image_layout_image_half_top_k_100
DATA=out/issue22_s32/synth20 benchmarks/replay_ab.sh out/ready_ab ${1:-3} 1 \
  "full=$EXPORT,full,on,,int8,,,,,,,,," \
  "pl_before=$EXPORT,phase-locked,on,${CODE_BEFORE:?a build of b2ce1b7 installed apart (replay_ab.sh CODE)},int8,,,,,1,,16,," \
  "pl_ready=$EXPORT,phase-locked,on,,int8,,,,,1,,16,,"
.venv/bin/python -m streamdet.benchmarks.replay_table out/ready_ab --baseline full | tee out/ready_ab/line.md
