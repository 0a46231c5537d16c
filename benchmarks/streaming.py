"""The streaming section: slice-lane and image-lane latency of a real export on the bundled nuScenes sample.

Three ways to serve the same stream with one ``StreamingDetector`` (one intra-op thread per session: on a small CPU
the lanes are for latency isolation, not throughput):

(a) idle:       only slices; each ``detect_slice`` timed end to end (pillarize + graph + post-processing).
                Also with every usable CPU (at most MAX_SESSION_THREADS) given to the slice session (what the lane
                could do with the machine to itself; benchmarks/thread_counts.py).
(b) busy:       a thread calls ``update_images`` in a loop (the image lane never rests) while the slices are timed.
                (a), (a) with every CPU and (b) take turns, a sweep each, in rounds (``phase_rounds``): the busy/idle
                ratio is a target, and two phases measured one after the other compare the machine's states as much
                as the phases (benchmarks/RESULTS.md, **Timing**). The busy thread starts and stops every round.
(c) sequential: one worker serves image updates and slices in arrival order (slices every 100 ms / N, images at
                ``image_hz``); a slice's latency is its wait plus its processing. The worker runs the real jobs
                back to back and keeps a virtual clock (start = max(arrival, previous finish)), so no time is
                spent sleeping; like the image lane of ``runtime_ort.lanes``, a waiting image set is replaced
                by a newer one.
(d) schedules:  the image lane's ``full`` and ``phase-locked`` schedules on the wall clock at nuScenes rates
                (``streaming_schedules.py``): staleness added, image age, slice p99, drops, image-lane CPU; they take
                turns in ``schedule_rounds`` rounds.

Real-time factor = slice p50 / (100 ms / N) for a 10 Hz LiDAR delivering N slices: <= 1 keeps up.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from streamdet.benchmarks.ort_profile import ProfileSummary, summarize_profile
from streamdet.benchmarks.prepost import PrePostCase, measure_prepost
from streamdet.benchmarks.streaming_schedules import SCHEDULE_ROUNDS, measure_schedules
from streamdet.benchmarks.thread_counts import check_session_threads, default_session_threads
from streamdet.benchmarks.timing import TimingConfig, TimingStats, summarize
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector, lane_precision_label
from streamdet.runtime_ort.sessions import CPU_ONLY
from streamdet.runtime_ort.lanes import LaneConfig
from streamdet.runtime_ort.manifest import Manifest, ManifestError, read_manifest
from streamdet.runtime_ort.postprocess import PostprocessConfig
from streamdet.runtime_ort.stats import LatencyStats

Progress = Callable[[str], None]
SLICE, IMAGES = "slice", "images"


@dataclass(frozen=True)
class StreamingConfig:
    precision: str = "fp32"
    image_precision: str | None = None  # the image lane's graphs; None: precision
    num_slices: int | None = None  # None: the export's
    lidar_hz: float = 10.0  # sweeps per second of the LiDAR the slice lane must keep up with
    image_hz: float = 12.0  # camera rate of the sequential-queue schedule
    sweeps: int = 5  # timed sweeps in (a) and (b): sweeps x N slice latencies each, taken in turns (phase_rounds)
    image_updates: int = 3  # image updates timed with the slice lane idle ...
    image_budget_s: float = 20.0  # ... unless they would take longer than this (the paper preset: a minute each)
    queue_sweeps: int = 4  # sweeps of arrivals in (c)
    warmup_sweeps: int = 1
    # (d) seconds of the bundled sweep played at nuScenes rates through each image-lane schedule
    # (streaming_schedules.py); 0: skip
    schedule_seconds: float = 3.0
    schedule_rounds: int = SCHEDULE_ROUNDS  # (d) the schedules take turns in this many plays of schedule_seconds / rounds each
    schedule_slice_workers: int | None = None  # (d) slice workers (LaneConfig.max_in_flight); None: LaneConfig's default
    # (a) again: the slice session's threads (1..MAX_SESSION_THREADS; 1 skips it); None: every usable CPU, at most
    # MAX_SESSION_THREADS (benchmarks/thread_counts.py)
    wide_slice_threads: int | None = None

    def __post_init__(self) -> None:
        for name in ("sweeps", "image_updates", "queue_sweeps", "schedule_rounds"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"StreamingConfig.{name} must be a positive integer, got {v!r}")
        for name in ("lidar_hz", "image_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"StreamingConfig.{name} must be > 0 Hz, got {getattr(self, name)!r}")
        if not self.image_budget_s > 0:
            raise ValueError(f"StreamingConfig.image_budget_s must be > 0 s, got {self.image_budget_s!r}")
        if not self.schedule_seconds >= 0:
            raise ValueError(f"StreamingConfig.schedule_seconds must be >= 0 s, got {self.schedule_seconds!r}")
        if self.schedule_slice_workers is not None:
            try:  # LaneConfig's own rule for its workers, checked before the benchmark runs
                LaneConfig(max_in_flight=self.schedule_slice_workers)
            except ValueError:
                raise ValueError(f"StreamingConfig.schedule_slice_workers must be None or an int in 1..1024, "
                                 f"got {self.schedule_slice_workers!r}") from None  # fmt: skip
        if self.wide_slice_threads is not None:
            check_session_threads(self.wide_slice_threads, "StreamingConfig.wide_slice_threads")

    @property
    def wide_threads(self) -> int:
        """Threads of the slice session in (a) again: ``wide_slice_threads``, or every usable CPU, at most
        MAX_SESSION_THREADS."""
        return self.wide_slice_threads if self.wide_slice_threads is not None else default_session_threads()


# ---- the sequential queue ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Job:
    kind: str  # SLICE | IMAGES
    arrival_ms: float
    index: int  # slice index k for slices, the image set's number for images


@dataclass(frozen=True)
class Served:
    job: Job
    start_ms: float
    finish_ms: float

    @property
    def wait_ms(self) -> float:
        return self.start_ms - self.job.arrival_ms

    @property
    def latency_ms(self) -> float:
        return self.finish_ms - self.job.arrival_ms


@dataclass(frozen=True)
class QueueRun:
    served: tuple[Served, ...]  # in service order
    superseded: tuple[Job, ...]  # image sets replaced by a newer one before service

    def latencies(self, kind: str) -> np.ndarray:
        return np.array([s.latency_ms for s in self.served if s.job.kind == kind], dtype=np.float64)

    def waits(self, kind: str) -> np.ndarray:
        return np.array([s.wait_ms for s in self.served if s.job.kind == kind], dtype=np.float64)


def arrival_schedule(num_slices: int, lidar_hz: float, image_hz: float, sweeps: int) -> list[Job]:
    """Slices every 1000 / lidar_hz / N ms and image sets every 1000 / image_hz ms over ``sweeps`` LiDAR periods,
    sorted by arrival (a slice before an image set arriving at the same instant)."""
    if num_slices < 1 or sweeps < 1 or not lidar_hz > 0 or not image_hz > 0:
        raise ValueError(
            f"arrival_schedule needs num_slices, sweeps >= 1 and rates > 0, got {num_slices}, {sweeps}, {lidar_hz}, {image_hz}"
        )
    horizon_ms = sweeps * 1000.0 / lidar_hz
    slice_ms = 1000.0 / lidar_hz / num_slices
    jobs = [Job(SLICE, i * slice_ms, i % num_slices) for i in range(sweeps * num_slices)]
    num_images = int(np.ceil(horizon_ms * image_hz / 1000.0 - 1e-9))
    jobs += [Job(IMAGES, i * 1000.0 / image_hz, i) for i in range(num_images)]
    return sorted(jobs, key=lambda j: (j.arrival_ms, j.kind != SLICE))


def run_sequential_queue(jobs: Sequence[Job], process: Callable[[Job], float]) -> QueueRun:
    """Serve ``jobs`` with one worker in arrival order on a virtual clock.

    ``process(job)`` does the job and returns its duration in ms. A job starts at max(its arrival, the previous
    finish). An image set still waiting when a newer one arrives is dropped (superseded).
    """
    pending = collections.deque(sorted(jobs, key=lambda j: j.arrival_ms))  # stable: the caller's order at ties
    waiting: collections.deque[Job] = collections.deque()
    served: list[Served] = []
    superseded: list[Job] = []
    now = 0.0

    def admit(until_ms: float) -> None:
        while pending and pending[0].arrival_ms <= until_ms:
            job = pending.popleft()
            if job.kind == IMAGES:
                stale = [w for w in waiting if w.kind == IMAGES]
                superseded.extend(stale)
                for w in stale:
                    waiting.remove(w)
            waiting.append(job)

    while pending or waiting:
        admit(now)
        if not waiting:
            now = pending[0].arrival_ms
            continue
        job = waiting.popleft()
        start = max(now, job.arrival_ms)
        duration = float(process(job))
        if not (np.isfinite(duration) and duration >= 0):
            raise ValueError(f"process() must return a duration in ms >= 0, got {duration!r} for {job}")
        now = start + duration
        served.append(Served(job, start, now))
    return QueueRun(tuple(served), tuple(superseded))


# ---- measurement -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LaneStats:
    latency: TimingStats  # end-to-end per slice (or per image update)
    stages: dict[str, dict[str, float]]  # StreamingDetector.stats.summary() of the same phase

    def share(self, *stages: str) -> float | None:
        """Mean time of ``stages`` over the mean slice_total of the phase."""
        total = self.stages.get("slice_total", {}).get("mean_ms")
        if not total:
            return None
        return sum(self.stages.get(s, {}).get("mean_ms", 0.0) for s in stages) / total


@dataclass(frozen=True)
class StreamingResult:
    export_dir: str
    preset: str
    precision: str  # the slice graph's
    num_slices: int
    num_points: tuple[int, ...]  # per slice of the bundled sweep
    image_size: tuple[int, int]  # (width, height) of the export
    num_cameras: int
    slice_budget_ms: float  # 1000 / lidar_hz / N
    idle: LaneStats
    idle_all_cores: LaneStats | None  # slice session with every core; None when an image update is too slow to redo
    all_cores: int  # the threads of that session (StreamingConfig.wide_threads)
    busy: LaneStats
    image_alone: LaneStats  # update_images with the slice lane idle
    image_busy_updates: int  # image updates completed while the busy slices were timed
    sequential_slice: TimingStats
    sequential_wait: TimingStats
    sequential_images_served: int
    sequential_images_superseded: int
    sequential_horizon_ms: float
    config: StreamingConfig
    profiles: dict[str, ProfileSummary] = dataclasses.field(default_factory=dict)  # profile_streaming's, if run
    prepost: tuple[PrePostCase, ...] = ()  # the runtime's numpy stages timed alone (benchmarks/prepost.py)
    image_precision: str = ""  # the image lane's graphs; "" (older results): precision
    # (d) per image-lane schedule: staleness, image age, slice p99, drops, CPU per rotation (streaming_schedules.py)
    schedules: dict[str, dict] = dataclasses.field(default_factory=dict)
    providers: tuple[str, ...] = ()  # the slice session's onnxruntime providers; () in older results
    # (a), (a) with every CPU and (b) took turns in this many rounds (phase_rounds; 1: one after the other)
    phase_rounds: int = 1

    @property
    def precision_label(self) -> str:
        """``"fp32"``, or ``"int8 image lane + fp32 slices"`` when the lanes differ."""
        return lane_precision_label(self.precision, self.image_precision or None)

    @property
    def busy_over_idle_p95(self) -> float:
        return self.busy.latency.p95_ms / self.idle.latency.p95_ms

    def real_time_factor(self, lane: LaneStats) -> float:
        return lane.latency.median_ms / self.slice_budget_ms


def _bundled_inputs(det: StreamingDetector) -> tuple[dict[str, np.ndarray], list[np.ndarray]]:
    """The bundled sample's camera images at the export's size (name -> (H, W, 3) uint8) and its sweep's slices."""
    img = det.manifest.image
    sample = load_bundled_sample()
    if tuple(sample.rig.names) != det.camera_names:
        raise ValueError(f"the bundled sample's cameras {list(sample.rig.names)} differ from the export's {list(det.camera_names)}")
    stacked = sample.load_images((img.width, img.height))  # (J, H, W, 3) in rig order
    images = {name: np.ascontiguousarray(stacked[i]) for i, name in enumerate(det.camera_names)}
    return images, split_sweep(sample.points, det.num_slices, det.config.start_deg)


