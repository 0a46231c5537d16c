"""Slices held for their pair (`LaneConfig.pair_hold_load`): the policy (`PairHold`) against naive computations of
its period, load and hold, and the worker loop's hold (`WorkerLane` with `JobBatching.hold`): a holding worker gets
the job that joins it, a job that does not join or a close ends the hold, an idle worker never takes the reserved
job, and a loaded runner runs pairs."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from streamdet.runtime_ort import pair_hold
from streamdet.runtime_ort.coalesce import can_coalesce
from streamdet.runtime_ort.detector_results import SliceResult
from streamdet.runtime_ort.lanes import LaneConfig, StreamingRunner
from streamdet.runtime_ort.pair_hold import HOLD_PERIODS, MAX_HOLD_S, MIN_INTERVALS, MIN_RUNS, RELEASE_FRACTION, RUNS_KEPT, WARM_UP_RUNS, PairHold
from streamdet.runtime_ort.postprocess import Detections
from streamdet.runtime_ort.worker_lane import JobBatching, WorkerLane

WAIT_S = 30.0  # generous: the machine is shared; nothing here waits this long when it works


def _policy(load_above: float = 0.5, workers: int = 1, n: int = 8, period_s: float = 0.01, arrivals: int = 10,
            warm: bool = True) -> PairHold:  # fmt: skip
    """A policy that has seen ``arrivals`` slices ``period_s`` apart and (``warm``) its warm-up runs, long ones."""
    hold = PairHold(load_above, workers, n)
    for i in range(arrivals):
        hold.observe_arrival(100.0 + i * period_s)
    for _ in range(WARM_UP_RUNS if warm else 0):
        hold.record_run(1, 10.0)  # never counted, however long
    return hold


def _runs(hold: PairHold, wall_s: float, count: int = MIN_RUNS) -> None:
    for _ in range(count):
        hold.record_run(1, wall_s)


# ---- the policy ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_period_is_the_median_of_the_last_intervals(seed):
    rng = np.random.default_rng(seed)
    times = np.cumsum(rng.uniform(0.001, 0.02, 60))
    hold = PairHold(0.5, 1, 8)
    seen = []
    for t in times:
        hold.observe_arrival(float(t))
        seen.append(float(t))
        last = seen[-33:]  # 32 intervals
        want = None if len(last) <= MIN_INTERVALS else float(np.median(np.diff(last)))
        assert hold.period_s == want


def test_arrivals_out_of_order_or_repeated_are_ignored():
    hold = _policy(period_s=0.01)
    before = hold.period_s
    hold.observe_arrival(50.0)  # earlier than the last: another clock, ignored
    hold.observe_arrival(100.09)  # the same as the last
    assert hold.period_s == before


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("workers", [1, 2])
def test_the_load_is_the_median_cost_per_slice_of_the_recent_runs_over_the_period(seed, workers):
    rng = np.random.default_rng(seed)
    period_s = 0.01
    hold = _policy(workers=workers, period_s=period_s)
    costs = []
    for _ in range(150):
        n, wall = int(rng.integers(1, 3)), float(rng.uniform(0.001, 0.02))
        hold.record_run(n, wall)
        costs.append(wall / n)
        if len(costs) < MIN_RUNS:
            assert hold.load is None
            continue
        want = sorted(costs[-RUNS_KEPT:])  # naive median of the last RUNS_KEPT
        mid = len(want) // 2
        median = want[mid] if len(want) % 2 else (want[mid - 1] + want[mid]) / 2
        assert hold.load == pytest.approx(median / (period_s * workers), rel=1e-9)


def test_one_stalled_run_does_not_start_a_hold():
    hold = _policy(load_above=0.8, period_s=0.01)
    for _ in range(20):
        hold.record_run(1, 0.004)
    hold.record_run(1, 0.5)  # the process stalled for 0.5 s once
    assert hold.load == pytest.approx(0.4) and hold.hold_s(0, 100.0, 100.0) == 0.0


@pytest.mark.parametrize("bad", [math.nan, -1.0, math.inf])
def test_a_run_without_a_usable_time_is_not_counted(bad):
    hold = _policy()
    _runs(hold, 0.001, MIN_RUNS - 1)
    hold.record_run(1, bad)
    hold.record_run(0, 0.001)
    assert hold.load is None


def naive_hold(k: int, n: int, arrival: float, now: float, holding: bool) -> float:
    """Wait for the next slice of the quadrant: only slices with one while holding, until 1.5 periods (at most
    MAX_HOLD_S) after the first slice's arrival (period 10 ms)."""
    per_quadrant = n // 4
    has_partner = n >= 4 and per_quadrant >= 2 and (k % per_quadrant) != per_quadrant - 1
    if not has_partner or not holding:
        return 0.0
    return max(0.0, min(arrival + HOLD_PERIODS * 0.01, arrival + MAX_HOLD_S) - now)


