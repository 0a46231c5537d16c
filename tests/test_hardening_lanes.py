"""Hardening of the runner's lanes (audit H3, H5, H6 runner part, M7, L3): a LiDAR rate far past any sensor's (or a
tiny period measured from a burst of submits) never makes the phase-locked lane's pass scan hang under its lock; a
done-callback that raises a BaseException never ends a worker (and a lane whose workers are gone fails its queued
jobs at close); a slice is checked (type, shape, dtype, MAX_SLICE_POINTS) before it is copied, and so is an image
set on the full schedule; numpy ints are taken as nice values. Every wait here has a timeout: a hang fails."""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
import tracemalloc
from concurrent.futures import Future
from types import SimpleNamespace

import numpy as np
import pytest

from streamdet.core import points as core_points
from streamdet.runtime_ort import lanes
from streamdet.runtime_ort.detector_results import SliceResult
from streamdet.runtime_ort.lanes import LaneConfig, StreamingRunner
from streamdet.runtime_ort.phase_lock import LIDAR_HZ_RANGE, RotationPhase, plan_lift
from streamdet.runtime_ort.phase_locked_lane import PhaseLockedImageLane
from streamdet.runtime_ort.postprocess import Detections
from streamdet.runtime_ort.thread_priority import check_nice
from streamdet.runtime_ort.worker_lane import JobBatching, WorkerLane

from thread_helpers import returns_within

WAIT_S = 10.0
CAMS = ("CAM_A", "CAM_B")


# ---- stand-ins ---------------------------------------------------------------------------------------------------
class SliceFake:
    """A StreamingDetector stand-in for the slice lane: its first slice waits for ``gate``; records every run.
    ``detect_slices`` (coalescing) only when ``joins`` is True."""

    uses_images = False
    num_slices = 8
    config = SimpleNamespace(start_deg=0.0, clockwise=False)

    def __init__(self, joins: bool = False) -> None:
        self.gate = threading.Event()
        self.started = threading.Event()
        self.runs: list[tuple[int, ...]] = []
        if joins:
            self.detect_slices = self._detect_slices

    def _hold(self) -> None:
        if not self.started.is_set():
            self.started.set()
            assert self.gate.wait(WAIT_S), "the test never opened the gate"

    def detect_slice(self, points, slice_index, timestamp=None):
        self._hold()
        self.runs.append((slice_index,))
        return _result(slice_index, timestamp, ())

    def _detect_slices(self, points, slice_indices, timestamps, num_slices=None):
        self._hold()
        ks = tuple(int(k) for k in slice_indices)
        self.runs.append(ks)
        return tuple(_result(k, t, ks) for k, t in zip(ks, timestamps))


def _result(k, t, run) -> SliceResult:
    return SliceResult(Detections.empty(), k, 8, t, None, 0, 0, 0, coalesced=run)


class ImageFake:
    """A camera + LiDAR stand-in for both image-lane schedules: two cameras of 4x6 images, every quadrant seen by
    both; records the image dicts it was asked to check and the updates it ran."""

    uses_images = True
    num_slices = 8
    camera_names = CAMS
    config = SimpleNamespace(start_deg=0.0, clockwise=False)

    def __init__(self) -> None:
        self.checked: list[object] = []
        self.updates: list[float | None] = []

    def quadrant_cameras(self, quadrants):
        return CAMS

    def check_images(self, images) -> None:
        self.checked.append(images)
        unknown = [n for n in images if n not in CAMS]
        if unknown:
            raise ValueError(f"unknown camera names {unknown}")
        for name, a in images.items():
            if not isinstance(a, np.ndarray) or a.dtype != np.uint8 or a.shape != (4, 6, 3):
                raise ValueError(f"image {name!r} must be uint8 RGB of shape (4, 6, 3), got {getattr(a, 'shape', a)}")

    def encode_images(self, images):
        return {n: np.zeros((1, 1, 1), np.float32) for n in images}

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None, camera_timestamps=None):
        self.updates.append(timestamp)
        return timestamp

    def detect_slice(self, points, slice_index, timestamp=None):
        return _result(slice_index, timestamp, ())


