"""The image lane's back-pressure: a waiting image set is replaced by a newer one (its future fails with
ImagesSuperseded), the running one finishes, and the newest always runs."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from streamdet.runtime_ort.detector import ImageUpdate
from streamdet.runtime_ort.lanes import ImagesSuperseded, StreamingRunner

WAIT_S = 30.0  # generous: the machine is shared; nothing here waits this long when it works


class GatedDetector:
    """Stands in for a StreamingDetector whose image lane stays busy until the gate opens, so the test decides
    when the lane is free (a real encoder's run time would make the outcome depend on the machine)."""

    uses_images = True

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.first_started = threading.Event()
        self.ran: list[float] = []  # timestamps of the updates that ran, in order

    def update_images(self, images, timestamp=None) -> ImageUpdate:
        self.first_started.set()
        assert self.gate.wait(WAIT_S), "the test never opened the gate"
        self.ran.append(timestamp)
        return ImageUpdate(timestamp, tuple(images), ())


def naive_image_lane(num_while_busy: int) -> tuple[list[int], list[int]]:
    """Reference of the policy for one running set and ``num_while_busy`` later submits: (sets that run, sets
    superseded), by submit position. One set waits at most; each newer one replaces it."""
    ran, superseded, waiting = [0], [], None
    for k in range(1, num_while_busy + 1):
        if waiting is not None:
            superseded.append(waiting)
        waiting = k
    if waiting is not None:
        ran.append(waiting)
    return ran, superseded


@pytest.mark.parametrize("num_while_busy", [0, 1, 2, 5])
def test_waiting_image_sets_are_superseded_by_newer_ones(num_while_busy):
    det = GatedDetector()
    images = {"CAM_FRONT": np.zeros((4, 6, 3), np.uint8)}
    runner = StreamingRunner(det)
    try:
        futures = [runner.submit_images(images, timestamp=0.0)]
        assert det.first_started.wait(WAIT_S)  # set 0 runs: the lane is busy from here on
        futures += [runner.submit_images(images, timestamp=float(k)) for k in range(1, num_while_busy + 1)]
        ran, superseded = naive_image_lane(num_while_busy)
        for k in superseded:  # failed at once, before the lane is free
            with pytest.raises(ImagesSuperseded, match="superseded by a newer one"):
                futures[k].result(WAIT_S)
        assert runner.images_superseded == len(superseded)
        det.gate.set()
        for k in ran:
            assert futures[k].result(WAIT_S).timestamp == float(k)
        assert det.ran == [float(k) for k in ran]  # a superseded set never reaches the detector
    finally:
        det.gate.set()
        runner.close()


def test_a_superseded_future_the_caller_cancelled_is_not_counted():
    det = GatedDetector()
    images = {"CAM_FRONT": np.zeros((4, 6, 3), np.uint8)}
    runner = StreamingRunner(det)
    try:
        runner.submit_images(images, timestamp=0.0)
        assert det.first_started.wait(WAIT_S)
        waiting = runner.submit_images(images, timestamp=1.0)
        assert waiting.cancel()  # the caller gave up on it while it waited
        newest = runner.submit_images(images, timestamp=2.0)
        assert runner.images_superseded == 0 and waiting.cancelled()
        det.gate.set()
        assert newest.result(WAIT_S).timestamp == 2.0 and det.ran == [0.0, 2.0]
    finally:
        det.gate.set()
        runner.close()
