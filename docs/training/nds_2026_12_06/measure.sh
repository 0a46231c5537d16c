#!/bin/bash
# Re-measure the README's accuracy table after the evaluation fix (d6f223a): every model exported fp32, scored on
# all 600 val60w4 samples at the slice counts the README lists. Run from the repository root:
#   streamdet-synth --out val60w4 --scenes 60 --seed 8 --resolution 480x270   # the held-out world-4 set (about 3 min)
#   DATA=val60w4 OUT=nds docs/training/nds_2026_12_06/measure.sh               # exports and scores in OUT (~40 min, 2 cores)
# small.world6.s8.json (thirty-eighth session): the same 60 scenes generated as world 6 (commit b19c426 or later) and
# small.pt scored on them the same way:
#   streamdet-synth --out val60w6 --scenes 60 --seed 8 --resolution 480x270 --workers 2
#   streamdet-eval --data val60w6 --export-dir nds/small --split all --slices 8 --precision fp32 --json nds/small.world6.s8.json
set -euo pipefail
mkdir -p "${OUT:-nds}"
for m in small small_lidar_only small_lite small_v3_swift; do
  [ -f "${OUT:-nds}"/$m/manifest.json ] || .venv/bin/streamdet-export --checkpoint models/weights/$m.pt --out "${OUT:-nds}"/$m > "${OUT:-nds}"/$m.export.log 2>&1
done
run() { # model slices
  [ -f "${OUT:-nds}"/$1.s$2.json ] && return 0
  /usr/bin/time -f "%e s" .venv/bin/streamdet-eval --data "${DATA:-val60w4}" --export-dir "${OUT:-nds}"/$1 --split all --slices $2 --precision fp32 --json "${OUT:-nds}"/$1.s$2.json > "${OUT:-nds}"/$1.s$2.log 2>&1
}
run small_lidar_only 1
run small_v3_swift 1
run small 8
run small_lidar_only 8
run small_lite 8
run small_v3_swift 8
run small 32
run small_lidar_only 32
run small_v3_swift 32
echo done