@pytest.mark.parametrize("n", [1, 2, 4, 8, 16])
@pytest.mark.parametrize("cost_s", [0.002, 0.006, 0.02])
@pytest.mark.parametrize("late_s", [0.0, 0.004, 0.02, 0.2])
def test_hold_against_a_naive_rule(n, cost_s, late_s):
    hold = _policy(load_above=0.5, n=n, period_s=0.01)
    _runs(hold, cost_s)
    arrival = 200.0
    for k in range(n):
        want = naive_hold(k, n, arrival, arrival + late_s, cost_s / 0.01 > 0.5)
        assert hold.hold_s(k, arrival, arrival + late_s) == pytest.approx(want), (k, n)
        assert can_coalesce(k, k + 1, n) or want == 0.0


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_holding_starts_above_the_line_and_ends_below_the_release(seed):
    """A naive two-state walk over random loads: holding from a load above the line until one under half of it."""
    rng = np.random.default_rng(seed)
    hold = _policy(load_above=0.8, period_s=0.01)
    _runs(hold, 0.001)
    holding = False
    for _ in range(200):
        wall = float(rng.uniform(0.0, 0.012))
        hold.record_run(1, wall)
        load = hold.load
        holding = load > 0.8 if not holding else load >= RELEASE_FRACTION * 0.8
        assert (hold.hold_s(0, 300.0, 300.0) > 0) == holding
        assert hold.holding == holding
        assert hold.hold_s(1, 300.0, 300.0) == 0.0  # slice 1 ends its quadrant: never held


def test_no_hold_before_the_period_and_a_cost_are_known():
    hold = _policy(load_above=0.0, arrivals=MIN_INTERVALS)  # one interval short
    _runs(hold, 1.0)
    assert hold.load is None and hold.hold_s(0, 100.0, 100.0) == 0.0
    hold = _policy(load_above=0.0)
    _runs(hold, 1.0, MIN_RUNS - 1)  # one run short
    assert hold.load is None and hold.hold_s(0, 100.0, 100.0) == 0.0
    hold.record_run(1, 1.0)
    assert hold.load == pytest.approx(100.0) and hold.hold_s(0, 100.0, 100.0) > 0


def test_the_warm_up_runs_are_not_counted():
    hold = _policy(load_above=0.5, warm=False)
    _runs(hold, 1.0, WARM_UP_RUNS)  # a slow start
    assert hold.load is None and hold.hold_s(0, 100.0, 100.0) == 0.0
    _runs(hold, 0.001)
    assert hold.load == pytest.approx(0.1) and hold.hold_s(0, 100.0, 100.0) == 0.0


def test_a_long_period_holds_at_most_max_hold():
    hold = _policy(load_above=0.1, period_s=1.0)
    _runs(hold, 0.5)
    assert hold.hold_s(0, 10.0, 10.0) == pytest.approx(MAX_HOLD_S)


@pytest.mark.parametrize("bad", [-0.1, 16.5, math.nan, True, "0.5", None])
def test_pair_hold_refuses_a_bad_load(bad):
    with pytest.raises(ValueError, match="load_above"):
        PairHold(bad, 1, 8)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_pair_hold_refuses_bad_workers(bad):
    with pytest.raises(ValueError, match="workers"):
        PairHold(0.5, bad, 8)


@pytest.mark.parametrize("bad", [-0.1, 16.5, math.nan, math.inf, True, "0.7"])
def test_lane_config_refuses_a_bad_pair_hold_load(bad):
    with pytest.raises(ValueError, match="pair_hold_load"):
        LaneConfig(pair_hold_load=bad)


def test_lane_config_pair_hold_needs_coalescing():
    with pytest.raises(ValueError, match="coalesce_slices"):
        LaneConfig(pair_hold_load=0.5, coalesce_slices=1)
    assert LaneConfig(pair_hold_load=0.0).pair_hold_load == 0.0
    assert LaneConfig().pair_hold_load is None


# ---- the worker loop's hold ---------------------------------------------------------------------------------------


def _lane(workers: int, hold_s: float, most: int = 2) -> tuple[WorkerLane, list]:
    """A lane whose payloads are ints; n joins m when n == m + 1 and m is even (pairs 0-1, 2-3, ...)."""
    runs: list[tuple[int, ...]] = []
    batch = JobBatching(joins=lambda a, b: b == a + 1 and a % 2 == 0, run=lambda ps: (runs.append(tuple(ps)), ps)[1],
                        most=most, hold=lambda p: hold_s if p % 2 == 0 else 0.0)  # fmt: skip
    return WorkerLane("test", workers, None, batch=batch), runs


def _submit(lane: WorkerLane, runs: list, k: int):
    return lane.submit(lambda: runs.append((k,)) or k, payload=k)


def _wait_until(cond, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.002)


@pytest.mark.parametrize("workers", [1, 2])
def test_a_holding_worker_gets_the_job_that_joins_it(workers):
    lane, runs = _lane(workers, hold_s=WAIT_S)
    try:
        first = _submit(lane, runs, 0)
        _wait_until(lambda: lane.held == 1, "the hold")
        assert not first.done()
        second = _submit(lane, runs, 1)  # with two workers the idle one must leave it to the holder
        assert (first.result(WAIT_S), second.result(WAIT_S)) == (0, 1)
    finally:
        lane.close()
    assert runs == [(0, 1)] and lane.joined == 1 and lane.held == 1


