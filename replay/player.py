"""The real-time player: a drive's slices and image sets handed to a mode at their release times.

The player runs its own thread, as a vehicle's sensor driver would: it sleeps until the next release, submits it
and moves on. Submitting never blocks on the detector (the lanes queue, drop or supersede instead), so a slow
detector cannot slow the sensors down; the record shows what it costs instead. Every time in the record is drive
time (`DriveClock`: wall seconds over the time scale).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from streamdet.core.sectors import quadrants_of_sector
from streamdet.replay.assemble import SetAssembler
from streamdet.replay.clock import PLAYER, Clock, DriveClock
from streamdet.replay.modes import MODES, Detector, JobKey, ModeRunner, open_mode
from streamdet.replay.record import ImageRecord, Recording, SliceRecord, percentiles
from streamdet.replay.schedule import SLICE, Release, check_delivery, check_time_scale, release_schedule
from streamdet.replay.source import Drive
from streamdet.runtime_ort.heap import GcPauses, frozen_heap
from streamdet.runtime_ort.lanes import ImagesSuperseded, LaneConfig, SliceDropped

Progress = Callable[[str], None]
# An image timestamp earlier than this is a warm-up (run.WARM_UP_TIMESTAMP_S), not a picture of the drive: a slice fused
# with it counts as fused with no image, and has no image age.
WARM_UP_BEFORE_S = -1e6


@dataclass(frozen=True)
class PlayerConfig:
    mode: str = "streaming"  # one of MODES
    num_slices: int = 8  # slices per rotation in streaming and sequential modes
    start_deg: float = 0.0  # the LiDAR's scan layout (the detector's DetectorConfig.start_deg and clockwise, below)
    time_scale: float = 1.0  # wall seconds per drive second: 2 plays twice as slowly (a 2x faster computer)
    lanes: LaneConfig = field(default_factory=LaneConfig)  # the runner's slice-lane workers and queue
    progress_every_s: float = 0.5  # wall seconds between progress lines
    # every camera frame reaches the detector this long after its capture (exposure, readout, ISP, transport); its
    # timestamp stays the capture time. 0: at capture
    camera_delivery_ms: float = 0.0
    # freeze the heap alive when the drive starts out of the garbage collector's full collections (runtime_ort/heap.py),
    # as a vehicle process would after its start-up: such a collection stalls every Python thread for tens of ms
    freeze_heap: bool = True
    clockwise: bool = False  # the LiDAR turns clockwise seen from above (with start_deg: its scan layout)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"PlayerConfig.mode must be one of {MODES}, got {self.mode!r}")
        if not (isinstance(self.num_slices, int) and self.num_slices >= 1):
            raise ValueError(f"PlayerConfig.num_slices must be an integer >= 1, got {self.num_slices!r}")
        check_time_scale(self.time_scale, "PlayerConfig.time_scale")
        check_delivery(self.camera_delivery_ms, "PlayerConfig.camera_delivery_ms", "ms")


class _Book:
    """The player's bookkeeping, shared by the player thread and the workers' callbacks."""

    def __init__(self, clock: DriveClock, mode: ModeRunner) -> None:
        self.clock = clock
        self.mode = mode
        self.lock = threading.Lock()
        self.by_key: dict[JobKey, tuple[SliceRecord | ImageRecord, str]] = {}
        self.waiting = {lane: 0 for lane in mode.workers}  # released, not started, not dropped
        self.outstanding = {lane: 0 for lane in mode.workers}  # released, future not done
        self.joined = {lane: 0 for lane in mode.workers}  # running inside another job's run (coalesced slices)
        self.player_active = True
        self.errors: list[BaseException] = []
        self.held: list[ImageRecord] = []  # image releases collected by the SetAssembler, not handed over yet

    def sleepers_expected(self) -> int:
        """Threads that must be asleep in a FakeClock before it may advance (read without the lock, see FakeClock)."""
        # a coalesced run is one busy worker however many jobs it holds
        busy = sum(min(self.outstanding[lane] - self.joined[lane], n) for lane, n in self.mode.workers.items())
        return int(self.player_active) + busy

    def job_started(self, key: JobKey, joined: bool = False) -> None:
        with self.lock:
            rec, lane = self.by_key[key]
            self.joined[lane] += int(joined)
            if math.isnan(rec.start_s):  # a release the runner splits into several jobs starts once
                rec.start_s = self.clock.now()
                self.waiting[lane] -= 1

    def job_ended(self, key: JobKey, cpu_s: float, joined: bool = False) -> None:
        with self.lock:
            rec, lane = self.by_key[key]
            self.joined[lane] -= int(joined)
            rec.end_s = self.clock.now()
            rec.cpu_s += cpu_s

    def done(self, rec: SliceRecord | ImageRecord, lane: str, fut: concurrent.futures.Future) -> None:
        exc = fut.exception()
        with self.lock:
            if isinstance(exc, SliceDropped):
                rec.dropped = True  # type: ignore[union-attr]
                self.waiting[lane] -= 1
            elif isinstance(exc, ImagesSuperseded):
                rec.superseded = True  # type: ignore[union-attr]
                self.waiting[lane] -= 1
            elif exc is not None:
                self.errors.append(exc)
            else:
                rec.emit_s = self.clock.now()
                if isinstance(rec, ImageRecord) and math.isnan(rec.start_s):
                    self.waiting[lane] -= 1  # used by an update another release started (batched, or a later lift)
                if isinstance(rec, SliceRecord):
                    result = fut.result()
                    rec.detections = result.detections
                    rec.num_detections = len(result.detections)
                    rec.fallback = bool(getattr(result, "fallback", False))
                    rec.coalesced = max(1, len(getattr(result, "coalesced", ())))
                    ts = result.image_timestamp
                    rec.image_capture_s = float(ts) if ts is not None and ts > WARM_UP_BEFORE_S else math.nan
            self.outstanding[lane] -= 1
        poke = getattr(self.clock.base, "poke", None)
        if poke is not None:
            poke()


def play(
    drive: Drive, detector: Detector, clock: Clock, config: PlayerConfig = PlayerConfig(), progress: Progress | None = None
) -> Recording:
    """Play ``drive`` through ``detector`` in ``config.mode`` on ``clock``; returns the record of every release."""
    dclock = DriveClock(clock, config.time_scale)
    book: _Book
    mode = open_mode(config.mode, detector, config.num_slices, _Hooks(lambda: book), config.lanes)
    book = _Book(dclock, mode)
    delivery_s = config.camera_delivery_ms / 1e3
    schedule = release_schedule(drive, mode.num_slices, config.start_deg, images=detector.uses_images,
                                camera_delivery_s=delivery_s, clockwise=config.clockwise)  # fmt: skip
    records = [_record(r) for r in schedule]
    # an image lane that updates from every camera at once gets whole sets (assemble.py); a phase-locked one each frame
    phase_locked = getattr(mode.runner, "phase_lock", None) is not None
    cameras = tuple(dict.fromkeys(n for s in drive.image_sets for n in s.images))
    timeout = config.lanes.camera_timeout_s  # the runner's (wall) seconds: drive seconds for the assembler
    assembler = SetAssembler(cameras, None if timeout is None else timeout / config.time_scale) if cameras and not phase_locked else None
    if hasattr(clock, "set_participants"):
        clock.set_participants(book.sleepers_expected)
    futures: list[concurrent.futures.Future] = []
    cpu = {"player": 0.0}
    process0 = time.process_time()
    at_top_k0 = getattr(detector, "slice_runs_at_top_k", 0)  # the warm-up's runs are not the drive's

    def drive_sensors() -> None:
        cpu0 = time.thread_time()
        try:
            for release, rec in zip(schedule, records):
                dclock.sleep_until(release.time_s, PLAYER)
                fut = _submit(mode, book, release, rec, assembler)
                if fut is not None:
                    futures.append(fut)
        except BaseException as e:  # reported by play() after the workers finish, never lost in a thread
            book.errors.append(e)
        finally:
            cpu["player"] = time.thread_time() - cpu0
            book.player_active = False
            poke = getattr(clock, "poke", None)
            if poke is not None:
                poke()

    with frozen_heap(config.freeze_heap), GcPauses() as gc_pauses:
        dclock.start(0.0)
        thread = threading.Thread(target=drive_sensors, name="replay-player", daemon=True)
        thread.start()
        while thread.is_alive():
            thread.join(timeout=config.progress_every_s if progress else None)
            if progress and thread.is_alive():
                progress(_progress_line(config.mode, drive, dclock.now(), records))
        concurrent.futures.wait(futures)
        mode.close()
    for rec in book.held:  # frames at the drive's end whose set never completed: never used
        rec.superseded = True
    image_lane_cpu_s = getattr(mode.runner, "image_lane_cpu_s", float("nan"))  # the sequential queue has no image lane
    phase_lock = getattr(mode.runner, "phase_lock", None)  # what a phase-locked image lane did
    _newest_images_by_scan_start(drive, records, getattr(detector, "quadrant_cameras", None), config.start_deg, delivery_s,
                                 config.clockwise, None if timeout is None else timeout / config.time_scale)  # fmt: skip
    if book.errors:
        _raise_failure(f"{config.mode} replay of {drive.name}", book.errors[0])
    slices = tuple(r for r in records if isinstance(r, SliceRecord))
    images = tuple(r for r in records if isinstance(r, ImageRecord))
    times = [r.release_s for r in records] + [r.emit_s for r in records if math.isfinite(r.emit_s)]
    wall_s = (max(times) - min(times)) * config.time_scale if records else 0.0
    return Recording(config.mode, drive.name, config.time_scale, slices, images, wall_s, cpu["player"],
                     time.process_time() - process0, image_lane_cpu_s, len(drive.sweeps),
                     None if phase_lock is None else dataclasses.asdict(phase_lock), gc_pauses.to_dict(),
                     getattr(mode.runner, "slices_held", 0), getattr(detector, "slice_runs_at_top_k", 0) - at_top_k0)  # fmt: skip


def _newest_images_by_scan_start(
    drive: Drive, records: list, quadrant_cameras: Callable[[tuple[int, ...]], tuple[str, ...]] | None, start_deg: float,
    delivery_s: float = 0.0, clockwise: bool = False, timeout_s: float | None = None,
) -> None:  # fmt: skip
    """Each slice record's ``newest_capture_s``: how old the newest images of its quadrants could be when the sensor
    started scanning the slice's sector: per camera that sees its quadrant(s) (``quadrant_cameras``; None: every
    camera), the newest frame released (delivered: captured ``delivery_s`` earlier) by then; the oldest of those (a
    quadrant is as old as its oldest camera's frame, as the runtime stamps it). With simultaneous triggers: the
    newest image set released by then. A camera whose newest frame was released more than ``timeout_s`` (drive
    seconds; LaneConfig.camera_timeout_s) before is out, as the lanes count it, and left out: its last frame, however
    old, made the reference seconds old and the staleness added hugely negative during an outage."""
    captures: dict[str, list[float]] = {}
    for s in drive.image_sets:  # in time order (Drive checks)
        for name in s.images:
            captures.setdefault(name, []).append(s.capture_s)
    times = {n: np.array(t, dtype=np.float64) for n, t in captures.items()}
    sweeps = {s.index: s for s in drive.sweeps}
    seen: dict[tuple[int, int], tuple[str, ...]] = {}
    for rec in records:
        if isinstance(rec, SliceRecord) and times:
            key = (rec.slice_index, rec.num_slices)
            if key not in seen:
                cams = tuple(times) if quadrant_cameras is None else tuple(
                    quadrant_cameras(quadrants_of_sector(rec.slice_index, rec.num_slices, start_deg, clockwise)))  # fmt: skip
                seen[key] = tuple(n for n in cams if n in times) or tuple(times)
            sweep = sweeps[rec.sweep]
            scan_start = sweep.start_s + sweep.duration_s * rec.slice_index / rec.num_slices
            newest = []
            for name in seen[key]:
                i = int(np.searchsorted(times[name], scan_start - delivery_s, side="right")) - 1
                if i >= 0 and (timeout_s is None or times[name][i] + delivery_s >= scan_start - timeout_s):
                    newest.append(float(times[name][i]))
            rec.newest_capture_s = min(newest) if newest else math.nan


class ReplayInputError(ValueError, RuntimeError):
    """A replay stopped by its input (a ValueError or OSError inside the detector or the player: bad data, a file
    that cannot be read). A ValueError, so that the tools report the cause in one line as they do any input error,
    and a RuntimeError, as every failed replay was before, for callers that catch that."""


def _raise_failure(where: str, error: BaseException) -> None:
    """Raise the first error of a replay, named after ``where``: bad input as a `ReplayInputError` whose message is
    the cause's own (one line for the user), anything else as a RuntimeError chained to it (a bug: its traceback is
    what a report needs)."""
    if not isinstance(error, Exception):  # KeyboardInterrupt, SystemExit: as they are
        raise error
    if isinstance(error, (ValueError, OSError)):
        raise ReplayInputError(f"{where}: {error}") from error
    raise RuntimeError(f"{where} failed: {error!r}") from error


class _Hooks:
    """Forwards the Instrumented detector's calls to the book, which exists only once the mode is open."""

    def __init__(self, book: Callable[[], _Book]) -> None:
        self._book = book

    def job_started(self, key: JobKey, joined: bool = False) -> None:
        self._book().job_started(key, joined)

    def job_ended(self, key: JobKey, cpu_s: float, joined: bool = False) -> None:
        self._book().job_ended(key, cpu_s, joined)