def _images() -> dict[str, np.ndarray]:
    return {n: np.zeros((4, 6, 3), np.uint8) for n in CAMS}


def _returns_within(fn, seconds: float = WAIT_S):
    return returns_within(fn, seconds)


def _counting_deadlines(phase: RotationPhase, most: int) -> list[int]:
    """Make ``phase.deadline_s`` count its calls and fail past ``most`` (a pass scan that walks from far away)."""
    calls = [0]
    real = phase.deadline_s

    def deadline_s(k, rotation):
        calls[0] += 1
        assert calls[0] <= most, f"the pass scan computed more than {most} deadlines"
        return real(k, rotation)

    phase.deadline_s = deadline_s  # type: ignore[method-assign]
    return calls


# ---- H3: the LiDAR rate and the pass scan ---------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [1e300, 10**400, 1e4, 100.001, 0.49, 0.0, -20.0, float("nan"), float("inf"), True, "20"])
def test_a_lidar_rate_outside_the_physical_range_is_refused(bad):
    with pytest.raises(ValueError, match=r"LaneConfig\.lidar_hz must be None or a finite rate > 0 Hz within 0\.5\.\.100 Hz") as e:
        LaneConfig(schedule="phase-locked", lidar_hz=bad)
    assert repr(bad) in str(e.value)  # the bad value is quoted
    with pytest.raises(ValueError, match=r"lidar_hz must be None or a finite rate > 0 Hz within 0\.5\.\.100 Hz"):
        RotationPhase(8, 0.0, bad)


@pytest.mark.parametrize("good", [LIDAR_HZ_RANGE[0], 20, LIDAR_HZ_RANGE[1], np.float32(10.0), np.float64(20.0), None])
def test_lidar_rates_within_the_range_are_taken(good):
    assert LaneConfig(schedule="phase-locked", lidar_hz=good).lidar_hz == good
    phase = RotationPhase(8, 0.0, good)
    if good is not None:
        assert phase.period_s == pytest.approx(1.0 / float(good))
    assert LIDAR_HZ_RANGE == (0.5, 100.0)


def _passes_from_the_anchor(phase: RotationPhase, after_s: float, count: int) -> list[tuple[float, int, int]]:
    """What passes() gave before the fix: the scan from rotation -1 (the reference)."""
    out, rotation = [], -1
    while len(out) < count:
        here = [(phase.deadline_s(k, rotation), k, q) for k, q in phase.slice_quadrants]
        out += sorted(p for p in here if p[0] > after_s)
        rotation += 1
    return out[:count]


@pytest.mark.parametrize("hz", [LIDAR_HZ_RANGE[0], 20.0, LIDAR_HZ_RANGE[1]])
def test_the_pass_scan_starts_next_to_after_and_gives_what_it_gave(hz):
    phase = RotationPhase(8, 0.0, hz)
    phase.observe(3, 10.0)
    p = phase.period_s
    afters = [10.0 - 5 * p, 10.0 - p, 10.0, 10.0 + p / 16, 10.0 + p / 8, 10.0 + 2.5 * p, 10.0 + 7 * p,
              phase.deadline_s(0, 4), phase.deadline_s(5, 2)]  # fmt: skip
    for after in afters:
        assert list(_take(phase.passes(after), 40)) == _passes_from_the_anchor(phase, after, 40), after


@pytest.mark.parametrize("hz", [LIDAR_HZ_RANGE[1], 20.0])
def test_the_pass_scan_does_not_grow_with_the_time_since_the_anchor(hz):
    """A day after the last slice (a paused LiDAR): the first pass is found in three rotations' deadlines, as a
    period after the anchor, not (day / period) rotations of them (the lane's lock is held while it scans)."""
    phase = RotationPhase(8, 0.0, hz)
    phase.observe(0, 0.0)
    per_rotation = len(phase.slice_quadrants)
    for after in (0.0, 1.0, 86_400.0, 86_400.0 * 365):
        calls = _counting_deadlines(phase, 3 * per_rotation)
        first = next(phase.passes(after))
        assert after < first[0] <= after + phase.period_s + 1e-6 * max(1.0, after)
        assert calls[0] <= 3 * per_rotation
        del phase.deadline_s  # the next round counts afresh


