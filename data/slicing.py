"""Streaming slices: a full LiDAR sweep cut into n azimuth sectors, as a rotating sensor would deliver it.

The sensor scans counter-clockwise from ``start_deg``; slice k of n covers the azimuths
``[start + k * 360 / n, start + (k + 1) * 360 / n)`` (``streamdet.calibration.grid``). A slice's points are
``(N, 6)`` float32 ``x, y, z, reflectance, relative time, slice index`` (docs/architecture.md "Points"), where
the relative time of a point is its azimuth offset from the scan start as a fraction of the sweep duration,
plus the time lag of its sweep for points of past sweeps. A ground-truth box belongs to every slice whose sector
holds its centre or any of its four BEV corners (the paper's rule), so an object cut by a sector boundary is
annotated in both slices, even where one of them holds none of its points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.calibration.grid import azimuth_deg, check_num_slices, quadrants_of_sector, sector_bounds_deg, slice_index_of
from streamdet.calibration.sectors import cameras_overlapping_sector
from streamdet.data.sample import Sample
from streamdet.runtime_ort.boxes import BOX_DIM, box_corners_bev

SWEEP_DURATION_S = 0.05  # nuScenes LIDAR_TOP spins at 20 Hz
SWEEP_COLUMNS = 5  # x, y, z, intensity (0..255), ring
SLICE_COLUMNS = 6  # x, y, z, reflectance (0..1), relative time (s), slice index


@dataclass(frozen=True, eq=False)
class Slice:
    """One streaming slice of a sample: its points, the quadrants and cameras it needs, its ground truth."""

    index: int  # k, 0..n-1 in scan order
    num_slices: int  # n
    start_deg: float  # azimuth where slice 0 starts
    points: np.ndarray  # (N, 6) float32: x, y, z, reflectance, relative time (s), slice index
    quadrants: tuple[int, ...]  # increasing; the BEV quadrants the sector touches
    camera_names: tuple[str, ...]  # cameras whose horizontal FoV overlaps the sector, in rig order
    gt_boxes: np.ndarray  # (M, 9) boxes with the centre or a BEV corner inside the sector
    gt_labels: np.ndarray  # (M,) int64 indexing CLASS_NAMES, -1 = not a detection class
    gt_indices: np.ndarray  # (M,) int64 rows of these boxes in the sample's gt_boxes

    @property
    def sector_deg(self) -> tuple[float, float]:
        """Azimuth interval [lo, hi) of the sector in degrees (lo in [0, 360), hi may exceed 360)."""
        return sector_bounds_deg(self.index, self.num_slices, self.start_deg)


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
    their input order.
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
    out[:, 3] = points[:, 3] / 255.0
    out[:, 4] = relative_time_s(points, start_deg, sweep_duration_s) + lag
    k = slice_index_of(points[:, 0], points[:, 1], n, start_deg)
    out[:, 5] = k
    # A stable sort by slice keeps the input order inside each slice and costs one pass.
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


def slice_sample(
    sample: Sample,
    n: int,
    start_deg: float = 0.0,
    sweep_duration_s: float = SWEEP_DURATION_S,
    camera_range_m: float | None = None,
) -> list[Slice]:
    """All n slices of a sample: its sweep and past sweeps (with their time lag), ground truth and cameras.

    ``camera_range_m`` is passed to ``cameras_overlapping_sector``: None compares directions only.
    """
    check_num_slices(n, start_deg)
    parts = [split_sweep(sample.points, n, start_deg, sweep_duration_s)]
    for sweep in sample.sweeps:
        parts.append(split_sweep(sweep.points, n, start_deg, sweep_duration_s, time_lag_s=sweep.time_lag_s))
    slices = []
    for k in range(n):
        mask = boxes_in_sector(sample.gt_boxes, k, n, start_deg)
        slices.append(
            Slice(
                index=k,
                num_slices=n,
                start_deg=float(start_deg),
                points=np.concatenate([p[k] for p in parts], axis=0),  # (N_k, 6)
                quadrants=quadrants_of_sector(k, n, start_deg),
                camera_names=cameras_overlapping_sector(sample.rig, k, n, start_deg, camera_range_m),
                gt_boxes=sample.gt_boxes[mask],
                gt_labels=sample.gt_labels[mask],
                gt_indices=np.flatnonzero(mask).astype(np.int64),
            )
        )
    return slices


def _check_points(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < SWEEP_COLUMNS:
        raise ValueError(f"{name} must be (N, {SWEEP_COLUMNS}) x, y, z, intensity, ring; got shape {points.shape}")
    if not np.issubdtype(points.dtype, np.floating):
        raise ValueError(f"{name} must be a float array, got dtype {points.dtype}")
    return points
