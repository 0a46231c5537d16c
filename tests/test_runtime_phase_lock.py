"""The phase-locked image lane: the rotation learnt from slice arrivals, the order and timing of quadrant lifts on a
fake clock with a fake detector, how it degrades when lifts are slow, and that the slice lane never waits for it."""

from __future__ import annotations

import math
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from streamdet.benchmarks.lane_sim import ManualClock, play_events
from streamdet.core.sectors import quadrants_of_sector
from streamdet.runtime_ort.detector import ImageUpdate
from streamdet.runtime_ort.lanes import ImagesSuperseded, LaneConfig, StreamingRunner
from streamdet.runtime_ort.phase_lock import RotationPhase, plan_lift, slice_quadrants
from streamdet.runtime_ort.phase_locked_lane import MAX_HOLD_S, YIELD_POLL_S, PhaseLockedImageLane

WAIT_S = 30.0
CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
# which cameras the bundled rig's LUT reads in each quadrant (test_runtime_quadrant_updates checks the real one)
SEES = {0: {"CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT"}, 1: {"CAM_FRONT", "CAM_FRONT_LEFT", "CAM_BACK_LEFT"},
        2: {"CAM_BACK", "CAM_BACK_LEFT"}, 3: {"CAM_BACK", "CAM_BACK_RIGHT"}}  # fmt: skip


class FakeDetector:
    """Takes ``encode_s`` per camera encoded and ``lift_s`` per quadrant lifted, on the fake clock; records lifts."""

    uses_images = True
    camera_names = CAMERAS

    def __init__(self, clock: ManualClock, encode_s: float, lift_s: float, num_slices: int = 8) -> None:
        self.clock = clock
        self.encode_s = encode_s
        self.lift_s = lift_s
        self.num_slices = num_slices
        self.config = SimpleNamespace(start_deg=0.0, clockwise=False)
        self.encoded: list[str] = []
        self.lifts: list[tuple[tuple[int, ...], float, float, float]] = []  # (quadrants, image ts, start, end)

    def quadrant_cameras(self, quadrants):
        return tuple(n for n in CAMERAS if any(n in SEES[q] for q in quadrants))

    def check_images(self, images) -> None:
        pass

    def encode_images(self, images):
        self.clock.t += self.encode_s * len(images)
        self.encoded += list(images)
        return {n: np.zeros((1, 1, 1), np.float32) for n in images}

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None):
        assert encoded is not None and set(encoded) == set(images)  # every frame reaches the lift encoded, once
        start = self.clock.t
        self.clock.t += self.lift_s * (len(quadrants) if quadrants else 4)
        self.lifts.append((tuple(quadrants) if quadrants else (0, 1, 2, 3), timestamp, start, self.clock.t))
        return ImageUpdate(timestamp, tuple(images), (), quadrants=tuple(quadrants) if quadrants else (0, 1, 2, 3))


def simulate(lift_s: float, seconds: float = 1.0, lidar_hz: float = 20.0, camera_hz: float = 12.0, n: int = 8,
             encode_s: float = 0.001, margin_s: float = 0.002, known_rate: bool = False, backlog=None, yield_at: int = 0):  # fmt: skip
    """A drive on the fake clock: slice k of rotation r arrives at (r * n + k + 1) / (n * lidar_hz), image sets at
    i / camera_hz + 0.003; the lane's step runs whenever it asked to and after every event. ``backlog``: slices
    waiting in the slice lane at a clock time (with ``yield_at``). Returns the lane, the detector, the slices
    (arrival, k, quadrants) and the image set times."""
    clock = ManualClock()
    det = FakeDetector(clock, encode_s, lift_s, n)
    waiting = None if backlog is None else (lambda: backlog(clock.t))
    lane = PhaseLockedImageLane(det, n, 0.0, lidar_hz if known_rate else None, margin_s, clock=clock, thread=False,
                                superseded=lambda: ImagesSuperseded("superseded"), backlog=waiting, yield_at=yield_at)  # fmt: skip
    slices = [((i + 1) / (n * lidar_hz), i % n) for i in range(int(seconds * lidar_hz * n))]
    images = [i / camera_hz + 0.003 for i in range(int(seconds * camera_hz))]
    events = sorted([(t, 0, k) for t, k in slices] + [(t, 1, None) for t in images])
    futures = []

    def act(t: float, kind: int, k: int | None):
        if kind == 0:
            return lambda: lane.observe_slice(k, t)
        return lambda: futures.append(lane.submit_images({c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}, t))

    play_events(lane, clock, [(t, act(t, kind, k)) for t, kind, k in events])
    return lane, det, [(t, k, quadrants_of_sector(k, n)) for t, k in slices], images, futures


def image_read(det: FakeDetector, quadrant: int, at_s: float) -> float | None:
    """Timestamp of the image BEV quadrant ``quadrant`` holds at ``at_s`` (the newest lift that ended by then)."""
    ts = [(end, ts) for qs, ts, start, end in det.lifts if quadrant in qs and end <= at_s]
    return max(ts)[1] if ts else None