def test_a_plan_long_after_the_last_slice_is_short():
    """plan_lift a day after the anchor at 100 Hz, lifts of 30 ms: a few rotations of passes, not 8.6 million."""
    phase = RotationPhase(8, 0.0, LIDAR_HZ_RANGE[1])
    phase.observe(7, 5.0)
    calls = _counting_deadlines(phase, 20 * len(phase.slice_quadrants))
    plan = _returns_within(lambda: plan_lift(phase, 86_405.0, lambda q: 0.03, 0.002))
    assert plan is not None and plan.deadline_s >= 86_405.0 + 0.03
    assert calls[0] <= 20 * len(phase.slice_quadrants)


def test_a_burst_of_arrivals_is_no_rotation_period():
    """33 slices handed over microseconds apart (a driver flushing its backlog) imply a period of microseconds: not
    taken, so the lane stays unlocked (full updates) rather than planning passes microseconds apart."""
    phase = RotationPhase(8, 0.0, None)
    for i in range(33):
        phase.observe(i % 8, 100.0 + i * 1e-6)
    assert not phase.locked and np.isnan(phase.period_s)


def test_a_burst_after_the_lock_keeps_the_period_physical():
    phase = RotationPhase(8, 0.0, None)
    for i in range(24):  # three rotations at 20 Hz
        phase.observe(i % 8, i * 0.00625)
    assert phase.period_s == pytest.approx(0.05)
    for i in range(24, 24 + 64):  # then a long burst, a microsecond apart
        phase.observe(i % 8, 0.15 + i * 1e-6)
        assert 1.0 / LIDAR_HZ_RANGE[1] <= phase.period_s <= 1.0 / LIDAR_HZ_RANGE[0]
    calls = _counting_deadlines(phase, 200 * len(phase.slice_quadrants))
    plan = _returns_within(lambda: plan_lift(phase, 3600.0, lambda q: 0.5, 0.002))
    assert plan is not None and calls[0] <= 200 * len(phase.slice_quadrants)


def test_a_stalled_first_rotation_is_no_rotation_period():
    """Two arrivals 10 s apart before any lock: a 0.1 Hz LiDAR is none; the lane waits for a real measurement."""
    phase = RotationPhase(8, 0.0, None)
    phase.observe(0, 0.0)
    phase.observe(1, 10.0)  # 1/8 rotation in 10 s: 80 s a rotation
    assert not phase.locked


def test_the_phase_locked_lane_steps_quickly_a_day_after_its_last_slice():
    """The lane itself on a fake clock: one slice, images, then a step a day later at 100 Hz."""
    clock = SimpleNamespace(t=0.0)
    det = ImageFake()
    lane = PhaseLockedImageLane(det, 8, 0.0, LIDAR_HZ_RANGE[1], clock=lambda: clock.t, thread=False)
    lane.observe_slice(0, 0.0)
    fut = lane.submit_images(_images(), 0.0)
    _counting_deadlines(lane._phase, 20 * len(lane._phase.slice_quadrants))  # three steps: a few rotations each
    for now in (86_400.0, 86_400.5, 2 * 86_400.0):
        _returns_within(lambda: lane.step(now))
    assert fut.result(WAIT_S) is not None and lane.stats.quadrant_lifts >= 1
    assert lane.close()


