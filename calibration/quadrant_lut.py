"""One quadrant's rows of the projection LUT, addressing only the cameras that see that quadrant.

The lifter graph (``volumetric_lifter.onnx``) is dynamic in the quadrant count Q, the camera count J and the slot
count K, and it appends its all-zero sentinel row after the J feature maps it is given. So one quadrant can be
lifted from the feature maps of its own cameras alone: take the quadrant's rows of the LUT, renumber every valid
row ``j * Hf * Wf + cell`` to ``j' * Hf * Wf + cell`` with ``j'`` the camera's position among the quadrant's
cameras, move the sentinel to ``J' * Hf * Wf``, and drop the trailing slots that are sentinels in every voxel of
the quadrant. The lifted BEV of that quadrant is the full lift's (each quadrant is a batch element of the lifter's
convolutions; the dropped slots added zeros) - ``tests/test_runtime_quadrant_updates.py`` checks it.

A quadrant no camera sees keeps one camera slot of zeros (``camera_indices`` empty: feed one all-zero feature
map), so the lifter still runs and gives what the full lift gives there (the convolutions of an empty volume).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.calibration.lut import Lut
from streamdet.core.sectors import NUM_QUADRANTS


@dataclass(frozen=True, eq=False)
class QuadrantLut:
    """The LUT of quadrant ``quadrant`` for the feature maps of ``camera_names`` alone, stacked in that order."""

    quadrant: int
    camera_indices: tuple[int, ...]  # positions in Lut.camera_names, increasing; empty: no camera sees it
    camera_names: tuple[str, ...]
    index: np.ndarray  # (1, Kq, Z, Yq, Xq) int32, rows of the (max(1, J') * Hf * Wf + 1, C) table; sentinel last
    weight: np.ndarray  # (1, Kq, Z, Yq, Xq) float32, the full LUT's weights of the kept slots

    @property
    def num_feature_maps(self) -> int:
        """J' fed to the lifter: the quadrant's cameras, or one zero map when none sees it."""
        return max(1, len(self.camera_indices))


def quadrant_lut(lut: Lut, quadrant: int) -> QuadrantLut:
    """The rows of ``lut`` for ``quadrant`` (0..3), renumbered for the feature maps of the cameras that see it."""
    if isinstance(quadrant, bool) or not isinstance(quadrant, (int, np.integer)) or not 0 <= quadrant < NUM_QUADRANTS:
        raise ValueError(f"quadrant must be an int in 0..{NUM_QUADRANTS - 1}, got {quadrant!r}")
    q = int(quadrant)
    cells = lut.feature_height * lut.feature_width
    index = lut.index[q]  # (K, Z, Yq, Xq)
    weight = lut.weight[q]
    valid = index != lut.sentinel  # (K, Z, Yq, Xq)
    cameras = np.unique(index[valid] // cells)  # (J',) increasing
    # valid slots come first (the Lut checks it): the slots past the largest per-voxel count are sentinels everywhere
    kq = max(1, int(valid.sum(axis=0).max(initial=0)))
    renumber = np.full(lut.num_cameras, -1, dtype=np.int64)  # (J,) old camera -> position among the quadrant's
    renumber[cameras] = np.arange(cameras.size)
    sentinel = max(1, cameras.size) * cells
    rows = renumber[np.where(valid, index // cells, 0)] * cells + index % cells
    new_index = np.where(valid, rows, sentinel)[:kq].astype(np.int32)  # (Kq, Z, Yq, Xq)
    new_weight = np.where(valid, weight, 0.0)[:kq].astype(np.float32)
    return QuadrantLut(
        quadrant=q,
        camera_indices=tuple(int(j) for j in cameras),
        camera_names=tuple(lut.camera_names[int(j)] for j in cameras),
        index=np.ascontiguousarray(new_index[None]),  # (1, Kq, Z, Yq, Xq)
        weight=np.ascontiguousarray(new_weight[None]),
    )


def quadrant_luts(lut: Lut) -> tuple[QuadrantLut, ...]:
    """``quadrant_lut`` of every quadrant 0..3."""
    return tuple(quadrant_lut(lut, q) for q in range(NUM_QUADRANTS))