# ---- the rotation ----------------------------------------------------------------------------------------------
def test_slice_quadrants_follow_the_sectors():
    assert slice_quadrants(8) == tuple((k, k // 2) for k in range(8))
    assert slice_quadrants(1) == ((0, 0), (0, 1), (0, 2), (0, 3))
    assert [q for _, q in slice_quadrants(4, 90.0)] == [1, 2, 3, 0]


@pytest.mark.parametrize("known_rate", [True, False])
def test_the_phase_predicts_the_next_arrivals(known_rate):
    phase = RotationPhase(8, 0.0, 20.0 if known_rate else None)
    assert not phase.locked
    for i in range(9):
        phase.observe(i % 8, 1.0 + i * 0.00625)
    assert phase.locked and phase.period_s == pytest.approx(0.05)
    # the anchor is slice 0 at 1.05: slice 1 next at 1.05625, slice 0 again a rotation later
    assert phase.deadline_s(1, 0) == pytest.approx(1.05625) and phase.deadline_s(0, 0) == pytest.approx(1.1)
    assert [p[1:] for p in _take(phase.passes(1.05), 3)] == [(1, 0), (2, 1), (3, 1)]


def _take(it, n):
    return [next(it) for _ in range(n)]


def test_a_pause_and_late_arrivals_do_not_move_the_period():
    phase = RotationPhase(8, 0.0, None)
    for i in range(16):
        phase.observe(i % 8, i * 0.00625)
    phase.observe(0, 5.0)  # the sensor paused for seconds: no period of 40 s
    phase.observe(1, 4.0)  # an arrival older than the anchor is ignored
    assert phase.period_s == pytest.approx(0.05)


@pytest.mark.parametrize("n, slow_hz", [(4, 5.0), (8, 4.0), (8, 2.0), (16, 1.0)])
def test_a_lidar_that_turns_far_slower_is_learnt_again(n, slow_hz):
    """More than 1 + n / 2 times slower, every step looks like a pause: a rotation's worth of them in a row drops the
    old period, and the new one is learnt (the review found 20 -> 4 Hz at 8 slices kept 20 Hz for good)."""
    phase = RotationPhase(n, 0.0, None)
    t = 0.0
    for i in range(3 * n):  # 20 Hz
        t += 0.05 / n
        phase.observe(i % n, t)
    assert phase.period_s == pytest.approx(0.05)
    for i in range(4 * n):  # then slow_hz
        t += 1.0 / slow_hz / n
        phase.observe(i % n, t)
    assert phase.period_s == pytest.approx(1.0 / slow_hz)
    fixed = RotationPhase(n, 0.0, 20.0)  # a rate the caller gave is kept
    for i in range(4 * n):
        fixed.observe(i % n, (i + 1) / slow_hz / n)
    assert fixed.period_s == pytest.approx(0.05)


def test_single_pauses_keep_the_period():
    """A pause now and then (fewer than a rotation's worth in a row) is a pause: the period stays."""
    phase = RotationPhase(8, 0.0, None)
    t, k = 0.0, 0
    for rotation in range(6):
        for _ in range(8):
            t += 0.05 / 8
            phase.observe(k % 8, t)
            k += 1
        t += 1.0  # the driver stalls a second after every rotation
    assert phase.period_s == pytest.approx(0.05)


def _arrivals(n: int, rotations: int, period_s: float, swap=(), resend=(), jitter_s: float = 0.0, seed: int = 0):
    """(slice index, arrival s) of a LiDAR with ``n`` slices: ``swap`` holds the slice numbers (counted over the
    drive) that arrive just after their successor, ``resend`` those that arrive twice (again 1 ms later)."""
    rng = np.random.default_rng(seed)
    out = [(i % n, (i + 1) * period_s / n + rng.uniform(0, jitter_s)) for i in range(rotations * n)]
    for i in sorted(swap):
        if i + 1 < len(out):
            (k0, t0), (k1, _) = out[i], out[i + 1]
            out[i], out[i + 1] = (k1, t0), (k0, t0 + 1e-4)  # the next slice first, this one right after it
    for i in sorted(resend, reverse=True):
        out.insert(i + 1, (out[i][0], out[i][1] + 1e-3))
    return out


# with 2 slices a steady swap is each slice half a rotation late (a burst of a whole rotation), not a reorder
@pytest.mark.parametrize("n, pattern", [(n, p) for n in (1, 2, 4, 8, 16)
                                        for p in ("steady swap", "one swap", "one resend", "resend each rotation")
                                        if not (p == "steady swap" and n <= 2)])  # fmt: skip
def test_reordered_and_resent_slices_do_not_shrink_the_period(n, pattern):
    """A driver handing over slices out of order, or a slice twice: read as steps forward, they counted rotations
    that never passed (a steady swap of slices 2 / 3 learnt a quarter of the period)."""
    period = 0.1
    rotations = 12
    swap = {"steady swap": range(2 % n, rotations * n, n), "one swap": [n + 1]}.get(pattern, ()) if n > 1 else ()
    resend = {"one resend": [n + 2], "resend each rotation": range(n - 1, rotations * n, n)}.get(pattern, ())
    phase = RotationPhase(n, 0.0, None)
    taken = [phase.observe(k, t) for k, t in _arrivals(n, rotations, period, swap, resend)]
    assert phase.period_s == pytest.approx(period, rel=0.02)
    assert taken.count(False) == len(swap) + len(resend)  # each late or repeated slice, and nothing else


def test_the_period_holds_at_every_arrival_through_reordering():
    phase = RotationPhase(8, 0.0, None)
    arrivals = _arrivals(8, 10, 0.1, swap=[10, 27, 43], resend=[20, 50], jitter_s=1e-3, seed=3)
    periods = []
    for k, t in arrivals:
        phase.observe(k, t)
        periods.append(phase.period_s)
    known = [p for p in periods if math.isfinite(p)]
    assert known and min(known) > 0.09 and max(known) < 0.11


def test_the_lane_counts_slices_out_of_order():
    clock = ManualClock()
    lane = PhaseLockedImageLane(FakeDetector(clock, 0.001, 0.001, 8), 8, 0.0, None, 0.002, clock=clock, thread=False,
                                superseded=lambda: ImagesSuperseded("superseded"))  # fmt: skip
    for k, t in _arrivals(8, 6, 0.1, swap=[10, 30], resend=[20]):
        lane.observe_slice(k, t)
    assert lane.stats.slices_out_of_order == 3 and lane._phase.period_s == pytest.approx(0.1, rel=0.02)


def test_the_worker_counts_and_logs_a_step_that_raises_and_goes_on(caplog):
    """An encode ahead of its lift, or the planning, completes no future: its error was dropped without a trace."""
    lane = PhaseLockedImageLane(FakeDetector(ManualClock(), 0.001, 0.001, 8), 8, 0.0, None, 0.002,
                                superseded=lambda: ImagesSuperseded("superseded"))  # fmt: skip
    real_step, calls = lane.step, []

    def step(now_s):
        calls.append(now_s)
        if len(calls) <= 3:
            raise RuntimeError(f"onnxruntime failed ({len(calls)})")
        return real_step(now_s)

    lane.step = step
    try:
        with caplog.at_level("ERROR", logger="streamdet.runtime_ort.phase_locked_lane"):
            for k in range(4):
                lane.observe_slice(k, time.monotonic())  # each wakes the worker
                deadline = time.monotonic() + 5
                while len(calls) <= k and time.monotonic() < deadline:
                    time.sleep(0.001)
    finally:
        lane.close()
    assert lane.stats.errors == 3 and len(calls) >= 4  # it went on after each
    records = [r for r in caplog.records if "phase-locked schedule raised" in r.getMessage()]
    assert len(records) == 1 and "onnxruntime failed (1)" in str(records[0].exc_info[1])  # the first; then rate-limited


@pytest.mark.parametrize("n", [4, 8])
def test_a_step_of_more_than_half_a_rotation_at_its_pace_is_taken(n):
    """Slices lost on the way: a step forward of most of a rotation, arriving when it should, is not a late slice."""
    period = 0.1
    phase = RotationPhase(n, 0.0, None)
    step = n // 2 + 1  # every arrival steps past half a rotation
    t = 0.0
    for i in range(4 * n):
        t += period * step / n
        assert phase.observe((i * step) % n, t)
    assert phase.period_s == pytest.approx(period)
    phase.observe(0, t + 3.0)  # after a pause of seconds, a step behind is a step forward: taken
    assert phase._anchor == (0, t + 3.0)


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), "20"])
def test_a_bad_lidar_rate_is_refused(bad):
    with pytest.raises(ValueError, match="lidar_hz must be None or a finite rate > 0 Hz"):
        RotationPhase(8, 0.0, bad)