def test_a_burst_of_submits_never_blocks_the_callers_of_a_phase_locked_runner(monkeypatch):
    """The audit's burst repro on a stand-in: 33 slices a microsecond apart, a pause, then submits return at once
    (before the fix the measured period was microseconds and every plan walked the pause in passes).

    The runner stamps arrivals with its clock (``lanes.time.monotonic``): during the burst that clock steps 1 us a
    call from the wall clock's present, so the arrivals are a burst however slowly a loaded machine runs the loop
    (on the wall clock a cold loop can take a rotation of the fastest LiDAR, and be no burst); the clock is the wall
    clock again for the pause and after."""
    det = ImageFake()
    points = np.zeros((1, 6), np.float32)
    with StreamingRunner(det, LaneConfig(schedule="phase-locked", queue_size=64)) as runner:
        ticks = iter(range(10**6))
        start = time.monotonic()
        burst_clock = SimpleNamespace(monotonic=lambda: start + next(ticks) * 1e-6, perf_counter=time.perf_counter)
        monkeypatch.setattr(lanes, "time", burst_clock)
        try:
            futures = [runner.submit_slice(points, i % 8, float(i)) for i in range(33)]
        finally:
            monkeypatch.setattr(lanes, "time", time)
        phase = runner._phase_locked._phase
        assert not phase.locked  # a burst is no rotation: no period taken from it
        time.sleep(0.3)
        images = _returns_within(lambda: runner.submit_images(_images(), 1.0), 5.0)
        _returns_within(lambda: runner.submit_slice(points, 1, 2.0), 5.0)
        # the pause after the burst is no rotation either (33 arrivals' span + the pause once made a plausible one)
        assert not phase._periods, phase._periods
        again = _returns_within(lambda: runner.submit_images(_images(), 3.0), 5.0)
        for f in futures:
            f.result(WAIT_S)
        assert _returns_within(lambda: runner.close(timeout=WAIT_S), WAIT_S + 5)
    assert images.done() and again.done()  # used, superseded, or cancelled at close: none left pending


def test_a_burst_then_a_pause_measures_no_rotation():
    """A backlog of 33 slices handed over at once, then one slice after a pause: the burst's span and the pause
    once averaged into a plausible period (0.3 s x 8 / 33), taken as a measured rotation that later medians kept. A
    rotation's worth of arrivals faster than any LiDAR is a burst: the history starts again after it."""
    phase = RotationPhase(8)
    for i in range(33):
        phase.observe(i % 8, 10.0 + i * 1e-6)
    assert not phase.locked
    phase.observe(1, 10.3)
    assert not phase._periods  # at most a provisional period, replaced by the first whole rotation measured
    for i in range(2, 2 + 16):  # then a real 20 Hz LiDAR
        phase.observe(i % 8, 10.3 + (i - 1) * 0.05 / 8)
    assert phase.period_s == pytest.approx(0.05)


# ---- H5: a done-callback's BaseException never ends a worker ------------------------------------------------------
def _gated_lane(**kw) -> tuple[WorkerLane, threading.Event, threading.Event, Future]:
    """A one-worker lane whose first job holds the worker until the gate opens."""
    lane = WorkerLane("test-lane", 1, None, **kw)
    gate, started = threading.Event(), threading.Event()

    def first():
        started.set()
        assert gate.wait(WAIT_S)
        return "first"

    fut = lane.submit(first)
    assert started.wait(WAIT_S)
    return lane, gate, started, fut


@pytest.mark.parametrize("raised", [SystemExit(3), KeyboardInterrupt(), RuntimeError("handler bug")])
def test_a_raising_done_callback_never_ends_the_worker(raised, caplog):
    lane, gate, _, first = _gated_lane()
    calls = []

    def callback(f):
        calls.append(f)
        raise raised

    first.add_done_callback(callback)
    later = [lane.submit(lambda k=k: k) for k in range(3)]
    with caplog.at_level(logging.ERROR):
        gate.set()
        assert first.result(WAIT_S) == "first" and calls == [first]
        assert [f.result(WAIT_S) for f in later] == [0, 1, 2]
    assert all(t.is_alive() for t in lane._threads)
    if not isinstance(raised, Exception):  # concurrent.futures logs an Exception itself; the lane the rest
        assert "done-callback" in caplog.text
    assert lane.close(time.monotonic() + WAIT_S)


def test_a_raising_callback_of_a_joined_run_spares_the_other_jobs():
    batch = JobBatching(joins=lambda a, b: True, run=lambda ps: [p * 10 for p in ps], most=2)
    lane, gate, _, first = _gated_lane(batch=batch)
    a, b = lane.submit(lambda: 1, payload=1), lane.submit(lambda: 2, payload=2)  # wait behind the first: one run
    a.add_done_callback(lambda f: sys.exit(3))
    gate.set()
    assert first.result(WAIT_S) == "first"
    assert a.result(WAIT_S) == 10 and b.result(WAIT_S) == 20 and lane.joined == 1
    assert lane.submit(lambda: "after").result(WAIT_S) == "after"
    assert lane.close(time.monotonic() + WAIT_S)


