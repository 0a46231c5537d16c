"""Which cameras see which streaming slice: horizontal field of view against the slice's azimuth sector.

The paper assigns cameras to a slice by their predefined FoVs; here the FoV is measured from the calibration
(``Camera.fov_azimuth_deg``: the azimuth interval of the rays through the image border, LiDAR frame).
"""

from __future__ import annotations

import math

import numpy as np

from streamdet.calibration.camera import Camera, Rig
from streamdet.core.sectors import sector_bounds_deg

# Sampling of a sector for the finite-range test: fine enough that a sliver narrower than this is ignored.
_AZIMUTH_STEP_DEG = 0.1
_RADIAL_SAMPLES = 256


def intervals_overlap_deg(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Whether two azimuth intervals [lo, hi) (degrees, hi >= lo, any winding) share a positive length."""
    a_lo, a_hi = a
    b_lo, b_hi = b
    if a_hi - a_lo >= 360.0 or b_hi - b_lo >= 360.0:
        return a_hi > a_lo and b_hi > b_lo
    shift = (b_lo - a_lo) // 360.0 * 360.0  # bring b_lo into [a_lo, a_lo + 360)
    b_lo, b_hi = b_lo - shift, b_hi - shift
    return (b_lo < a_hi) or (b_hi > a_lo + 360.0)


def camera_sees_sector(camera: Camera, k: int, n: int, start_deg: float = 0.0, max_range_m: float | None = None) -> bool:
    """Whether ``camera``'s horizontal FoV overlaps slice k of n.

    ``max_range_m=None``: compare ray directions only (the FoV interval against the sector interval), exact
    far away. With a range, the camera's BEV wedge starts at its optical centre, not at the LiDAR, so near the
    car it reaches azimuths its directions alone do not; the sector is sampled out to ``max_range_m``
    (every 0.1 deg, 256 radii) and each sample is tested against the wedge from the camera centre.
    """
    lo, hi = sector_bounds_deg(k, n, start_deg)
    fov = camera.fov_azimuth_deg
    if max_range_m is None:
        return intervals_overlap_deg((lo, hi), fov)
    if not (isinstance(max_range_m, (int, float)) and math.isfinite(max_range_m) and max_range_m > 0):
        raise ValueError(f"max_range_m must be a finite positive number of metres or None, got {max_range_m!r}")
    az = np.radians(np.linspace(lo, hi, max(2, math.ceil((hi - lo) / _AZIMUTH_STEP_DEG) + 1)))  # (A,)
    r = np.linspace(0.0, max_range_m, _RADIAL_SAMPLES + 1)[1:]  # (R,) the origin itself has no azimuth
    x = (r[:, None] * np.cos(az)[None, :]).ravel()  # (R * A,)
    y = (r[:, None] * np.sin(az)[None, :]).ravel()
    cx, cy = camera.center_lidar[:2]
    rel = np.mod(np.degrees(np.arctan2(y - cy, x - cx)) - fov[0], 360.0)  # azimuth from the camera, from lo
    return bool(np.any(rel <= fov[1] - fov[0]))


def cameras_overlapping_sector(
    rig: Rig, k: int, n: int, start_deg: float = 0.0, max_range_m: float | None = None
) -> tuple[str, ...]:
    """Names of the cameras whose horizontal FoV overlaps slice k of n, in rig order (see camera_sees_sector)."""
    return tuple(c.name for c in rig.cameras if camera_sees_sector(c, k, n, start_deg, max_range_m))


def sector_camera_table(
    rig: Rig, n: int, start_deg: float = 0.0, max_range_m: float | None = None
) -> tuple[tuple[str, ...], ...]:
    """``cameras_overlapping_sector`` for every slice k = 0..n-1."""
    return tuple(cameras_overlapping_sector(rig, k, n, start_deg, max_range_m) for k in range(n))
