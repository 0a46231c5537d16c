"""A whole replay: scenes of a dataset split played in each mode through a real export, then scored.

For every (scene, mode) a fresh `StreamingDetector` is opened, warmed up (its first image set and first sweep
run once, untimed, at WARM_UP_TIMESTAMP_S, the warm-up picture then dropped: slices before the first real image
update read no image, and no slice is fused with a picture captured after it) and played
on the wall clock; its stage statistics (with the GMAC executed) are kept. The scores pool all scenes of a mode;
the streaming mAP of each scene alone gives the spread of the modes' difference over scenes.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from streamdet.core.points import NUSCENES_CAMERA_HZ, NUSCENES_LIDAR_HZ
from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.calibration.camera import CalibrationError
from streamdet.data.splits import SplitsFileMissing
from streamdet.data.splits import split_scenes as data_split_scenes
from streamdet.evaluation.config import DetectionConfig
from streamdet.replay.clock import WallClock
from streamdet.replay.latency_eval import ModeScores, QueryTruth, query_truth, score_mode
from streamdet.replay.modes import MODES
from streamdet.replay.nuscenes_source import DatasetTables, load_drive
from streamdet.replay.outages import CameraOutage, apply_outages, check_outage_cameras
from streamdet.replay.player import PlayerConfig, play
from streamdet.replay.record import Recording
from streamdet.replay.scan_layout import ScanLayout, check_layout
from streamdet.replay.schedule import check_delivery, check_rate, check_time_scale, slice_sweep
from streamdet.replay.source import Drive
from streamdet.replay.triggers import DEFAULT_TRIGGER, check_trigger
from streamdet.replay.truth import load_ground_truth
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.lanes import LaneConfig
from streamdet.runtime_ort.phase_lock import LIDAR_HZ_RANGE

Progress = Callable[[str], None]
WARM_UP_TIMESTAMP_S = -1e9  # earlier than player.WARM_UP_BEFORE_S: the player knows it for a warm-up


@dataclass(frozen=True)
class ReplayConfig:
    data: Path  # nuScenes-format dataset root
    export_dir: Path
    version: str = DEFAULT_TABLE_VERSION
    split: str | None = "val"  # scenes of splits.json; None: every scene
    scenes: int | None = None  # the first N scenes of the split; None: all
    precision: str = "fp32"  # the slice graph's
    image_precision: str | None = None  # the image lane's; None: precision
    lidar_hz: float = NUSCENES_LIDAR_HZ
    num_slices: int | None = None  # None: the export's
    camera_hz: float = NUSCENES_CAMERA_HZ
    # how the cameras fire (triggers.py): "lidar-synced" (nuScenes: each as the LiDAR crosses its optical axis) or
    # "simultaneous" (all at once)
    camera_trigger: str = DEFAULT_TRIGGER
    modes: tuple[str, ...] = MODES
    time_scale: float = 1.0  # wall seconds per drive second
    max_seconds: float | None = None  # play only the first seconds of each scene
    threads: int = 1  # intra-op threads of each onnxruntime session
    image_lane_threads: int | None = None  # the image lane's sessions' (DetectorConfig.image_lane_threads); None: threads
    lanes: LaneConfig = field(default_factory=LaneConfig)
    # a LiDAR-only export for the slices without usable camera features (DetectorConfig.fallback_export_dir); None: none
    fallback_export_dir: Path | None = None
    fallback_after_s: float | None = None  # also fall back when the image BEV is older than this (drive seconds)
    camera_terms: bool | None = None  # per-camera lifts of quadrant updates (DetectorConfig.camera_terms); None: auto
    # every camera frame reaches the runtime this long after its capture (PlayerConfig.camera_delivery_ms); 0: at capture
    camera_delivery_ms: float = 0.0
    freeze_heap: bool = True  # PlayerConfig.freeze_heap: the heap alive at a drive's start is out of full collections
    providers: tuple[str, ...] | None = None  # onnxruntime's execution providers (DetectorConfig.providers); None: default
    camera_outages: tuple[CameraOutage, ...] = ()  # cameras that send nothing for a while (outages.py)
    # the LiDAR's scan layout (core/sectors.py): where its sweep starts and whether it turns clockwise; None: from the
    # data (scan_layout.py: the per-point times, else nuScenes' LIDAR_TOP, clockwise from 180 deg)
    start_deg: float | None = None
    clockwise: bool | None = None

    def __post_init__(self) -> None:
        unknown = [m for m in self.modes if m not in MODES]
        if unknown or not self.modes:
            raise ValueError(f"modes must be a non-empty subset of {MODES}, got {list(self.modes)}")
        for name in ("lidar_hz", "camera_hz"):
            check_rate(getattr(self, name), f"ReplayConfig.{name}")
        check_time_scale(self.time_scale, "ReplayConfig.time_scale")
        check_trigger(self.camera_trigger)
        start_deg, clockwise = check_layout(self.start_deg, self.clockwise)
        object.__setattr__(self, "start_deg", start_deg)  # Python numbers: the config goes into the JSON report
        object.__setattr__(self, "clockwise", clockwise)
        check_delivery(self.camera_delivery_ms, "ReplayConfig.camera_delivery_ms", "ms")
        if not isinstance(self.camera_outages, tuple) or not all(isinstance(o, CameraOutage) for o in self.camera_outages):
            raise ValueError(f"ReplayConfig.camera_outages must be a tuple of CameraOutage, got {self.camera_outages!r}")
        if self.max_seconds is not None and not self.max_seconds > 0:
            raise ValueError(f"ReplayConfig.max_seconds must be > 0 s, got {self.max_seconds!r}")
        for name in ("threads", "image_lane_threads"):
            v = getattr(self, name)
            if (v is not None or name == "threads") and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise ValueError(f"ReplayConfig.{name} must be an int >= 1, got {v!r}")
        if self.lanes.schedule == "phase-locked" and self.lanes.lidar_hz is None:
            hz, (lo, hi) = self.lidar_hz / self.time_scale, LIDAR_HZ_RANGE
            if not lo <= hz <= hi:  # the lane takes no rate a spinning LiDAR cannot have (runtime_ort/phase_lock.py)
                raise ValueError(f"the phase-locked schedule at time scale {self.time_scale:g} would see the LiDAR turn at "
                                 f"{hz:g} Hz of wall time, outside {lo:g}..{hi:g} Hz (LIDAR_HZ_RANGE): use a time scale "
                                 f"in {self.lidar_hz / hi:g}..{self.lidar_hz / lo:g} for a {self.lidar_hz:g} Hz drive")  # fmt: skip

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "lanes"}
        d.update(data=str(self.data), export_dir=str(self.export_dir), modes=list(self.modes),
                 providers=None if self.providers is None else list(self.providers),
                 fallback_export_dir=None if self.fallback_export_dir is None else str(self.fallback_export_dir),
                 slice_workers=self.lanes.max_in_flight, slice_queue=self.lanes.queue_size,
                 schedule=self.lanes.schedule, image_lane_nice=self.lanes.image_lane_nice,
                 image_lane_yield_slices=self.lanes.image_lane_yield_slices,
                 coalesce_slices=self.lanes.coalesce_slices, pair_hold_load=self.lanes.pair_hold_load,
                 camera_timeout_s=self.lanes.camera_timeout_s, camera_outages=[str(o) for o in self.camera_outages])  # fmt: skip
        return d


@dataclass(frozen=True)
class ModeResult:
    recordings: tuple[Recording, ...]  # one per scene
    scores: ModeScores
    stages: dict[str, dict[str, float]]  # stage -> {runs, mean_ms, gmac_per_run, gflop_per_s}, all scenes


@dataclass(frozen=True)
class ReplayResult:
    config: ReplayConfig
    num_slices: int
    precision_label: str
    scenes: tuple[str, ...]
    drives: tuple[Drive, ...]
    truths: tuple[QueryTruth, ...]
    modes: dict[str, ModeResult]
    notes: tuple[str, ...]  # the sources' notes (rates, held images)
    truth_source: str
    camera_terms: bool = False  # whether the detector's quadrant updates used per-camera lifts (DetectorConfig.camera_terms)
    uses_images: bool = True  # False: a LiDAR-only export (no cameras played, no image lane)
    providers: tuple[str, ...] = ()  # the providers the slice session ran on (its onnxruntime session's)


def split_scenes(tables: DatasetTables, split: str | None, count: int | None) -> list[str]:
    """Scene names of ``split`` (``splits.json`` beside the tables), the first ``count`` of them."""
    names = tables.scene_names()
    unknown: list[str] = []
    if split is not None:
        try:
            chosen = set(data_split_scenes(tables.root, split))
        except SplitsFileMissing as e:
            raise ValueError(f"{e} (or pass --split all)") from None
        unknown = sorted(chosen - set(names))[:5]
        names = [n for n in names if n in chosen]
    if not names:
        why = f": its scenes {unknown} are not in the tables" if unknown else ""
        raise ValueError(f"split {split!r} of {tables.root} holds no scene{why}")
    return names[:count] if count else names


def open_detector(config: ReplayConfig, num_slices: int | None = None, layout: ScanLayout | None = None) -> StreamingDetector:
    """The detector of a replay; ``layout``: the drive's scan layout (None: the default, for a probe)."""
    scan = {} if layout is None else {"start_deg": layout.start_deg, "clockwise": layout.clockwise}
    return StreamingDetector(config.export_dir, DetectorConfig(
        precision=config.precision, image_lane_precision=config.image_precision, num_slices=num_slices or config.num_slices,
        image_lane_threads=config.image_lane_threads or config.threads, slice_lane_threads=config.threads,
        fallback_export_dir=config.fallback_export_dir, fallback_after_s=config.fallback_after_s,
        camera_terms=config.camera_terms, providers=config.providers, **scan))  # fmt: skip


