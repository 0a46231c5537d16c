"""Streaming sectors and quadrants by azimuth: the angular conventions of streamdet, defined once.

Everything is in the LiDAR frame of the sweep (nuScenes LIDAR_TOP: x right, y forward, z up). Azimuth is
``atan2(y, x)`` in degrees, wrapped to [0, 360).

The BEV plane is split at the sensor origin into four quadrants, numbered counter-clockwise by azimuth::

    q = 0: x >= 0, y >= 0   (azimuth [0, 90) deg)        q = 1: x < 0, y >= 0   ([90, 180))
    q = 2: x < 0,  y < 0    ([180, 270))                  q = 3: x >= 0, y < 0   ([270, 360))

The scan layout is where the LiDAR's sweep starts (``start_deg``) and which way it turns (``clockwise``, seen from
+z). Slices are numbered in the order the sensor delivers them; every sector is half-open, ``[lo, lo + 360 / n)``:

- counter-clockwise (the default): slice k of n covers ``[start + k * 360 / n, start + (k + 1) * 360 / n)``;
- clockwise (the Velodyne HDL-32E of nuScenes' LIDAR_TOP turns so, from about the car's left): slice k covers
  ``[start - (k + 1) * 360 / n, start - k * 360 / n)``, the counter-clockwise sector n - 1 - k.

With ``start_deg`` a multiple of 90 and n >= 4 (n a multiple of 4), a slice lies in one quadrant; n = 2 touches two
and n = 1 all four. The layout decides which points form a slice and when it arrives, never the points' features
(``core/slicing.py``). The metric grid over the quadrants is ``streamdet.calibration.grid.GridSpec``.
"""

from __future__ import annotations

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


