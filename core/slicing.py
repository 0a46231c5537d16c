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
from streamdet.core.sectors import azimuth_deg, check_num_slices, sector_bounds_deg, slice_index_of


# The azimuth where the slices of training start (training/dataset.py, training/torch_eval.py): a model learns its
# points' slice-index and time features counted from here. A runtime slicing from another start (DetectorConfig.
# start_deg) cuts the same sectors but feeds other feature values for them (runtime_ort: SliceStartWarning).
TRAINED_START_DEG = 0.0


def relative_time_s(points: np.ndarray, start_deg: float = 0.0, sweep_duration_s: float = SWEEP_DURATION_S) -> np.ndarray:
    """(N,) float64 time of each point after the scan start, from its azimuth (counter-clockwise scan)."""
    points = np.asarray(points)
    offset_deg = np.mod(azimuth_deg(points[:, 0], points[:, 1]) - start_deg, 360.0)
    return offset_deg / 360.0 * sweep_duration_s


def split_sweep(
    points: np.ndarray,
    n: int,
    start_deg: float = 0.0,
    sweep_duration_s: float = SWEEP_DURATION_S,
    time_lag_s: float | np.ndarray = 0.0,
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
    out[:, SLICE_TIME] = relative_time_s(points, start_deg, sweep_duration_s) + lag
    k = slice_index_of(points[:, 0], points[:, 1], n, start_deg)
    out[:, SLICE_INDEX] = k
    # A stable sort by slice keeps the input order inside each slice and costs one pass; -1 (no azimuth) sorts
    # before slice 0's bound and is in no slice.
    order = np.argsort(k, kind="stable")
    bounds = np.searchsorted(k[order], np.arange(n + 1))
    return [out[order[bounds[i] : bounds[i + 1]]] for i in range(n)]


def boxes_in_sector(boxes: np.ndarray, k: int, n: int, start_deg: float = 0.0) -> np.ndarray:
    """(M,) bool: the box's BEV centre or any of its four BEV corners lies in slice k of n."""
    sector_bounds_deg(k, n, start_deg)  # validates k, n and start_deg before any work
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != BOX_DIM:
        raise ValueError(f"boxes must be (M, {BOX_DIM}), got shape {boxes.shape}")
    if len(boxes) == 0:
        return np.zeros(0, dtype=bool)
    xy = np.concatenate([box_corners_bev(boxes), boxes[:, None, :2]], axis=1)  # (M, 5, 2): 4 corners + centre
    return np.any(slice_index_of(xy[..., 0], xy[..., 1], n, start_deg) == k, axis=1)


def _check_points(points: np.ndarray, name: str) -> np.ndarray:
    points = check_sweep(points, name, exact=False)  # readers may keep extra trailing columns
    if not np.issubdtype(points.dtype, np.floating):
        raise ValueError(f"{name} must be a float array, got dtype {points.dtype}")
    return points