def warm_up(det: StreamingDetector, drive: Drive, num_slices: int, per_quadrant: bool = False) -> None:
    """Two untimed image updates (at WARM_UP_TIMESTAMP_S), dropped again, and the first sweep, then fresh stats.
    ``per_quadrant``: also one update of each quadrant alone (the phase-locked image lane's sizes: onnxruntime's
    first run of a new input shape is slow)."""
    if drive.rig is not None and det.uses_images and drive.rig.sha256() != det.lut.calibration_sha256:
        try:  # the dataset's own rig: a new LUT for the same graphs
            det.set_calibration(drive.rig)
        except CalibrationError as e:  # a rig the export cannot take (another aspect, other cameras): name the scene
            raise CalibrationError(f"scene {drive.name}: {e}") from None
    # twice: onnxruntime's first two runs of a graph were measured 4-20x slower than the third (the first real image
    # update of every replay ran 0.13-0.2 s at scale 2, its slices queued behind it)
    for _ in range(2) if det.uses_images and drive.image_sets else ():
        det.update_images(drive.image_sets[0].images, timestamp=WARM_UP_TIMESTAMP_S)
        for q in range(4) if per_quadrant else ():
            det.update_images(drive.image_sets[0].images, timestamp=WARM_UP_TIMESTAMP_S, quadrants=[q])
    def slices_once() -> None:
        for n in {num_slices, 1}:
            for s in slice_sweep(drive.sweeps[0], n, det.config.start_deg, det.config.clockwise):
                det.detect_slice(s.points, s.slice_index, WARM_UP_TIMESTAMP_S, n)

    slices_once()
    # The warm-up picture is the drive's first image set, captured after the drive's first slices: they must not see
    # it. Until the first real update they read no image, as a vehicle starting up does; with a LiDAR-only fallback
    # they run its graph, which is warmed here too (its first runs would be the drive's).
    if det.uses_images:
        det.forget_images()
        if det.config.fallback_export_dir is not None:
            slices_once()
    det.stats.reset()


