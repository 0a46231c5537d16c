"""A StreamingRunner dropped without close() (race audit S5): nothing its lanes' threads hold refers to it, so it is
collected, and its finalizer ends the workers once the jobs already queued are done (their futures complete), as
concurrent.futures' pools do. Before, the slice lane's coalescing held the runner's bound methods and its threads
lived as long as the process. Every wait has a timeout: a hang fails."""

from __future__ import annotations

import gc
import threading
import weakref
from concurrent.futures import wait
from types import SimpleNamespace

import numpy as np
import pytest

from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.lanes import LaneConfig, StreamingRunner

from lane_fakes import StandInDetector

WAIT_S = 10.0
CAMERAS = ("CAM_FRONT", "CAM_BACK")
POINTS = np.zeros((3, 6), np.float32)


class SliceDetector(StandInDetector):
    """With detect_slices: the slice lane coalesces and may hold pairs."""

    camera_names = CAMERAS

    def detect_slices(self, points, indices, stamps):
        return tuple(SimpleNamespace(slice_index=k) for k in indices)


def _lane_threads(runner: StreamingRunner) -> list[threading.Thread]:
    threads = list(runner._slices._threads)
    if runner._images is not None:
        threads += runner._images._threads
    else:
        threads.append(runner._phase_locked._thread)
    assert threads and all(t.is_alive() for t in threads)
    return threads


def _drop(runner_box: list) -> weakref.ref:
    ref = weakref.ref(runner_box[0])
    runner_box.clear()
    gc.collect()
    return ref


def _assert_ended(threads: list[threading.Thread]) -> None:
    for t in threads:
        t.join(WAIT_S)
    assert not [t.name for t in threads if t.is_alive()], "lane threads outlived their runner"


@pytest.mark.parametrize("schedule", ["full", "phase-locked"])
@pytest.mark.parametrize("pair_hold_load", [None, 0.0])
def test_a_dropped_runner_ends_its_workers_after_its_queued_jobs(schedule, pair_hold_load):
    config = LaneConfig(schedule=schedule, max_in_flight=2, queue_size=8, pair_hold_load=pair_hold_load)
    box = [StreamingRunner(SliceDetector(), config)]
    images = box[0].submit_images({n: np.zeros((2, 2, 3), np.uint8) for n in CAMERAS}, 0.0)
    slices = [box[0].submit_slice(POINTS, k, 0.0125 * k) for k in range(8)]
    threads = _lane_threads(box[0])
    ref = _drop(box)
    assert ref() is None, "the runner is still referenced (by its lanes' threads?)"
    done, pending = wait(slices, WAIT_S)
    assert not pending and [f.result().slice_index for f in slices] == list(range(8))
    done, pending = wait([images], WAIT_S)  # phase-locked: lifted already, or cancelled as at close()
    assert not pending and (images.cancelled() or images.result().timestamp == 0.0)
    _assert_ended(threads)


def test_a_runner_in_use_keeps_its_workers():
    runner = StreamingRunner(SliceDetector(), LaneConfig(pair_hold_load=0.0))
    threads = _lane_threads(runner)
    gc.collect()
    assert all(t.is_alive() for t in threads)
    assert runner.submit_slice(POINTS, 0, 0.0).result(WAIT_S).slice_index == 0
    assert runner.close(WAIT_S)
    _assert_ended(threads)


@pytest.mark.parametrize("schedule", ["full", "phase-locked"])
def test_a_dropped_runner_of_a_real_detector_ends_its_workers(tiny_export, schedule):
    det = StreamingDetector(tiny_export)
    sample = load_bundled_sample()
    box = [StreamingRunner(det, LaneConfig(schedule=schedule))]
    size = (det.image.width, det.image.height)
    box[0].submit_images(dict(zip(sample.rig.names, sample.load_images(size))), 0.0)
    slices = [box[0].submit_slice(s, k, 0.0125 * k) for k, s in enumerate(split_sweep(sample.points, det.num_slices))]
    threads = _lane_threads(box[0])
    ref = _drop(box)
    assert ref() is None
    done, pending = wait(slices, 60.0)
    assert not pending and all(f.exception() is None for f in slices)
    _assert_ended(threads)
    det.detect_slice(split_sweep(sample.points, det.num_slices)[0], 0)  # the detector is the caller's: still usable
    det.close()
