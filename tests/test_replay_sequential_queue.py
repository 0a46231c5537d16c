"""The replay's sequential mode runs on the runtime's worker loop (`WorkerLane`, unbounded, one worker): every
slice runs in arrival order, a waiting image set is superseded by a newer one, the running one never is."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from streamdet.replay.modes import open_mode
from streamdet.runtime_ort.lanes import ImagesSuperseded, RunnerClosed, WorkerLane

WAIT_S = 30.0  # generous: the machine is shared; nothing here waits this long when it works


class GatedDetector:
    """The first job blocks until the gate opens, so the test decides what waits behind it."""

    uses_images = True

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.first_started = threading.Event()
        self.ran: list[tuple[str, float]] = []  # (kind, timestamp) of the jobs that ran, in order

    def _job(self, kind: str, timestamp: float) -> tuple[str, float]:
        self.first_started.set()
        assert self.gate.wait(WAIT_S), "the test never opened the gate"
        self.ran.append((kind, timestamp))
        return kind, timestamp

    def detect_slice(self, points, slice_index, timestamp=None, num_slices=None):
        return self._job("slice", timestamp)

    def update_images(self, images, timestamp=None):
        return self._job("images", timestamp)


class NoHooks:
    def job_started(self, key) -> None:
        pass

    def job_ended(self, key, cpu_s) -> None:
        pass


def naive_sequential(submits: list[str]) -> tuple[list[int], list[int]]:
    """Reference for one running job (submit 0) and later submits while it runs: (submits that run, in order;
    image sets superseded). Every slice runs; an image set waiting when a newer one arrives is removed."""
    waiting: list[int] = []
    superseded: list[int] = []
    for k, kind in enumerate(submits[1:], start=1):
        if kind == "images":
            superseded += [j for j in waiting if submits[j] == "images"]
            waiting = [j for j in waiting if submits[j] != "images"]
        waiting.append(k)
    return [0] + waiting, superseded


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_sequential_mode_matches_the_naive_queue(seed):
    rng = np.random.default_rng(seed)
    submits = ["images" if rng.random() < 0.4 else "slice" for _ in range(int(rng.integers(1, 30)))]
    det = GatedDetector()
    mode = open_mode("sequential", det, num_slices=4, hooks=NoHooks())
    points = np.zeros((3, 4), np.float32)
    images = {"CAM_FRONT": np.zeros((4, 6, 3), np.uint8)}
    futures = []
    try:
        for k, kind in enumerate(submits):
            if kind == "slice":
                futures.append(mode.runner.submit_slice(points, k % 4, float(k)))
            else:
                futures.append(mode.runner.submit_images(images, float(k)))
            if k == 0:
                assert det.first_started.wait(WAIT_S)  # the worker is busy from here on
        ran, superseded = naive_sequential(submits)
        for k in superseded:  # failed at once, before the worker is free
            with pytest.raises(ImagesSuperseded, match="superseded by a newer one"):
                futures[k].result(WAIT_S)
        det.gate.set()
        for k in ran:
            assert futures[k].result(WAIT_S) == (submits[k], float(k))
    finally:
        det.gate.set()
        mode.close()
    assert det.ran == [(submits[k], float(k)) for k in ran]
    assert mode.runner.images_superseded == len(superseded) and mode.runner.slices_dropped == 0


def test_the_unbounded_lane_never_drops_and_refuses_submits_after_close():
    gate = threading.Event()
    lane = WorkerLane("test-lane", workers=1, capacity=None)
    futures = [lane.submit(lambda k=k: gate.wait(WAIT_S) and k, kind="slice") for k in range(200)]
    gate.set()
    assert [f.result(WAIT_S) for f in futures] == list(range(200))
    assert lane.close() and lane.dropped == 0 and lane.superseded == 0
    with pytest.raises(RunnerClosed, match="test-lane: submit after close"):
        lane.submit(lambda: None)


def test_a_bounded_lane_needs_an_overflow_error():
    with pytest.raises(ValueError, match=r"bad-lane: a lane with a capacity \(3\) needs an overflow error"):
        WorkerLane("bad-lane", workers=1, capacity=3)


def test_a_cancelled_waiting_image_set_is_neither_superseded_nor_run():
    det = GatedDetector()
    mode = open_mode("sequential", det, num_slices=4, hooks=NoHooks())
    images = {"CAM_FRONT": np.zeros((4, 6, 3), np.uint8)}
    try:
        first = mode.runner.submit_slice(np.zeros((3, 4), np.float32), 0, 0.0)
        assert det.first_started.wait(WAIT_S)
        waiting = mode.runner.submit_images(images, 1.0)
        assert waiting.cancel()
        newest = mode.runner.submit_images(images, 2.0)
        det.gate.set()
        assert first.result(WAIT_S) == ("slice", 0.0) and newest.result(WAIT_S) == ("images", 2.0)
    finally:
        det.gate.set()
        mode.close()
    assert mode.runner.images_superseded == 0 and det.ran == [("slice", 0.0), ("images", 2.0)]
