"""Spare workers of a `WorkerLane` (the slice lane borrowing the image lane's core, LaneConfig.spare_slice_workers):
when they may take a job, what counts as waiting, joined and dropped while their gate is closed, the image lanes'
idle signals, and the runner's gate under both schedules."""

from __future__ import annotations

import math
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from streamdet.runtime_ort.lanes import LaneConfig, StreamingRunner
from streamdet.runtime_ort.phase_locked_lane import PhaseLockedImageLane
from streamdet.runtime_ort.worker_lane import JobBatching, WorkerLane

WAIT_S = 30.0  # generous: the machine is shared; nothing here waits this long when it works
NOT_YET_S = 0.05  # how long a job that must not start is given to start wrongly
CAMERAS = ("CAM_FRONT", "CAM_BACK")


def _name() -> str:
    return threading.current_thread().name


class Hold:
    """A job that runs until released; ``running`` tells when it has started."""

    def __init__(self) -> None:
        self.running = threading.Event()
        self.release = threading.Event()

    def __call__(self) -> str:
        self.running.set()
        assert self.release.wait(WAIT_S), "the test never released the job"
        return _name()


def _until(predicate) -> None:
    deadline = time.monotonic() + WAIT_S
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.001)


def test_a_spare_worker_needs_a_gate():
    with pytest.raises(ValueError, match="spare_gate"):
        WorkerLane("t", 1, None, spare=1)


@pytest.mark.parametrize("bad", [-1, 65, True, 1.5, "1", None])
def test_lane_config_refuses_bad_spare_workers(bad):
    with pytest.raises(ValueError, match="spare_slice_workers"):
        LaneConfig(spare_slice_workers=bad)


def test_a_spare_worker_takes_nothing_while_a_worker_is_free():
    lane = WorkerLane("t", 1, None, spare=1, spare_gate=lambda: True)
    try:
        names = [lane.submit(_name).result(WAIT_S) for _ in range(20)]  # one at a time: the worker is always free
        assert all("spare" not in n for n in names)
        assert lane.spare_runs == 0
    finally:
        lane.close()


def test_a_spare_worker_waits_for_its_gate_then_runs_beside_the_busy_worker():
    gate = [False]
    lane = WorkerLane("t", 1, None, spare=1, spare_gate=lambda: gate[0])
    hold = Hold()
    try:
        first = lane.submit(hold)
        assert hold.running.wait(WAIT_S)
        second = lane.submit(_name)
        time.sleep(NOT_YET_S)
        assert not second.done() and lane.waiting == 1  # a gated spare worker is not free
        gate[0] = True
        lane.wake()
        assert "spare" in second.result(WAIT_S)
        assert not first.done() and lane.waiting == 0
        hold.release.set()
        assert "spare" not in first.result(WAIT_S)
        assert lane.spare_runs == 1
    finally:
        hold.release.set()
        lane.close()


@pytest.mark.parametrize("open_gate", [False, True])
def test_a_closed_gate_leaves_the_job_waiting_where_the_queue_drops_it(open_gate):
    lane = WorkerLane("t", 1, 1, lambda: RuntimeError("dropped"), spare=1, spare_gate=lambda: open_gate)
    hold, spare_hold = Hold(), Hold()
    try:
        first = lane.submit(hold)
        assert hold.running.wait(WAIT_S)
        second = lane.submit(spare_hold)
        if open_gate:
            assert spare_hold.running.wait(WAIT_S)  # in flight on the spare worker: it holds no place in the queue
        third = lane.submit(_name)  # the queue holds one: behind a closed gate the second is the oldest waiting
        hold.release.set()
        spare_hold.release.set()
        assert first.result(WAIT_S)
        assert third.result(WAIT_S)
        if open_gate:
            assert "spare" in second.result(WAIT_S)
        else:
            with pytest.raises(RuntimeError, match="dropped"):
                second.result(WAIT_S)
        assert lane.dropped == (0 if open_gate else 1)
    finally:
        hold.release.set()
        spare_hold.release.set()
        lane.close()