def test_a_jobs_own_base_exception_still_goes_to_its_future():
    lane = WorkerLane("test-lane", 1, None)
    failed = lane.submit(lambda: sys.exit(4))
    with pytest.raises(SystemExit):
        failed.result(WAIT_S)
    assert lane.submit(lambda: "next").result(WAIT_S) == "next"
    assert lane.close(time.monotonic() + WAIT_S)


def test_a_future_its_owner_finished_is_skipped_not_fatal():
    """A caller that sets the result of a future it was handed (not its to set) makes set_running_or_notify_cancel
    raise: the worker skips that job and goes on."""
    lane, gate, _, first = _gated_lane()
    ran = []
    taken = lane.submit(lambda: ran.append("taken"))
    taken.set_result("mine")
    after = lane.submit(lambda: "after")
    gate.set()
    assert first.result(WAIT_S) == "first" and after.result(WAIT_S) == "after"
    assert taken.result(0) == "mine" and ran == []
    assert lane.close(time.monotonic() + WAIT_S)


class _DeadWorkers(WorkerLane):
    """A lane whose workers end at once, as a worker killed by an error would: nobody runs its jobs."""

    def _serve(self) -> None:
        return


def test_waiting_counts_no_job_its_owner_cancelled():
    """The phase-locked lane holds back while slices wait (image_lane_yield_slices): a slice nobody waits for
    any more must not hold it back."""
    lane, gate, _, first = _gated_lane()  # the one worker is busy
    queued = [lane.submit(lambda k=k: k) for k in range(3)]
    assert lane.waiting == 3
    queued[1].cancel()
    assert lane.waiting == 2
    gate.set()
    assert first.result(WAIT_S) == "first" and [f.result(WAIT_S) for f in (queued[0], queued[2])] == [0, 2]
    assert lane.close(time.monotonic() + WAIT_S)


@pytest.mark.parametrize("deadline", [None, 0.5])
def test_close_fails_the_queued_jobs_of_a_lane_whose_workers_died(deadline):
    lane = _DeadWorkers("dead-lane", 2, None)
    for t in lane._threads:
        t.join(WAIT_S)
    waiting = [lane.submit(lambda k=k: k) for k in range(3)]
    waiting[1].cancel()  # its owner's choice stays
    done = _returns_within(lambda: lane.close(None if deadline is None else time.monotonic() + deadline))
    assert done is False  # not everything ran
    for f in (waiting[0], waiting[2]):
        with pytest.raises(RuntimeError, match="dead-lane: no worker left to run this job"):
            f.result(0)
    assert waiting[1].cancelled()


def test_the_audit_repro_a_sys_exit_in_a_slice_callback():
    """r_callback_baseexception.py on a stand-in: later slices still get their results, close() finishes."""
    det = SliceFake()
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1, coalesce_slices=1))
    points = np.zeros((2, 6), np.float32)
    first = runner.submit_slice(points, 0, 0.0)
    assert det.started.wait(WAIT_S)
    first.add_done_callback(lambda f: sys.exit(3))
    later = [runner.submit_slice(points, k, 0.0) for k in range(1, 4)]
    det.gate.set()
    assert [f.result(WAIT_S).slice_index for f in [first, *later]] == [0, 1, 2, 3]
    assert all(t.is_alive() for t in runner._slices._threads)
    assert runner.close(timeout=WAIT_S)


# ---- H6 (the runner): a slice is checked before it is copied --------------------------------------------------------
def test_the_runner_uses_the_cores_slice_limit():
    assert lanes.MAX_SLICE_POINTS is core_points.MAX_SLICE_POINTS