def quadrant_of_xy(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Quadrant index (int64) of each (x, y); a point on an axis goes to the non-negative side (x = 0 to q0 / q3,
    y = 0 to q0 / q1), as the grid's cells split there (``GridSpec``). NaN goes to q3 (such a point is in no slice)."""
    x = np.asarray(x)
    y = np.asarray(y)
    return np.where(y >= 0, np.where(x >= 0, 0, 1), np.where(x < 0, 2, 3)).astype(np.int64)


def azimuth_deg(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Azimuth atan2(y, x) in degrees, wrapped to [0, 360), in float64 whatever the input's dtype."""
    # float64 (the cast of a float32 sweep is exact): a float32 atan2 rounds a point on a sector bound, (1, 1) at 45,
    # off it into the sector that ends there, and layouts and the slice-index feature then disagreed about it
    a = np.mod(np.degrees(np.arctan2(np.asarray(y, np.float64), np.asarray(x, np.float64))), 360.0)
    # a tiny negative angle wraps to 360 - tiny, which rounds to exactly 360 in float: that is azimuth 0
    return np.where(a >= 360.0, 0.0, a) if np.ndim(a) else (0.0 if a >= 360.0 else a)


def angle_diff_deg(a, b):
    """``a - b`` in degrees wrapped to [-180, 180): the signed angular distance from ``b`` to ``a`` (arrays broadcast)."""
    d = np.mod(np.subtract(a, b) + 180.0, 360.0) - 180.0
    # as in azimuth_deg: the mod of a tiny negative number rounds to exactly 360, which is -180 here, not +180
    return np.where(d >= 180.0, d - 360.0, d) if np.ndim(d) else (d - 360.0 if d >= 180.0 else d)


def scan_fraction(azimuth, start_deg: float = 0.0, clockwise: bool = False):
    """The share of a rotation (in [0, 1]) after which a sensor of this scan layout points at ``azimuth`` (degrees,
    arrays broadcast). A clockwise scan reaches its start azimuth itself last (1.0): that point is in its last slice."""
    offset = np.mod(np.subtract(azimuth, start_deg), 360.0)
    return (360.0 - offset if clockwise else offset) / 360.0


def ccw_position(k: int, n: int, start_deg: float, clockwise: bool) -> int:
    """The counter-clockwise position from ``start_deg`` of slice k's sector: k, or n - 1 - k for a clockwise scan
    (ValueError for a bad k, n or start)."""
    check_num_slices(n, start_deg)
    if isinstance(k, bool) or not (isinstance(k, (int, np.integer)) and 0 <= k < n):
        raise ValueError(f"slice index must be in [0, {n}), got {k!r}")
    return n - 1 - int(k) if clockwise else int(k)


def sector_bounds_deg(k: int, n: int, start_deg: float = 0.0, clockwise: bool = False) -> tuple[float, float]:
    """Azimuth interval [lo, hi) of slice k of n, in degrees from the x axis (lo in [0, 360), hi = lo + 360/n)."""
    j = ccw_position(k, n, start_deg, clockwise)
    # 360 * j / n, not j * (360 / n): the division is exact where the bound is an axis (39 * (360 / 156) is
    # 89.99999999999999, which put that slice in the quadrant before it)
    lo = (start_deg + 360.0 * j / n) % 360.0
    return lo, lo + 360.0 / n


def run_bounds_deg(first: int, last: int, n: int, start_deg: float = 0.0, clockwise: bool = False) -> tuple[float, float]:
    """Azimuth interval [lo, hi) of the consecutive slices ``first..last`` of n (scan order), as sector_bounds_deg."""
    if isinstance(last, bool) or not (isinstance(last, (int, np.integer)) and first <= last):
        raise ValueError(f"a run of slices ends at or after its first slice {first!r}, got {last!r}")
    lo = sector_bounds_deg(last if clockwise else first, n, start_deg, clockwise)[0]
    sector_bounds_deg(first if clockwise else last, n, start_deg, clockwise)  # the other end is a slice too
    return lo, lo + 360.0 * (int(last) - int(first) + 1) / n


def slice_index_of(x: np.ndarray, y: np.ndarray, n: int, start_deg: float = 0.0, clockwise: bool = False) -> np.ndarray:
    """Slice index (int64, 0..n-1) of each point by azimuth, in scan order; -1 where x or y is NaN (no azimuth: in
    no slice). Casting the NaN gave INT64_MIN on x86 and 0 elsewhere, with a warning."""
    check_num_slices(n, start_deg)
    az = azimuth_deg(x, y)  # float64
    no_azimuth = np.isnan(az)
    q = quadrant_of_xy(x, y)
    quarter = round(start_deg % 360.0 / 90.0) % NUM_QUADRANTS  # quarter turns from +x to the start (any multiple of 90)
    if n < NUM_QUADRANTS:  # n = 1 or 2: each quadrant lies whole in one slice, and the quadrant decides
        j = np.mod(q - quarter, NUM_QUADRANTS) * n // NUM_QUADRANTS
    else:
        # The default layout's sector, counter-clockwise from +x. az * n / 360 rounds as sector_bounds_deg's
        # 360 * j / n: a point on a sector's bound is in the sector it starts.
        j = np.floor(np.where(no_azimuth, 0.0, az) * n / 360.0).astype(np.int64)
        j = np.minimum(j, n - 1)  # az * n can round up to exactly 360 n in float
        # A point on an axis (0, 5), (-5, 0), or rounded onto one ((10, -1e-15) has azimuth 0 but y < 0), is in the
        # quadrant quadrant_of_xy gives it (its grid cell's): its slice must be one that reads that quadrant, else
        # pillarize drops it as outside. Quadrant q's slices are lo = q n / 4 .. hi = (q + 1) n / 4 - 1. Such a
        # point lies on the quadrant's edge, so it goes to the end of that range nearer its azimuth going round the
        # circle: past the 0 / 360 wrap (azimuth 0, quadrant 3) that is hi, the slice next to it, not lo a quarter
        # turn away.
        lo, hi = q * (n // NUM_QUADRANTS), (q + 1) * (n // NUM_QUADRANTS) - 1
        off = (j < lo) | (j > hi)
        if off.any():  # points on an axis only: a sweep pays the compare
            j = np.where(off, np.where((lo - j) % n <= (j - hi) % n, lo, hi), j)
        # The layout's sectors are the default ones shifted by a whole number of them (n is a multiple of 4): an
        # integer shift, not azimuth - start in float, which rounds a point near a bound across it in some layouts
        # only. So every layout agrees point for point with the default one, which the slice-index feature counts.
        j = np.mod(j - quarter * (n // NUM_QUADRANTS), n) if quarter else j
    k = n - 1 - j if clockwise else j
    return np.where(no_azimuth, -1, k) if no_azimuth.any() else k


def quadrants_of_sector(k: int, n: int, start_deg: float = 0.0, clockwise: bool = False) -> tuple[int, ...]:
    """Quadrants (increasing) that slice k of n touches."""
    j = ccw_position(k, n, start_deg, clockwise)
    # in integers of a quarter turn / n: the sector is [a, a + 4) from the +x axis, no rounding at the axes
    a = round(start_deg / 90.0) * n + 4 * j
    first, last = a // n, (a + 4 + n - 1) // n - 1
    return tuple(sorted({q % NUM_QUADRANTS for q in range(first, last + 1)}))
