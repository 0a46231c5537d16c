"""Which way a recorded drive's LiDAR turns and where its sweep starts: the replay's scan layout.

The replay hands the detector each slice as the sensor delivered it, so it slices every sweep in the sensor's own
layout (``core/sectors.py``: ``start_deg``, ``clockwise``; the detector is built with the same). Unless the caller
names one (``ReplayConfig.start_deg`` / ``clockwise``, the CLI's ``--scan-start-deg`` / ``--clockwise``), the data
says it (``core/scan_layout.py``): the first sweep's per-point times, else nuScenes' LIDAR_TOP (clockwise from 180).

The points' features do not depend on the layout (``core.slicing.slice_features``): a model sees the same values
whichever way its sensor turns.
"""

from __future__ import annotations

from collections.abc import Sequence

from streamdet.core.scan_layout import (  # noqa: F401 (public here too)
    NUSCENES_LIDAR_TOP, ScanLayout, check_layout, choose_layout, layout_from_times,
)
from streamdet.replay.source import LidarSweep


def drive_layout(sweeps: Sequence[LidarSweep]) -> ScanLayout:
    """The layout of a drive's LiDAR: its first sweep with per-point times that shows one, else NUSCENES_LIDAR_TOP."""
    timed = False
    for sweep in sweeps:
        if sweep.point_time_s is not None:
            timed = True
            found = layout_from_times(sweep.points, sweep.point_time_s)
            if found is not None:
                return found
    if timed:  # times that show no steady turn (constant, shuffled): said so, not "no times"
        return ScanLayout(NUSCENES_LIDAR_TOP.start_deg, NUSCENES_LIDAR_TOP.clockwise,
                          "nuScenes LIDAR_TOP: the sweeps' per-point times show no steady turn")  # fmt: skip
    return NUSCENES_LIDAR_TOP


def resolve_layout(sweeps: Sequence[LidarSweep], start_deg: float | None, clockwise: bool | None) -> ScanLayout:
    """The layout the replay slices with: what the caller named, the rest from the data (``drive_layout``)."""
    return choose_layout(drive_layout(sweeps) if None in (start_deg, clockwise) else None, NUSCENES_LIDAR_TOP, start_deg, clockwise)
