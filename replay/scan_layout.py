"""Which way a recorded drive's LiDAR turns and where its sweep starts: the replay's scan layout.

The replay hands the detector each slice as the sensor delivered it, so it slices every sweep in the sensor's own
layout (``core/sectors.py``: ``start_deg``, ``clockwise``; the detector is built with the same). Unless the caller
names one (``ReplayConfig.start_deg`` / ``clockwise``, the CLI's ``--scan-start-deg`` / ``--clockwise``):

- where the sweeps have per-point firing times (the synthetic world's ``<file>.time``), the times say it: the way
  the azimuth moves as time goes on, and the azimuth of the first firings rounded to the nearest axis (slices align
  with the quadrants, so the start is a multiple of 90 degrees);
- otherwise the layout of nuScenes' LIDAR_TOP, a Velodyne HDL-32E: it turns clockwise seen from above and starts
  near 185-190 deg in the LiDAR frame (the bundled sample's point order and its six cameras' trigger times say so,
  ``docs/replay.md``), the nearest axis being 180 deg.

The points' features do not depend on the layout (``core.slicing.slice_features``): a model sees the same values
whichever way its sensor turns.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from streamdet.core.sectors import angle_diff_deg, azimuth_deg
from streamdet.replay.source import LidarSweep

# Fewer timed points than this say nothing reliable about the rotation: the nuScenes default is taken instead.
MIN_TIMED_POINTS = 100
# The timed points are cut into this many groups in firing order: the turn is read from the groups' mean azimuths, as
# the points within one firing (rings, returns, dropouts) jump about in azimuth far more than the spin moves.
TIME_GROUPS = 360


@dataclass(frozen=True)
class ScanLayout:
    start_deg: float  # azimuth where the sweep, and slice 0, starts (a multiple of 90 in [0, 360))
    clockwise: bool  # seen from above (+z)
    source: str  # what said so, for the report

    def describe(self) -> str:
        way = "clockwise" if self.clockwise else "counter-clockwise"
        return f"LiDAR scan layout: {way} from {self.start_deg:g} deg ({self.source})"


NUSCENES_LIDAR_TOP = ScanLayout(180.0, True, "nuScenes LIDAR_TOP: the sweeps have no per-point times")


def layout_from_times(points: np.ndarray, times: np.ndarray) -> ScanLayout | None:
    """The layout the per-point firing ``times`` (N,) of a sweep's ``points`` (N, >=2) show; None with fewer than
    MIN_TIMED_POINTS usable points or no clear direction."""
    pts = np.asarray(points, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    usable = np.isfinite(t) & np.isfinite(pts[:, 0]) & np.isfinite(pts[:, 1]) & (np.hypot(pts[:, 0], pts[:, 1]) > 0)
    if int(usable.sum()) < MIN_TIMED_POINTS:
        return None
    order = np.argsort(t[usable], kind="stable")
    rad = np.radians(azimuth_deg(pts[usable, 0], pts[usable, 1])[order])  # (M,) in firing order
    groups = np.array_split(np.arange(len(rad)), min(TIME_GROUPS, len(rad)))
    means = np.array([math.degrees(math.atan2(np.sin(rad[g]).mean(), np.cos(rad[g]).mean())) for g in groups])  # (G,)
    turned = float(angle_diff_deg(means[1:], means[:-1]).sum())  # about +-360 for one rotation
    if abs(turned) < 90.0:
        return None
    start = float(np.mod(round(means[0] / 90.0) * 90.0, 360.0))  # the first firings' azimuth, to the nearest axis
    return ScanLayout(start, turned < 0, "from the sweeps' per-point times")


def drive_layout(sweeps: Sequence[LidarSweep]) -> ScanLayout:
    """The layout of a drive's LiDAR: its first sweep with per-point times that shows one, else NUSCENES_LIDAR_TOP."""
    for sweep in sweeps:
        if sweep.point_time_s is not None:
            found = layout_from_times(sweep.points, sweep.point_time_s)
            if found is not None:
                return found
    return NUSCENES_LIDAR_TOP


def check_layout(start_deg: float | None, clockwise: bool | None) -> None:
    """ValueError quoting the bad value unless ``start_deg`` is None or a multiple of 90 in [-360, 360) and
    ``clockwise`` None or a bool."""
    if start_deg is not None and (isinstance(start_deg, bool) or not isinstance(start_deg, (int, float))
                                  or not math.isfinite(start_deg) or not -360.0 <= start_deg < 360.0 or start_deg % 90.0):
        raise ValueError(f"the scan start must be None (from the data) or a multiple of 90 degrees in [-360, 360), got {start_deg!r}")
    if clockwise is not None and not isinstance(clockwise, bool):
        raise ValueError(f"clockwise must be None (from the data), True or False, got {clockwise!r}")


def resolve_layout(sweeps: Sequence[LidarSweep], start_deg: float | None, clockwise: bool | None) -> ScanLayout:
    """The layout the replay slices with: what the caller named, the rest from the data (``drive_layout``)."""
    check_layout(start_deg, clockwise)
    if start_deg is not None and clockwise is not None:
        return ScanLayout(float(start_deg) % 360.0, clockwise, "as given")
    found = drive_layout(sweeps)
    return ScanLayout(found.start_deg if start_deg is None else float(start_deg) % 360.0,
                      found.clockwise if clockwise is None else clockwise,
                      found.source if (start_deg, clockwise) == (None, None) else f"partly given, the rest {found.source}")  # fmt: skip
