"""Streaming slices of a sample: its sweep, past sweeps, cameras and ground truth cut into n azimuth sectors.

Cutting one sweep (``split_sweep``, ``boxes_in_sector``) lives in ``streamdet.core.slicing`` and is importable
from here as before. The sensor scans counter-clockwise from ``start_deg``; slice k of n covers the azimuths
``[start + k * 360 / n, start + (k + 1) * 360 / n)`` (``streamdet.core.sectors``). A slice's points are
``(N, 6)`` float32 ``x, y, z, reflectance, relative time, slice index`` (docs/architecture.md "Points"), where
the time and index features are counted counter-clockwise from +x whatever ``start_deg`` (the azimuth as a
fraction of the sweep duration, plus the time lag of its sweep for points of past sweeps;
``core.slicing.slice_features``). A ground-truth box belongs to every slice whose sector
holds its centre or any of its four BEV corners (the paper's rule), so an object cut by a sector boundary is
annotated in both slices, even where one of them holds none of its points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.calibration.sectors import cameras_overlapping_sector
from streamdet.core.points import SWEEP_DURATION_S  # noqa: F401 (public here too)
from streamdet.core.sectors import check_num_slices, quadrants_of_sector, sector_bounds_deg
from streamdet.core.slicing import boxes_in_sector, relative_time_s, split_sweep  # noqa: F401 (public here too)
from streamdet.data.sample import Sample


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
