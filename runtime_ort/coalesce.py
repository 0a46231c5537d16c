"""Slices detected together: what may share one slice-graph run, and whose detections are whose.

When the slice lane falls behind (a CPU that cannot run one slice graph per slice period), the runtime can detect
consecutive waiting slices of **one rotation and one quadrant** in a single run instead of dropping the oldest: the
slice graph reads a quadrant crop whatever the sector, so two slices of the same quadrant cost one graph run and one
pillarisation of their points together (`LaneConfig.coalesce_slices`; `StreamingDetector.detect_slices`).

Each point keeps its own slice index column (the ``s`` feature, core/points.py): the net sees what it was trained
on, just more of the quadrant at once (the ``1 slice`` column of docs/training/RESULTS.md is the same net on whole
sweeps). A coalesced run's detections go back to the slices by the azimuth of their BEV centre; a box centred
outside every sector of the run (the graph sees its quadrant whole) goes to the run's last slice, the one a single
run of it would have been reported with last.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from streamdet.core.boxes import X, Y
from streamdet.core.sectors import quadrants_of_sector, slice_index_of
from streamdet.runtime_ort.postprocess import Detections


def can_coalesce(first: int, then: int, num_slices: int, start_deg: float = 0.0, clockwise: bool = False) -> bool:
    """True when slice ``then`` may join a run that ends with slice ``first`` (both of ``num_slices``): it is the
    next slice of the same rotation (no wrap past the last slice) and reads the same quadrant(s)."""
    if then != first + 1 or then >= num_slices:
        return False
    return quadrants_of_sector(first, num_slices, start_deg, clockwise) == quadrants_of_sector(then, num_slices, start_deg, clockwise)


def check_coalesced(slice_indices: Sequence[int], num_slices: int, start_deg: float = 0.0, clockwise: bool = False) -> tuple[int, ...]:
    """``slice_indices`` as ints, or a ValueError quoting them: one or more consecutive slices of ``num_slices`` in
    scan order, all reading the same quadrant(s)."""
    ks = tuple(slice_indices)
    bad = [k for k in ks if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 0 <= k < num_slices]
    if not ks or bad:
        raise ValueError(f"slice indices must be one or more ints in [0, {num_slices}), got {ks!r}")
    ks = tuple(int(k) for k in ks)
    for a, b in zip(ks, ks[1:]):
        if not can_coalesce(a, b, num_slices, start_deg, clockwise):
            raise ValueError(
                f"slices detected together must be consecutive slices of {num_slices} in one quadrant, got {ks!r} "
                f"(slice {a} reads quadrants {quadrants_of_sector(a, num_slices, start_deg, clockwise)}, "
                f"slice {b} {quadrants_of_sector(b, num_slices, start_deg, clockwise)})"
            )
    return ks


def split_by_slice(dets: Detections, slice_indices: Sequence[int], num_slices: int, start_deg: float = 0.0,
                   clockwise: bool = False) -> list[Detections]:  # fmt: skip
    """The detections of one coalesced run, one part per slice of ``slice_indices`` (consecutive, scan order): each
    box goes to the slice whose sector holds its BEV centre, a box outside all of them to the last slice."""
    ks = np.asarray(slice_indices, dtype=np.int64)  # (S,)
    if len(ks) == 1:
        return [dets]
    owner = slice_index_of(dets.boxes[:, X], dets.boxes[:, Y], num_slices, start_deg, clockwise) - ks[0]  # (N,) position in the run
    owner = np.where((owner >= 0) & (owner < len(ks)), owner, len(ks) - 1)
    return [dets.select(owner == i) for i in range(len(ks))]