def test_the_plan_starts_as_late_as_possible_and_skips_what_cannot_finish():
    phase = RotationPhase(8, 0.0, 20.0)
    phase.observe(7, 0.0)  # slice 0 next at 6.25 ms
    plan = plan_lift(phase, 0.0, lambda q: 0.003, 0.001)
    assert (plan.slice_index, plan.quadrant) == (0, 0) and plan.start_s == pytest.approx(0.00625 - 0.004)
    slow = plan_lift(phase, 0.0, lambda q: 0.010, 0.001)  # slice 0 comes too soon for a 10 ms lift, slice 1 not
    assert (slow.slice_index, slow.quadrant) == (1, 0) and slow.start_s == pytest.approx(0.0125 - 0.011)
    assert [(k, q) for _, k, q in slow.skipped] == [(0, 0)]
    slower = plan_lift(phase, 0.0, lambda q: 0.013, 0.001)
    assert (slower.slice_index, slower.quadrant) == (2, 1) and slower.start_s == pytest.approx(0.01875 - 0.014)
    assert [(k, q) for _, k, q in slower.skipped] == [(0, 0), (1, 0)]
    done = [(plan.deadline_s, 0, 0)]
    after = plan_lift(phase, 0.0, lambda q: 0.003, 0.001, done, wanted=lambda q: q != 1)
    assert (after.slice_index, after.quadrant) == (1, 0)  # the same quadrant's next slice; quadrant 1 not wanted
    assert plan_lift(phase, 0.0, lambda q: 0.003, 0.001, wanted=lambda q: False) is None


