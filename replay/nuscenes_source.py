"""A `Drive` from one scene of a nuScenes-format dataset (the synthetic world or real nuScenes tables).

LiDAR: every ``LIDAR_TOP`` sample_data of the scene (key frames and the sweeps between them), in time order, with
its ego pose and the per-point times of the ``<file>.time`` sidecar where the synthetic world wrote one. When the
data has sweeps faster than ``lidar_hz`` some are skipped so that rotations do not overlap; when slower, the drive
has gaps between rotations (the report says which rate the data had).

Cameras: each camera triggers at ``camera_hz`` by the trigger model (``triggers.py``: ``simultaneous``, all at once
from drive time 0, or ``lidar-synced``, each as the LiDAR crosses its optical axis, as nuScenes does); a trigger
delivers the newest recorded image of that camera at or before it, and the cameras
triggered at the same moment form one `ImageSet`. A frame stamped up to ``TRIGGER_MATCH_S`` after its trigger is
the trigger's, delivered at its stamp; a trigger before a camera's first frame delivers nothing from it (never a
frame from the future). Real nuScenes records cameras at 12 Hz, and so does the synthetic world generated with
``--camera-hz 12`` (at the crossings this trigger model picks), so the images are close to their trigger; generated
without it, the synthetic world has images at key frames only (2 Hz), *held* between key frames: the image lane does
the work of a 12 Hz rig, on older pictures. Both are written to ``Drive.notes``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from streamdet.core.points import NUSCENES_CAMERA_HZ, NUSCENES_LIDAR_HZ
from streamdet.calibration.camera import make_transform, quaternion_to_matrix
from streamdet.data.nuscenes import CAMERA_CHANNELS, LIDAR_CHANNEL, NuScenesReader
from streamdet.data.sample import load_image, load_point_times, load_points
from streamdet.data.synth_world import world_version_of
from streamdet.replay.scan_layout import resolve_layout
from streamdet.replay.source import Drive, ImageSet, LidarSweep
from streamdet.replay.triggers import (
    DEFAULT_TRIGGER, camera_axis_azimuths_deg, check_trigger, lidar_synced_triggers, simultaneous_triggers)

# A recorded frame stamped at most this long after a trigger is that trigger's frame: the replay times a LiDAR crossing
# from the sweep's points to within a fraction of a millisecond, and one camera's frames lie a rotation (50 ms) apart.
TRIGGER_MATCH_S = 0.002


class DatasetTables:
    """The scenes, LiDAR and camera records of a nuScenes-format dataset, as the player reads them.

    The tables are read and checked by `data.nuscenes.NuScenesReader` (one reader of them: a malformed row is a
    ValueError naming table, row and field; a file a row names is a relative path inside the dataset root), which
    also gives the drive its camera rig."""

    def __init__(self, root: str | Path, version: str) -> None:
        self.reader = NuScenesReader(root, version)
        self.root = self.reader.root
        self.version = version

    def scene_names(self) -> list[str]:
        return [self.reader.row("scene", s)["name"] for s in self.reader.rows("scene")]

    def scene(self, name: str) -> dict:
        for s in self.reader.rows("scene"):
            if self.reader.row("scene", s)["name"] == name:
                return s
        raise ValueError(f"scene {name!r} is not in {self.root / self.version} (it has {self.scene_names()[:5]}...)")

    def sample(self, token: str) -> dict:
        """The sample row of ``token`` (KeyError when there is none)."""
        return self.reader.by_token("sample", token)

    def sample_tokens(self, scene: dict) -> list[str]:
        rows = [r for r in (self.reader.row("sample", r) for r in self.reader.rows("sample")) if r["scene_token"] == scene["token"]]
        return [r["token"] for r in sorted(rows, key=lambda r: r["timestamp"])]

    def channel_data(self, scene: dict, channel: str) -> list[dict]:
        """sample_data of ``channel`` in the scene (key frames and sweeps), by timestamp."""
        samples = set(self.sample_tokens(scene))
        # rows are objects with tokens (the reader's index); each of the scene's is checked before it is read
        rows = [self.reader.row("sample_data", r) for r in self.reader.rows("sample_data") if r.get("sample_token") in samples]
        return sorted((r for r in rows if self.reader.channel(r) == channel), key=lambda r: r["timestamp"])

    def pose(self, sample_data: dict) -> tuple[np.ndarray, np.ndarray]:
        """(sensor2ego, ego2global) 4x4 of a sample_data."""
        cs = self.reader.ref("sample_data", sample_data, "calibrated_sensor_token", "calibrated_sensor")
        ego = self.reader.ref("sample_data", sample_data, "ego_pose_token", "ego_pose")
        return _matrix(cs), _matrix(ego)

    def file(self, sample_data: dict) -> Path:
        """The file of a sample_data row (inside the dataset root)."""
        return self.reader.file(sample_data)


def load_drive(
    tables: DatasetTables,
    scene_name: str,
    image_size: tuple[int, int] | None,
    lidar_hz: float = NUSCENES_LIDAR_HZ,
    camera_hz: float = NUSCENES_CAMERA_HZ,
    max_seconds: float | None = None,
    progress: Callable[[str], None] = lambda msg: None,
    camera_trigger: str = DEFAULT_TRIGGER,
    start_deg: float | None = None,
    clockwise: bool | None = None,
) -> Drive:
    """The scene as a `Drive`; images resized to ``image_size`` (W, H), None: no images (a LiDAR-only detector).
    ``camera_trigger``: a model of ``triggers.TRIGGER_MODELS``; ``start_deg``, ``clockwise``: the LiDAR's scan
    layout (None: from the data, ``scan_layout.py``), which the drive carries (``Drive.scan_layout``) and which times
    the lidar-synced triggers where the sweeps have no per-point times."""
    check_trigger(camera_trigger)
    if not lidar_hz > 0 or not camera_hz > 0:
        raise ValueError(f"lidar_hz and camera_hz must be > 0, got {lidar_hz}, {camera_hz}")
    scene = tables.scene(scene_name)
    period_s = 1.0 / lidar_hz
    lidar = _keep_every_rotation(tables.channel_data(scene, LIDAR_CHANNEL), period_s)
    if not lidar:
        raise ValueError(f"scene {scene_name!r} has no {LIDAR_CHANNEL} sample_data")
    t0_us = int(lidar[0]["timestamp"]) - int(round(period_s * 1e6))
    if max_seconds is not None:
        lidar = [r for r in lidar if (int(r["timestamp"]) - t0_us) * 1e-6 <= max_seconds + 1e-9] or lidar[:1]
    progress(f"[{scene_name}] reading {len(lidar)} LiDAR sweeps")
    sweeps = []
    timed = 0
    bad_points = bad_times = 0
    for i, sd in enumerate(lidar):
        path = tables.file(sd)
        points = load_points(path)
        times = load_point_times(path, len(points))
        # Non-finite points and times are kept as they are read (streamdet-eval reads the same files): the slices
        # hand the points to the detector, which drops and counts them, and the release schedule and the camera
        # triggers leave them out of their timing (LidarSweep.timing_rows, schedule.slice_sweep).
        bad_points += int(len(points) - np.count_nonzero(np.isfinite(points).all(axis=1)))
        if times is not None:
            timed += 1
            times = times.astype(np.float64)
            finite = np.isfinite(times)
            bad_times += int(len(times) - np.count_nonzero(finite))
            # a sweep recorded at another rate keeps its order; an inf time stays unknown (NaN), not a clipped end
            times = np.where(finite, np.clip(times, 0.0, period_s), np.nan)
        lidar2ego, ego2global = tables.pose(sd)
        sweeps.append(LidarSweep(i, (int(sd["timestamp"]) - t0_us) * 1e-6, period_s, points, times, lidar2ego, ego2global, sd["token"]))
    end_s = sweeps[-1].end_s
    layout = resolve_layout(sweeps, start_deg, clockwise)
    notes = [_lidar_note(lidar, lidar_hz, timed), layout.describe()]
    world = world_version_of(tables.root)
    if world is not None:  # the worlds differ (sensor timing, annotations): results are labelled with theirs
        notes.append(f"data: streamdet-synth world {world} (world.json; data/synth_world.py WORLD_VERSION's history)")
    if bad_points or bad_times:
        notes.append(f"LiDAR of {scene_name}: {bad_points} point(s) with a NaN / inf value (the detector drops and counts "
                     f"them; one without an azimuth is in no slice, as in streamdet-eval), {bad_times} non-finite "
                     f"per-point time(s); neither times a slice release or a camera trigger")  # fmt: skip
    image_sets: list[ImageSet] = []
    rig = None
    if image_size is not None:
        rig = tables.reader.get(tables.sample_tokens(scene)[0]).rig
        channels = [c for c in CAMERA_CHANNELS if tables.channel_data(scene, c)]
        if camera_trigger == "lidar-synced":
            axes = camera_axis_azimuths_deg(rig)
            # each sweep's finite points alone: a NaN time would make a crossing (a trigger) NaN
            timing = [s.for_timing() for s in sweeps]
            triggers = lidar_synced_triggers(timing, {c: axes[c] for c in channels if c in axes}, camera_hz, layout.start_deg,
                                             layout.clockwise)  # fmt: skip
        else:
            triggers = simultaneous_triggers(end_s, camera_hz, channels)
        image_sets, note = _image_sets(tables, scene, t0_us, triggers, camera_hz, camera_trigger, image_size, progress)
        notes.append(note)
    return Drive(scene_name, tuple(sweeps), tuple(image_sets), t0_us, rig, tuple(notes), layout)


def _keep_every_rotation(rows: list[dict], period_s: float) -> list[dict]:
    """Skip sweeps that would start before the previous kept one ended (data faster than the LiDAR rate asked)."""
    kept: list[dict] = []
    for r in rows:
        if not kept or (int(r["timestamp"]) - int(kept[-1]["timestamp"])) * 1e-6 >= period_s - 1e-4:
            kept.append(r)
    return kept


def _lidar_note(rows: list[dict], lidar_hz: float, timed: int) -> str:
    gaps = np.diff([int(r["timestamp"]) for r in rows]) * 1e-6
    rate = f"{1.0 / np.median(gaps):.1f} Hz" if len(gaps) else "one sweep"
    times = "per-point times from the data" if timed == len(rows) else (
        "point times from the azimuth" if timed == 0 else f"per-point times for {timed} of {len(rows)} sweeps, else azimuth")
    return f"LiDAR: {len(rows)} rotations of {1000.0 / lidar_hz:.1f} ms, data at {rate}; {times}"


def _image_sets(
    tables: DatasetTables, scene: dict, t0_us: int, triggers: dict[str, np.ndarray], camera_hz: float, model: str,
    size: tuple[int, int], progress: Callable[[str], None],
) -> tuple[list[ImageSet], str]:
    channels = [c for c in CAMERA_CHANNELS if c in triggers]
    if not channels:
        raise ValueError(f"scene {scene['name']!r} has no camera sample_data")
    recorded = {c: tables.channel_data(scene, c) for c in channels}
    stamps = {c: (np.array([int(r["timestamp"]) for r in rows]) - t0_us) * 1e-6 for c, rows in recorded.items()}
    cache: dict[str, np.ndarray] = {}
    moments: dict[float, list[str]] = {}  # trigger time -> the cameras firing then, in rig order
    for c in channels:
        for t in triggers[c]:
            moments.setdefault(float(t), []).append(c)
    progress(f"[{scene['name']}] reading images of {len(channels)} cameras for {len(moments)} trigger moments")
    found = []  # (capture time, images, recorded time) per trigger moment that delivers any image
    lags = []
    early = 0
    for t in sorted(moments):
        images, times = {}, []
        for c in moments[t]:
            j = int(np.searchsorted(stamps[c], t + TRIGGER_MATCH_S, side="right")) - 1  # newest by the trigger
            if j < 0:  # nothing recorded yet: a camera delivers no frame before its first (never one from the future)
                early += 1
                continue
            row = recorded[c][j]
            if row["token"] not in cache:
                recorded_size = (row["width"], row["height"]) if row["width"] and row["height"] else None
                cache[row["token"]] = load_image(tables.file(row), size, expected_size=recorded_size)
            images[c] = cache[row["token"]]
            times.append(stamps[c][j])
        if not images:
            continue
        recorded_s = float(min(times))
        # a frame stamped just after its trigger was timed a little early from the points: it is captured at its stamp
        capture_s = max(float(t), float(max(times)))
        lags.append(capture_s - recorded_s)
        found.append((capture_s, images, recorded_s))
    found.sort(key=lambda f: f[0])
    sets = [ImageSet(i, capture, images, recorded_s) for i, (capture, images, recorded_s) in enumerate(found)]
    first = stamps[channels[0]]
    span = float(first[-1] - first[0]) if len(first) > 1 else 0.0
    rate = span / (len(first) - 1) if span > 0 else float("inf")  # mean period: lidar-synced intervals are 50 or 100 ms
    lag = f"median {1e3 * np.median(lags):.0f} ms older than the trigger" if lags else "none delivered"
    note = (f"cameras: {len(channels)} triggered at {camera_hz:g} Hz ({model}); data records them at "
            f"{1.0 / rate:.1f} Hz, so each trigger delivers the newest recorded images ({lag})"
            f"{'; images are held between key frames' if 1.0 / rate < camera_hz / 2 else ''}"
            f"{f'; {early} camera trigger(s) before the camera first recorded a frame delivered nothing' if early else ''}")  # fmt: skip
    return sets, note


def _matrix(record: dict) -> np.ndarray:
    return make_transform(quaternion_to_matrix(record["rotation"]), record["translation"])
