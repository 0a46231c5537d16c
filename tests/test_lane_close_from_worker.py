"""close() from a future's done-callback that runs on the lane's own worker (a result handler that decides to shut
down): the worker cannot wait for itself, so close() neither raises ("cannot join current thread", which
concurrent.futures would log and swallow, leaving the other lanes open) nor hangs. It closes every lane, returns
False, and the calling worker still runs what was queued, then ends. Every wait here has a timeout: a hang fails."""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future

import numpy as np
import pytest

from streamdet.runtime_ort.lanes import LaneConfig, StreamingRunner
from streamdet.runtime_ort.worker_lane import RunnerClosed, WorkerLane

from test_lane_callbacks import GatedDetector, _images

WAIT_S = 10.0
POINTS = np.zeros((2, 6), np.float32)


class ClosingCallback:
    """A done-callback that calls ``close()``: what it returned or raised, once it has run (``outcome``)."""

    def __init__(self, close) -> None:
        self._close = close
        self._ran = threading.Event()
        self.returned: list = []
        self.raised: list = []

    def __call__(self, _f: Future) -> None:
        try:
            self.returned.append(self._close())
        except BaseException as e:  # noqa: BLE001  # handed to the test
            self.raised.append(e)
        finally:
            self._ran.set()

    def outcome(self) -> tuple[list, list]:
        """(returned, raised), after the callback ran (it runs on the worker after the future's result is set)."""
        assert self._ran.wait(WAIT_S), "the done-callback never ran"
        return self.returned, self.raised


def _threads_end(threads: list[threading.Thread]) -> None:
    for t in threads:
        t.join(WAIT_S)
        assert not t.is_alive(), f"{t.name} still running {WAIT_S} s after close()"


def _lane_threads(before: set[threading.Thread]) -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t not in before]


@pytest.mark.parametrize("timeout", [None, WAIT_S])
def test_a_slice_callback_that_closes_the_runner_on_its_worker(timeout):
    before = set(threading.enumerate())
    det = GatedDetector()
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1, queue_size=4, coalesce_slices=1))
    threads = _lane_threads(before)
    running = runner.submit_slice(POINTS, 0, 0.0)
    assert det.started.wait(WAIT_S)
    queued = runner.submit_slice(POINTS, 1, 0.0)
    callback = ClosingCallback(lambda: runner.close(timeout=timeout))
    running.add_done_callback(callback)
    det.gate.set()
    assert running.result(WAIT_S).slice_index == 0
    assert callback.outcome() == ([False], [])  # it could not wait for the worker it ran on
    assert queued.result(WAIT_S).slice_index == 1  # no deadline passed: the worker runs it before it ends
    with pytest.raises(RunnerClosed):
        runner.submit_slice(POINTS, 2, 0.0)
    with pytest.raises(RunnerClosed):
        runner.submit_images(_images(), 1.0)
    _threads_end(threads)  # the image and calibration lanes were closed too
    assert runner.close(timeout=WAIT_S) is True  # from the owner's thread afterwards: all ended


@pytest.mark.parametrize("schedule", ["full", "phase-locked"])
def test_an_image_callback_that_closes_the_runner_on_the_image_worker(schedule):
    before = set(threading.enumerate())
    det = GatedDetector()
    det.gate.set()
    runner = StreamingRunner(det, LaneConfig(schedule=schedule))
    threads = _lane_threads(before)
    first = runner.submit_images(_images(), 0.0)
    callback = ClosingCallback(runner.close)
    first.add_done_callback(callback)
    first.result(WAIT_S)
    returned, raised = callback.outcome()
    assert raised == [] and len(returned) == 1
    with pytest.raises(RunnerClosed):
        runner.submit_slice(POINTS, 0, 0.0)
    _threads_end(threads)
    assert runner.close(timeout=WAIT_S) is True


def test_a_worker_lane_closed_from_its_own_worker_past_its_deadline_cancels_the_queued_jobs():
    lane = WorkerLane("test-lane", 1, None)
    gate = threading.Event()
    callback = ClosingCallback(lambda: lane.close(deadline=time.monotonic()))
    first = lane.submit(lambda: gate.wait(WAIT_S))
    queued = lane.submit(lambda: "queued")
    first.add_done_callback(callback)
    gate.set()
    assert first.result(WAIT_S) is True
    assert callback.outcome() == ([False], [])
    assert queued.cancelled()
    _threads_end(list(lane._threads))


@pytest.mark.parametrize("pair", ["two slice workers", "a slice worker and the image worker"])
def test_two_callbacks_closing_the_runner_at_once_do_not_wait_for_each_other(pair):
    """Each callback runs on a worker the other close() would join: neither may wait (audit of the thirty-second
    session: with joins, both waited for good)."""
    before = set(threading.enumerate())
    det = GatedDetector()
    det.gate.set()
    workers = 2 if pair == "two slice workers" else 1
    runner = StreamingRunner(det, LaneConfig(max_in_flight=workers, queue_size=4, coalesce_slices=1))
    threads = _lane_threads(before)
    together = threading.Barrier(2, timeout=WAIT_S)

    def close_together():
        together.wait()  # both callbacks inside close() at the same time
        return runner.close()

    callbacks = [ClosingCallback(close_together), ClosingCallback(close_together)]
    first = runner.submit_slice(POINTS, 0, 0.0)
    second = runner.submit_slice(POINTS, 1, 0.0) if workers == 2 else runner.submit_images(_images(), 0.0)
    first.add_done_callback(callbacks[0])
    second.add_done_callback(callbacks[1])
    assert [c.outcome() for c in callbacks] == [([False], []), ([False], [])]
    _threads_end(threads)
    assert runner.close(timeout=WAIT_S) is True


