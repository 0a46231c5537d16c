"""Worker threads, bounded queues and back-pressure around a `StreamingDetector`.

Back-pressure policy (what happens when work arrives faster than it is done):

- **Slice lane**: up to `max_in_flight` slices run at once, up to `queue_size` more wait. When the queue is full,
  the **oldest waiting** slice is dropped: its future fails with `SliceDropped`. A stale slice is worth less
  than a fresh one to a vehicle, and the caller (the LiDAR driver) must never block.
- **Image lane**: one update runs at a time and at most one waits. A newer image set **replaces** the waiting
  one (its future fails with `ImagesSuperseded`): only the newest images matter, and the slice lane always reads
  the newest finished image BEV.

Both lanes run at the same time; each graph has its own onnxruntime session and thread pool, and onnxruntime
releases the GIL, so on a small CPU a slice does not wait behind a long image-encoder run.
"""

from __future__ import annotations

import collections
import threading
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np

from streamdet.runtime_ort.detector import ImageUpdate, SliceResult, StreamingDetector


class SliceDropped(RuntimeError):
    """The slice waited in a full queue and was dropped for a newer one."""


class ImagesSuperseded(RuntimeError):
    """The image set was replaced by a newer one before the image lane got to it."""


@dataclass(frozen=True)
class LaneConfig:
    max_in_flight: int = 2  # slices processed at once (worker threads of the slice lane)
    queue_size: int = 8  # slices waiting beyond those in flight; when full the oldest waiting one is dropped

    def __post_init__(self) -> None:
        if self.max_in_flight < 1 or self.queue_size < 1:
            raise ValueError(f"LaneConfig needs max_in_flight >= 1 and queue_size >= 1, got {self}")


class _Lane:
    """A bounded FIFO served by worker threads; when full, the oldest waiting job is failed with `overflow`."""

    def __init__(self, name: str, workers: int, capacity: int, overflow: Callable[[], Exception]) -> None:
        self._jobs: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._capacity = capacity
        self._overflow = overflow
        self._closed = False
        self.dropped = 0
        self._threads = [threading.Thread(target=self._serve, name=f"{name}-{i}", daemon=True) for i in range(workers)]
        for t in self._threads:
            t.start()

    def submit(self, fn: Callable[[], object]) -> Future:
        fut: Future = Future()
        with self._cond:
            if self._closed:
                raise RuntimeError("the lane is closed")
            while len(self._jobs) >= max(self._capacity, 1) and self._jobs:
                _, old = self._jobs.popleft()
                self.dropped += 1
                old.set_exception(self._overflow())
            self._jobs.append((fn, fut))
            self._cond.notify()
        return fut

    def _serve(self) -> None:
        while True:
            with self._cond:
                while not self._jobs and not self._closed:
                    self._cond.wait()
                if not self._jobs:
                    return
                fn, fut = self._jobs.popleft()
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(fn())
            except BaseException as e:  # handed to the caller through the future, never swallowed
                fut.set_exception(e)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        for t in self._threads:
            t.join()


class StreamingRunner:
    """Asynchronous front of a StreamingDetector: `submit_images` and `submit_slice` return futures."""

    def __init__(self, detector: StreamingDetector, config: LaneConfig = LaneConfig()) -> None:
        self.detector = detector
        self.config = config
        self._slices = _Lane("slice-lane", config.max_in_flight, config.queue_size, lambda: SliceDropped("slice dropped: queue full"))
        self._images = _Lane("image-lane", 1, 1, lambda: ImagesSuperseded("image set superseded by a newer one"))

    def submit_images(self, images: Mapping[str, np.ndarray], timestamp: float | None = None) -> "Future[ImageUpdate]":
        """Queue an image update. A LiDAR-only detector has no image lane: NoImageLaneError at once, in the
        caller's thread, rather than in a future nobody may read."""
        if not self.detector.uses_images:
            self.detector.update_images(images, timestamp)  # raises NoImageLaneError naming the export
        return self._images.submit(lambda: self.detector.update_images(images, timestamp))

    def submit_slice(self, points: np.ndarray, slice_index: int, timestamp: float | None = None) -> "Future[SliceResult]":
        return self._slices.submit(lambda: self.detector.detect_slice(points, slice_index, timestamp))

    @property
    def slices_dropped(self) -> int:
        return self._slices.dropped

    @property
    def images_superseded(self) -> int:
        return self._images.dropped

    def close(self) -> None:
        """Finish the queued work, then stop the workers."""
        self._slices.close()
        self._images.close()

    def __enter__(self) -> "StreamingRunner":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
