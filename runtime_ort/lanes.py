"""Worker threads, bounded queues and back-pressure around a `StreamingDetector`.

Back-pressure policy (what happens when work arrives faster than it is done):

- **Slice lane**: up to `max_in_flight` slices run at once, up to `queue_size` more wait. When the queue is full,
  the **oldest waiting** slice is dropped: its future fails with `SliceDropped`. A stale slice is worth less
  than a fresh one to a vehicle, and the caller (the LiDAR driver) must never block. With
  `LaneConfig.coalesce_slices` > 1 (the default: 2) a worker that starts a slice while the next slice of the same rotation and
  quadrant waits (and no other worker is free) detects them in one run (runtime_ort/coalesce.py): a lane that has
  fallen behind catches up at the cost of one graph run for the quadrant instead of dropping slices. With
  `LaneConfig.pair_hold_load` a loaded lane does not wait to fall behind: a worker holds a quadrant's first slice
  until the next one arrives (at most 1.5 slice periods) and detects both together (runtime_ort/pair_hold.py).
- **Image lane**: one update runs at a time and at most one waits. A newer image set **replaces** the waiting
  one (its future fails with `ImagesSuperseded`): only the newest images matter, and the slice lane always reads
  the newest finished image BEV. That is the ``full`` schedule; under ``LaneConfig.schedule = "phase-locked"`` the
  lane keeps the newest frame of each camera and lifts one quadrant at a time just before the LiDAR reaches it
  (`phase_locked_lane.py` says how, and how it degrades).

Both lanes run at the same time; each graph has its own onnxruntime session and thread pool, and onnxruntime
releases the GIL, so on a small CPU a slice does not wait behind a long image-encoder run.

Contracts:

- A submit never raises for another job's state: a future the caller cancelled is skipped (it neither runs nor
  counts as dropped) and never makes `submit_slice` fail. A submit raises only for its own arguments or a closed
  runner (`RunnerClosed`).
- A slice an idle worker is about to take counts as in flight, not waiting: a burst of submits to idle workers
  drops the oldest slice that would really wait, never one a free worker picks up.
- The points and images are copied at submit: the caller may reuse its buffers at once. They are checked first, so a
  corrupt one costs the caller's thread no copy: points that are no (N, 6) float32 array of at most
  ``MAX_SLICE_POINTS`` rows fail their future at once (never queued, so no waiting slice is dropped for them); a bad
  image set raises ValueError (``check_images``).
- ``timestamp=None`` means the submit time (``time.monotonic()`` when `submit_*` is called), not the run time.
- `close(timeout)` finishes the queued work; past the timeout it cancels what has not started and returns False.
  The phase-locked image lane has no queue: its image sets that no lift has used yet are cancelled at close.
  Every future a lane cancels or skips (the caller cancelled it) is one ``concurrent.futures.wait`` and
  ``as_completed`` see done.
- A runner dropped without `close()` is collected (its lanes' threads hold no reference to it): its workers end once
  the jobs already queued are done, as concurrent.futures' pools do; the phase-locked lane's unused image sets are
  cancelled. `close()` is still the way to wait for them.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import threading
import time
import warnings
import weakref
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from streamdet.calibration.camera import Rig
from streamdet.calibration.lut import Lut
from streamdet.core.camera_timeout import DEFAULT_CAMERA_TIMEOUT_S, check_camera_timeout
from streamdet.core.cpu import usable_cpus
from streamdet.core.points import MAX_SLICE_POINTS, SLICE_COLUMNS, slice_points_problem
from streamdet.runtime_ort.call_checks import slice_index_problem, timestamp_problem
from streamdet.runtime_ort.coalesce import can_coalesce
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.detector_results import ImageUpdate, SliceResult
from streamdet.runtime_ort.image_cache import check_camera_timestamps
from streamdet.runtime_ort.pair_hold import PairHold
from streamdet.runtime_ort.phase_lock import check_lidar_hz
from streamdet.runtime_ort.sessions import CPU_PROVIDER
from streamdet.runtime_ort.phase_locked_lane import PhaseLockedImageLane, PhaseLockStats
from streamdet.runtime_ort.thread_priority import check_nice
from streamdet.runtime_ort.worker_lane import JobBatching, RunnerClosed, WorkerLane

__all__ = ["ImagesSuperseded", "JobBatching", "LaneConfig", "RunnerClosed", "SliceDropped", "StreamingRunner", "WorkerLane"]


class SliceDropped(RuntimeError):
    """The slice waited in a full queue and was dropped for a newer one."""


class ImagesSuperseded(RuntimeError):
    """The image set was replaced by a newer one before the image lane got to it."""


class CalibrationSuperseded(RuntimeError):
    """The calibration was replaced by a newer one before the calibration lane got to it."""


SCHEDULES: tuple[str, ...] = ("full", "phase-locked")


@dataclass(frozen=True)
class LaneConfig:
    max_in_flight: int = 2  # slices processed at once (worker threads of the slice lane)
    queue_size: int = 8  # slices waiting beyond those in flight; when full the oldest waiting one is dropped
    # When the image lane works (docs/architecture.md, "Image-lane schedules"):
    # "full": every image set is encoded (all cameras) and lifted into all four quadrants as it arrives;
    # "phase-locked": the newest frame of each camera is kept and one quadrant at a time is lifted from the cameras
    # that see it, timed to finish just before the LiDAR's first slice of that quadrant arrives
    # (runtime_ort/phase_locked_lane.py, which states how it degrades when it cannot keep up).
    schedule: str = "full"
    # phase-locked only: LiDAR rotations per second on the runner's clock, within 0.5..100 Hz (LIDAR_HZ_RANGE,
    # runtime_ort/phase_lock.py: a spinning LiDAR's; a measured rate outside is not taken either); None: measured from
    # the slices' arrivals (what to use when the clock is scaled, e.g. a replay at --time-scale 2)
    lidar_hz: float | None = None
    lift_margin_ms: float = 2.0  # phase-locked only: a lift is timed to end this long before its first slice arrives
    # phase-locked only: a camera that has sent no frame for this long (seconds on the runner's clock, from its last
    # frame's arrival) counts as out: its last frame is no longer fused, the quadrants that see it are lifted again
    # without it (SliceResult.cameras_missing names it) and a quadrant none of whose cameras is left reads no image
    # (the LiDAR-only fallback export, else the camera-less BEV) until a frame comes (phase_locked_lane.py). A camera whose frame
    # period is over a third of this gets three of its periods instead, once its second frame tells its period
    # (core/camera_timeout.py). None: a camera's last frame is fused however old. (Under "full" each image set stands
    # alone: a camera not in it is zeros already, and a quadrant none of whose cameras it holds is cleared.)
    camera_timeout_s: float | None = DEFAULT_CAMERA_TIMEOUT_S
    # added to the image lane's thread's nice value (0..19, Linux; 0: unchanged): where the lanes share cores, the
    # slice lane's work is then served first and the image lane runs in the time left (runtime_ort/thread_priority.py).
    # Only the lane's own thread: with DetectorConfig.image_lane_threads != 1 onnxruntime's pool threads keep nice 0
    # (the runner warns)
    image_lane_nice: int = 0
    # phase-locked only: while this many slices (or more) wait in the slice lane's queue, the image lane starts no
    # encode or lift (one running finishes), so that where the lanes share cores a backlog of slices gets them before
    # it overflows the queue; passes that can then no longer be made are skipped (phase_locked_lane.py). A holding
    # back lasts at most 0.1 s (MAX_HOLD_S), then the lane works as long again. 0: never. Unlike image_lane_nice it
    # costs the images nothing while the slice lane keeps up. Measured no better than 0 (docs/replay.md).
    image_lane_yield_slices: int = 0
    # the most waiting slices one slice-graph run detects together when the slice lane is behind (consecutive slices
    # of one rotation and one quadrant: runtime_ort/coalesce.py); a slice joins the run a worker starts only when no
    # other worker is free to take it, so a lane that keeps up never coalesces. 2: pairs (a quadrant holds two of 8
    # slices); 1: never, every slice its own run and a backlog only drains by dropping (docs/replay.md, "Coalesced slices").
    # Slices of two rotations are told apart by their timestamps (one stamped before the run's last never joins it):
    # a driver that may hand a slice over after the next rotation's first should pass the scan timestamps, since
    # ``timestamp=None`` stamps the arrival, and such a late slice could then join that first slice's run.
    coalesce_slices: int = 2
    # hold a quadrant's first slice for the next one and detect both in one run while the slice lane is loaded: from
    # when its measured load (a slice's run time over the slice period per worker) is above this until it falls under
    # half of it (pair_hold.RELEASE_FRACTION). The pair's first slice waits about a slice period; a pair costs about
    # 0.6 of two single runs, so a loaded lane does a fifth less work at the same slice tail (measured: docs/replay.md,
    # "Slices held for their pair"; runtime_ort/pair_hold.py). Needs coalesce_slices >= 2. None (the default): never
    # hold, a slice waits only for a busy worker.
    pair_hold_load: float | None = None

    def __post_init__(self) -> None:
        for name in ("max_in_flight", "queue_size"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= 1024:
                raise ValueError(f"LaneConfig.{name} must be an int in 1..1024, got {v!r}")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"LaneConfig.schedule must be one of {SCHEDULES}, got {self.schedule!r}")
        check_lidar_hz(self.lidar_hz, "LaneConfig.lidar_hz")  # bounded: a rate of 1e300 Hz hung the lane's pass scan
        v = self.lift_margin_ms
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or not 0 <= v <= 1000:
            raise ValueError(f"LaneConfig.lift_margin_ms must be a number of ms in [0, 1000], got {v!r}")
        check_nice(self.image_lane_nice, "LaneConfig.image_lane_nice")
        check_camera_timeout(self.camera_timeout_s, "LaneConfig.camera_timeout_s")
        v = self.coalesce_slices
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= 64:
            raise ValueError(f"LaneConfig.coalesce_slices must be an int in 1..64 (1: never), got {v!r}")
        v = self.pair_hold_load
        if v is not None:
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or not 0 <= v <= 16:
                raise ValueError(f"LaneConfig.pair_hold_load must be None or a load in [0, 16], got {v!r}")
            if self.coalesce_slices < 2:
                raise ValueError(f"LaneConfig.pair_hold_load={v} needs coalesce_slices >= 2 (a held slice runs with its "
                                 f"partner), got coalesce_slices={self.coalesce_slices}")  # fmt: skip
        v = self.image_lane_yield_slices
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= v <= 1024:
            raise ValueError(f"LaneConfig.image_lane_yield_slices must be an int in 0..1024 (0: never yield), got {v!r}")
        if v and self.schedule != "phase-locked":
            raise ValueError(
                f"LaneConfig.image_lane_yield_slices={v} needs schedule='phase-locked' (the full schedule's update is one "
                f"job that cannot hold back between quadrants), got schedule={self.schedule!r}"
            )


def lanes_oversubscribe(image_threads: int, slice_threads: int, cpus: int) -> str | None:
    """The two lanes' intra-op threads (0: every CPU), which a runner runs at once, as ``"2 + 1"`` where together they
    exceed ``cpus`` and fewer would do; None where they fit (or are 1 + 1: on one CPU the lanes take turns whatever
    the setting)."""
    image, slices = image_threads or cpus, slice_threads or cpus
    return f"{image} + {slices}" if image + slices > cpus and image + slices > 2 else None


class StreamingRunner:
    """Asynchronous front of a StreamingDetector: `submit_images` and `submit_slice` return futures."""

    def __init__(self, detector: StreamingDetector, config: LaneConfig = LaneConfig()) -> None:
        if not isinstance(config, LaneConfig):
            raise ValueError(f"StreamingRunner takes a LaneConfig, got {type(config).__name__}")
        self.detector = detector
        self.config = config
        # What the lanes' threads run holds no reference to the runner (the slice jobs are _SliceJobs', the image jobs
        # the detector's): a runner dropped without close() is collected, and its finalizer stops the workers.
        self._slice_jobs = _SliceJobs(detector, config)
        batch = None  # a detector without detect_slices (a stand-in) runs every slice alone
        if self._slice_jobs.sector_layout is not None:
            jobs = self._slice_jobs
            hold = None if jobs.pair_hold is None else jobs.hold_s
            batch = JobBatching(joins=jobs.joins, run=jobs.detect_together, most=config.coalesce_slices, hold=hold, fits=_run_fits)
        slices = self._slices = WorkerLane("slice-lane", config.max_in_flight, config.queue_size,
                                           lambda: SliceDropped("slice dropped: queue full"), batch=batch)  # fmt: skip
        superseded = lambda: ImagesSuperseded("image set superseded by a newer one")  # noqa: E731
        self._phase_locked: PhaseLockedImageLane | None = None
        self._images: WorkerLane | None = None
        self._cleared = _Count()  # quadrants the full schedule's updates cleared (ImageUpdate.cleared)
        if config.schedule == "phase-locked" and detector.uses_images:
            self._phase_locked = PhaseLockedImageLane(
                detector, detector.num_slices, detector.config.start_deg, config.lidar_hz, config.lift_margin_ms * 1e-3,
                superseded=superseded, closed=lambda: RunnerClosed("image-lane: submit after close()"), nice=config.image_lane_nice,
                backlog=lambda: slices.waiting, yield_at=config.image_lane_yield_slices, camera_timeout_s=config.camera_timeout_s,
                clockwise=bool(detector.config.clockwise),
            )  # fmt: skip
        else:
            self._images = WorkerLane("image-lane", 1, 1, superseded, nice=config.image_lane_nice)
        # calibration swaps (submit_calibration): one at a time off the caller's thread, a newer one replacing one waiting
        self._calibration = WorkerLane("calibration-lane", 1, 1,
                                       lambda: CalibrationSuperseded("calibration superseded by a newer one"))  # fmt: skip
        weakref.finalize(self, _stop_lanes, self._slices, self._images if self._images is not None else self._phase_locked,
                         self._calibration)  # fmt: skip
        threads = getattr(getattr(detector, "config", None), "image_lane_threads", 1)
        if config.image_lane_nice and threads != 1 and detector.uses_images:
            warnings.warn(f"LaneConfig.image_lane_nice={config.image_lane_nice} renices the image lane's own thread only: "
                          f"with DetectorConfig.image_lane_threads={threads} onnxruntime's pool threads of the image "
                          "sessions keep nice 0 and compete with the slice lane as before; use image_lane_threads=1",
                          RuntimeWarning, stacklevel=2)  # fmt: skip
        slice_threads = getattr(getattr(detector, "config", None), "slice_lane_threads", 1)
        on_cpu = tuple(getattr(detector, "providers", (CPU_PROVIDER,)))[:1] == (CPU_PROVIDER,)
        if detector.uses_images and on_cpu and (busy := lanes_oversubscribe(threads, slice_threads, usable_cpus())):
            warnings.warn(f"the image lane's and the slice lane's intra-op threads run at once: {busy} on "
                          f"{usable_cpus()} usable CPU(s), so they take turns and the slice lane waits on the image "
                          "lane's work (DetectorConfig.image_lane_threads / slice_lane_threads count per session)",
                          RuntimeWarning, stacklevel=2)  # fmt: skip

    def submit_images(
        self, images: Mapping[str, np.ndarray], timestamp: float | None = None, camera_timestamps: Mapping[str, float] | None = None,
    ) -> "Future[ImageUpdate]":  # fmt: skip
        """Queue an image update. A LiDAR-only detector has no image lane: NoImageLaneError at once, in the
        caller's thread, rather than in a future nobody may read. ``camera_timestamps``: each camera's capture time
        where the cameras fired at different moments (``StreamingDetector.update_images``)."""
        if not self.detector.uses_images:
            self.detector.update_images(images, timestamp)  # raises NoImageLaneError naming the export
        if not isinstance(images, Mapping):
            self.detector.update_images(images, timestamp)  # raises ValueError naming the type, in the caller's thread
        stamp = time.monotonic() if timestamp is None else timestamp
        # a bad timestamp fails here too, under either schedule: queued, it would supersede a good set waiting
        problem = timestamp_problem(timestamp)
        if problem is not None:
            raise ValueError(problem)
        # a bad image set (an unknown camera, a wrong size) fails here, in the caller's thread, before any copy and not
        # in a later lift or update; a stand-in detector without the check is checked by its update_images
        check = getattr(self.detector, "check_images", None) if self._phase_locked is None else self.detector.check_images
        if check is not None:
            check(images)
        # copies: the driver may refill its buffers as soon as this returns
        own = {name: np.array(a, copy=True) if isinstance(a, np.ndarray) else a for name, a in images.items()}
        cameras = check_camera_timestamps(camera_timestamps, own)
        if self._phase_locked is not None:
            return self._phase_locked.submit_images(own, stamp, cameras)
        options = {} if camera_timestamps is None else {"camera_timestamps": cameras}
        update = self.detector.update_images  # the job holds the detector's method and the count, not the runner
        cleared = self._cleared

        def job():
            result = update(own, stamp, **options)
            cleared.add(len(getattr(result, "cleared", ())))
            return result

        return self._images.submit(job)

    def submit_calibration(self, calibration: Rig | Lut | Mapping | str | os.PathLike) -> "Future[None]":
        """``StreamingDetector.set_calibration`` off the caller's thread: a LUT build and a re-lift take a good part of
        a second of CPU, which a vehicle's calibration callback should not spend itself. One swap runs at a time; a
        newer calibration replaces one still waiting (its future fails with CalibrationSuperseded). The future holds
        None, or the swap's error (CalibrationError: the LUT in use stays). A parsed calibration.json (a dict) is
        read into a Rig here, in the caller's thread (its errors raise here, and the caller may reuse the dict); a
        LiDAR-only detector raises NoImageLaneError here."""
        if not self.detector.uses_images:
            self.detector.set_calibration(calibration)  # raises NoImageLaneError naming the export
        if isinstance(calibration, Mapping):
            calibration = Rig.from_calibration_json(calibration)
        swap = self.detector.set_calibration  # the job holds the detector's method, not the runner
        return self._calibration.submit(lambda: swap(calibration))

    def submit_slice(self, points: np.ndarray, slice_index: int, timestamp: float | None = None) -> "Future[SliceResult]":
        """Queue one slice; its future holds the SliceResult, or the error (bad points, SliceDropped). Points that are
        no (N, 6) float32 array of at most MAX_SLICE_POINTS rows, a ``slice_index`` outside [0, num_slices) and a
        ``timestamp`` that is no finite number fail their future at once: such a slice is neither copied nor queued
        (no good slice waiting is dropped for it)."""
        arrival = time.monotonic()
        stamp = arrival if timestamp is None else timestamp
        # before the copy (a huge array would be copied in the driver's thread) and never queued (it would push a good
        # slice out of a full queue only to fail in its worker)
        index_problem = slice_index_problem(slice_index, getattr(self.detector, "num_slices", None))
        refused = _points_refused(points) or index_problem or timestamp_problem(timestamp)
        own = np.array(points, copy=True) if refused is None else None  # the driver may reuse its buffer
        tracked = self._slice_jobs.pair_hold is not None or self._phase_locked is not None  # they learn the LiDAR's timing
        valid = tracked and index_problem is None
        if self._slice_jobs.pair_hold is not None and valid:
            self._slice_jobs.pair_hold.observe_arrival(arrival)  # before the submit: a worker may decide on its hold at once
        if refused is not None:  # still an arrival of the LiDAR's: its timing was observed
            future: Future = Future()
            future.set_exception(ValueError(refused))
        else:
            detect = self._slice_jobs.detect_one  # the job holds _SliceJobs', not the runner
            future = self._slices.submit(lambda: detect(own, slice_index, stamp, arrival), payload=(own, slice_index, stamp, arrival))
        if self._phase_locked is not None and valid:
            self._phase_locked.observe_slice(int(slice_index), arrival)  # its arrival on the runner's clock
        return future

    @property
    def slices_dropped(self) -> int:
        """Slices dropped so far because the slice queue was full (``LaneConfig.queue_size``): each time, the oldest
        waiting slice's future failed with ``SliceDropped``. A count that keeps rising means the slice lane is short
        of CPU for the slice rate."""
        return self._slices.dropped

    @property
    def slices_waiting(self) -> int:
        """Slices queued now and not yet taken by a worker (at most ``LaneConfig.queue_size``): the slice lane's
        backlog at this moment, where ``slices_dropped`` counts what it has cost so far."""
        return self._slices.waiting

    @property
    def slices_coalesced(self) -> int:
        """Slices detected inside another slice's run (LaneConfig.coalesce_slices): graph runs saved."""
        return self._slices.joined

    @property
    def slices_held(self) -> int:
        """Slice runs whose first slice waited for the next one of its quadrant (LaneConfig.pair_hold_load)."""
        return self._slices.held

    @property
    def pair_hold_load(self) -> float | None:
        """The slice lane's measured load, the median cost of a slice over its recent runs over the slice period per
        worker (LaneConfig.pair_hold_load); None without the hold, or before the period and the cost are measured."""
        return None if self._slice_jobs.pair_hold is None else self._slice_jobs.pair_hold.load

    @property
    def images_superseded(self) -> int:
        """Image sets replaced by a newer one before the image lane used them, so far: each one's future failed
        with ``ImagesSuperseded``. Under ``schedule="full"`` a set still waiting when the next arrives; under
        ``"phase-locked"`` a set none of whose frames was lifted before newer frames of its cameras replaced them."""
        return self._images.dropped if self._images is not None else self._phase_locked.images_superseded

    @property
    def quadrants_cleared(self) -> int:
        """Quadrants left without image BEV so far because none of their cameras had a frame: under ``"full"`` the
        quadrants of each image update given none of their cameras (``ImageUpdate.cleared``); under
        ``"phase-locked"`` also those whose cameras all timed out (``PhaseLockStats.quadrants_cleared``). Their
        slices read the camera-less BEV or the LiDAR-only fallback and name the cameras in ``cameras_missing``."""
        return self._cleared.value if self._images is not None else self._phase_locked.stats.quadrants_cleared

    @property
    def image_lane_cpu_s(self) -> float:
        """CPU seconds the image lane's updates have used so far (its worker's thread time)."""
        return self._images.cpu_s if self._images is not None else self._phase_locked.cpu_s

    @property
    def slice_lane_cpu_s(self) -> float:
        """CPU seconds the slice lane's jobs have used so far (its workers' thread time)."""
        return self._slices.cpu_s

    @property
    def phase_lock(self) -> PhaseLockStats | None:
        """What the phase-locked image lane did (lifts, skips, full updates before the lock); None under "full"."""
        return None if self._phase_locked is None else self._phase_locked.stats

    def close(self, timeout: float | None = None) -> bool:
        """Finish the queued work, then stop the workers; later submits raise RunnerClosed.

        With ``timeout`` (seconds, for the slice, image and calibration lanes together), work not started by then is cancelled (its futures
        report cancelled) and this returns False while a job still runs (its worker ends after it); True when
        everything finished. Called from a done-callback on one of the runner's own workers, it closes every lane
        without waiting for that worker (it ends once the callback returns and its queued work is done) and returns
        False.
        """
        if timeout is not None and (isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not timeout >= 0):
            raise ValueError(f"close(timeout=...) takes None or seconds >= 0, got {timeout!r}")
        deadline = None if timeout is None else time.monotonic() + timeout
        lanes = (self._slices, self._images if self._images is not None else self._phase_locked, self._calibration)
        if any(lane.runs_on(threading.current_thread()) for lane in lanes):
            # on a worker (a done-callback): wait for none, or two callbacks closing at once would wait for each other
            for lane in lanes:
                lane.close(deadline, wait=False)
            return False
        return all([lane.close(deadline) for lane in lanes])  # a list: every lane is closed, whatever one returns

    def __enter__(self) -> "StreamingRunner":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _SliceJobs:
    """What the slice lane's workers run: one slice, or slices of one quadrant together (coalesced), and the pair
    hold's timing. Apart from the runner so that the lane's threads never hold it (runner finalizer)."""

    def __init__(self, detector: StreamingDetector, config: LaneConfig) -> None:
        self.detector = detector
        self.pair_hold: PairHold | None = None
        self.sector_layout: tuple[int, float, bool] | None = None  # (n, start_deg, clockwise); None: every slice runs alone
        if config.coalesce_slices > 1 and callable(getattr(detector, "detect_slices", None)):
            # read once, here: a join runs in a worker under the lane's lock and must not fail
            self.sector_layout = (int(detector.num_slices), float(detector.config.start_deg), bool(detector.config.clockwise))
            if config.pair_hold_load is not None:
                self.pair_hold = PairHold(config.pair_hold_load, config.max_in_flight, *self.sector_layout)

    def detect_one(self, points: np.ndarray, slice_index: int, stamp: float, arrival: float) -> SliceResult:
        if self.pair_hold is None:
            return _timed(self.detector.detect_slice(points, slice_index, stamp), arrival)
        t0 = time.perf_counter()
        result = self.detector.detect_slice(points, slice_index, stamp)
        self.pair_hold.record_run(1, time.perf_counter() - t0)
        return _timed(result, arrival)

    def hold_s(self, payload: tuple) -> float:
        """Seconds the worker that took this slice waits for the next one of its quadrant (PairHold)."""
        if not _well_formed(payload):
            return 0.0
        return self.pair_hold.hold_s(int(payload[1]), payload[3], time.monotonic())

    def joins(self, run_last: tuple, waiting: tuple) -> bool:
        """May the waiting slice join a run that ends with ``run_last``? Both well-formed (a bad slice runs alone, so
        its error is its own), the next slice of the rotation in the same quadrant(s)."""
        if not (_well_formed(run_last) and _well_formed(waiting)) or waiting[2] < run_last[2]:
            return False
        n, start_deg, clockwise = self.sector_layout
        return run_last[1] < n and can_coalesce(int(run_last[1]), int(waiting[1]), n, start_deg, clockwise)

    def detect_together(self, payloads: list) -> tuple[SliceResult, ...]:
        points, indices, stamps, arrivals = zip(*payloads)
        t0 = time.perf_counter()
        results = self.detector.detect_slices(points, indices, stamps)
        if self.pair_hold is not None:
            self.pair_hold.record_run(len(payloads), time.perf_counter() - t0)
        return tuple(_timed(r, a) for r, a in zip(results, arrivals))


