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
