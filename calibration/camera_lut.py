"""One camera's share of one quadrant's LUT: the cells it sees and its own rows there, for a per-camera lift.

The lifter's gather is linear in the feature maps: a voxel's row is ``sum_k weight * table[index]`` over its K
slots, each slot a pixel of one camera (``lut.py``). Split the slots by camera and the quadrant's gathered volume is
the sum of one volume per camera, each non-zero only on the cells that camera sees. The flat lifter's first layer
(a 1x1 convolution over the z-stacked channels, ``models/flat_lifter.py``) is linear too, so a camera's share can
be carried through it: when one camera sends a new frame, only its share has to be gathered and projected again,
the other cameras' shares are reused, and what follows the first layer runs once on their sum. Whether that pays
is measured by ``benchmarks/partial_lift.py`` (results: docs/replay.md, "Per-camera partial lifts").

Layout of a share (``CameraLut``), for a quadrant of ``Yq * Xq`` cells and ``Z`` heights:

- ``cells`` (N,): the flat cells ``y * Xq + x`` where the camera has at least one valid slot, increasing;
- ``index`` (N, Z, S): rows of **that camera's own** table, ``(Hf * Wf + 1, C)`` with the all-zero row last
  (``cells_per_map``); S = the most slots the camera holds in one voxel (the LUT's heights per voxel);
- ``weight`` (N, Z, S): the LUT's weights of those slots (0 on padding).

``sum over cameras of scatter(cells, gather(share))`` is the quadrant's K-slot gather up to the order of the
floating-point additions (``tests/test_camera_lut.py`` checks it against a per-voxel loop).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.calibration.quadrant_lut import QuadrantLut


@dataclass(frozen=True, eq=False)
class CameraLut:
    """Camera ``camera_name``'s slots in quadrant ``quadrant``, for its own (Hf * Wf + 1, C) feature table."""

    quadrant: int
    camera_name: str
    cells: np.ndarray  # (N,) int64 flat cells y * Xq + x of the quadrant, increasing
    index: np.ndarray  # (N, Z, S) int64 rows of the camera's table; cells_per_map = the zero row
    weight: np.ndarray  # (N, Z, S) float32

    @property
    def num_cells(self) -> int:
        return int(self.cells.size)


def camera_luts(qlut: QuadrantLut, cells_per_map: int) -> tuple[CameraLut, ...]:
    """The share of each of ``qlut.camera_names`` (in that order) of the quadrant LUT ``qlut``, whose rows address
    the stacked ``(J' * cells_per_map + 1, C)`` table of those cameras (``quadrant_lut.py``)."""
    if isinstance(cells_per_map, bool) or not isinstance(cells_per_map, (int, np.integer)) or cells_per_map < 1:
        raise ValueError(f"cells_per_map must be a positive int (Hf * Wf), got {cells_per_map!r}")
    index = np.asarray(qlut.index)
    weight = np.asarray(qlut.weight)
    if index.ndim != 5 or index.shape[0] != 1 or weight.shape != index.shape:
        raise ValueError(f"a quadrant LUT holds (1, K, Z, Yq, Xq) index and weight, got {index.shape} and {weight.shape}")
    k, z, yq, xq = index.shape[1:]
    sentinel = qlut.num_feature_maps * cells_per_map
    if index.size and (index.min() < 0 or index.max() > sentinel):
        raise ValueError(f"LUT rows must lie in 0..{sentinel} (the sentinel) for {qlut.num_feature_maps} maps of "
                         f"{cells_per_map} cells, got {index.min()}..{index.max()}")  # fmt: skip
    flat_index = index[0].reshape(k, z, yq * xq)  # (K, Z, V)
    flat_weight = weight[0].reshape(k, z, yq * xq)
    valid = flat_index != sentinel
    camera = flat_index // cells_per_map  # (K, Z, V); the sentinel's camera is J', matching none
    shares = []
    for j, name in enumerate(qlut.camera_names):
        mine = valid & (camera == j)  # (K, Z, V)
        cells = np.flatnonzero(mine.any(axis=(0, 1)))  # (N,)
        mine = mine[:, :, cells]  # (K, Z, N)
        # this camera's slots first in every voxel (stable: the LUT's slot order kept), then cut to the most it holds
        order = np.argsort(~mine, axis=0, kind="stable")
        s = max(1, int(mine.sum(axis=0).max(initial=0)))
        keep = np.take_along_axis(mine, order, 0)[:s]  # (S, Z, N)
        rows = np.take_along_axis(flat_index[:, :, cells], order, 0)[:s] % cells_per_map
        w = np.take_along_axis(flat_weight[:, :, cells], order, 0)[:s]
        shares.append(CameraLut(
            quadrant=qlut.quadrant,
            camera_name=name,
            cells=cells.astype(np.int64),
            index=np.ascontiguousarray(np.where(keep, rows, cells_per_map).transpose(2, 1, 0), dtype=np.int64),  # (N, Z, S)
            weight=np.ascontiguousarray(np.where(keep, w, 0.0).transpose(2, 1, 0), dtype=np.float32),
        ))  # fmt: skip
    return tuple(shares)


def gather_share(features: np.ndarray, share: CameraLut) -> np.ndarray:
    """(N, Z * C) z-major rows of one camera's share from its (C, Hf, Wf) feature map: channel ``z * C + c``, the
    flat lifter's folded order (numpy; the reference of the partial-lift graph)."""
    c = features.shape[0]
    table = np.concatenate([features.reshape(c, -1).T, np.zeros((1, c), features.dtype)])  # (Hf*Wf + 1, C)
    n, z, _ = share.index.shape
    rows = table[share.index] * share.weight[..., None]  # (N, Z, S, C)
    return rows.sum(axis=2).reshape(n, z * c)  # (N, Z*C)