def run_replay(config: ReplayConfig, progress: Progress = lambda msg: None) -> ReplayResult:
    tables = DatasetTables(config.data, config.version)
    scenes = split_scenes(tables, config.split, config.scenes)
    probe = open_detector(config)
    check_outage_cameras(config.camera_outages, probe.camera_names if probe.uses_images else ())
    n = probe.num_slices
    image_size = (probe.image.width, probe.image.height) if probe.uses_images else None
    label = probe.precision_label
    drives, truths = [], []
    recordings: dict[str, list[Recording]] = {m: [] for m in config.modes}
    stages: dict[str, list[dict]] = {m: [] for m in config.modes}
    sources = set()
    for i, scene in enumerate(scenes):
        progress(f"scene {i + 1}/{len(scenes)} {scene}: loading")
        drive = load_drive(tables, scene, image_size, config.lidar_hz, config.camera_hz, config.max_seconds, progress,
                           config.camera_trigger, config.start_deg, config.clockwise)  # fmt: skip
        drive = apply_outages(drive, config.camera_outages)
        truth = load_ground_truth(config.data, config.version, scene, reader=tables.reader)
        sources.add(truth.source)
        drives.append(drive)
        truths.append(query_truth(drive, truth))
        for mode in config.modes:
            det = open_detector(config, layout=drive.scan_layout)
            warm_up(det, drive, n, per_quadrant=config.lanes.schedule == "phase-locked")
            player = PlayerConfig(mode, n, det.config.start_deg, config.time_scale, _lanes(config),
                                  camera_delivery_ms=config.camera_delivery_ms, freeze_heap=config.freeze_heap,
                                  clockwise=det.config.clockwise)  # fmt: skip
            recordings[mode].append(play(drive, det, WallClock(), player, progress))
            stages[mode].append(det.stats.summary())
            det.close()
    nms = probe.config.nms
    results = {}
    for mode in config.modes:
        progress(f"scoring {mode}")
        scores = score_mode(drives, recordings[mode], truths, nms, DetectionConfig())
        results[mode] = ModeResult(tuple(recordings[mode]), scores, merge_stages(stages[mode]))
    notes = tuple(dict.fromkeys(note for d in drives for note in d.notes))
    return ReplayResult(config, n, label, tuple(scenes), tuple(drives), tuple(truths), results, notes,
                        " + ".join(sorted(sources)), probe.camera_terms, probe.uses_images, tuple(probe.providers))  # fmt: skip


