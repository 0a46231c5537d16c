#!/usr/bin/env bash
# Per-key-frame generation time of synthetic world 1 against world 2, taking turns (issue 18's "at most 2x" target).
#
#   benchmarks/synth_generation.sh [ROUNDS] [REVISION...]
#
# Each round generates a 2-scene dataset (20 key frames, 480x270, 1 worker) with world 1 (the commit before world 2,
# cd73936^), then with each REVISION (default: the working tree), and prints one JSON line per run: wall and CPU
# seconds per key frame (CPU time is the steadier figure on a shared machine). The older revisions are exported
# with `git archive` into a scratch folder and imported ahead of the installed package via PYTHONPATH.
set -euo pipefail
ROUNDS=${1:-5}
shift || true
REVISIONS=("$@")
ROOT=$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel)
PY=${PYTHON:-$ROOT/.venv/bin/python}
SCRATCH=$(mktemp -d)
trap 'rm -rf "$SCRATCH"' EXIT

export_revision() {  # $1: revision -> prints a PYTHONPATH folder holding its streamdet package
  local src="$SCRATCH/src-$1" pkg="$SCRATCH/pkg-$1"
  mkdir -p "$src" "$pkg"
  git -C "$ROOT" archive "$1" | tar -x -C "$src"
  # the package root's folder: toplevel/ (streamdet/ in revisions before the thirty-ninth session)
  if [ -d "$src/toplevel" ]; then cp -r "$src/toplevel" "$pkg/streamdet"; else cp -r "$src/streamdet" "$pkg/streamdet"; fi
  for d in calibration core models export runtime_ort benchmarks data training evaluation studies bag replay; do
    if [ -d "$src/$d" ]; then ln -s "$src/$d" "$pkg/streamdet/$d"; fi
  done
  echo "$pkg"
}

BENCH='
import json, sys, time
from streamdet.data.synth_writer import SynthConfig, generate_dataset
import streamdet.data.synth_world as world
cpu, wall = time.process_time(), time.perf_counter()
s = generate_dataset(sys.argv[1], SynthConfig(num_scenes=2, seed=7, resolution=(480, 270)))
print(json.dumps({"label": sys.argv[2], "world": getattr(world, "WORLD_VERSION", 1), "key_frames": s.num_samples,
                  "wall_s_per_key_frame": round((time.perf_counter() - wall) / s.num_samples, 4),
                  "cpu_s_per_key_frame": round((time.process_time() - cpu) / s.num_samples, 4)}))
'
W1=$(export_revision cd73936^)
declare -A PATHS
for rev in "${REVISIONS[@]}"; do PATHS[$rev]=$(export_revision "$rev"); done
for round in $(seq "$ROUNDS"); do
  (cd "$SCRATCH" && PYTHONPATH="$W1" "$PY" -c "$BENCH" "$SCRATCH/out-$round-w1" world1)
  for rev in "${REVISIONS[@]}"; do
    (cd "$SCRATCH" && PYTHONPATH="${PATHS[$rev]}" "$PY" -c "$BENCH" "$SCRATCH/out-$round-$rev" "$rev")
  done
  if [ ${#REVISIONS[@]} -eq 0 ]; then (cd "$ROOT" && "$PY" -c "$BENCH" "$SCRATCH/out-$round-worktree" worktree); fi
  rm -rf "$SCRATCH"/out-*
done
