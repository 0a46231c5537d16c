"""onnxruntime profiles (``SessionOptions.enable_profiling``) reduced to time per op type.

A profile is a JSON list of Chrome-trace events. Node events (``cat == "Node"``, names ending in ``_kernel_time``)
carry ``dur`` in microseconds and ``args.op_name``; ``model_run`` session events give each run's wall time. The
summary says where a graph's time goes, which is what a missed target must be explained with.
"""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class OpTime:
    op_type: str
    ms_per_run: float
    share: float  # of the summed kernel time
    nodes: int  # distinct nodes of this type that ran


@dataclass(frozen=True)
class ProfileSummary:
    runs: int  # model_run events in the profile
    run_ms: float  # median wall time of one run as the profiler saw it
    kernel_ms: float  # summed kernel time per run (can exceed run_ms: kernels of parallel threads are summed once each)
    ops: tuple[OpTime, ...] = field(default_factory=tuple)  # by time, largest first

    def top(self, n: int = 5) -> tuple[OpTime, ...]:
        return self.ops[:n]

    def to_dict(self, top: int | None = None) -> dict:
        ops = self.ops if top is None else self.ops[:top]
        return {
            "runs": self.runs,
            "run_ms": self.run_ms,
            "kernel_ms": self.kernel_ms,
            "ops": [{"op_type": o.op_type, "ms_per_run": o.ms_per_run, "share": o.share, "nodes": o.nodes} for o in ops],
        }

    def format(self, top: int = 5) -> str:
        return ", ".join(f"{o.op_type} {o.share:.0%} ({o.ms_per_run:.2f} ms)" for o in self.top(top))


def summarize_events(events: list[dict]) -> ProfileSummary:
    """Time per op type from the events of one profile (all of its runs; per-run figures divide by the run count)."""
    if not isinstance(events, list):
        raise ValueError(f"an onnxruntime profile is a JSON list of events, got {type(events).__name__}")
    run_us = sorted(float(e["dur"]) for e in events if e.get("cat") == "Session" and e.get("name") == "model_run")
    runs = len(run_us)
    if runs == 0:
        raise ValueError("the profile holds no model_run event: the session was never run while profiling")
    by_op: dict[str, float] = defaultdict(float)
    nodes: dict[str, set[str]] = defaultdict(set)
    for e in events:
        if e.get("cat") != "Node" or not str(e.get("name", "")).endswith("_kernel_time"):
            continue
        op = e.get("args", {}).get("op_name", "?")
        by_op[op] += float(e.get("dur", 0.0))
        nodes[op].add(e["name"])
    total_us = sum(by_op.values())
    ops = tuple(
        OpTime(op, us / runs / 1e3, us / total_us if total_us else 0.0, len(nodes[op]))
        for op, us in sorted(by_op.items(), key=lambda kv: -kv[1])
    )
    return ProfileSummary(runs=runs, run_ms=run_us[runs // 2] / 1e3, kernel_ms=total_us / runs / 1e3, ops=ops)


def summarize_profile(path: str | Path) -> ProfileSummary:
    path = Path(path)
    try:
        events = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"cannot read onnxruntime profile {path}: {e}") from None
    return summarize_events(events)