def _timed(result: SliceResult, arrival: float) -> SliceResult:
    """``result`` with the runner's submit and completion times (a stand-in's result of another type as it is)."""
    if not isinstance(result, SliceResult):
        return result
    return dataclasses.replace(result, submitted_s=arrival, completed_s=time.monotonic())


def _stop_lanes(slices: WorkerLane, images: "WorkerLane | PhaseLockedImageLane", calibration: WorkerLane) -> None:
    """A runner dropped without close(): its workers end once they have done the jobs already queued (their futures
    still complete); nothing is waited for here (this may run on any thread, a worker's included)."""
    slices.stop()
    images.stop()
    calibration.stop()


def _run_fits(payloads: list) -> bool:
    """May these well-formed slices (``_slices_join`` said so) run together? Their points together are no more than
    MAX_SLICE_POINTS, the most one slice-graph run takes: slices each within it never fail a run for their sum."""
    return sum(p[0].shape[0] for p in payloads) <= MAX_SLICE_POINTS


def _points_refused(points: object) -> str | None:
    """Why ``points`` cannot be a slice (the detector's own words, core/points.py), read from its type and shape alone;
    None if it can."""
    problem = slice_points_problem(points)
    if problem is not None:
        return problem
    if points.shape[0] > MAX_SLICE_POINTS:
        return f"points: a slice of {points.shape[0]} points, more than MAX_SLICE_POINTS = {MAX_SLICE_POINTS} (a corrupt array?)"
    return None


def _well_formed(payload: tuple) -> bool:
    """A slice job's (points, slice_index, timestamp, arrival) that `detect_slices` takes as it is."""
    points, k, stamp = payload[:3]
    return (
        isinstance(points, np.ndarray) and points.dtype == np.float32 and points.ndim == 2
        and points.shape[1] == SLICE_COLUMNS
        and isinstance(k, (int, np.integer)) and not isinstance(k, bool) and k >= 0
        and isinstance(stamp, numbers.Real) and not isinstance(stamp, bool) and math.isfinite(stamp)
    )  # fmt: skip


class _Count:
    """A counter jobs on the lanes' threads add to (held by the jobs, not by the runner)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.value = 0

    def add(self, n: int) -> None:
        with self._lock:
            self.value += n