def test_a_closed_gate_lets_the_waiting_jobs_join_and_an_open_one_runs_them_apart():
    for open_gate in (False, True):
        runs: list[tuple] = []
        batch = JobBatching(joins=lambda a, b: True, run=lambda ps: runs.append(tuple(ps)) or ps, most=2)
        lane = WorkerLane("t", 1, None, batch=batch, spare=1, spare_gate=lambda: open_gate)
        hold = Hold()
        try:
            first = lane.submit(hold)
            assert hold.running.wait(WAIT_S)
            spare_hold = Hold()
            second = lane.submit(spare_hold, payload="a")
            if open_gate:
                assert spare_hold.running.wait(WAIT_S)  # the spare worker took it alone, at once
            third = lane.submit(lambda: "b alone", payload="b")
            hold.release.set()
            spare_hold.release.set()
            first.result(WAIT_S)
            if open_gate:
                assert "spare" in second.result(WAIT_S) and third.result(WAIT_S) == "b alone"
                assert runs == [] and lane.joined == 0
            else:  # the worker took "a" with "b" waiting and no worker free: one run
                assert (second.result(WAIT_S), third.result(WAIT_S)) == ("a", "b")
                assert runs == [("a", "b")] and lane.joined == 1
        finally:
            hold.release.set()
            lane.close()


def test_a_lane_tells_when_it_goes_idle():
    idle = threading.Event()
    lane = WorkerLane("t", 1, None, on_idle=idle.set)
    hold = Hold()
    try:
        assert lane.idle
        first = lane.submit(hold)
        assert hold.running.wait(WAIT_S)
        second = lane.submit(lambda: None)
        assert not lane.idle and not idle.is_set()
        hold.release.set()
        first.result(WAIT_S)
        second.result(WAIT_S)
        assert idle.wait(WAIT_S)
        _until(lambda: lane.idle)
    finally:
        hold.release.set()
        lane.close()


def test_closing_finishes_the_jobs_a_gated_spare_worker_left():
    lane = WorkerLane("t", 1, None, spare=2, spare_gate=lambda: False)
    futures = [lane.submit(lambda k=k: k) for k in range(10)]
    assert lane.close(time.monotonic() + WAIT_S)
    assert [f.result(0) for f in futures] == list(range(10))
    assert lane.spare_runs == 0


# ---- the runner's gate ---------------------------------------------------------------------------------------
class StandIn:
    """A detector stand-in for both lanes: its first slice holds until released, its image encoding until ``image_gate``
    opens; records the threads that ran each slice."""

    camera_names = CAMERAS

    def __init__(self, uses_images: bool = True) -> None:
        self.uses_images = uses_images
        self.num_slices = 8
        self.config = SimpleNamespace(start_deg=0.0)
        self.first = Hold()
        self.image_gate = threading.Event()
        self.encoding = threading.Event()
        self.threads: dict[int, str] = {}

    def quadrant_cameras(self, quadrants):
        return CAMERAS

    def check_images(self, images) -> None:
        pass

    def encode_images(self, images):
        self.encoding.set()
        assert self.image_gate.wait(WAIT_S)
        return {n: np.zeros((1, 1, 1), np.float32) for n in images}

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None, **options):
        if encoded is None:
            self.encode_images(images)
        return SimpleNamespace(timestamp=timestamp)

    def detect_slice(self, points, slice_index, timestamp=None):
        if not self.first.running.is_set():
            self.first()
        self.threads[slice_index] = _name()
        return SimpleNamespace(slice_index=slice_index, timestamp=timestamp)


POINTS = np.zeros((0, 6), np.float32)
IMAGES = {c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}


@pytest.mark.parametrize("schedule", ["full", "phase-locked"])
def test_the_spare_slice_worker_waits_while_the_image_lane_works(schedule):
    det = StandIn()
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1, schedule=schedule, spare_slice_workers=1))  # type: ignore[arg-type]
    try:
        runner.submit_images(IMAGES, 0.0)
        assert det.encoding.wait(WAIT_S)  # the image lane is busy
        first = runner.submit_slice(POINTS, 0, 0.0)
        assert det.first.running.wait(WAIT_S)  # the slice worker is busy
        second = runner.submit_slice(POINTS, 1, 0.01)
        time.sleep(NOT_YET_S)
        assert not second.done()  # the image lane has the other core
        det.image_gate.set()  # its update ends; it waits for frames (or slices): idle
        assert second.result(WAIT_S).slice_index == 1 and "spare" in det.threads[1]
        assert not first.done()
        det.first.release.set()
        assert first.result(WAIT_S).slice_index == 0
        assert runner.slices_on_spare_workers == 1 and runner.slices_dropped == 0
    finally:
        det.image_gate.set()
        det.first.release.set()
        runner.close(WAIT_S)


