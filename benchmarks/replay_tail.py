"""Where a replay's slice-latency tail comes from: queueing behind a backlog, or long runs.

    python -m streamdet.benchmarks.replay_tail OUT_DIR [--near 0.8]

Reads the ``OUT_DIR/r<round>_scale<S>_<label>/replay.json`` files of ``benchmarks/replay_ab.sh`` (streaming mode,
written with ``streamdet-replay --out``: every slice's record) and prints one row per run and drive: the slice p99
latency (last point scanned to detections, as the replay reports it), the run length (start to end) p50 / p99, and for the **tail** (the emitted slices whose latency is at least
``near`` x the drive's p99): how many, their mean wait in the queue (release to start) and mean run, the share of them
detected in a coalesced run (``LaneConfig.coalesce_slices``); and how late the player itself released slices (release
minus scan end, every slice of the drive): how many more than 10 ms late, and the most. All in drive ms, as the replay
records them (wall / time scale).
A tail of long waits and ordinary runs is a backlog (the lane short of CPU for a while); a tail of long runs is
contention inside the run. A player that released slices late was held up itself: it is one thread that sleeps until
each scan end and then submits, so the process stalled (the machine did not run it) or the submit was slow; a backlog
after such a stall is the lane catching up, not the lane's own doing. The threshold is in drive ms (10 x the time
scale in wall ms).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from streamdet.benchmarks.replay_table import streaming_runs

HEADER = ("| scale | variant | round | drive | slice p99 ms | run p50 / p99 ms | tail slices | tail wait / run ms "
          "| tail in pairs | released > 10 ms late (most ms) |")  # fmt: skip
LATE_MS = 10.0  # drive ms: a release this much after the slice's scan end means the player itself was held up


def drive_tail(recording: dict, near: float = 0.8) -> dict | None:
    """The tail figures of one recording (``Recording.to_dict``) in drive ms; None when no slice was emitted."""
    if not 0 < near <= 1:
        raise ValueError(f"near must be in (0, 1], got {near!r}")
    late = np.array([(s["release_s"] - s["scan_end_s"]) * 1e3 for s in recording["slices"]
                     if s.get("release_s") is not None and s.get("scan_end_s") is not None], dtype=np.float64)  # fmt: skip
    slices = [s for s in recording["slices"] if not s["dropped"] and s.get("emit_s") is not None]
    if not slices:
        return None

    def column(a: str, b: str) -> np.ndarray:  # (S,) drive ms from a to b (the records are in drive seconds)
        return np.array([(s[b] - s[a]) * 1e3 for s in slices], dtype=np.float64)

    latency, wait, run = column("scan_end_s", "emit_s"), column("release_s", "start_s"), column("start_s", "end_s")
    paired = np.array([s.get("coalesced", 1) > 1 for s in slices])
    p99 = float(np.percentile(latency, 99))
    tail = latency >= near * p99
    return {
        "drive": recording["drive"], "p99_ms": p99, "run_p50_ms": float(np.median(run)),
        "run_p99_ms": float(np.percentile(run, 99)), "tail": int(tail.sum()), "tail_wait_ms": float(wait[tail].mean()),
        "tail_run_ms": float(run[tail].mean()), "tail_paired": float(paired[tail].mean()),
        "released_late": int((late > LATE_MS).sum()), "release_late_max_ms": float(late.max(initial=0.0)),
    }  # fmt: skip


def table(out: Path, near: float = 0.8) -> str:
    rows = []
    for rnd, scale, label, name, mode in streaming_runs(Path(out)):
        if "recordings" not in mode:
            raise ValueError(f"{name}: its replay.json holds no streaming recordings (streamdet-replay --mode streaming --out)")
        for rec in mode["recordings"]:
            t = drive_tail(rec, near)
            if t is not None:
                rows.append(((scale, label, rnd, t["drive"]), t))
    if not rows:
        raise ValueError(f"{out} holds no r<round>_scale<S>_<label>/replay.json with emitted slices")
    lines = [f"tail: emitted slices with latency >= {near:g} x the drive's p99 (drive ms)", "", HEADER,
             "|---" * (HEADER.count("|") - 1) + "|"]  # fmt: skip
    for (scale, label, rnd, drive), t in sorted(rows):
        lines.append(f"| {scale:g} | {label} | {rnd} | {drive} | {t['p99_ms']:.1f} | {t['run_p50_ms']:.1f} / {t['run_p99_ms']:.1f} "
                     f"| {t['tail']} | {t['tail_wait_ms']:.1f} / {t['tail_run_ms']:.1f} | {100 * t['tail_paired']:.0f} % "
                     f"| {t['released_late']} ({t['release_late_max_ms']:.0f}) |")  # fmt: skip
    return "\n".join(lines)


USAGE = "usage: python -m streamdet.benchmarks.replay_tail OUT_DIR [--near 0.8]"


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if "--help" in args or "-h" in args:  # before the parsing below, which would take it for OUT_DIR
        print(f"{USAGE}\n\n{__doc__ or ''}")
        return 0
    near = 0.8
    if "--near" in args:
        i = args.index("--near")
        try:
            near = float(args[i + 1])
        except (IndexError, ValueError):
            print("replay_tail: --near needs a number in (0, 1]", file=sys.stderr)
            return 2
        del args[i : i + 2]
    if len(args) != 1:
        print(USAGE, file=sys.stderr)
        return 2
    try:
        print(table(Path(args[0]), near))
    except (ValueError, OSError, KeyError, TypeError, json.JSONDecodeError) as e:
        print(f"replay_tail: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
