"""Slicing of a sweep: a full LiDAR sweep cut into n azimuth sectors, as a rotating sensor would deliver it.

Slice k of n covers the azimuths ``[start + k * 360 / n, start + (k + 1) * 360 / n)`` (``streamdet.core.sectors``).
A slice's points are in the slice layout of ``streamdet.core.points`` (N, 6), where the relative time of a point
is its azimuth offset from the scan start as a fraction of the sweep duration, plus the time lag of its sweep for
points of past sweeps. A ground-truth box belongs to every slice whose sector holds its centre or any of its four
BEV corners (the paper's rule), so an object cut by a sector boundary is annotated in both slices, even where one
of them holds none of its points. Slicing a whole ``Sample`` (its past sweeps, cameras and ground truth) is
``streamdet.data.slicing.slice_sample``.
"""

from __future__ import annotations

import numpy as np

from streamdet.core.boxes import BOX_DIM, box_corners_bev
from streamdet.core.points import (
    INTENSITY_SCALE,
    SLICE_COLUMNS,
    SLICE_INDEX,
    SLICE_REFLECTANCE,
    SLICE_TIME,
    SWEEP_DURATION_S,
    SWEEP_INTENSITY,
    check_sweep,
)
from streamdet.core.sectors import azimuth_deg, ccw_position, check_num_slices, scan_fraction, sector_bounds_deg, slice_index_of


def relative_time_s(points: np.ndarray, start_deg: float = 0.0, sweep_duration_s: float = SWEEP_DURATION_S,
                    clockwise: bool = False) -> np.ndarray:  # fmt: skip
    """(N,) float64 time of each point after the scan start, from its azimuth: when a sensor of this scan layout
    (``core/sectors.py``) passes it. A clockwise scan reaches its start azimuth itself last (time = the duration),
    as that point lies in its last slice."""
    points = np.asarray(points)
    return scan_fraction(azimuth_deg(points[:, 0], points[:, 1]), start_deg, clockwise) * sweep_duration_s


def split_sweep(
    points: np.ndarray,
    n: int,
    start_deg: float = 0.0,
    sweep_duration_s: float = SWEEP_DURATION_S,
    time_lag_s: float | np.ndarray = 0.0,
    clockwise: bool = False,
) -> list[np.ndarray]:
    """Cut a sweep ``(N, 5)`` (x, y, z, intensity, ring) into n slices ``(N_k, 6)`` float32, in scan order.

    ``time_lag_s`` (scalar or (N,)) is added to each point's relative time: the age of the point's sweep for
    points of past sweeps (nuScenes multi-sweep input), 0 for the current sweep. Within a slice the points keep
    their input order. A point whose x or y is NaN has no azimuth and is in no slice (``slice_index_of``: -1); one
    with another non-finite value goes into its slice, where the detector drops and counts it.
    """
    check_num_slices(n, start_deg)
    points = _check_points(points, "points")
    if not (np.isfinite(sweep_duration_s) and sweep_duration_s > 0):
        raise ValueError(f"sweep_duration_s must be a positive number of seconds, got {sweep_duration_s!r}")
    lag = np.asarray(time_lag_s, dtype=np.float64)
    if lag.ndim and lag.shape != (len(points),):
        raise ValueError(f"time_lag_s must be a scalar or ({len(points)},), got shape {lag.shape}")
    out = np.empty((len(points), SLICE_COLUMNS), dtype=np.float32)
    out[:, :3] = points[:, :3]
    out[:, SLICE_REFLECTANCE] = points[:, SWEEP_INTENSITY] / INTENSITY_SCALE
    default = slice_index_of(points[:, 0], points[:, 1], n)  # (N,) the default layout's slices: the index feature
    k = default if (start_deg % 360.0 == 0.0 and not clockwise) else slice_index_of(points[:, 0], points[:, 1], n, start_deg, clockwise)
    out[:, SLICE_TIME], out[:, SLICE_INDEX] = slice_features(points, n, sweep_duration_s, lag, default)
    # A stable sort by slice keeps the input order inside each slice and costs one pass; -1 (no azimuth) sorts
    # before slice 0's bound and is in no slice.
    order = np.argsort(k, kind="stable")
    bounds = np.searchsorted(k[order], np.arange(n + 1))
    return [out[order[bounds[i] : bounds[i + 1]]] for i in range(n)]


def slice_features(points: np.ndarray, n: int, sweep_duration_s: float = SWEEP_DURATION_S,
                   time_lag_s: float | np.ndarray = 0.0, default_slices: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The (N,) time and slice-index features of the points of a sweep cut into n slices (``SLICE_TIME``,
    ``SLICE_INDEX``), counted counter-clockwise from the +x axis whatever the scan layout: they say where a point
    lies, as the models learn them from recorded sweeps sliced so (the paper's setup), so a sensor that starts
    elsewhere or turns the other way feeds the model the same values for the same azimuths. Only a slice's points
    and the order slices arrive in follow the layout. ``time_lag_s``: added to the time (past sweeps' age);
    ``default_slices``: the points' ``slice_index_of(x, y, n)`` where the caller has it (not computed twice)."""
    az = azimuth_deg(points[:, 0], points[:, 1])  # (N,) in [0, 360); NaN without an azimuth (in no slice)
    if default_slices is None:
        default_slices = slice_index_of(points[:, 0], points[:, 1], n)
    return az / 360.0 * sweep_duration_s + time_lag_s, np.maximum(default_slices, 0)  # -1 (no azimuth): in no slice


def feature_index(k: int, n: int, start_deg: float = 0.0, clockwise: bool = False) -> int:
    """The slice-index feature (``slice_features``) of the points of slice k of n in this scan layout: the index
    counter-clockwise from +x of the sector it covers (k itself in the default layout)."""
    j = ccw_position(k, n, start_deg, clockwise)  # checked
    # in integers (floor(lo * n / 360) in floats gave slice 11 of 28 the index 10): the sector starts a / 4 sectors
    # of n from +x, with a in quarter turns / n
    a = round(start_deg / 90.0) * n + 4 * j
    return (a // 4) % n


def boxes_in_sector(boxes: np.ndarray, k: int, n: int, start_deg: float = 0.0, clockwise: bool = False) -> np.ndarray:
    """(M,) bool: the box's BEV centre or any of its four BEV corners lies in slice k of n."""
    sector_bounds_deg(k, n, start_deg, clockwise)  # validates k, n and start_deg before any work
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != BOX_DIM:
        raise ValueError(f"boxes must be (M, {BOX_DIM}), got shape {boxes.shape}")
    if len(boxes) == 0:
        return np.zeros(0, dtype=bool)
    xy = np.concatenate([box_corners_bev(boxes), boxes[:, None, :2]], axis=1)  # (M, 5, 2): 4 corners + centre
    return np.any(slice_index_of(xy[..., 0], xy[..., 1], n, start_deg, clockwise) == k, axis=1)


def _check_points(points: np.ndarray, name: str) -> np.ndarray:
    points = check_sweep(points, name, exact=False)  # readers may keep extra trailing columns
    if not np.issubdtype(points.dtype, np.floating):
        raise ValueError(f"{name} must be a float array, got dtype {points.dtype}")
    return points
