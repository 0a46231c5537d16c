"""The two point layouts, defined once.

A **sweep** is ``(N, 5)`` float32, as nuScenes stores it::

    x, y, z      metres, LiDAR frame of the sweep
    intensity    0..255
    ring         laser index

A **slice** (what the slice graph's pillarisation reads) is ``(N, 6)`` float32, the paper's (x, y, z, r, m, s)::

    x, y, z      metres, LiDAR frame
    reflectance  intensity / 255, 0..1
    time         the azimuth's share of a rotation counter-clockwise from +x, in seconds (>= 0), plus the age of
                 the point's sweep for past sweeps: the time since the sweep start in the default scan layout
    slice        the index 0..n-1 of the point's sector counted counter-clockwise from +x: the slice's index in
                 the default scan layout

Both features say where a point lies whatever way the sensor turns (``core.slicing.slice_features``; the scan
layout, ``core/sectors.py``, only decides which slice a point arrives in).
"""

from __future__ import annotations

import numpy as np

SWEEP_COLUMNS = 5
SWEEP_X, SWEEP_Y, SWEEP_Z, SWEEP_INTENSITY, SWEEP_RING = range(SWEEP_COLUMNS)

SLICE_COLUMNS = 6
SLICE_X, SLICE_Y, SLICE_Z, SLICE_REFLECTANCE, SLICE_TIME, SLICE_INDEX = range(SLICE_COLUMNS)

INTENSITY_SCALE = 255.0  # reflectance = intensity / INTENSITY_SCALE
NUSCENES_LIDAR_HZ = 20.0  # LIDAR_TOP rotations per second
NUSCENES_CAMERA_HZ = 12.0  # frames per second of each camera
SWEEP_DURATION_S = 1.0 / NUSCENES_LIDAR_HZ  # one rotation
# The slice columns the net reads as features beside x, y, z have a range it was trained on: a point outside it is
# not a point of this sensor model (a corrupted record, an unscaled 16-bit intensity) and the pillarisation drops and
# counts it rather than let one such value drive the net's activations anywhere (runtime_ort/pillarize.py).
REFLECTANCE_RANGE = (0.0, 1.0)
MAX_POINT_TIME_S = 1.0  # a slice point's time: within its sweep, plus the age of a past sweep (nuScenes' 10: 0.5 s)
MAX_SLICE_INDEX = 4095  # the slice index column's bound: core/sectors.py MAX_NUM_SLICES - 1 (the schema's cap too)
# The most points one call may hand the runtime, refused (ValueError) before any work: a 128-beam spinning LiDAR
# gives a few hundred thousand points a sweep, a sweep with nuScenes' 10 past sweeps about 3.5 million. Past these an
# array is corrupt (or declared through zero strides), and its pillarisation would need gigabytes.
MAX_SLICE_POINTS = 1 << 22  # 4.2 M: one slice, or the slices of one coalesced run together
MAX_SWEEP_POINTS = 1 << 24  # 16.8 M: one sweep for detect_sweep


def check_sweep(points: np.ndarray, name: str = "sweep", *, exact: bool = True) -> np.ndarray:
    """``points`` as an array, or a ValueError naming ``name`` and the bad shape.

    ``exact`` False admits extra trailing columns (a reader that keeps more than the five).
    """
    points = np.asarray(points)
    width_ok = points.ndim == 2 and (points.shape[1] == SWEEP_COLUMNS if exact else points.shape[1] >= SWEEP_COLUMNS)
    if not width_ok:
        raise ValueError(f"{name} must be (N, {SWEEP_COLUMNS}) x, y, z, intensity, ring; got shape {points.shape}")
    return points


def slice_points_problem(points: object) -> str | None:
    """Why ``points`` cannot be a slice, read from its type, shape and dtype alone (no data touched); None if it can.
    What ``StreamingDetector`` raises and ``StreamingRunner.submit_slice`` fails a future with."""
    if not isinstance(points, np.ndarray) or points.ndim != 2 or points.shape[1] != SLICE_COLUMNS:
        got = getattr(points, "shape", type(points).__name__)
        return f"points must be a (N, {SLICE_COLUMNS}) float32 array (x, y, z, r, t, s), got {got}"
    if points.dtype != np.float32:
        return f"points must be float32, got {points.dtype}"
    if isinstance(points, np.ma.MaskedArray):  # a copy or a read drops the mask: masked rows detected as points
        return "points must be a plain array, got a masked array (drop the masked rows first: p[~p.mask.any(1)])"
    return None