def _record(release: Release) -> SliceRecord | ImageRecord:
    if release.kind == SLICE:
        s = release.item
        return SliceRecord(s.sweep, s.slice_index, s.num_slices, s.scan_end_s, len(s.points))
    return ImageRecord(release.item.index, release.item.capture_s)


def _submit(
    mode: ModeRunner, book: _Book, release: Release, rec: SliceRecord | ImageRecord, assembler: SetAssembler | None = None
) -> concurrent.futures.Future | None:  # fmt: skip
    """Hand one release to the mode; None when the assembler holds an image release for a later whole set."""
    lane = mode.lane_of[release.kind]
    item = release.item
    key = ("slice", item.scan_end_s, item.slice_index) if release.kind == SLICE else ("images", item.capture_s, 0)
    with book.lock:
        rec.release_s = book.clock.now()
        rec.queue_depth = book.waiting[lane]
        book.waiting[lane] += 1
        book.by_key[key] = (rec, lane)
    if release.kind == SLICE:
        recs = [rec]
        with book.lock:
            book.outstanding[lane] += 1
        fut = mode.runner.submit_slice(item.points, item.slice_index, item.scan_end_s)
    elif assembler is None:
        recs = [rec]
        with book.lock:
            book.outstanding[lane] += 1
        fut = mode.runner.submit_images(item.images, item.capture_s)
    else:
        whole = assembler.offer(item.images, item.capture_s)
        book.held.append(rec)
        if whole is None:
            return None
        recs, book.held = book.held, []
        with book.lock:
            book.outstanding[lane] += len(recs)
        options = {} if whole.camera_timestamps is None else {"camera_timestamps": whole.camera_timestamps}
        fut = mode.runner.submit_images(whole.images, whole.timestamp, **options)
    for r in recs:
        fut.add_done_callback(functools.partial(book.done, r, lane))
    return fut


def _progress_line(mode: str, drive: Drive, now_s: float, records: list) -> str:
    slices = [r for r in records if isinstance(r, SliceRecord) and r.release_s == r.release_s]
    done = [r.latency_ms for r in slices if r.emitted]
    p = percentiles(done[-200:], (50, 95))
    lat = f"latency p50 {p['p50']:.1f} / p95 {p['p95']:.1f} ms" if done else "no slice emitted yet"
    dropped = sum(r.dropped for r in slices)
    return (f"[{mode}] {drive.name}: {now_s:5.2f} / {drive.duration_s:.2f} s of drive, {len(done)}/{len(slices)} slices "
            f"emitted, {dropped} dropped, {lat}")  # fmt: skip