def test_a_huge_slice_fails_its_future_uncopied_and_unqueued():
    """10^8 rows declared through zero strides (24 real bytes, 2.2 GiB declared): refused in microseconds, no copy,
    never queued, naming the count and the limit."""
    det = SliceFake()
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1, queue_size=1))
    huge = np.broadcast_to(np.ones((1, 6), np.float32), (10**8, 6))
    tracemalloc.start()
    try:
        fut = runner.submit_slice(huge, 1, 0.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, f"submit_slice allocated {peak} bytes"
    with pytest.raises(ValueError, match=rf"100000000 points, more than MAX_SLICE_POINTS = {core_points.MAX_SLICE_POINTS}"):
        fut.result(0)
    assert runner._slices.waiting == 0 and det.runs == [] and runner.slices_dropped == 0
    assert runner.close(timeout=WAIT_S)


def test_the_slice_limit_is_inclusive(monkeypatch):
    monkeypatch.setattr(lanes, "MAX_SLICE_POINTS", 5)
    det = SliceFake()
    det.gate.set()
    with StreamingRunner(det, LaneConfig()) as runner:
        assert runner.submit_slice(np.zeros((5, 6), np.float32), 0, 0.0).result(WAIT_S).slice_index == 0
        with pytest.raises(ValueError, match="a slice of 6 points, more than MAX_SLICE_POINTS = 5"):
            runner.submit_slice(np.zeros((6, 6), np.float32), 1, 0.0).result(WAIT_S)
    assert det.runs == [(0,)]


@pytest.mark.parametrize(
    "bad, match",
    [([[0.0] * 6], r"points must be a \(N, 6\) float32 array .*got list"),
     (np.zeros(6, np.float32), r"points must be a \(N, 6\) float32 array .*got \(6,\)"),
     (np.zeros((3, 5), np.float32), r"got \(3, 5\)"), (np.zeros((2, 6, 1), np.float32), r"got \(2, 6, 1\)"),
     (np.zeros((3, 6), np.float64), "points must be float32, got float64"), (None, "got NoneType")],
)  # fmt: skip
def test_bad_points_fail_their_future_and_never_push_a_good_slice_out(bad, match):
    det = SliceFake()
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1, queue_size=1))
    good = np.zeros((2, 6), np.float32)
    first = runner.submit_slice(good, 0, 0.0)
    assert det.started.wait(WAIT_S)
    waiting = runner.submit_slice(good, 1, 0.0)  # the queue (1) is full from here on
    refused = runner.submit_slice(bad, 2, 0.0)
    with pytest.raises(ValueError, match=match):
        refused.result(0)  # failed at once, in the submit
    det.gate.set()
    assert first.result(WAIT_S).slice_index == 0 and waiting.result(WAIT_S).slice_index == 1
    assert runner.slices_dropped == 0 and det.runs == [(0,), (1,)]
    assert runner.close(timeout=WAIT_S)


def test_the_caller_may_reuse_its_buffer_after_a_checked_submit():
    det = SliceFake()
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1))
    seen = []
    det.detect_slice = lambda points, k, t=None: (seen.append(points.copy()), _result(k, t, ()))[1]
    buf = np.ones((3, 6), np.float32)
    fut = runner.submit_slice(buf, 0, 0.0)
    buf[:] = 7
    fut.result(WAIT_S)
    assert (seen[0] == 1).all()
    assert runner.close(timeout=WAIT_S)


@pytest.mark.parametrize("rows, runs", [(3, [(0,), (2,), (3,)]), (2, [(0,), (2, 3)])])
def test_a_coalesced_run_never_holds_more_than_the_limit(monkeypatch, rows, runs):
    """Two waiting slices of one quadrant join only while their points together are within MAX_SLICE_POINTS (the
    detector refuses a run past it: each slice within the limit must never fail for their sum)."""
    monkeypatch.setattr(lanes, "MAX_SLICE_POINTS", 5)
    det = SliceFake(joins=True)
    with StreamingRunner(det, LaneConfig(max_in_flight=1, coalesce_slices=2)) as runner:
        first = runner.submit_slice(np.zeros((1, 6), np.float32), 0, 0.0)
        assert det.started.wait(WAIT_S)
        a = runner.submit_slice(np.zeros((rows, 6), np.float32), 2, 0.01)
        b = runner.submit_slice(np.zeros((rows, 6), np.float32), 3, 0.02)
        det.gate.set()
        for f in (first, a, b):
            f.result(WAIT_S)
    assert det.runs == runs and runner.slices_coalesced == len(runs[-1]) - 1