def test_a_pass_the_newest_frames_cannot_make_is_planned_with_the_ready_ones():
    phase = RotationPhase(8, 0.0, 20.0)
    phase.observe(7, 0.0)  # slice 0 next at 6.25 ms, slice 1 at 12.5 ms
    ready = plan_lift(phase, 0.0, lambda q: 0.010, 0.001, ready_s=lambda q: 0.003)
    assert (ready.slice_index, ready.quadrant, ready.ready) == (0, 0, True)  # not skipped: lifted from what is ready
    assert ready.start_s == pytest.approx(0.00625 - 0.004) and ready.skipped == ()
    newest = plan_lift(phase, 0.0, lambda q: 0.003, 0.001, ready_s=lambda q: 0.001)
    assert not newest.ready  # the newest frames make it: never the ready ones
    none = plan_lift(phase, 0.0, lambda q: 0.010, 0.001, ready_s=lambda q: None)
    assert (none.slice_index, none.ready) == (1, False) and [(k, q) for _, k, q in none.skipped] == [(0, 0)]
    both_late = plan_lift(phase, 0.0, lambda q: 0.010, 0.001, ready_s=lambda q: 0.008)
    assert (both_late.slice_index, both_late.ready) == (1, False)  # slice 1 takes the newest frames again
    target = plan_lift(phase, 0.0, lambda q: 0.010, 0.001, target=0, ready_s=lambda q: 0.003)
    assert target.ready and target.start_s == 0.0  # a quadrant overdue starts at once


# ---- the lane on a fake clock ----------------------------------------------------------------------------------
@pytest.mark.parametrize("known_rate", [True, False])
def test_fast_lifts_follow_the_lidar_and_add_no_staleness(known_rate):
    lane, det, slices, images, futures = simulate(lift_s=0.002, known_rate=known_rate)
    # a pass whose frames arrive less than a lift before its slice is skipped (the slice's scan had started: it
    # adds no staleness, checked below); no lift ends late
    assert lane.stats.full_updates >= 1 and lane.stats.late_lifts == 0
    quadrant_lifts = [(qs[0], end) for qs, ts, start, end in det.lifts if len(qs) == 1]
    assert len(quadrant_lifts) == lane.stats.quadrant_lifts > 0
    # in LiDAR order: the slices each lift is for (the first of its quadrant after it) come in scan order, and a
    # lift is for the slice right after it, not one a rotation later
    served = [min(t for t, k, qs in slices if q in qs and t >= end) for q, end in quadrant_lifts]
    assert served == sorted(served)
    assert all(s - end < 0.05 / 4 for s, (q, end) in zip(served, quadrant_lifts))
    # once locked (from the third rotation on), every slice reads at least the newest images that had arrived by its
    # scan start: the phase-locked schedule adds no staleness when lifts are fast
    period = 0.05
    for t, k, (q,) in slices:
        if t < 3 * period:
            continue
        scan_start = t - period / 8
        newest = max(i for i in images if i <= scan_start)
        assert image_read(det, q, t) >= newest, (t, k, q)  # newer still when frames came during the scan
    # every camera frame encoded once; every image set used (none superseded: each lift takes the newest)
    assert len(det.encoded) == len(images) * len(CAMERAS)
    assert all(f.done() and not f.exception() for f in futures[:-1])


def test_each_quadrant_is_lifted_at_most_once_per_new_frame():
    lane, det, slices, images, _ = simulate(lift_s=0.002, seconds=2.0)
    for q in range(4):
        stamps = [ts for qs, ts, *_ in det.lifts if qs == (q,)]
        assert len(stamps) == len(set(stamps))  # never the same frames twice
    # the phase-locked lane lifts no more quadrants than the full schedule would (4 per image set)
    assert sum(len(qs) for qs, *_ in det.lifts) <= 4 * len(images)


def test_slow_lifts_skip_quadrants_in_time_order_and_never_finish_late():
    lift_s = 0.030  # longer than a quadrant's 12.5 ms: not every quadrant can be lifted every rotation
    lane, det, slices, images, futures = simulate(lift_s=lift_s, seconds=2.0, known_rate=True, encode_s=0.0)
    assert lane.stats.quadrants_skipped > 0
    assert lane.stats.late_lifts == 0  # the fake lifts take exactly what was measured: every planned one fits
    ends = [end for *_, end in det.lifts]
    starts = [start for *_, start, _ in det.lifts]
    assert all(s >= e - 1e-12 for s, e in zip(starts[1:], ends))  # one at a time
    # every quadrant still gets lifted and none starves: a quadrant that waited a rotation is lifted next, at once
    ends = {q: [end for qs, ts, start, end in det.lifts if qs == (q,)] for q in range(4)}
    assert all(len(e) > 5 and max(b - a for a, b in zip(e, e[1:])) <= 8 * lift_s for e in ends.values())
    busy = sum(end - start for qs, ts, start, end in det.lifts if len(qs) == 1)
    assert busy > 0.9 * (det.lifts[-1][3] - det.lifts[1][2])  # saturated: it never idles


def test_before_the_rotation_is_known_every_image_set_is_a_full_update():
    clock = ManualClock()
    det = FakeDetector(clock, 0.0, 0.001)
    lane = PhaseLockedImageLane(det, 8, clock=clock, thread=False)
    images = {c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}
    f1 = lane.submit_images(images, 1.0)
    assert lane.step(0.0) == 0.0 and det.lifts[-1][0] == (0, 1, 2, 3) and f1.result(0).quadrants == (0, 1, 2, 3)
    assert lane.step(0.0) is None  # nothing new
    lane.observe_slice(0, 0.01)
    assert lane.step(0.01) is None  # one arrival is no period yet, and nothing new to lift anyway
    assert lane.stats.full_updates == 1