def _time_slices(det: StreamingDetector, slices: Sequence[np.ndarray], sweeps: int) -> list[float]:
    out = []
    for _ in range(sweeps):
        for k, points in enumerate(slices):
            start = time.perf_counter()
            det.detect_slice(points, k)
            out.append((time.perf_counter() - start) * 1e3)
    return out


@contextlib.contextmanager
def busy_image_lane(det: StreamingDetector, images: dict[str, np.ndarray]) -> Iterator[list[int]]:
    """A thread calls ``update_images`` back to back until the block ends (then the running update finishes).

    Yields a one-element list counting the updates finished so far. The block starts once the first update is
    under way, so everything inside it runs against a busy image lane.
    """
    stop, started = threading.Event(), threading.Event()
    finished = [0]

    def loop() -> None:
        while not stop.is_set():
            started.set()
            det.update_images(images)
            finished[0] += 1

    worker = threading.Thread(target=loop, name="bench-image-lane", daemon=True)
    worker.start()
    started.wait()
    try:
        yield finished
    finally:
        stop.set()
        worker.join()


def phase_rounds(sweeps: int, update_s: float, budget_s: float) -> int:
    """Rounds in which (a), (a) with every CPU and (b) take turns, a share of the ``sweeps`` each round: one per
    sweep, fewer where stopping the busy image lane every round would wait too long. A stop waits for the running
    update to end (``update_s`` at most), so the stops may wait ``budget_s`` in all (StreamingConfig.image_budget_s);
    at least one round: a preset whose update takes longer than that (the paper's: a minute) runs the phases one
    after the other, and the report says so."""
    if update_s <= 0:
        return sweeps
    return max(1, min(sweeps, int(budget_s / update_s)))


