"""The three ways to serve the same drive, each behind the same two calls (``submit_slice``, ``submit_images``).

- ``streaming`` (the paper): `StreamingRunner` as a vehicle embeds it; slices as they arrive in the slice lane
  (bounded queue, the oldest waiting slice dropped when it is full), camera images in the image lane (a waiting set
  superseded by a newer one), both lanes at once.
- ``full-sweep``: the same runner, but the player waits for the whole rotation and hands over the sweep as one
  slice of a one-slice detector (the whole grid in one slice-graph run): what most deployed detectors do.
- ``sequential``: one FIFO served by one worker, slices and image sets in arrival order, no slice ever dropped
  (a waiting image set is still superseded by a newer one, as in the bench's sequential queue): each slice waits
  for everything before it, the bottleneck of memory-based streaming methods. When the work arriving per second
  exceeds a second, its latency grows without bound.

The detector only needs ``uses_images``, ``detect_slice(points, k, timestamp, num_slices)`` and
``update_images(images, timestamp)``: a `StreamingDetector`, or a fake one in tests; with ``detect_slices`` too the
runner may coalesce waiting slices (`LaneConfig.coalesce_slices`). `Instrumented` wraps it to
tell the player when each job starts and ends and how much CPU its thread spent; a job is known by its kind,
timestamp and slice index, so the player must give every slice of a drive its own (timestamp, slice index) and
every image set its own timestamp.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from streamdet.runtime_ort.lanes import ImagesSuperseded, LaneConfig, StreamingRunner, WorkerLane

MODES: tuple[str, ...] = ("streaming", "full-sweep", "sequential")
SLICE_LANE, IMAGE_LANE, ONE_QUEUE = "slice_lane", "image_lane", "one_queue"
# A job is known by what reaches the detector unchanged (the runner copies the data itself): kind, timestamp, slice.
JobKey = tuple[str, float, int]


class Detector(Protocol):
    uses_images: bool

    def detect_slice(self, points: np.ndarray, slice_index: int, timestamp: float | None = None,
                     num_slices: int | None = None): ...  # fmt: skip

    def update_images(self, images: Mapping[str, np.ndarray], timestamp: float | None = None, **options): ...


class JobHooks(Protocol):
    """What the player learns from inside a job (called on the worker's thread)."""

    # ``joined``: the job runs inside another job's run on the same thread (a coalesced slice after the run's first)
    def job_started(self, key: JobKey, joined: bool = False) -> None: ...

    def job_ended(self, key: JobKey, cpu_s: float, joined: bool = False) -> None: ...


class Instrumented:
    """A detector whose every call reports its start, end and thread CPU time; slices run as ``num_slices``."""

    def __init__(self, detector: Detector, num_slices: int, hooks: JobHooks) -> None:
        self.detector = detector
        self.uses_images = detector.uses_images
        self.num_slices = num_slices
        self.hooks = hooks
        if callable(getattr(detector, "detect_slices", None)):  # without it the runner never coalesces slices
            self.detect_slices = self._detect_slices

    def detect_slice(self, points: np.ndarray, slice_index: int, timestamp: float | None = None):
        return self._run(("slice", timestamp, int(slice_index)),
                         lambda: self.detector.detect_slice(points, slice_index, timestamp, self.num_slices))

    def _detect_slices(self, points, slice_indices, timestamps):
        """Slices the runner coalesced (LaneConfig.coalesce_slices): one run, each slice's start and end reported
        (all but the first as joined), the run's CPU time shared equally."""
        keys = [("slice", t, int(k)) for k, t in zip(slice_indices, timestamps)]
        for i, key in enumerate(keys):
            self.hooks.job_started(key, joined=i > 0)
        cpu0 = time.thread_time()
        try:
            return self.detector.detect_slices(points, slice_indices, timestamps, self.num_slices)
        finally:
            cpu_s = (time.thread_time() - cpu0) / len(keys)
            for i, key in enumerate(keys):
                self.hooks.job_ended(key, cpu_s, joined=i > 0)

    def update_images(self, images: Mapping[str, np.ndarray], timestamp: float | None = None, **options):
        # options (e.g. the quadrants of a partial update) pass through; one image set may then be several jobs
        return self._run(("images", timestamp, 0), lambda: self.detector.update_images(images, timestamp, **options))

    def __getattr__(self, name: str):
        # anything else the runner asks of its detector (camera names, LUT queries) is the wrapped detector's
        if name == "detector":  # not set yet: no recursion
            raise AttributeError(name)
        return getattr(self.detector, name)

    def _run(self, key: JobKey, job: Callable[[], object]):
        self.hooks.job_started(key)
        cpu0 = time.thread_time()
        try:
            return job()
        finally:
            self.hooks.job_ended(key, time.thread_time() - cpu0)


class SequentialRunner:
    """One FIFO, one worker: slices and image sets in arrival order; a waiting image set is superseded by a newer one.

    The runtime's own worker loop (`WorkerLane`), unbounded and with one worker: no slice is ever dropped.
    """

    def __init__(self, detector: Instrumented) -> None:
        self.detector = detector
        self._queue = WorkerLane("sequential-queue", workers=1, capacity=None)

    def submit_slice(self, points: np.ndarray, slice_index: int, timestamp: float | None = None) -> Future:
        return self._queue.submit(lambda: self.detector.detect_slice(points, slice_index, timestamp), kind="slice")

    def submit_images(self, images: Mapping[str, np.ndarray], timestamp: float | None = None, **options) -> Future:
        # options (camera_timestamps of a set whose cameras fired at different moments) pass through
        return self._queue.submit(lambda: self.detector.update_images(images, timestamp, **options), kind="images",
                                  supersede=lambda: ImagesSuperseded("image set superseded by a newer one"))  # fmt: skip

    @property
    def slices_dropped(self) -> int:
        return self._queue.dropped  # never: the queue is unbounded

    @property
    def images_superseded(self) -> int:
        return self._queue.superseded

    def close(self) -> None:
        self._queue.close()


@dataclass
class ModeRunner:
    """A mode opened on a detector: where the player submits, and how the work is laid out on threads."""

    name: str
    num_slices: int  # slices per sweep the player cuts and releases (1: full sweep)
    runner: StreamingRunner | SequentialRunner
    lane_of: dict[str, str]  # "slice" | "images" -> lane name
    workers: dict[str, int]  # lane name -> worker threads

    def close(self) -> None:
        self.runner.close()


def open_mode(name: str, detector: Detector, num_slices: int, hooks: JobHooks, lanes: LaneConfig = LaneConfig()) -> ModeRunner:
    """The mode ``name`` (one of MODES) around ``detector``; ``num_slices`` is the streaming slice count."""
    if name not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {name!r}")
    if name == "sequential":
        runner = SequentialRunner(Instrumented(detector, num_slices, hooks))
        return ModeRunner(name, num_slices, runner, {"slice": ONE_QUEUE, "images": ONE_QUEUE}, {ONE_QUEUE: 1})
    n = 1 if name == "full-sweep" else num_slices
    runner = StreamingRunner(Instrumented(detector, n, hooks), lanes)  # type: ignore[arg-type]  # the detector's interface
    return ModeRunner(name, n, runner, {"slice": SLICE_LANE, "images": IMAGE_LANE},
                      {SLICE_LANE: lanes.max_in_flight, IMAGE_LANE: 1})  # fmt: skip
