"""What StreamingRunner refuses at submit, in the caller's thread, under both image schedules: input that would
otherwise be queued, push good work out of the queue, and only then fail (found by a soak of the runtime as a
vehicle process runs it)."""

from __future__ import annotations

import gc
import logging
import math
import threading

import numpy as np
import pytest

from streamdet.runtime_ort.lanes import LaneConfig, StreamingRunner
from tests.lane_fakes import CAMERAS, StandInDetector

WAIT_S = 10.0
SCHEDULES = ("full", "phase-locked")


def _images():
    return {c: np.zeros((2, 2, 3), np.uint8) for c in CAMERAS}


class GatedImages(StandInDetector):
    """Image updates wait for a gate, so that a second set waits behind the first."""

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.started = threading.Event()

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None, camera_timestamps=None):
        self.started.set()
        assert self.gate.wait(WAIT_S)
        return super().update_images(images, timestamp, quadrants, encoded, camera_timestamps)


def _config(schedule: str) -> LaneConfig:
    return LaneConfig(schedule=schedule, lidar_hz=20.0) if schedule == "phase-locked" else LaneConfig(schedule=schedule)


@pytest.mark.parametrize("schedule", SCHEDULES)
@pytest.mark.parametrize("stamp", [math.nan, math.inf, -math.inf, "0.1", True])
def test_an_image_set_with_a_bad_timestamp_is_refused_at_submit(schedule, stamp):
    runner = StreamingRunner(StandInDetector(), _config(schedule))  # type: ignore[arg-type]
    try:
        with pytest.raises(ValueError, match="timestamp must be None or a finite number of seconds"):
            runner.submit_images(_images(), stamp)
        assert runner.images_superseded == 0
    finally:
        runner.close(WAIT_S)


@pytest.mark.parametrize("schedule", SCHEDULES)
def test_bad_camera_timestamps_are_refused_at_submit(schedule):
    runner = StreamingRunner(StandInDetector(), _config(schedule))  # type: ignore[arg-type]
    try:
        with pytest.raises(ValueError, match=r"camera_timestamps\['CAM_FRONT'\] must be a finite number"):
            runner.submit_images(_images(), 1.0, {"CAM_FRONT": math.nan})
        with pytest.raises(ValueError, match="names camera 'CAM_X'"):
            runner.submit_images(_images(), 1.0, {"CAM_X": 1.0})
    finally:
        runner.close(WAIT_S)


def test_a_bad_image_set_does_not_supersede_the_good_one_waiting():
    """Under "full" the lane keeps one set waiting; a NaN-stamped set used to replace it, then fail itself."""
    det = GatedImages()
    runner = StreamingRunner(det, LaneConfig(schedule="full"))  # type: ignore[arg-type]
    try:
        running = runner.submit_images(_images(), 0.0)
        assert det.started.wait(WAIT_S)
        waiting = runner.submit_images(_images(), 0.05)  # waits behind the running update
        with pytest.raises(ValueError):
            runner.submit_images(_images(), math.nan)
        det.gate.set()
        assert running.result(WAIT_S).timestamp == 0.0
        assert waiting.result(WAIT_S).timestamp == 0.05  # not superseded
        assert runner.images_superseded == 0
    finally:
        det.gate.set()
        runner.close(WAIT_S)


@pytest.mark.parametrize("schedule", SCHEDULES)
@pytest.mark.parametrize(
    ("index", "stamp", "match"),
    [(8, 0.0, r"slice_index must be an int in \[0, 8\), got 8"), (-1, 0.0, "slice_index"), (True, 0.0, "slice_index"),
     (2.0, 0.0, "slice_index"), (2, math.nan, "timestamp must be None or a finite"), (2, "now", "timestamp")],
)
def test_a_slice_with_a_bad_index_or_timestamp_fails_at_once_and_is_not_queued(schedule, index, stamp, match):
    runner = StreamingRunner(StandInDetector(), _config(schedule))  # type: ignore[arg-type]
    try:
        future = runner.submit_slice(np.zeros((0, 6), np.float32), index, stamp)
        assert future.done()  # failed in the caller's thread: never queued, no good slice pushed out for it
        with pytest.raises(ValueError, match=match):
            future.result(0)
        assert runner._slices.waiting == 0 and runner.slices_dropped == 0
        assert runner.submit_slice(np.zeros((0, 6), np.float32), 3, 0.1).result(WAIT_S).slice_index == 3
    finally:
        runner.close(WAIT_S)


def test_a_closed_phase_locked_runner_dropped_later_logs_nothing(caplog):
    """close() cancels the image sets no lift used; the runner's finalizer (stop()) used to claim them again, which
    concurrent.futures logs as CRITICAL "Future ... in unexpected state"."""
    det = GatedImages()
    with caplog.at_level(logging.WARNING):
        runner = StreamingRunner(det, _config("phase-locked"))  # type: ignore[arg-type]
        first = runner.submit_images(_images(), 0.0)
        assert det.started.wait(WAIT_S)  # the lane's first update holds the first set
        later = [runner.submit_images(_images(), float(i)) for i in (1, 2)]  # never used
        runner.close(0.05)  # cancels the sets never used; the running update goes on
        det.gate.set()
        assert first.result(WAIT_S) is not None and later[-1].cancelled()  # (the one before it: superseded)
        del runner
        gc.collect()
    assert not [r for r in caplog.records if r.levelno >= logging.CRITICAL], caplog.text


def test_slices_waiting_is_the_backlog_now():
    from tests.test_coalesce import GatedSliceDetector

    det = GatedSliceDetector()
    with StreamingRunner(det, LaneConfig(max_in_flight=1, coalesce_slices=1)) as runner:  # type: ignore[arg-type]
        assert runner.slices_waiting == 0
        first = runner.submit_slice(np.zeros((0, 6), np.float32), 0, 0.0)
        assert det.started.wait(WAIT_S)
        later = [runner.submit_slice(np.zeros((0, 6), np.float32), k, 0.01 * k) for k in (1, 2)]
        assert runner.slices_waiting == 2
        det.gate.set()
        for f in (first, *later):
            f.result(WAIT_S)
        assert runner.slices_waiting == 0


@pytest.mark.parametrize("coalesce", [1, 2])
def test_a_runners_slice_results_carry_their_latency(tiny_export, coalesce):
    import time

    from streamdet.core.slicing import split_sweep
    from streamdet.data.sample import load_bundled_sample
    from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector

    with StreamingDetector(tiny_export, DetectorConfig()) as det:
        slices = split_sweep(load_bundled_sample().points, det.num_slices)
        assert det.detect_slice(slices[0], 0, 0.0).latency_s is None  # the detector's own call: no runner clock
        with StreamingRunner(det, LaneConfig(max_in_flight=1, coalesce_slices=coalesce)) as runner:
            before = time.monotonic()
            futures = [runner.submit_slice(p, k, 0.01 * k) for k, p in enumerate(slices)]
            results = [f.result(WAIT_S) for f in futures]
            after = time.monotonic()
        for r in results:
            assert before <= r.submitted_s <= r.completed_s <= after
            assert r.latency_s == r.completed_s - r.submitted_s >= 0
