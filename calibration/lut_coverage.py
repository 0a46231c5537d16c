"""Does the LUT read an object's own pixels at the object's own BEV cell? (issue 19, height sampling)

For one camera image set with per-pixel instance masks (the synthetic world's ``<image>.mask.npz``) and the
ground-truth boxes of the sample, an object is *covered* when some slot of some voxel of the image-volume column
under its BEV centre reads a feature cell holding at least one pixel of that object. Short objects (pedestrians,
cones, barriers, bicycles) are where a centre-sampled LUT with tall voxels misses: the voxel centres project above
or below them. Objects with no pixel in any camera (hidden, out of view) are not counted: no LUT can read them.

numpy only; ``benchmarks/lut_coverage.py`` runs it over a dataset.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from streamdet.calibration.lut import Lut


@dataclass(frozen=True)
class ObjectCoverage:
    """Per object (M,): whether some camera shows it, and whether the LUT reads it at its own cell."""

    visible: np.ndarray  # (M,) bool: at least one pixel in some camera
    covered: np.ndarray  # (M,) bool: the LUT column under its centre reads one of its feature cells


def instance_feature_cells(instance: np.ndarray, stride: int, feature_hw: tuple[int, int]) -> np.ndarray:
    """(Hf, Wf, stride * stride): the instance ids of each feature cell's pixels (0 = none), the mask padded with
    zeros up to a multiple of ``stride`` (as the encoder's ceil(H / s) rounds)."""
    hf, wf = feature_hw
    padded = np.zeros((hf * stride, wf * stride), dtype=instance.dtype)
    h, w = min(instance.shape[0], hf * stride), min(instance.shape[1], wf * stride)
    padded[:h, :w] = instance[:h, :w]
    blocks = padded.reshape(hf, stride, wf, stride).transpose(0, 2, 1, 3)  # (Hf, Wf, s, s)
    return blocks.reshape(hf, wf, stride * stride)


def object_coverage(lut: Lut, instances: Sequence[np.ndarray], centres_xy: np.ndarray, object_ids: np.ndarray) -> ObjectCoverage:
    """Coverage of M objects with BEV centres ``centres_xy`` (M, 2) (LiDAR frame, m) and mask ids ``object_ids`` (M,).

    ``instances``: per camera of ``lut.camera_names``, the (H, W) instance mask at the LUT's image size (0 = none).
    An object whose centre lies outside the grid is neither visible nor covered here (it is not in the BEV).
    """
    if len(instances) != lut.num_cameras:
        raise ValueError(f"need {lut.num_cameras} instance masks (one per LUT camera), got {len(instances)}")
    centres_xy = np.asarray(centres_xy, dtype=np.float64).reshape(-1, 2)
    object_ids = np.asarray(object_ids).reshape(-1)
    if len(object_ids) != len(centres_xy):
        raise ValueError(f"object_ids ({len(object_ids)}) and centres_xy ({len(centres_xy)}) differ in length")
    hf, wf = lut.feature_height, lut.feature_width
    cells = [instance_feature_cells(m, lut.feature_stride, (hf, wf)) for m in instances]  # J x (Hf, Wf, s^2)
    table = np.concatenate([c.reshape(hf * wf, -1) for c in cells] + [np.zeros((1, cells[0].shape[-1]), cells[0].dtype)])
    visible = np.array([any(np.any(m == i) for m in instances) for i in object_ids.tolist()], dtype=bool)
    covered = np.zeros(len(object_ids), dtype=bool)
    in_grid = np.zeros(len(object_ids), dtype=bool)
    g = lut.grid
    q = g.quadrant_of_xy(centres_xy[:, 0], centres_xy[:, 1]) if len(centres_xy) else np.zeros(0, np.int64)
    for m, (x, y) in enumerate(centres_xy.tolist()):
        x0, y0 = g.quadrant_origin_m(int(q[m]))
        ix, iy = int((x - x0) // g.voxel_xy_m), int((y - y0) // g.voxel_xy_m)
        in_grid[m] = 0 <= ix < g.quadrant_nx and 0 <= iy < g.quadrant_ny
        if not (in_grid[m] and visible[m]):
            continue
        rows = np.unique(lut.index[q[m], :, :, iy, ix])  # every slot of every height of the column
        covered[m] = bool(np.any(table[rows] == object_ids[m]))
    return ObjectCoverage(visible=visible & in_grid, covered=covered)
