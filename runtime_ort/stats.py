"""Latency statistics of named pipeline stages, safe to record from several threads at once.

Each stage keeps its most recent `capacity` durations in a fixed ring buffer, so a process that runs for
days holds a bounded amount of memory; `count` still reports every sample ever recorded.

A stage may also be told the work each run executed (``gmac``: multiply-accumulates, 1e9, at the run's real sizes);
its summary then adds the GMAC executed and the achieved GFLOP/s (2 FLOP per MAC over all its runs' time), so a
vehicle process shows throttling or a wrong thread setting as a drop in GFLOP/s.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np


class _Ring:
    def __init__(self, capacity: int) -> None:
        self.values_ms = np.zeros(capacity, np.float64)
        self.count = 0  # all samples ever recorded; the buffer holds the last min(count, capacity)
        self.total_ms = 0.0  # over all samples ever recorded
        self.gmac = 0.0  # executed by all samples that reported their work

    def add(self, ms: float, gmac: float | None = None) -> None:
        self.values_ms[self.count % self.values_ms.size] = ms
        self.count += 1
        self.total_ms += ms
        if gmac is not None:
            self.gmac += gmac

    def window(self) -> np.ndarray:
        return self.values_ms[: min(self.count, self.values_ms.size)].copy()


class LatencyStats:
    """Recorder of stage durations in milliseconds.

    >>> stats = LatencyStats()
    >>> with stats.time("pre"):
    ...     pass
    >>> stats.summary()["pre"]["count"]
    1
    """

    def __init__(self, capacity: int = 1024) -> None:  # samples kept per stage for the percentiles
        if not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"LatencyStats capacity must be a positive integer, got {capacity!r}")
        self.capacity = capacity
        self._rings: dict[str, _Ring] = {}
        self._lock = threading.Lock()

    def record(self, stage: str, duration_ms: float, gmac: float | None = None) -> None:
        """Add one duration of `stage` (and the GMAC that run executed, if known). Negative or non-finite durations
        or GMAC are a caller bug and rejected."""
        if not isinstance(stage, str) or not stage:
            raise ValueError(f"stage must be a non-empty string, got {stage!r}")
        duration_ms = float(duration_ms)
        if not (duration_ms >= 0.0 and np.isfinite(duration_ms)):
            raise ValueError(f"duration_ms of stage {stage!r} must be finite and >= 0, got {duration_ms}")
        if gmac is not None and not (float(gmac) >= 0.0 and np.isfinite(gmac)):
            raise ValueError(f"gmac of stage {stage!r} must be finite and >= 0, got {gmac}")
        with self._lock:
            ring = self._rings.get(stage)
            if ring is None:
                ring = self._rings[stage] = _Ring(self.capacity)
            ring.add(duration_ms, None if gmac is None else float(gmac))

    @contextmanager
    def time(self, stage: str, gmac: float | None = None) -> Iterator[None]:
        """Time the body with `time.perf_counter` and record it under `stage` (also when the body raises), with the
        GMAC the body executes if given."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.record(stage, (time.perf_counter() - start) * 1e3, gmac)

    def summary(self) -> dict[str, dict[str, float]]:
        """{stage: {count, p50_ms, p95_ms, mean_ms, min_ms, max_ms}} over the samples still in each buffer.

        Percentiles use numpy's default linear interpolation; `count` is the number of samples ever recorded. The
        windows are runs, not time: at the same `capacity` a stage that runs per slice covers seconds of a drive
        where one that runs per image update covers minutes, and under the phase-locked schedule the image stages
        are per quadrant lift (a few cameras, one quadrant), under ``full`` per whole image set: compare a stage
        across schedules by its work (``gmac_per_run``), not its name alone. Call ``reset`` to start a window.
        Stages told their work also get ``gmac_total`` and ``gmac_per_run`` (GMAC executed, all samples ever) and
        ``gflop_per_s`` (2 * gmac_total over the total time of all samples ever).
        """
        with self._lock:
            windows = {stage: (ring.count, ring.window()) for stage, ring in self._rings.items()}
            work = {stage: (ring.gmac, ring.total_ms) for stage, ring in self._rings.items() if ring.gmac > 0}
        out = {}
        for stage, (count, values) in windows.items():
            p50, p95 = np.percentile(values, [50, 95])
            out[stage] = {
                "count": count,
                "p50_ms": float(p50),
                "p95_ms": float(p95),
                "mean_ms": float(values.mean()),
                "min_ms": float(values.min()),
                "max_ms": float(values.max()),
            }
            if stage in work:
                gmac, total_ms = work[stage]
                out[stage]["gmac_total"] = gmac
                out[stage]["gmac_per_run"] = gmac / count
                out[stage]["gflop_per_s"] = 2.0 * gmac / (total_ms * 1e-3) if total_ms > 0 else float("nan")
        return out

    def reset(self) -> None:
        with self._lock:
            self._rings.clear()


def format_latency(summary: dict) -> str:
    """``LatencyStats.summary()`` as a table, one stage per line, the runtime's stages first."""
    order = ["pre", "slice_head", "post", "slice_total", "image_encoder", "volumetric_lifter", "image_total", "sweep_nms"]
    # GMAC per run and GFLOP/s: the work each graph executed at this run's sizes (cameras, quadrants), and its speed
    lines = [f"{'stage':<20}{'count':>7}{'p50 ms':>10}{'p95 ms':>10}{'max ms':>10}{'GMAC/run':>10}{'GFLOP/s':>10}"]
    for stage in order + sorted(set(summary) - set(order)):
        if stage in summary:
            s = summary[stage]
            work = f"{s['gmac_per_run']:>10.3f}{s['gflop_per_s']:>10.1f}" if "gflop_per_s" in s else ""
            lines.append(f"{stage:<20}{s['count']:>7}{s['p50_ms']:>10.2f}{s['p95_ms']:>10.2f}{s['max_ms']:>10.2f}{work}")
    return "\n".join(lines)
