"""How a spinning LiDAR turns, read from its data: the scan layout (``core/sectors.py``: ``start_deg``, ``clockwise``).

Where a sweep has per-point firing times (the synthetic world's ``<file>.time``, a ROS driver's ``t`` field), they
say it: the way the azimuth moves as time goes on, and the azimuth of the first firings rounded to the nearest axis
(slices align with the quadrants, so the start is a multiple of 90 degrees). Without them, nuScenes' LIDAR_TOP is a
Velodyne HDL-32E: it turns clockwise seen from above and starts a little behind the car's left (the bundled
sample's point order, which is its firing order, and its six cameras' trigger times say so: docs/replay.md), the
nearest axis being 180 deg. ``streamdet-replay`` and ``streamdet-bag`` take the layout from here unless told one.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from streamdet.core.sectors import angle_diff_deg, azimuth_deg

# Fewer timed points, or fewer distinct times, than these say nothing reliable about the rotation.
MIN_TIMED_POINTS = 100
MIN_DISTINCT_TIMES = 32
# At least this share of the steps between consecutive groups must turn the way the whole does: random or shuffled
# times wander about and show no direction.
MIN_STEADY_SHARE = 0.75
# The timed points are cut into this many groups in firing order: the turn is read from the groups' mean azimuths, as
# the points within one firing (rings, returns, dropouts) jump about in azimuth far more than the spin moves.
TIME_GROUPS = 90


@dataclass(frozen=True)
class ScanLayout:
    start_deg: float  # azimuth where the sweep, and slice 0, starts (a multiple of 90 in [0, 360))
    clockwise: bool  # seen from above (+z)
    source: str  # what said so, for a report

    def describe(self) -> str:
        way = "clockwise" if self.clockwise else "counter-clockwise"
        return f"LiDAR scan layout: {way} from {self.start_deg:g} deg ({self.source})"


NUSCENES_LIDAR_TOP = ScanLayout(180.0, True, "nuScenes LIDAR_TOP: the sweeps have no per-point times")


def layout_from_times(points: np.ndarray, times: np.ndarray) -> ScanLayout | None:
    """The layout the per-point firing ``times`` (N,) of a sweep's ``points`` (N, >=2) show; None with fewer than
    MIN_TIMED_POINTS usable points or MIN_DISTINCT_TIMES times, or no steady turn of at least a quarter."""
    pts = np.asarray(points, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 2 or t.shape != (len(pts),):
        raise ValueError(f"layout_from_times takes (N, >=2) points and (N,) times, got {pts.shape} and {t.shape}")
    usable = np.isfinite(t) & np.isfinite(pts[:, 0]) & np.isfinite(pts[:, 1]) & (np.hypot(pts[:, 0], pts[:, 1]) > 0)
    if int(usable.sum()) < MIN_TIMED_POINTS or len(np.unique(t[usable])) < MIN_DISTINCT_TIMES:
        return None
    order = np.argsort(t[usable], kind="stable")
    rad = np.radians(azimuth_deg(pts[usable, 0], pts[usable, 1])[order])  # (M,) in firing order
    groups = np.array_split(np.arange(len(rad)), min(TIME_GROUPS, len(rad)))
    means = np.array([math.degrees(math.atan2(np.sin(rad[g]).mean(), np.cos(rad[g]).mean())) for g in groups])  # (G,)
    steps = angle_diff_deg(means[1:], means[:-1])  # (G - 1,) degrees
    turned = float(steps.sum())  # about +-360 for one rotation
    if abs(turned) < 90.0 or np.mean(np.sign(steps) == np.sign(turned)) < MIN_STEADY_SHARE:
        return None
    # the first group's mean lies half a group into the scan: its start is half a step before
    first = means[0] - 0.5 * turned / len(means)
    start = float(np.mod(round(first / 90.0) * 90.0, 360.0))  # the first firings' azimuth, to the nearest axis
    return ScanLayout(start, turned < 0, "from the per-point times")


def check_layout(start_deg: float | None, clockwise: bool | None, from_data: bool = True) -> tuple[float | None, bool | None]:
    """ValueError quoting the bad value unless ``start_deg`` is a multiple of 90 in [-360, 360) and ``clockwise`` a
    bool; with ``from_data`` either may also be None (read from the data). Returns them as a Python float and bool
    (numpy's are taken, and would not go into a JSON report)."""
    or_none = " (or None: from the data)" if from_data else ""
    # bounded: 1e300 is a multiple of 90 too, and its azimuths would put every point outside every sector
    if (start_deg is not None or not from_data) and (
            isinstance(start_deg, (bool, np.bool_)) or not isinstance(start_deg, numbers.Real)
            or not math.isfinite(start_deg) or not -360.0 <= start_deg < 360.0 or start_deg % 90.0):
        raise ValueError(f"start_deg must be a multiple of 90 degrees in [-360, 360){or_none}, got {start_deg!r}")
    if (clockwise is not None or not from_data) and not isinstance(clockwise, (bool, np.bool_)):
        raise ValueError(f"clockwise must be True or False{or_none}, got {clockwise!r}")
    return (None if start_deg is None else float(start_deg)), (None if clockwise is None else bool(clockwise))


def choose_layout(found: ScanLayout | None, fallback: ScanLayout, start_deg: float | None = None,
                  clockwise: bool | None = None) -> ScanLayout:  # fmt: skip
    """The layout to slice with: ``start_deg`` / ``clockwise`` where given, the rest from what the data showed
    (``found``), else from ``fallback``."""
    check_layout(start_deg, clockwise)
    if start_deg is not None and clockwise is not None:
        return ScanLayout(float(start_deg) % 360.0, clockwise, "as given")
    seen = found if found is not None else fallback
    return ScanLayout(seen.start_deg if start_deg is None else float(start_deg) % 360.0,
                      seen.clockwise if clockwise is None else clockwise,
                      seen.source if (start_deg, clockwise) == (None, None) else f"partly given, the rest {seen.source}")  # fmt: skip
