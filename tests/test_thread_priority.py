"""runtime_ort/thread_priority.py and LaneConfig.image_lane_nice: the image lane's worker thread runs at the nice
value asked for, the slice lane and the caller's thread stay as they were, bad values are refused, and a thread
whose priority cannot be set never runs its work."""

from __future__ import annotations

import os
import sys
import threading
from concurrent.futures import Future

import numpy as np
import pytest

from streamdet.runtime_ort.lanes import LaneConfig, StreamingRunner, WorkerLane
from streamdet.runtime_ort.phase_locked_lane import PhaseLockedImageLane
from streamdet.runtime_ort.thread_priority import MAX_NICE, check_nice, start_worker

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")


def _nice_of_thread(thread: threading.Thread) -> int:
    return os.getpriority(os.PRIO_PROCESS, thread.native_id)


def _own_nice() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


@pytest.mark.parametrize("bad", [-1, 20, 1.5, "3", True, None])
def test_bad_nice_values_are_refused_naming_the_value(bad):
    with pytest.raises(ValueError, match="image_lane_nice"):
        LaneConfig(image_lane_nice=bad)
    with pytest.raises(ValueError, match=r"0\.\.19"):
        check_nice(bad, "x")


def test_nonzero_nice_off_linux_is_refused(monkeypatch):
    monkeypatch.setattr(sys, "platform", "darwin")
    assert check_nice(0, "x") == 0
    with pytest.raises(ValueError, match="need Linux"):
        check_nice(5, "x")


@linux_only
@pytest.mark.parametrize("nice", [0, 3, MAX_NICE])
def test_a_worker_lane_runs_its_jobs_at_the_nice_value_asked_for(nice):
    base = _own_nice()
    lane = WorkerLane("test-lane", 2, None, nice=nice)
    seen = [lane.submit(_own_nice).result(timeout=10) for _ in range(4)]
    lane.close()
    assert seen == [min(MAX_NICE, base + nice)] * 4
    assert _own_nice() == base  # the caller's thread is untouched


@linux_only
def test_the_runner_lowers_the_image_lane_alone():
    """Full schedule: the image lane's worker is niced, the slice lane's workers are not."""

    class _Det:
        uses_images = True
        num_slices = 8

        def update_images(self, images, timestamp):
            return _own_nice()

        def check_images(self, images):
            pass

    base = _own_nice()
    runner = StreamingRunner(_Det(), LaneConfig(image_lane_nice=7))  # type: ignore[arg-type]
    try:
        assert runner.submit_images({"CAM": np.zeros((2, 2, 3), np.uint8)}, 1.0).result(timeout=10) == min(MAX_NICE, base + 7)
        assert {_nice_of_thread(t) for t in runner._slices._threads} == {base}
    finally:
        runner.close()


@linux_only
def test_the_phase_locked_lane_thread_is_niced():
    class _Det:
        def quadrant_cameras(self, quadrants):
            return ()

    base = _own_nice()
    lane = PhaseLockedImageLane(_Det(), 8, nice=4)
    try:
        assert _nice_of_thread(lane._thread) == min(MAX_NICE, base + 4)
    finally:
        lane.close()


def test_a_thread_whose_priority_cannot_be_set_raises_and_runs_nothing(monkeypatch):
    import streamdet.runtime_ort.thread_priority as tp

    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(tp.os, "setpriority", refuse)
    ran: Future = Future()
    with pytest.raises(OSError, match="could not add 5"):
        start_worker(lambda: ran.set_result(True), "w", 5)
    assert not ran.done()


def test_a_lane_whose_second_worker_cannot_be_niced_ends_the_first(monkeypatch):
    import streamdet.runtime_ort.worker_lane as lanes_mod

    started: list[threading.Thread] = []
    real = lanes_mod.start_worker

    def second_fails(target, name, nice=0):
        if started:
            raise OSError(f"{name}: refused")
        started.append(real(target, name, nice))
        return started[-1]

    monkeypatch.setattr(lanes_mod, "start_worker", second_fails)
    with pytest.raises(OSError, match="refused"):
        WorkerLane("two", 2, None, nice=0)
    started[0].join(timeout=10)
    assert not started[0].is_alive()


@pytest.mark.parametrize("threads, warned", [(1, False), (0, True), (4, True)])
def test_the_runner_says_when_the_nice_value_misses_onnxruntimes_pool_threads(threads, warned):
    """Only the lane's own thread is reniced: with more than one image-lane thread onnxruntime's pool keeps nice 0."""
    import warnings
    from types import SimpleNamespace

    from lane_fakes import StandInDetector

    det = StandInDetector()
    det.config = SimpleNamespace(start_deg=0.0, image_lane_threads=threads)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        runner = StreamingRunner(det, LaneConfig(image_lane_nice=5))  # type: ignore[arg-type]
        runner.close()
        StreamingRunner(det, LaneConfig()).close()  # no nice asked: nothing to say
    said = [w for w in seen if issubclass(w.category, RuntimeWarning) and "image_lane_nice" in str(w.message)]
    assert len(said) == int(warned)
    if warned:
        assert f"image_lane_threads={threads}" in str(said[0].message) and said[0].filename == __file__


def test_a_thread_that_cannot_start_is_an_os_error_naming_it(monkeypatch):
    """--slice-workers 1024 under a memory limit: "can't start new thread" was a RuntimeError traceback."""
    import threading

    def refuse(self):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(threading.Thread, "start", refuse)
    with pytest.raises(OSError, match="slice-worker-900: could not start the thread .* fewer workers"):
        start_worker(lambda: None, "slice-worker-900")