def test_a_huge_slice_through_the_real_runner(tiny_export):
    from streamdet.runtime_ort.detector import StreamingDetector

    det = StreamingDetector(tiny_export)
    with StreamingRunner(det, LaneConfig()) as runner:
        huge = np.broadcast_to(np.ones((1, 6), np.float32), (core_points.MAX_SLICE_POINTS + 1, 6))
        fut = _returns_within(lambda: runner.submit_slice(huge, 1, 0.0), 5.0)
        with pytest.raises(ValueError, match=f"{core_points.MAX_SLICE_POINTS + 1} points, more than MAX_SLICE_POINTS"):
            fut.result(0)
        assert runner.submit_slice(np.zeros((4, 6), np.float32), 1, 0.0).result(60).slice_index == 1


# ---- M7: an image set is checked before it is copied, on the full schedule too ----------------------------------------
@pytest.mark.parametrize("schedule", ["full", "phase-locked"])
@pytest.mark.parametrize(
    "images, match",
    [({"CAM_X": np.zeros((2000, 2000, 3), np.uint8)}, "unknown camera names"),
     ({"CAM_A": np.zeros((2000, 2000, 3), np.uint8)}, r"must be uint8 RGB of shape \(4, 6, 3\)")],
)  # fmt: skip
def test_a_bad_image_set_raises_in_the_callers_thread_before_any_copy(schedule, images, match):
    det = ImageFake()
    with StreamingRunner(det, LaneConfig(schedule=schedule)) as runner:
        tracemalloc.start()
        try:
            with pytest.raises(ValueError, match=match):
                runner.submit_images(images, 1.0)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 1 << 20, f"submit_images allocated {peak} bytes before refusing"  # the image is 12 MB
        assert det.checked and det.checked[0] is images  # the caller's dict itself, not a copy
        ok = runner.submit_images(_images(), 2.0)
        if schedule == "full":
            assert ok.result(WAIT_S) == 2.0
    assert det.updates in ([2.0], [])  # nothing of the bad set ran; phase-locked updates need a slice's rotation


def test_a_stand_in_without_check_images_still_works_on_the_full_schedule():
    class NoCheck(ImageFake):
        check_images = None  # type: ignore[assignment]

    det = NoCheck()
    with StreamingRunner(det, LaneConfig()) as runner:
        assert runner.submit_images(_images(), 1.0).result(WAIT_S) == 1.0


def test_a_bad_image_set_through_the_real_full_schedule(tiny_export):
    from streamdet.runtime_ort.detector import StreamingDetector

    det = StreamingDetector(tiny_export)
    with StreamingRunner(det, LaneConfig(schedule="full")) as runner:
        with pytest.raises(ValueError, match="unknown camera names"):
            runner.submit_images({"NOT_A_CAMERA": np.zeros((2, 2, 3), np.uint8)}, 1.0)
        name = det.camera_names[0]
        with pytest.raises(ValueError, match=f"image '{name}' must be uint8 RGB"):
            runner.submit_images({name: np.zeros((2, 2, 3), np.uint8)}, 1.0)
        assert runner.images_superseded == 0


# ---- L3: numpy ints as nice values ------------------------------------------------------------------------------------
@pytest.mark.parametrize("nice", [np.int64(5), np.int32(0), np.uint8(19), 7])
def test_numpy_ints_are_nice_values(nice):
    got = check_nice(nice, "x")
    assert got == int(nice) and type(got) is int
    assert LaneConfig(image_lane_nice=nice).image_lane_nice == nice


@pytest.mark.parametrize("bad", [np.bool_(True), np.float64(5.0), np.int64(20), np.int64(-1), True])
def test_numpy_values_that_are_no_nice_value_are_refused(bad):
    with pytest.raises(ValueError, match=r"LaneConfig\.image_lane_nice must be an int in 0\.\.19"):
        LaneConfig(image_lane_nice=bad)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_a_numpy_nice_value_is_applied_to_the_lanes_worker():
    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    lane = WorkerLane("nice-lane", 1, None, nice=np.int64(3))
    got = lane.submit(lambda: os.getpriority(os.PRIO_PROCESS, threading.get_native_id())).result(WAIT_S)
    assert got == min(19, base + 3)
    assert lane.close(time.monotonic() + WAIT_S)


def _take(it, n):
    return [next(it) for _ in range(n)]