def test_an_image_set_replaced_before_any_lift_is_superseded():
    clock = ManualClock()
    det = FakeDetector(clock, 0.0, 0.001)
    lane = PhaseLockedImageLane(det, 8, lidar_hz=20.0, clock=clock, thread=False,
                                superseded=lambda: ImagesSuperseded("superseded"))  # fmt: skip
    lane.observe_slice(7, 0.0)
    images = {c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}
    old = lane.submit_images(images, 1.0)
    new = lane.submit_images(images, 2.0)
    with pytest.raises(ImagesSuperseded):
        old.result(0)
    assert lane.images_superseded == 1 and not new.done()
    wake = lane.step(0.0)
    while wake == clock.t:  # the frames are encoded ahead of their lift, one per step
        wake = lane.step(clock.t)
    assert wake > 0.0 and not det.lifts  # too early: the first pass (slice 0 at 6.25 ms) starts later
    assert lane.stats.encoded_ahead == len(CAMERAS) and not new.done()  # encoding ahead uses no image set
    clock.t = wake
    lane.step(wake)
    assert new.result(0).quadrants == (0,) and det.lifts[-1][1] == 2.0


def test_frames_are_encoded_ahead_of_their_lifts_each_once():
    lane, det, *_ = simulate(lift_s=0.005, encode_s=0.002, known_rate=True)
    assert 0 < lane.stats.encoded_ahead <= lane.stats.cameras_encoded == len(det.encoded)
    assert lane.stats.quadrant_lifts > 0  # and every lift got its frames encoded (FakeDetector.update_images asserts)


# ---- the runner ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "field, bad, match",
    [("schedule", "phase", "schedule must be one of"), ("lidar_hz", 0.0, "lidar_hz must be None or a finite rate"),
     ("lidar_hz", True, "lidar_hz"), ("lift_margin_ms", -1.0, "lift_margin_ms must be"),
     ("lift_margin_ms", float("nan"), "lift_margin_ms")],
)  # fmt: skip
def test_lane_config_refuses_bad_schedule_fields(field, bad, match):
    with pytest.raises(ValueError, match=match):
        LaneConfig(**{field: bad})
    assert LaneConfig().schedule == "full"


class GatedImageDetector(FakeDetector):
    """Its image lane blocks until the gate opens; slices are instant."""

    def __init__(self) -> None:
        super().__init__(ManualClock(), 0.0, 0.0)
        self.gate = threading.Event()
        self.entered = threading.Event()

    def encode_images(self, images):
        self.entered.set()
        assert self.gate.wait(WAIT_S)
        return super().encode_images(images)

    def detect_slice(self, points, slice_index, timestamp=None):
        return SimpleNamespace(slice_index=slice_index, timestamp=timestamp)


def test_the_slice_lane_never_waits_for_a_stuck_phase_locked_image_lane():
    det = GatedImageDetector()
    runner = StreamingRunner(det, LaneConfig(queue_size=32, schedule="phase-locked", lidar_hz=20.0))  # type: ignore[arg-type]
    try:
        runner.submit_images({c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}, 0.0)
        assert det.entered.wait(WAIT_S)  # the image lane is stuck in an update
        futures = [runner.submit_slice(np.zeros((0, 6), np.float32), k % 8, float(k)) for k in range(16)]
        assert [f.result(WAIT_S).slice_index for f in futures] == [k % 8 for k in range(16)]
        assert runner.slices_dropped == 0
    finally:
        det.gate.set()
        runner.close(WAIT_S)


def test_a_phase_locked_runner_ends_with_the_full_update_bev(tiny_export):
    """A real export, a slow rotation (5 Hz) and one image set: every quadrant gets lifted (however long the first
    runs take on a busy machine), the cached BEV is then the full update's, and slices report the age of what they
    read."""
    from streamdet.core.slicing import split_sweep
    from streamdet.data.sample import load_bundled_sample
    from streamdet.runtime_ort.detector import StreamingDetector

    det = StreamingDetector(tiny_export)
    full = StreamingDetector(tiny_export)
    rng = np.random.default_rng(0)
    images = {n: rng.integers(0, 256, (det.image.height, det.image.width, 3), dtype=np.uint8) for n in det.camera_names}
    full.update_images(images, timestamp=0.5)
    points = split_sweep(load_bundled_sample().points, det.num_slices)
    runner = StreamingRunner(det, LaneConfig(schedule="phase-locked", lidar_hz=5.0))
    try:
        t0 = time.monotonic()
        runner.submit_slice(points[7], 7, t0)  # anchors the phase: slice 0 next
        fut = runner.submit_images(images, 0.5)
        i = 0
        while det.image_timestamps != (0.5,) * 4 and time.monotonic() < t0 + WAIT_S:  # rotations of 200 ms
            time.sleep(max(0.0, t0 + (i + 1) * 0.025 - time.monotonic()))
            runner.submit_slice(points[i % 8], i % 8, 1.0 + i).result(WAIT_S)
            i += 1
        assert fut.result(WAIT_S).timestamp == 0.5
        late = [runner.submit_slice(points[k], k, 100.0 + k).result(WAIT_S) for k in range(8)]
    finally:
        runner.close(WAIT_S)
    assert det.image_timestamps == (0.5, 0.5, 0.5, 0.5)
    np.testing.assert_allclose(det.image_state.bev, full.image_state.bev, rtol=0, atol=1e-6)
    assert all(r.image_timestamp == 0.5 and r.image_age_s == pytest.approx(r.timestamp - 0.5) for r in late)
    assert runner.phase_lock.quadrant_lifts + runner.phase_lock.full_updates >= 1
    assert runner.image_lane_cpu_s > 0.0