def sweeps_per_round(sweeps: int, rounds: int) -> list[int]:
    """``sweeps`` spread over ``rounds`` as evenly as they go, the larger shares first."""
    return [sweeps // rounds + (r < sweeps % rounds) for r in range(rounds)]


@contextlib.contextmanager
def copied_into(stats: LatencyStats, phase: LatencyStats) -> Iterator[LatencyStats]:
    """Every duration ``stats`` records inside the block goes into ``phase`` too (from any thread).

    The phases take turns on one detector, whose ``stats`` would mix them; it cannot be swapped for a phase's own,
    since the per-camera lifts hold the same object and time their runs into it. So each phase's stage summary is
    a copy of what ``stats`` recorded while the phase ran."""
    record = stats.record

    def both(stage: str, duration_ms: float, gmac: float | None = None) -> None:
        record(stage, duration_ms, gmac)
        phase.record(stage, duration_ms, gmac)

    stats.record = both  # type: ignore[method-assign]  # stats.time() calls self.record: it finds this one
    try:
        yield phase
    finally:
        del stats.record  # the class's method again


def _detector(export_dir: Path, cfg: StreamingConfig, profiling: bool = False, slice_threads: int = 1,
              profile_dir: str | None = None) -> StreamingDetector:  # fmt: skip
    return StreamingDetector(
        export_dir,
        DetectorConfig(
            precision=cfg.precision,
            image_lane_precision=cfg.image_precision,
            image_lane_threads=1,
            slice_lane_threads=slice_threads,
            num_slices=cfg.num_slices,
            enable_profiling=profiling,
            profile_dir=profile_dir,
            providers=CPU_ONLY,
        ),
    )


def profile_streaming(
    export_dir: str | Path, cfg: StreamingConfig, profile_dir: Path, progress: Progress = lambda msg: None
) -> dict[str, ProfileSummary]:
    """onnxruntime profiles of the slice lane with the image lane idle and busy (fresh profiling sessions per phase).

    Keys ``"<phase>/<graph>"``; the JSON files go to ``profile_dir/streaming_<phase>.<graph>.json``. onnxruntime
    writes them first into a temporary folder (``DetectorConfig.profile_dir``), never into the export directory.
    """
    profile_dir.mkdir(parents=True, exist_ok=True)
    summaries: dict[str, ProfileSummary] = {}
    with tempfile.TemporaryDirectory(prefix="streamdet_stream_profile_") as tmp:
        for phase in ("idle", "busy"):
            progress(f"[streaming] profiling the slice lane, image lane {phase}: {cfg.sweeps} sweep(s)")
            det = _detector(Path(export_dir), cfg, profiling=True, profile_dir=tmp)
            images, slices = _bundled_inputs(det)
            det.update_images(images)
            if phase == "idle":
                _time_slices(det, slices, cfg.sweeps)
            else:
                with busy_image_lane(det, images):
                    _time_slices(det, slices, cfg.sweeps)
            for written in det.close():
                graph = Path(written).name.split(".profile")[0]
                target = profile_dir / f"streaming_{phase}.{graph}.json"
                shutil.move(written, target)
                summaries[f"{phase}/{graph}"] = summarize_profile(target)
    return summaries


def export_unfit(manifest: Manifest, cfg: StreamingConfig | None = None) -> str | None:
    """Why the streaming section cannot time an export with this manifest, as the end of a sentence that starts with
    the export's name; None if it can. Read from the manifest and the bundled sample's calibration alone (no graph
    is loaded), so that a caller can refuse the export before any timing. With ``cfg``, its graphs' precisions too.
    """
    if not manifest.use_image:
        # the section measures the two lanes against each other; a LiDAR-only export has one
        return ("is a LiDAR-only export: the streaming section times the slice lane with the image lane idle and "
                "busy, so it needs a camera + LiDAR export")  # fmt: skip
    if cfg is not None:
        for precision in dict.fromkeys((cfg.precision, cfg.image_precision or cfg.precision)):
            if precision not in manifest.precisions:
                return f"has no {precision} graphs (it has {', '.join(manifest.precisions)}); re-export with --{precision}"
    cameras = tuple(load_bundled_sample().rig.names)  # the section feeds the bundled sample's images
    if tuple(manifest.image.camera_names) != cameras:
        return (f"takes the cameras {list(manifest.image.camera_names)}, but the streaming section feeds the bundled "
                f"sample's {list(cameras)}")  # fmt: skip
    return None


def check_streaming_export(export_dir: str | Path, cfg: StreamingConfig | None = None) -> Manifest:
    """The export's manifest if the streaming section can time it (``export_unfit``), else a one-line ValueError
    naming the export; an unreadable manifest is a ValueError too."""
    try:
        manifest = read_manifest(export_dir)
    except (ManifestError, OSError) as e:
        raise ValueError(f"{export_dir} is not a usable export: {e}") from None
    problem = export_unfit(manifest, cfg)
    if problem is not None:
        raise ValueError(f"{export_dir} {problem}")
    return manifest


def verify_streaming_export(export_dir: str | Path, cfg: StreamingConfig) -> None:
    """Open the export as the streaming section will (``StreamingDetector``'s start-up: every graph's file against its
    sha256, its real signature against the manifest and the runtime, the LUT) and close it again: a ValueError (one
    line, naming the export) for an export the runtime refuses. The manifest alone (``check_streaming_export``) does
    not tell a swapped graph whose sha256 was updated with it; run before any timing, this costs one session start
    per graph, where the section would fail only after every row was timed (minutes)."""
    try:
        det = _detector(Path(export_dir), cfg)
    except (ValueError, KeyError, OSError) as e:  # ManifestError, CalibrationError, ProviderError are ValueErrors
        raise ValueError(f"{export_dir} is not a usable export: {e}") from None
    det.close()


def measure_streaming(
    export_dir: str | Path, cfg: StreamingConfig = StreamingConfig(), progress: Progress = lambda msg: None
) -> StreamingResult:
    check_streaming_export(export_dir, cfg)  # before the sessions are made
    det = _detector(Path(export_dir), cfg)
    n = det.num_slices
    img = det.manifest.image
    images, slices = _bundled_inputs(det)
    budget_ms = 1000.0 / cfg.lidar_hz / n

    progress(f"[streaming] image lane alone: {cfg.image_updates} + 2 warm-up updates of {len(images)} cameras")
    det.update_images(images)  # warm-up, and the image BEV every later slice reads
    start = time.perf_counter()
    det.update_images(images)  # onnxruntime's second run of a graph is still slow (replay/run.py warm_up)
    warm_s = time.perf_counter() - start
    updates_to_time = max(1, min(cfg.image_updates, int(cfg.image_budget_s / warm_s)))
    if updates_to_time < cfg.image_updates:
        progress(f"[streaming] an image update takes {warm_s:.1f} s: timing {updates_to_time} of {cfg.image_updates}")
    det.stats.reset()
    image_ms = []
    for _ in range(updates_to_time):
        start = time.perf_counter()
        det.update_images(images)
        image_ms.append((time.perf_counter() - start) * 1e3)
    image_alone = LaneStats(summarize(image_ms, requested=cfg.image_updates), det.stats.summary())

    cores = cfg.wide_threads  # at most MAX_SESSION_THREADS, which DetectorConfig takes
    wide = None
    if cores > 1 and warm_s <= cfg.image_budget_s:
        wide = _detector(Path(export_dir), cfg, slice_threads=cores)
        wide.update_images(images)  # the same image BEV, so post-processing sees the same boxes
        _time_slices(wide, slices, cfg.warmup_sweeps)
        wide.stats.reset()
    rounds = phase_rounds(cfg.sweeps, warm_s, cfg.image_budget_s)
    phases = "(a) slices, image lane idle" + (f"; (a) again with {cores} threads in the slice session" if wide else "")
    progress(f"[streaming] {phases}; (b) slices, image lane busy: {cfg.sweeps} sweep(s) of {n} each, taking turns in "
             f"{rounds} round(s)")  # fmt: skip
    _time_slices(det, slices, cfg.warmup_sweeps)
    idle_stats, busy_stats = LatencyStats(), LatencyStats()
    idle_ms: list[float] = []
    wide_ms: list[float] = []
    busy_ms: list[float] = []
    busy_updates = 0
    for sweeps in sweeps_per_round(cfg.sweeps, rounds):
        with copied_into(det.stats, idle_stats):
            idle_ms += _time_slices(det, slices, sweeps)
        if wide is not None:
            wide_ms += _time_slices(wide, slices, sweeps)
        # the copy outlasts the busy lane: the update running when it stops finishes (and records) inside it
        with copied_into(det.stats, busy_stats), busy_image_lane(det, images) as finished:
            busy_ms += _time_slices(det, slices, sweeps)
            busy_updates += finished[0]  # updates finished while the busy slices ran
    idle = LaneStats(summarize(idle_ms), idle_stats.summary())
    busy = LaneStats(summarize(busy_ms), busy_stats.summary())
    idle_all_cores = None
    if wide is not None:
        idle_all_cores = LaneStats(summarize(wide_ms), wide.stats.summary())
        wide.close()  # its sessions, image BEV and LUT views: not held through (c), (d) and the rest

    jobs = arrival_schedule(n, cfg.lidar_hz, cfg.image_hz, cfg.queue_sweeps)
    progress(
        f"[streaming] (c) one sequential queue: {sum(j.kind == SLICE for j in jobs)} slices, "
        f"{sum(j.kind == IMAGES for j in jobs)} image sets arriving over {cfg.queue_sweeps * 1000 / cfg.lidar_hz:.0f} ms"
    )

    def process(job: Job) -> float:
        start = time.perf_counter()
        if job.kind == SLICE:
            det.detect_slice(slices[job.index], job.index)
        else:
            det.update_images(images)
        return (time.perf_counter() - start) * 1e3

    run = run_sequential_queue(jobs, process)
    det.close()
    schedules = {}
    if cfg.schedule_seconds > 0:
        progress(f"[streaming] (d) image-lane schedules: {cfg.schedule_seconds:g} s at 20 Hz x {n} slices, 12 Hz cameras, each, "
                 f"taking turns in {cfg.schedule_rounds} round(s)")
        schedules = measure_schedules(export_dir, cfg.precision, cfg.image_precision, cfg.schedule_seconds,
                                      slice_workers=cfg.schedule_slice_workers, rounds=cfg.schedule_rounds)  # fmt: skip
    progress("[streaming] pillarize and post-processing alone")
    pillars = det.manifest.preset["pillars"]
    prepost = measure_prepost(det.grid, int(pillars["max_points_per_pillar"]), int(pillars["max_pillars"]),
                              PostprocessConfig(score_threshold=float(det.manifest.post["score_threshold"]), nms=det.config.nms),
                              TimingConfig(repeat=10 if cfg.sweeps <= 2 else 50, budget_s=5.0))  # fmt: skip
    return StreamingResult(
        export_dir=str(export_dir),
        preset=det.manifest.preset_name,
        precision=cfg.precision,
        image_precision=det.config.image_precision,
        num_slices=n,
        num_points=tuple(len(s) for s in slices),
        image_size=(img.width, img.height),
        num_cameras=len(images),
        slice_budget_ms=budget_ms,
        idle=idle,
        idle_all_cores=idle_all_cores,
        all_cores=cores,
        busy=busy,
        image_alone=image_alone,
        image_busy_updates=busy_updates,
        sequential_slice=summarize(run.latencies(SLICE)),
        sequential_wait=summarize(run.waits(SLICE)),
        sequential_images_served=int(sum(s.job.kind == IMAGES for s in run.served)),
        sequential_images_superseded=len(run.superseded),
        sequential_horizon_ms=cfg.queue_sweeps * 1000.0 / cfg.lidar_hz,
        config=cfg,
        prepost=prepost,
        schedules=schedules,
        providers=tuple(det.providers),
        phase_rounds=rounds,
    )
