"""When each camera of the rig exposes a frame: the camera trigger models of the replay.

- ``simultaneous``: every camera fires at once at ``camera_hz`` from drive time 0 (one image set of all cameras
  per trigger). Simple, but not how the reference rig works.
- ``lidar-synced`` (nuScenes): "the exposure of a camera is triggered when the top LiDAR sweeps across the centre
  of the camera's FOV" (the nuScenes paper). The bundled real sample shows it: its six frames are 0.5 to 43 ms
  older than the LiDAR sweep, one camera after the other in the order the LiDAR passes their optical axes
  (clockwise in the nuScenes LiDAR frame, 7.2 deg per ms = 20 Hz). A camera running slower than the LiDAR fires at
  one of the LiDAR's crossings of its axis: trigger ``i`` of a camera is the first crossing at or after
  ``i / camera_hz``, so the mean rate is ``camera_hz`` and intervals are whole rotations (50 or 100 ms for 12 Hz
  cameras on a 20 Hz LiDAR).

When the LiDAR points at an azimuth is read from the data: where the sweep has per-point firing times (the
synthetic world's ``<file>.time``), the median time of the points within ``WINDOW_DEG`` of the camera's axis, so
the start azimuth and the direction of rotation are the data's own; otherwise the release schedule's scan layout
(``schedule.py``: ``start_deg``, ``clockwise``), so triggers and slice releases agree with each other.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from streamdet.core.sectors import angle_diff_deg, azimuth_deg, scan_fraction
from streamdet.replay.schedule import check_rate
from streamdet.replay.source import LidarSweep

TRIGGER_MODELS: tuple[str, ...] = ("simultaneous", "lidar-synced")
DEFAULT_TRIGGER = "lidar-synced"  # the reference rig's (nuScenes); docs/replay.md says which figures use which
WINDOW_DEG = 1.0  # half width of the azimuth window whose points time a crossing
MIN_POINTS = 3  # fewer points in the window: the azimuth convention times the crossing instead


def check_trigger(model: str) -> str:
    if model not in TRIGGER_MODELS:
        raise ValueError(f"camera trigger model must be one of {TRIGGER_MODELS}, got {model!r}")
    return model


def camera_axis_azimuths_deg(rig) -> dict[str, float]:
    """Azimuth in [0, 360) of each camera's optical axis in the LiDAR frame (a `Rig` of cameras)."""
    return {cam.name: cam.axis_azimuth_deg for cam in rig.cameras}


def crossing_phase_s(sweep: LidarSweep, azimuth: float, start_deg: float = 0.0, clockwise: bool = False) -> float:
    """Seconds after the rotation start at which the LiDAR points at ``azimuth`` (degrees, LiDAR frame)."""
    if sweep.point_time_s is not None and len(sweep.points):
        az = azimuth_deg(sweep.points[:, 0], sweep.points[:, 1])
        off = np.abs(angle_diff_deg(az, azimuth))  # angular distance, degrees
        near = off <= WINDOW_DEG
        if int(near.sum()) >= MIN_POINTS:
            return float(np.median(np.asarray(sweep.point_time_s)[near]))
    return float(scan_fraction(azimuth, start_deg, clockwise) * sweep.duration_s)


def simultaneous_triggers(end_s: float, camera_hz: float, cameras: Sequence[str]) -> dict[str, np.ndarray]:
    """Every camera at ``0, 1 / camera_hz, ...`` up to ``end_s``."""
    _check_rate(camera_hz)
    times = np.arange(0.0, end_s + 1e-9, 1.0 / camera_hz)
    return {c: times.copy() for c in cameras}


def lidar_synced_triggers(
    sweeps: Sequence[LidarSweep], axes_deg: Mapping[str, float], camera_hz: float, start_deg: float = 0.0,
    clockwise: bool = False,
) -> dict[str, np.ndarray]:
    """Each camera's trigger times (drive seconds, increasing): the first crossing of its axis at or after each
    ``i / camera_hz`` (see the module doc). A camera asked to be faster than the LiDAR fires at every crossing (its
    rate is capped at the LiDAR's)."""
    _check_rate(camera_hz)
    if not sweeps:
        return {c: np.zeros(0) for c in axes_deg}
    out = {}
    for name, axis in axes_deg.items():
        crossings = np.array([s.start_s + crossing_phase_s(s, axis, start_deg, clockwise) for s in sweeps])  # (R,) increasing
        nominal = np.arange(0.0, crossings[-1] + 1e-9, 1.0 / camera_hz)
        picked = np.searchsorted(crossings, nominal - 1e-9)  # first crossing at or after each nominal time
        out[name] = crossings[np.unique(picked[picked < len(crossings)])]
    return out


def _check_rate(camera_hz: float) -> None:
    check_rate(camera_hz, "camera_hz")
