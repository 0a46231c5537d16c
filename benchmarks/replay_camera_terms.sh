#!/usr/bin/env bash
# Issue 22: the phase-locked image lane with and without per-camera lifts (DetectorConfig.camera_terms), beside the
# full schedule, on the drives and int8 export of benchmarks/replay_readme.sh (made here when missing): streaming mode,
# LiDAR-synchronised cameras, nuScenes rates, time scales 1 and 2, ROUNDS rounds taking turns; each run is preceded by
# the host-speed probe (2048^3 MatMul GFLOP/s: the shared machine's fast or slow state). Writes
# replay_<round>_<schedule>_terms-<on|off>_scale<S>.txt, probes_gflops.txt and table.md (two values per cell: rounds).
#   benchmarks/replay_camera_terms.sh [OUT_DIR [ROUNDS]]   (default out/replay_readme, 2 rounds: about 15 minutes)
# Run it on a quiet machine. Results: docs/replay.md, "Per-camera lifts in the runtime".
set -euo pipefail
OUT=${1:-out/replay_readme}
ROUNDS=${2:-2}
BIN=${BIN:-.venv/bin}
source "$(dirname "$0")/replay_prep.sh"  # DATA, EXPORT
uptime > "$OUT/terms_uptime_before.txt"
: > "$OUT/probes_gflops.txt"
for ROUND in $(seq 1 "$ROUNDS"); do
  for SCALE in 1 2; do
    for V in full:off phase-locked:off phase-locked:on; do
      SCHEDULE=${V%%:*}; TERMS=${V##*:}
      NAME="k${ROUND}_${SCHEDULE}_terms-${TERMS}_scale$SCALE"
      echo "$NAME $("$BIN/python" -c 'from streamdet.benchmarks.probe import measure_peak; print(max(measure_peak(2).run_gflops_per_s))')" \
        >> "$OUT/probes_gflops.txt"
      "$BIN/streamdet-replay" --data "$DATA" --split val --export-dir "$EXPORT" --precision fp32 --image-precision int8 \
        --lidar-hz 20 --slices 8 --camera-hz 12 --camera-trigger lidar-synced --mode streaming --schedule "$SCHEDULE" \
        --camera-terms "$TERMS" --time-scale "$SCALE" --json "$OUT/replay_$NAME.json" --out "$OUT/$NAME" \
        > "$OUT/replay_$NAME.txt"
    done
  done
done
uptime > "$OUT/terms_uptime_after.txt"
"$BIN/python" - "$OUT" > "$OUT/table.md" <<'PY'
import json, re, sys
from pathlib import Path
out = Path(sys.argv[1])
probes = dict(line.split() for line in (out / "probes_gflops.txt").read_text().splitlines() if line.strip())
rows = {}
for f in sorted(out.glob("k*_terms-*_scale*/replay.json")):
    r, sched, terms, scale = re.match(r"k(\d+)_(.*)_terms-(on|off)_scale(\d+)", f.parent.name).groups()
    s = json.loads(f.read_text())["modes"]["streaming"]
    rows.setdefault((scale, sched, terms), []).append((s, float(probes[f.parent.name])))
print("| scale | schedule | staleness added p50 / p95 ms | image age p95 ms | slice p99 ms | dropped of 1600 "
      "| image-lane CPU ms / rotation | streaming mAP | probe GFLOP/s |")
print("|---|---|---|---|---|---|---|---|---|")
def cells(runs, fn):
    return ", ".join(fn(s, p) for s, p in runs)


for (scale, sched, terms), runs in sorted(rows.items()):
    stale = cells(runs, lambda s, p: "%.0f / %.0f" % (s["staleness_ms"]["p50"], s["staleness_ms"]["p95"]))
    age = cells(runs, lambda s, p: "%.0f" % s["image_age_ms"]["p95"])
    p99 = cells(runs, lambda s, p: "%.1f" % s["latency_ms"]["p99"])
    dropped = cells(runs, lambda s, p: str(s["slices_dropped"]))
    cpu = cells(runs, lambda s, p: "%.1f" % s["image_lane_cpu_ms_per_rotation"])
    mean_ap = cells(runs, lambda s, p: "%.1f" % (100 * s["map_streaming"]))
    probe = cells(runs, lambda s, p: "%.0f" % p)
    label = sched + (", per-camera lifts" if terms == "on" else "")
    print(f"| {scale} | {label} | {stale} | {age} | {p99} | {dropped} | {cpu} | {mean_ap} | {probe} |")
PY
echo "wrote $OUT/table.md"