def test_without_an_image_lane_a_spare_slice_worker_is_a_worker():
    det = StandIn(uses_images=False)
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1, spare_slice_workers=1))  # type: ignore[arg-type]
    try:
        first = runner.submit_slice(POINTS, 0, 0.0)
        assert det.first.running.wait(WAIT_S)
        assert runner.submit_slice(POINTS, 1, 0.01).result(WAIT_S).slice_index == 1
        assert "spare" in det.threads[1]
        det.first.release.set()
        first.result(WAIT_S)
    finally:
        det.first.release.set()
        runner.close(WAIT_S)


def test_the_phase_locked_lane_says_when_it_works_next():
    det = StandIn()
    det.image_gate.set()
    idle = threading.Event()
    lane = PhaseLockedImageLane(det, 8, on_idle=idle.set)
    try:
        assert idle.wait(WAIT_S)  # nothing to do: it waits for frames
        assert lane.idle_until() == math.inf
        unstarted = PhaseLockedImageLane(det, 8, thread=False)
        assert unstarted.idle_until() == -math.inf  # never served: never idle
    finally:
        lane.close(time.monotonic() + WAIT_S)


def test_the_phase_locked_gate_closes_before_a_planned_lift():
    """The gate compares the time to the lane's next planned work with one slice run."""
    det = StandIn()
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1, schedule="phase-locked", spare_slice_workers=1))  # type: ignore[arg-type]
    try:
        lane = runner._phase_locked
        _until(lambda: lane.idle_until() == math.inf)
        assert runner._image_lane_idle()
        lane._idle_until = lane.clock() + 0.5  # a lift planned in half a second, slices of 1 s each: closed
        runner._slices._run_s.extend([1.0, 1.0])
        assert not runner._image_lane_idle()
        runner._slices._run_s.clear()  # slices of no time yet: open
        assert runner._image_lane_idle()
    finally:
        det.image_gate.set()
        runner.close(WAIT_S)


@pytest.mark.parametrize("bad", [-1, 1025, True, 2.0, "4"])
def test_lane_config_refuses_a_bad_backlog_rule(bad):
    with pytest.raises(ValueError, match="spare_at_backlog"):
        LaneConfig(spare_slice_workers=1, spare_at_backlog=bad)
    with pytest.raises(ValueError, match="needs spare_slice_workers"):
        LaneConfig(spare_at_backlog=4)


def test_a_backlog_opens_the_spare_workers_gate_while_the_image_lane_works():
    det = StandIn()
    config = LaneConfig(max_in_flight=1, schedule="phase-locked", spare_slice_workers=1, spare_at_backlog=2)
    runner = StreamingRunner(det, config)  # type: ignore[arg-type]
    try:
        runner.submit_images(IMAGES, 0.0)
        assert det.encoding.wait(WAIT_S)  # the image lane is busy, and stays so
        first = runner.submit_slice(POINTS, 0, 0.0)
        assert det.first.running.wait(WAIT_S)
        second = runner.submit_slice(POINTS, 1, 0.01)
        time.sleep(NOT_YET_S)
        assert not second.done()  # one queued: below the backlog
        third = runner.submit_slice(POINTS, 2, 0.02)  # two queued: the spare worker takes the older one
        assert second.result(WAIT_S).slice_index == 1 and "spare" in det.threads[1]
        time.sleep(NOT_YET_S)
        assert not third.done() and not first.done()  # one queued again: below the backlog
        det.first.release.set()
        assert [f.result(WAIT_S).slice_index for f in (first, third)] == [0, 2]
    finally:
        det.image_gate.set()
        det.first.release.set()
        runner.close(WAIT_S)