def test_a_hold_ends_at_its_time_and_the_job_runs_alone():
    lane, runs = _lane(1, hold_s=0.05)
    try:
        t0 = time.monotonic()
        assert _submit(lane, runs, 0).result(WAIT_S) == 0
        assert time.monotonic() - t0 >= 0.05
    finally:
        lane.close()
    assert runs == [(0,)] and lane.held == 1 and lane.joined == 0


def test_a_job_that_does_not_join_ends_the_hold():
    lane, runs = _lane(1, hold_s=WAIT_S)
    try:
        first = _submit(lane, runs, 0)
        _wait_until(lambda: lane.held == 1, "the hold")
        other = _submit(lane, runs, 5)  # not 0's partner
        assert (first.result(WAIT_S), other.result(WAIT_S)) == (0, 5)
    finally:
        lane.close()
    assert runs == [(0,), (5,)]


def test_close_ends_a_hold_at_once():
    lane, runs = _lane(1, hold_s=WAIT_S)
    first = _submit(lane, runs, 0)
    _wait_until(lambda: lane.held == 1, "the hold")
    t0 = time.monotonic()
    assert lane.close(time.monotonic() + WAIT_S)
    assert first.result(0) == 0 and time.monotonic() - t0 < WAIT_S / 2
    assert runs == [(0,)]


def test_a_job_cancelled_during_its_hold_does_not_run():
    lane, runs = _lane(1, hold_s=WAIT_S)
    try:
        first = _submit(lane, runs, 0)
        _wait_until(lambda: lane.held == 1, "the hold")
        assert first.cancel()
        second = _submit(lane, runs, 1)
        assert second.result(WAIT_S) == 1
    finally:
        lane.close()
    assert runs == [(1,)]  # the run's cancelled job left out; its partner ran alone


def test_no_hold_keeps_the_free_worker_rule():
    """A hold of 0 (the policy says no): a waiting partner still does not join while another worker is free."""
    lane, runs = _lane(2, hold_s=0.0)
    gate = threading.Event()
    try:
        blocked = lane.submit(lambda: gate.wait(WAIT_S) and 9, payload=None)  # one worker busy, one free
        results = [_submit(lane, runs, k).result(WAIT_S) for k in (0, 1)]
        gate.set()
        assert blocked.result(WAIT_S) == 9 and results == [0, 1]
    finally:
        gate.set()
        lane.close()
    assert runs == [(0,), (1,)] and lane.held == 0


# ---- the runner ----------------------------------------------------------------------------------------------------


class _Config:
    start_deg = 0.0
    clockwise = False


class SlowDetector:
    """A StreamingDetector stand-in whose runs take fixed times: a single run SINGLE_S, a pair PAIR_S."""

    SINGLE_S, PAIR_S = 0.03, 0.035
    uses_images = False
    num_slices = 8
    config = _Config()

    def __init__(self) -> None:
        self.runs: list[tuple[int, ...]] = []

    def detect_slice(self, points, slice_index, timestamp=None, num_slices=None) -> SliceResult:
        time.sleep(self.SINGLE_S)
        self.runs.append((slice_index,))
        return SliceResult(Detections.empty(), slice_index, 8, timestamp, None, 0, 0, 0)

    def detect_slices(self, points, slice_indices, timestamps, num_slices=None):
        time.sleep(self.PAIR_S)
        ks = tuple(int(k) for k in slice_indices)
        self.runs.append(ks)
        return tuple(SliceResult(Detections.empty(), k, 8, t, None, 0, 0, 0, coalesced=ks) for k, t in zip(ks, timestamps))


@pytest.mark.parametrize("pair_hold_load", [None, 0.5])
def test_a_loaded_runner_runs_pairs_only_with_the_hold(pair_hold_load, monkeypatch):
    """Slices every 20 ms, runs of 30 ms alone (load 1.5): with the hold the lane runs pairs and keeps up; every
    slice gets its result either way. (No warm-up runs here, and a decision after 4 runs: a short test.)"""
    monkeypatch.setattr(pair_hold, "WARM_UP_RUNS", 0)
    monkeypatch.setattr(pair_hold, "MIN_RUNS", 4)
    det = SlowDetector()
    points = np.zeros((2, 6), np.float32)
    with StreamingRunner(det, LaneConfig(max_in_flight=1, queue_size=64, pair_hold_load=pair_hold_load)) as runner:
        futures = []
        for i in range(32):
            futures.append(runner.submit_slice(points, i % 8, 0.02 * i))
            time.sleep(0.02)
        results = [f.result(WAIT_S) for f in futures]
        load, held = runner.pair_hold_load, runner.slices_held
    assert [r.slice_index for r in results] == [i % 8 for i in range(32)]
    if pair_hold_load is None:
        assert load is None and held == 0
    else:
        assert load is not None and load > RELEASE_FRACTION * pair_hold_load  # 30 ms alone, 17.5 per slice in pairs, every 20 ms
        assert held >= 1 and any(len(run) == 2 for run in det.runs)
