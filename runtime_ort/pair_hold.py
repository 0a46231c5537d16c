"""Holding a quadrant's first slice for the next one (`LaneConfig.pair_hold_load`): a loaded slice lane runs pairs.

A quadrant holds two of the eight slices of a rotation, and the slice graph reads the whole quadrant crop whatever
the sector: two slices of one quadrant detected together (runtime_ort/coalesce.py) cost little more than one, a
single graph run and one pillarisation of both slices' points (docs/replay.md, "Slices held for their pair"). Plain
coalescing only pairs slices that already wait, i.e. once the lane has fallen behind; by then the slices in the
backlog have waited, and the backlog is what sets a loaded lane's latency tail.

`PairHold` decides, for the slice a worker has just taken, whether to wait for the next slice of its quadrant
instead: only where the lane is **loaded** (running every slice alone it would be busy more than ``load_above`` of
its workers' time), only where that slice has a partner (the next slice of the same rotation and quadrant), and
for at most 1.5 slice periods after the first slice arrived (a partner that does not come, e.g. a lost packet,
costs the first slice that long, never more than `MAX_HOLD_S`). The first slice of a pair then waits about one
slice period longer; every slice runs in a lane that does about 0.6 of the work per slice, so the lane stops
queueing.

The load is measured, not configured: the slice period from the arrivals (median of the recent intervals), the cost
of a slice from the wall time of the recent runs (median; a run of n slices costs each of them 1/n of it). Medians,
because one run stalled by the rest of the process (tens of ms) must not start a hold. Holding lowers the load it
is decided on (a pair costs little more than one slice), so the hold starts above ``load_above`` and ends only below
``RELEASE_FRACTION`` of it: a lane at the line does not flip between the two ways at every run.
"""

from __future__ import annotations

import collections
import math
import threading

import numpy as np

from streamdet.runtime_ort.coalesce import can_coalesce

MAX_HOLD_S = 0.1  # the longest a slice ever waits for its partner, whatever the measured period
HOLD_PERIODS = 1.5  # a partner later than this many slice periods after the first slice's arrival is not waited for
ARRIVALS_KEPT = 33  # arrival times kept: the period is the median of the last 32 intervals
MIN_INTERVALS = 4  # intervals measured before any hold (the period must be known)
RUNS_KEPT = 64  # runs whose cost per slice is kept: the cost is their median
# the lane's first runs are not counted: they share the cores with the image lane's first full updates and
# onnxruntime's first runs, a start-up load that passes (replays on the Zen 4 guest held pairs in the first 0.2 s of
# a drive at time scale 1 and raised the slice p99 with them: docs/replay.md, "Slices held for their pair")
WARM_UP_RUNS = 64
MIN_RUNS = 16  # runs counted before any hold
# holding ends when the load falls under this fraction of load_above: pairs cost about 0.6 of two single runs per
# slice, so a lane held at a load just above the line measures about 0.6 of it and must keep holding
RELEASE_FRACTION = 0.5


class PairHold:
    """The slice lane's hold policy; thread-safe (arrivals come from the caller's thread, runs from the workers)."""

    def __init__(self, load_above: float, workers: int, num_slices: int, start_deg: float = 0.0, clockwise: bool = False) -> None:
        if isinstance(load_above, bool) or not isinstance(load_above, (int, float)) or not 0.0 <= load_above <= 16.0:
            raise ValueError(f"PairHold.load_above must be a load in [0, 16], got {load_above!r}")
        if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
            raise ValueError(f"PairHold.workers must be an int >= 1, got {workers!r}")
        self.load_above = float(load_above)
        self._workers = int(workers)
        self._n = int(num_slices)
        self._start_deg = float(start_deg)
        self._clockwise = bool(clockwise)
        self._lock = threading.Lock()
        self._arrivals: collections.deque[float] = collections.deque(maxlen=ARRIVALS_KEPT)
        self._costs: collections.deque[float] = collections.deque(maxlen=RUNS_KEPT)  # recent runs' wall time per slice
        self._runs_seen = 0
        self.holding = False  # whether slices with a partner wait for it (the load went above the line, not yet under the release)

    def observe_arrival(self, t: float) -> None:
        """A slice arrived at ``t`` (time.monotonic(), the runner's clock)."""
        with self._lock:
            if not self._arrivals or t > self._arrivals[-1]:
                self._arrivals.append(t)

    def record_run(self, num_slices: int, wall_s: float) -> None:
        """A slice-graph run of ``num_slices`` slices took ``wall_s`` seconds (release of the worker to its end)."""
        if num_slices < 1 or not math.isfinite(wall_s) or wall_s < 0:
            return
        with self._lock:
            self._runs_seen += 1
            if self._runs_seen > WARM_UP_RUNS:
                self._costs.append(wall_s / num_slices)

    @property
    def period_s(self) -> float | None:
        """The slice period: median interval of the recent arrivals; None until MIN_INTERVALS were seen."""
        with self._lock:
            return self._period_s()

    def _period_s(self) -> float | None:
        if len(self._arrivals) <= MIN_INTERVALS:
            return None
        return float(np.median(np.diff(np.asarray(self._arrivals))))

    @property
    def load(self) -> float | None:
        """The lane's measured load: the median cost of a slice over the recent runs (in pairs or alone, as they ran)
        over the slice period per worker; None until both are measured (the cost after WARM_UP_RUNS + MIN_RUNS runs)."""
        with self._lock:
            return self._load()

    def _load(self) -> float | None:
        period = self._period_s()
        if period is None or period <= 0 or len(self._costs) < MIN_RUNS:
            return None
        return float(np.median(np.asarray(self._costs))) / (period * self._workers)

    def hold_s(self, slice_index: int, arrival: float, now: float) -> float:
        """How long the worker that took slice ``slice_index`` (arrived at ``arrival``) waits for the next slice of its
        quadrant, from ``now``: 0 (run at once) where it has none or the lane is not holding. The lane starts holding
        when its load is above ``load_above`` and stops when it is below ``RELEASE_FRACTION * load_above``."""
        if not can_coalesce(slice_index, slice_index + 1, self._n, self._start_deg, self._clockwise):
            return 0.0
        with self._lock:
            load = self._load()
            if load is not None:
                self.holding = load > self.load_above or (self.holding and load >= RELEASE_FRACTION * self.load_above)
            if not self.holding:
                return 0.0
            return max(0.0, min(arrival + HOLD_PERIODS * self._period_s(), arrival + MAX_HOLD_S) - now)
