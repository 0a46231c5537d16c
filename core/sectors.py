"""Streaming sectors and quadrants by azimuth: the angular conventions of streamdet, defined once.

Everything is in the LiDAR frame of the sweep (nuScenes LIDAR_TOP: x right, y forward, z up). Azimuth is
``atan2(y, x)`` in degrees, wrapped to [0, 360).

The BEV plane is split at the sensor origin into four quadrants, numbered counter-clockwise by azimuth::

    q = 0: x >= 0, y >= 0   (azimuth [0, 90) deg)        q = 1: x < 0, y >= 0   ([90, 180))
    q = 2: x < 0,  y < 0    ([180, 270))                  q = 3: x >= 0, y < 0   ([270, 360))

The LiDAR scans counter-clockwise from ``start_deg``; slice k of n covers azimuths
``[start + k * 360 / n, start + (k + 1) * 360 / n)``. With ``start_deg`` a multiple of 90 and n >= 4 (n a
multiple of 4), a slice lies in one quadrant; n = 2 touches two and n = 1 all four. The metric grid over the
quadrants is ``streamdet.calibration.grid.GridSpec``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable

import numpy as np

NUM_QUADRANTS = 4


def check_quadrants(quadrants: Iterable[int]) -> tuple[int, ...]:
    """The quadrants of one slice or one image update as a tuple of ints: a non-empty, strictly increasing list of
    0..3 (ints or numpy integers, not bools); ValueError quoting the bad value otherwise."""
    if type(quadrants) is tuple or type(quadrants) is list:  # the hot path (every slice, several times): plain ints
        qs = tuple(quadrants)
        if qs and all(type(q) is int and 0 <= q < NUM_QUADRANTS for q in qs) and all(a < b for a, b in zip(qs, qs[1:])):
            return qs
    try:
        qs = None if isinstance(quadrants, (str, bytes)) else tuple(quadrants)
    except TypeError:
        qs = None
    ok = (
        qs is not None and len(qs) > 0
        and all(isinstance(q, numbers.Integral) and not isinstance(q, bool) and 0 <= q < NUM_QUADRANTS for q in qs)
        and all(a < b for a, b in zip(qs, qs[1:]))
    )  # fmt: skip
    if not ok:
        raise ValueError(f"quadrants must be a non-empty strictly increasing list of 0..3, got {quadrants!r}")
    return tuple(int(q) for q in qs)


# The most slices per sweep (sectors of 0.09 deg): manifest.schema.json's num_slices maximum, and the bound of the slice
# index column the pillarisation accepts (core/points.py MAX_SLICE_INDEX); a larger count is a typo, not a slicing.
MAX_NUM_SLICES = 4096


def check_num_slices(n: int, start_deg: float = 0.0) -> None:
    """n slices must align with the quadrant split: n in {1, 2} or a multiple of 4 up to MAX_NUM_SLICES, start on an
    axis."""
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or not 1 <= n <= MAX_NUM_SLICES:
        raise ValueError(f"number of slices must be an integer in 1..{MAX_NUM_SLICES}, got {n!r}")
    if n not in (1, 2) and n % 4:
        raise ValueError(f"number of slices must be 1, 2 or a multiple of 4 (sectors aligned to quadrants), got {n}")
    if start_deg % 90.0:
        raise ValueError(f"slice start angle must be a multiple of 90 deg, got {start_deg}")


def azimuth_deg(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Azimuth atan2(y, x) in degrees, wrapped to [0, 360)."""
    a = np.degrees(np.arctan2(y, x))
    return np.mod(a, 360.0)


def angle_diff_deg(a, b):
    """``a - b`` in degrees wrapped to [-180, 180): the signed angular distance from ``b`` to ``a`` (arrays broadcast)."""
    return np.mod(np.subtract(a, b) + 180.0, 360.0) - 180.0


def sector_bounds_deg(k: int, n: int, start_deg: float = 0.0) -> tuple[float, float]:
    """Azimuth interval [lo, hi) of slice k of n, in degrees from the x axis (lo in [0, 360), hi = lo + 360/n)."""
    check_num_slices(n, start_deg)
    if not (isinstance(k, (int, np.integer)) and 0 <= k < n):
        raise ValueError(f"slice index must be in [0, {n}), got {k!r}")
    width = 360.0 / n
    lo = (start_deg + k * width) % 360.0
    return lo, lo + width


def slice_index_of(x: np.ndarray, y: np.ndarray, n: int, start_deg: float = 0.0) -> np.ndarray:
    """Slice index (int64, 0..n-1) of each point by azimuth, in scan order from start_deg; -1 where x or y is NaN
    (no azimuth: in no slice). Casting the NaN gave INT64_MIN on x86 and 0 elsewhere, with a warning."""
    check_num_slices(n, start_deg)
    rel = np.mod(azimuth_deg(x, y) - start_deg, 360.0)
    no_azimuth = np.isnan(rel)
    k = np.floor(np.where(no_azimuth, 0.0, rel) / (360.0 / n)).astype(np.int64)
    k = np.minimum(k, n - 1)  # rel can round up to exactly 360 in float
    return np.where(no_azimuth, -1, k) if no_azimuth.any() else k


def quadrants_of_sector(k: int, n: int, start_deg: float = 0.0) -> tuple[int, ...]:
    """Quadrants (increasing) that slice k of n touches."""
    lo, hi = sector_bounds_deg(k, n, start_deg)
    first = int(lo // 90.0)
    count = max(1, math.ceil((hi - lo) / 90.0 - 1e-9))
    return tuple(sorted({(first + i) % NUM_QUADRANTS for i in range(count)}))