def test_close_from_a_worker_cancels_the_queued_slices_not_started_by_its_deadline():
    det = GatedDetector()
    det.gate.set()
    runner = StreamingRunner(det, LaneConfig(max_in_flight=1, queue_size=8, coalesce_slices=1))
    slow = threading.Event()
    calls: list[int] = []
    detect = det.detect_slice

    def slow_detect(points, slice_index, timestamp=None):
        calls.append(slice_index)
        if slice_index > 0:
            slow.wait(0.2)  # never set: each queued slice takes 0.2 s
        return detect(points, slice_index, timestamp)

    det.detect_slice = slow_detect
    gate = threading.Event()
    first = runner.submit_slice(POINTS, 0, 0.0)
    callback = ClosingCallback(lambda: (gate.wait(WAIT_S), runner.close(timeout=0.05))[1])
    first.add_done_callback(callback)
    queued = [runner.submit_slice(POINTS, k, 0.0) for k in range(1, 6)]
    gate.set()
    assert callback.outcome() == ([False], [])
    for fut in queued:  # each settles: run (started before the deadline) or cancelled (not started by it)
        assert fut.cancelled() or fut.result(WAIT_S) is not None
    started = [k for k in calls if k > 0]
    assert len(started) <= 2 and sum(f.cancelled() for f in queued) >= 3, (started, [f.cancelled() for f in queued])
    assert runner.close(timeout=WAIT_S) is False  # every worker has ended, but not every slice ran


class _GatedFirstUpdate:
    """A phase-locked lane's detector: the first update waits for ``gate``; records when each update starts."""

    camera_names = ("a", "b", "c")

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.calls: list[float] = []

    def quadrant_cameras(self, quadrants):
        return self.camera_names

    def encode_images(self, images):
        return {n: np.zeros((1, 1, 1), np.float32) for n in images}

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None, camera_timestamps=None):
        self.calls.append(time.monotonic())
        if len(self.calls) == 1:
            assert self.gate.wait(WAIT_S)
        return sorted(images)

    def forget_images(self, through=None, quadrants=None, cameras_out=False):
        pass


def test_the_phase_locked_lane_closed_from_an_expired_sets_callback_starts_no_update(caplog):
    from streamdet.runtime_ort.phase_locked_lane import PhaseLockedImageLane

    det = _GatedFirstUpdate()
    lane = PhaseLockedImageLane(det, 8, camera_timeout_s=0.05)
    img = np.zeros((2, 2, 3), np.uint8)
    lane.submit_images({"a": img}, 0.0)  # its full update waits in the detector
    deadline = time.monotonic() + WAIT_S
    while not det.calls and time.monotonic() < deadline:
        time.sleep(0.005)
    expiring = lane.submit_images({"b": img}, 1.0)  # times out unused while that update waits
    closed_at: list[float] = []
    callback = ClosingCallback(lambda: (closed_at.append(time.monotonic()), lane.close())[1])
    expiring.add_done_callback(callback)
    time.sleep(0.04)
    later = lane.submit_images({"c": img}, 2.0)  # not timed out yet when the first update ends
    time.sleep(0.03)
    det.gate.set()
    returned, raised = callback.outcome()
    assert raised == [] and returned == [False]
    time.sleep(0.2)
    assert [t for t in det.calls if t > closed_at[0]] == []  # no update began after close()
    # settled and never used: close() cancels it (or, on a machine slow enough, it timed out unused first); no result
    assert later.done(), "an image set queued before close() was left pending"
    assert later.cancelled() or later.exception(0) is not None, later.result(0)
    assert not [r for r in caplog.records if r.levelname == "CRITICAL"]  # no future claimed twice
    assert lane.close(deadline=time.monotonic() + WAIT_S) is True


def test_close_with_a_deadline_reports_the_jobs_the_workers_cancelled():
    """Past close()'s deadline the workers cancel the jobs not started (here: close() without waiting, then the
    running job ends); a later close() must still say not everything ran."""
    lane = WorkerLane("test-lane", 1, None)
    gate, started = threading.Event(), threading.Event()
    running = lane.submit(lambda: (started.set(), gate.wait(WAIT_S))[1])
    assert started.wait(WAIT_S)
    queued = [lane.submit(lambda: "queued") for _ in range(3)]
    assert lane.close(deadline=time.monotonic(), wait=False) is False
    gate.set()
    assert running.result(WAIT_S) is True
    _threads_end(list(lane._threads))  # the worker cancelled the queued jobs, then ended
    assert all(f.cancelled() for f in queued)
    assert lane.close() is False