def test_an_image_set_replaced_while_a_lift_uses_it_still_gets_that_lift():
    """The frames of set A are replaced by set B during A's lift (the driver's thread): A's future holds the lift's
    ImageUpdate, not ImagesSuperseded, and nothing fails."""
    clock = ManualClock()
    images = {c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}

    class Replacing(FakeDetector):
        def update_images(self, imgs, timestamp=None, quadrants=None, encoded=None):
            if timestamp == 1.0:
                self.later = lane.submit_images(images, 2.0)  # arrives mid-lift
            return super().update_images(imgs, timestamp, quadrants, encoded)

    det = Replacing(clock, 0.0, 0.001)
    lane = PhaseLockedImageLane(det, 8, lidar_hz=20.0, clock=clock, thread=False,
                                superseded=lambda: ImagesSuperseded("superseded"))  # fmt: skip
    first = lane.submit_images(images, 1.0)
    assert lane.step(0.0) == 0.0  # not locked: a full update of set A
    assert first.result(0).timestamp == 1.0 and lane.images_superseded == 0 and not det.later.done()


def test_slices_handed_over_in_bursts_still_give_the_rotation_period():
    """A busy driver hands over slices late and then several at once: the period stays the rotation's."""
    phase = RotationPhase(8, 0.0, None)
    rng = np.random.default_rng(0)
    for i in range(64):
        release = (i + 1) * 0.00625
        burst_end = (i // 4 + 1) * 4 * 0.00625  # four slices at a time, at the last one's release
        phase.observe(i % 8, max(release, burst_end) + rng.uniform(0, 1e-4))
    assert phase.period_s == pytest.approx(0.05, rel=0.1)


def test_close_cancels_image_sets_no_lift_used_and_refuses_later_submits():
    from streamdet.runtime_ort.lanes import RunnerClosed

    clock = ManualClock()
    lane = PhaseLockedImageLane(FakeDetector(clock, 0.0, 0.001), 8, lidar_hz=20.0, clock=clock, thread=False,
                                closed=lambda: RunnerClosed("closed"))  # fmt: skip
    waiting = lane.submit_images({c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}, 1.0)
    assert lane.close() and waiting.cancelled()
    with pytest.raises(RunnerClosed):
        lane.submit_images({"CAM_FRONT": np.zeros((2, 2, 3), np.uint8)}, 2.0)


# ---- holding back for a backlog of slices (LaneConfig.image_lane_yield_slices) -----------------------------------
@pytest.mark.parametrize("yield_at", [1, 3])
def test_a_backlog_of_slices_holds_back_encodes_and_lifts_then_the_lane_catches_up(yield_at):
    clock = ManualClock()
    det = FakeDetector(clock, 0.001, 0.002)
    waiting = [yield_at]
    lane = PhaseLockedImageLane(det, 8, lidar_hz=20.0, clock=clock, thread=False, backlog=lambda: waiting[0], yield_at=yield_at)
    lane.observe_slice(7, 0.0)  # slice 0 next at 6.25 ms
    future = lane.submit_images({c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}, 0.0)
    assert lane.step(0.0) == pytest.approx(YIELD_POLL_S) and not det.encoded and not det.lifts  # nothing started
    clock.t = 0.0005
    assert lane.step(clock.t) == pytest.approx(0.0005 + YIELD_POLL_S)
    assert lane.stats.yields == 1 and lane.stats.yielded_ms == 0.0  # one episode, still open
    waiting[0] = yield_at - 1  # fewer than yield_at: the lane goes on
    clock.t = 0.001
    while not det.lifts:
        wake = lane.step(clock.t)
        clock.t = max(clock.t, wake)
    assert lane.stats.yields == 1 and lane.stats.yielded_ms == pytest.approx(1.0)
    assert det.lifts[0][0] == (0,) and future.result(0).quadrants == (0,)


def test_before_the_lock_a_backlog_holds_back_the_full_update_too():
    clock = ManualClock()
    det = FakeDetector(clock, 0.0, 0.001)
    waiting = [2]
    lane = PhaseLockedImageLane(det, 8, clock=clock, thread=False, backlog=lambda: waiting[0], yield_at=2)
    lane.submit_images({c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}, 1.0)
    assert lane.step(0.0) == pytest.approx(YIELD_POLL_S) and not det.lifts
    waiting[0] = 0
    assert lane.step(0.002) == 0.002 and det.lifts[-1][0] == (0, 1, 2, 3)
    assert lane.stats.full_updates == 1 and lane.stats.yielded_ms == pytest.approx(2.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_no_update_starts_during_a_backlog_and_freshness_returns_after_it(seed):
    """Random windows of waiting slices on the fake clock: no encode or lift starts inside one, passes that could not
    be made are skipped (more than without the windows), and a rotation after the last window every slice reads the
    newest images again (fast lifts)."""
    rng = np.random.default_rng(seed)
    starts = np.sort(rng.uniform(0.2, 1.2, 4))
    windows = [(a, a + rng.uniform(0.01, 0.06)) for a in starts]
    backlog = lambda t: 2 if any(a <= t < b for a, b in windows) else 0  # noqa: E731
    base, *_ = simulate(lift_s=0.002, seconds=2.0, known_rate=True)
    lane, det, slices, images, _ = simulate(lift_s=0.002, seconds=2.0, known_rate=True, backlog=backlog, yield_at=2)
    assert all(backlog(start) == 0 for _, _, start, _ in det.lifts)
    assert lane.stats.yields >= 1 and lane.stats.yielded_ms > 0
    assert lane.stats.quadrants_skipped >= base.stats.quadrants_skipped and lane.stats.late_lifts == 0
    period = 0.05
    last = max(b for _, b in windows)
    for t, k, (q,) in slices:
        if t < last + period:
            continue
        newest = max(i for i in images if i <= t - period / 8)
        assert image_read(det, q, t) >= newest, (t, k, q)


def test_a_backlog_that_never_drains_still_leaves_the_images_half_the_time():
    lane, det, *_ = simulate(lift_s=0.002, seconds=2.0, known_rate=True, backlog=lambda t: 5, yield_at=1)
    base, base_det, *_ = simulate(lift_s=0.002, seconds=2.0, known_rate=True)
    period = 0.05
    # a cut comes after MAX_HOLD_S of holding back and is followed by MAX_HOLD_S without: at most one per 2 x MAX_HOLD_S
    assert 0 < lane.stats.holds_cut <= 2.0 / (2 * MAX_HOLD_S) + 1 and lane.stats.yields >= lane.stats.holds_cut
    assert lane.stats.yielded_ms <= 0.6 * 2000  # held back about half of the drive at most
    for q in range(4):  # every quadrant is still refreshed, at least 40 % as often as without the backlog
        ends = [end for qs, _, _, end in det.lifts if q in qs]
        base_lifts = len([1 for qs, *_ in base_det.lifts if q in qs])
        assert base_lifts > 0 and len(ends) >= 0.4 * base_lifts  # the run without a backlog lifts q too
        assert max(b - a for a, b in zip(ends, ends[1:])) <= 2 * MAX_HOLD_S + 2 * period


@pytest.mark.parametrize("bad", [-1, True, 1.5, 2000])
def test_lane_config_refuses_a_bad_yield_and_a_yield_without_the_phase_locked_schedule(bad):
    with pytest.raises(ValueError, match="image_lane_yield_slices"):
        LaneConfig(schedule="phase-locked", image_lane_yield_slices=bad)
    with pytest.raises(ValueError, match="needs schedule='phase-locked'"):
        LaneConfig(image_lane_yield_slices=2)
    assert LaneConfig().image_lane_yield_slices == 0
    with pytest.raises(ValueError, match="needs a backlog"):
        PhaseLockedImageLane(FakeDetector(ManualClock(), 0.0, 0.0), 8, thread=False, yield_at=1)
    with pytest.raises(ValueError, match="yield_at must be an int"):
        PhaseLockedImageLane(FakeDetector(ManualClock(), 0.0, 0.0), 8, thread=False, backlog=lambda: 0, yield_at=-1)


class BlockingSliceDetector(FakeDetector):
    """Slices block until their gate opens; the image lane records when it starts encoding."""

    def __init__(self) -> None:
        super().__init__(ManualClock(), 0.0, 0.0)
        self.slice_gate = threading.Event()
        self.encoding = threading.Event()

    def encode_images(self, images):
        self.encoding.set()
        return super().encode_images(images)

    def detect_slice(self, points, slice_index, timestamp=None):
        assert self.slice_gate.wait(WAIT_S)
        return SimpleNamespace(slice_index=slice_index, timestamp=timestamp)


def test_a_runner_image_lane_waits_while_slices_queue_and_works_once_they_drain():
    det = BlockingSliceDetector()
    config = LaneConfig(max_in_flight=1, queue_size=8, schedule="phase-locked", image_lane_yield_slices=2)
    runner = StreamingRunner(det, config)  # type: ignore[arg-type]
    try:
        futures = [runner.submit_slice(np.zeros((0, 6), np.float32), k, float(k)) for k in range(3)]  # 1 runs, 2 wait
        deadline = time.monotonic() + WAIT_S
        while runner._slices.waiting < 2:  # the first slice reaches its worker
            assert time.monotonic() < deadline
            time.sleep(0.001)
        update = runner.submit_images({c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}, 0.0)
        assert not det.encoding.wait(0.5 * MAX_HOLD_S)  # held back while two slices wait (a hold lasts 0.1 s)
        det.slice_gate.set()
        assert [f.result(WAIT_S).slice_index for f in futures] == [0, 1, 2]
        assert det.encoding.wait(WAIT_S) and isinstance(update.result(WAIT_S), ImageUpdate)
        assert runner.phase_lock.yields >= 1 and runner.slices_dropped == 0
    finally:
        det.slice_gate.set()
        runner.close(WAIT_S)


def test_worker_lane_waiting_counts_jobs_beyond_those_running():
    from streamdet.runtime_ort.lanes import WorkerLane

    gate = threading.Event()
    lane = WorkerLane("test", 1, None)
    try:
        assert lane.waiting == 0
        first = lane.submit(lambda: gate.wait(WAIT_S))
        rest = [lane.submit(lambda: None) for _ in range(3)]
        deadline = time.monotonic() + WAIT_S
        while lane.waiting != 3:  # the first job reaches the worker
            assert time.monotonic() < deadline
            time.sleep(0.001)
        gate.set()
        assert first.result(WAIT_S) and all(f.result(WAIT_S) is None for f in rest)
        assert lane.waiting == 0
    finally:
        gate.set()
        lane.close()


# ---- ready lifts: the frames a pass may be lifted from ---------------------------------------------------------------
def _lane_with_frames(timeout_s: float | None = None):
    clock = ManualClock()
    det = FakeDetector(clock, 0.001, 0.001)
    lane = PhaseLockedImageLane(det, 8, 0.0, 20.0, 0.002, clock=clock, thread=False, camera_timeout_s=timeout_s,
                                superseded=lambda: ImagesSuperseded("superseded"))  # fmt: skip
    return lane, det, clock


def test_a_frame_replaced_while_it_was_encoded_becomes_its_cameras_previous():
    """submit_images saw it without features (it was being encoded inside a lift): once its features come, it is the
    newest encoded frame of its camera and a ready lift may use it, not the frame before it."""
    lane, det, clock = _lane_with_frames()
    frame = np.zeros((2, 2, 3), np.uint8)
    lane.submit_images({"CAM_BACK": frame}, 0.0)
    first = lane._frames["CAM_BACK"]
    first.features, first.owner.used = np.zeros((1, 1, 1), np.float32), True
    lane.submit_images({"CAM_BACK": frame}, 0.05)
    second = lane._frames["CAM_BACK"]
    assert lane._previous["CAM_BACK"] is first
    second.owner.used = True  # a lift took it and is encoding it ...
    lane.submit_images({"CAM_BACK": frame}, 0.1)  # ... when the next frame comes
    assert lane._previous["CAM_BACK"] is first  # it had no features yet
    lane._store_features({"CAM_BACK": second}, {"CAM_BACK": np.ones((1, 1, 1), np.float32)})
    assert lane._previous["CAM_BACK"] is second
    lane._store_features({"CAM_BACK": first}, {"CAM_BACK": np.ones((1, 1, 1), np.float32)})  # an older one: not taken
    assert lane._previous["CAM_BACK"] is second


def test_a_camera_that_times_out_leaves_no_previous_frame():
    lane, det, clock = _lane_with_frames(timeout_s=0.2)
    frame = np.zeros((2, 2, 3), np.uint8)
    lane.submit_images({c: frame for c in CAMERAS}, 0.0)
    for f in lane._frames.values():
        f.features, f.owner.used = np.zeros((1, 1, 1), np.float32), True
    lane.submit_images({"CAM_BACK": frame}, 0.05)
    assert "CAM_BACK" in lane._previous
    clock.t = 1.0  # every camera silent for longer than the timeout
    lane.step(clock.t)
    assert lane.stats.cameras_timed_out == len(CAMERAS) and lane._previous == {}


@pytest.mark.parametrize("given_hz, said", [(10.0, 1), (20.0, 0), (None, 0)])
def test_a_given_rate_the_arrivals_contradict_is_said_once(caplog, given_hz, said):
    """lidar_hz fixes the period the lane plans with; where the slices arrive at another rate its lifts end at the
    wrong moments, and nothing else says why: logged once, counted in the stats."""
    clock = ManualClock()
    lane = PhaseLockedImageLane(FakeDetector(clock, 0.001, 0.002, 8), 8, 0.0, given_hz, 0.002, clock=clock, thread=False,
                                superseded=lambda: ImagesSuperseded("superseded"))  # fmt: skip
    with caplog.at_level("WARNING", logger="streamdet.runtime_ort.phase_locked_lane"):
        for i in range(5 * 8):  # 20 Hz
            lane.observe_slice(i % 8, (i + 1) * 0.05 / 8)
    assert lane.stats.given_rate_contradicted == said
    warned = [r for r in caplog.records if "lidar_hz is" in r.getMessage()]
    assert len(warned) == said
    if said:
        assert "the slices arrive at 20 Hz" in warned[0].getMessage()


def test_a_skipped_pass_is_counted_once():
    """A plan gives up every pass it cannot make, rotations ahead where a lift is expected to take that long; the
    same far passes come back in the next plan: each counts once in quadrants_skipped."""
    clock = ManualClock()
    lane = PhaseLockedImageLane(FakeDetector(clock, 0.001, 0.002, 8), 8, 0.0, 20.0, 0.002, clock=clock, thread=False,
                                superseded=lambda: ImagesSuperseded("superseded"))  # fmt: skip
    passes = tuple((1.0 + 0.05 * r + 0.00625 * k, k, k // 2) for r in range(40) for k in range(8))
    assert lane._newly_skipped(passes) == len(passes)
    assert lane._newly_skipped(passes[::-1]) == 0  # the same passes again (another plan's): none new
    assert lane._newly_skipped(tuple((d + 0.002, k, q) for d, k, q in passes[:5])) == 0  # recomputed: moved a little
    assert lane._newly_skipped(((99.0, 0, 0),)) == 1
