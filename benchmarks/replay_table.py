"""The table of ``benchmarks/replay_ab.sh``: one row per (time scale, variant), one value per round in each cell.

    python -m streamdet.benchmarks.replay_table OUT_DIR

Reads ``OUT_DIR/r<round>_scale<S>_<label>/replay.json`` (``streamdet-replay --out``, streaming mode) and
``OUT_DIR/probes_gflops.txt`` (``<run name> <GFLOP/s>`` per line, the host-speed probe before each run).
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

RUN = re.compile(r"r(\d+)_scale([0-9.]+)_(.+)")
HEADER = ("| scale | variant | staleness added p50 / p95 ms | image age p95 ms | slice p99 ms | dropped "
          "| image-lane CPU ms / rotation | streaming mAP | probe GFLOP/s |")  # fmt: skip


def collect(out: Path) -> dict[tuple[float, str], list[tuple[int, dict, float]]]:
    """(scale, label) -> [(round, the streaming mode's summary, probe GFLOP/s)], rounds in order."""
    probes_file = out / "probes_gflops.txt"
    probes = {}
    if probes_file.is_file():
        for line in probes_file.read_text().splitlines():
            parts = line.split()
            if len(parts) == 2:
                probes[parts[0]] = float(parts[1])
    rows: dict[tuple[float, str], list[tuple[int, dict, float]]] = {}
    for f in sorted(out.glob("r*_scale*_*/replay.json")):
        m = RUN.fullmatch(f.parent.name)
        if m is None:
            continue
        modes = json.loads(f.read_text())["modes"]
        if "streaming" not in modes:
            raise ValueError(f"{f}: no streaming mode in this replay")
        key = (float(m.group(2)), m.group(3))
        rows.setdefault(key, []).append((int(m.group(1)), modes["streaming"], probes.get(f.parent.name, float("nan"))))
    for runs in rows.values():
        runs.sort(key=lambda r: r[0])
    return rows


def table(out: Path) -> str:
    rows = collect(out)
    if not rows:
        raise ValueError(f"{out}: no r<round>_scale<S>_<label>/replay.json found")
    lines = [HEADER, "|---|---|---|---|---|---|---|---|---|"]

    def cells(runs, fn) -> str:
        return ", ".join(fn(s, p) for _, s, p in runs)

    for (scale, label), runs in sorted(rows.items()):
        lines.append("| " + " | ".join([
            f"{scale:g}", label,
            cells(runs, lambda s, p: "%.0f / %.0f" % (s["staleness_ms"]["p50"], s["staleness_ms"]["p95"])),
            cells(runs, lambda s, p: "%.0f" % s["image_age_ms"]["p95"]),
            cells(runs, lambda s, p: "%.1f" % s["latency_ms"]["p99"]),
            cells(runs, lambda s, p: str(s["slices_dropped"])),
            cells(runs, lambda s, p: "%.1f" % s["image_lane_cpu_ms_per_rotation"]),
            cells(runs, lambda s, p: "%.1f" % (100 * s["map_streaming"])),
            cells(runs, lambda s, p: "%.0f" % p),
        ]) + " |")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m streamdet.benchmarks.replay_table OUT_DIR", file=sys.stderr)
        return 2
    try:
        print(table(Path(args[0])))
    except (ValueError, OSError, KeyError, json.JSONDecodeError) as e:
        print(f"replay_table: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