def _lanes(config: ReplayConfig) -> LaneConfig:
    """The runner's lanes; a phase-locked image lane is told the LiDAR rate on the wall clock (the rate over the
    time scale), as a vehicle's driver knows its sensor's, unless the lanes name one."""
    lanes = config.lanes
    if lanes.schedule == "phase-locked" and lanes.lidar_hz is None:
        lanes = dataclasses.replace(lanes, lidar_hz=config.lidar_hz / config.time_scale)  # in range: __post_init__
    return lanes


def merge_stages(summaries: list[dict[str, dict[str, float]]]) -> dict[str, dict[str, float]]:
    """Stage statistics of several runs pooled: runs, mean ms and, where known, GMAC per run and GFLOP/s."""
    out: dict[str, dict[str, float]] = {}
    for stage in sorted({s for summary in summaries for s in summary}):
        parts = [summary[stage] for summary in summaries if stage in summary]
        runs = sum(p["count"] for p in parts)
        total_ms = sum(p["mean_ms"] * p["count"] for p in parts)
        entry = {"runs": runs, "mean_ms": total_ms / runs if runs else math.nan}
        if all("gmac_total" in p for p in parts):
            gmac = sum(p["gmac_total"] for p in parts)
            entry["gmac_per_run"] = gmac / runs
            entry["gflop_per_s"] = 2.0 * gmac / (total_ms * 1e-3) if total_ms > 0 else math.nan
        out[stage] = entry
    return out
