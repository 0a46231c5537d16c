"""What the player plays: a drive, as timed LiDAR sweeps and timed camera image sets.

This is the whole interface between a data source and the player. A source (the nuScenes-format reader in
``nuscenes_source.py``; a ROS 2 bag reader could be another) builds one `Drive`:

- ``sweeps``: every LiDAR rotation in time order, with its points in the LiDAR frame at the rotation's end (the
  nuScenes convention), each point's firing time after the rotation start when the data has it (else None: the
  player derives it from the azimuth), and the ego pose at the rotation's end (where the detections of its slices
  are placed in the world, as a planner would);
- ``image_sets``: the camera images as the vehicle's cameras deliver them, each set with its capture time.

All times are **drive seconds**, 0 being the start of the first rotation; ``t0_us`` anchors them to the dataset's
microsecond timestamps (where the ground truth lives). The player slices each sweep and releases the slices
itself (``schedule.py``), so a source never needs to know how many slices a mode uses.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class LidarSweep:
    """One LiDAR rotation."""

    index: int  # 0, 1, ... in time order
    end_s: float  # drive time the rotation completed (the sweep's timestamp)
    duration_s: float  # one rotation (1 / LiDAR rate)
    points: np.ndarray  # (N, 5) float32 x, y, z (LiDAR frame at end_s), intensity 0..255, ring
    point_time_s: np.ndarray | None  # (N,) firing time after the rotation start, s; None: derive from the azimuth
    lidar2ego: np.ndarray  # (4, 4)
    ego2global: np.ndarray  # (4, 4) ego pose at end_s
    token: str = ""  # the source's id of the sweep (nuScenes: sample_data token)

    def __post_init__(self) -> None:
        pts = np.asarray(self.points)
        if pts.ndim != 2 or pts.shape[1] != 5:
            raise ValueError(f"LidarSweep {self.index}: points must be (N, 5) x, y, z, intensity, ring, got {pts.shape}")
        if self.point_time_s is not None and np.shape(self.point_time_s) != (len(pts),):
            raise ValueError(f"LidarSweep {self.index}: point_time_s has shape {np.shape(self.point_time_s)} for {len(pts)} points")
        if not self.duration_s > 0:
            raise ValueError(f"LidarSweep {self.index}: duration_s must be > 0, got {self.duration_s!r}")

    @property
    def start_s(self) -> float:
        return self.end_s - self.duration_s

    def timing_rows(self) -> np.ndarray:
        """(N,) bool: the points that may time a slice release or a camera trigger: every column finite and, where
        the sweep has per-point times, a finite time. The others (a NaN / inf coordinate, intensity or time: a
        corrupted file, a non-dense cloud) still reach the detector in their slice, which drops and counts them
        (``SliceResult.num_nonfinite_dropped``) as it does in streamdet-eval; only the replay's timing ignores them."""
        pts = np.asarray(self.points)
        ok = np.isfinite(pts).all(axis=1)
        if self.point_time_s is not None:
            ok &= np.isfinite(np.asarray(self.point_time_s, dtype=np.float64))
        return ok

    def for_timing(self) -> LidarSweep:
        """This sweep with only its `timing_rows` (itself where every row is one): what a timing model that reads
        the points (``triggers.crossing_phase_s``) must be given."""
        ok = self.timing_rows()
        if ok.all():
            return self
        times = None if self.point_time_s is None else np.asarray(self.point_time_s)[ok]
        return LidarSweep(self.index, self.end_s, self.duration_s, np.asarray(self.points)[ok], times, self.lidar2ego,
                          self.ego2global, self.token)  # fmt: skip


@dataclass(frozen=True, eq=False)
class ImageSet:
    """The images of the cameras at one camera trigger."""

    index: int
    # drive time of the trigger (or of its frame, stamped up to nuscenes_source.TRIGGER_MATCH_S after a trigger timed
    # a little early): the image BEV made from this set is as old as now - capture_s
    capture_s: float
    images: Mapping[str, np.ndarray]  # camera name -> (H, W, 3) uint8 RGB at the detector's image size
    recorded_s: float  # drive time the images were recorded at (earlier than capture_s where a source holds images)


@dataclass(frozen=True, eq=False)
class Drive:
    """One drive (a scene) as the vehicle's sensors deliver it."""

    name: str
    sweeps: tuple[LidarSweep, ...]
    image_sets: tuple[ImageSet, ...]
    t0_us: int  # dataset timestamp (us) of drive time 0
    rig: object | None = None  # streamdet.calibration.camera.Rig of the cameras, None where unknown
    notes: tuple[str, ...] = ()  # what the source did that a reader of the report must know (held images, ...)
    # scan_layout.ScanLayout: how the LiDAR turns, which the player slices with; None: counter-clockwise from 0 deg
    scan_layout: object | None = None

    def __post_init__(self) -> None:
        ends = [s.end_s for s in self.sweeps]
        if any(b <= a for a, b in zip(ends, ends[1:])):
            raise ValueError(f"drive {self.name!r}: sweeps must be in increasing time order")
        captures = [s.capture_s for s in self.image_sets]
        if any(b < a for a, b in zip(captures, captures[1:])):
            raise ValueError(f"drive {self.name!r}: image sets must be in time order")

    @property
    def duration_s(self) -> float:
        return max([s.end_s for s in self.sweeps] + [s.capture_s for s in self.image_sets] + [0.0])

    def time_us(self, drive_s: float | np.ndarray) -> np.ndarray:
        """Dataset timestamps (us, float) of drive times."""
        return self.t0_us + np.asarray(drive_s, dtype=np.float64) * 1e6
