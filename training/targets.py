"""CenterPoint training targets on one quadrant's head map (numpy arrays; the decode inverse comes from models/).

For every ground-truth box whose centre falls inside the quadrant, the head map gets:

- a Gaussian peak on its class channel at the centre cell, radius ``gaussian_radius((l, w) in head cells,
  min_overlap)`` (CenterPoint / CornerNet's rule, floored to an int, at least ``min_radius_cells``), merged with
  other peaks by maximum;
- one regression row at the centre cell: ``reg_x, reg_y, z, log w, log l, log h, sin yaw, cos yaw, vx, vy``,
  the exact inverse of ``models/decode.py`` (``encode_center`` gives the cell and the sub-cell offset).

Coordinates are quadrant-local: x, y minus ``GridSpec.quadrant_origin_m(q)``, the frame of the head maps.
A box cut by a quadrant border is a target only in the quadrant holding its centre, as in the runtime's uncrop.
A net without the quadrant crop (``Preset.slice_crop`` False, ``calibration/slice_maps.py``) has one map of the
whole grid per slice: ``quadrant=None``, coordinates relative to the grid's minimum corner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.calibration.grid import GridSpec
from streamdet.calibration.slice_maps import map_cells, slice_maps
from streamdet.core.boxes import BOX_DIM, H, L, VX, VY, W, X, Y, YAW, Z
from streamdet.core.classes import CLASS_NAMES
from streamdet.models.decode import encode_center

BOX_CODE_SIZE = 10  # reg_x, reg_y, z, log w, log l, log h, sin, cos, vx, vy (head outputs reg, height, dim, rot, vel)


@dataclass(frozen=True)
class TargetConfig:
    min_overlap: float = 0.1  # CenterPoint's nuScenes gaussian_overlap
    min_radius_cells: int = 2  # CenterPoint's min_radius
    max_objects: int = 128  # regression rows per quadrant map; more objects than this are dropped (and counted)

    def __post_init__(self) -> None:
        if not 0.0 < self.min_overlap < 1.0:
            raise ValueError(f"TargetConfig.min_overlap must be in (0, 1), got {self.min_overlap!r}")
        for name in ("min_radius_cells", "max_objects"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < (0 if name == "min_radius_cells" else 1):
                raise ValueError(f"TargetConfig.{name} must be a {'non-negative' if name == 'min_radius_cells' else 'positive'} integer, got {v!r}")


@dataclass(frozen=True)
class MapTargets:
    """The targets of one quadrant head map."""

    heatmap: np.ndarray  # (num_classes, Hh, Wh) float32 in [0, 1], 1 exactly at each centre cell
    index: np.ndarray  # (max_objects,) int64 flat cell row * Wh + col; 0 on unused rows
    mask: np.ndarray  # (max_objects,) bool, True on the rows that hold an object
    label: np.ndarray  # (max_objects,) int64 class; 0 on unused rows
    box: np.ndarray  # (max_objects, BOX_CODE_SIZE) float32 regression targets; 0 on unused rows
    num_dropped: int  # objects beyond max_objects

    @property
    def num_objects(self) -> int:
        return int(self.mask.sum())


def gaussian_radius(height: np.ndarray, width: np.ndarray, min_overlap: float) -> np.ndarray:
    """CenterPoint's (CornerNet's) radius rule, vectorised: the smallest of the three quadratic-bound radii.

    ``height``, ``width`` are the box extent in head cells (CenterPoint passes (l, w)). The formula is the one
    CenterPoint ships (including its r1 / r2 / r3 as published), not a corrected derivation.
    """
    h = np.asarray(height, dtype=np.float64)
    w = np.asarray(width, dtype=np.float64)
    b1 = h + w
    c1 = w * h * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + np.sqrt(b1**2 - 4 * c1)) / 2
    b2 = 2 * (h + w)
    c2 = (1 - min_overlap) * w * h
    r2 = (b2 + np.sqrt(b2**2 - 16 * c2)) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (h + w)
    c3 = (min_overlap - 1) * w * h
    r3 = (b3 + np.sqrt(b3**2 - 4 * a3 * c3)) / 2
    return np.minimum(np.minimum(r1, r2), r3)


def draw_gaussians(heatmap: np.ndarray, channel: np.ndarray, row: np.ndarray, col: np.ndarray, radius: np.ndarray) -> None:
    """Max-merge CenterNet Gaussians into ``heatmap`` (C, Hh, Wh) in place, one per (channel, row, col, radius).

    Object i's Gaussian spans the (2 r + 1)^2 window around its cell with sigma = (2 r + 1) / 6, values below
    eps * peak cut to zero (CenterNet's ``gaussian2D``); the window is clipped at the map border.
    """
    n = len(row)
    if n == 0:
        return
    r = np.asarray(radius, dtype=np.int64)
    reach = int(r.max())
    offsets = np.arange(-reach, reach + 1)
    dy = offsets[None, :, None]  # (1, D, 1)
    dx = offsets[None, None, :]  # (1, 1, D)
    sigma = (2 * r + 1) / 6.0
    g = np.exp(-(dx * dx + dy * dy) / (2 * sigma[:, None, None] ** 2))  # (N, D, D)
    g[g < np.finfo(np.float64).eps] = 0.0  # the peak is 1, so eps * peak == eps
    inside = (np.abs(dy) <= r[:, None, None]) & (np.abs(dx) <= r[:, None, None])  # each object's own window
    rows = row[:, None, None] + dy  # (N, D, 1)
    cols = col[:, None, None] + dx  # (N, 1, D)
    _, hh, wh = heatmap.shape
    keep = inside & (rows >= 0) & (rows < hh) & (cols >= 0) & (cols < wh)  # (N, D, D)
    ch = np.broadcast_to(channel[:, None, None], keep.shape)[keep]
    rr = np.broadcast_to(rows, keep.shape)[keep]
    cc = np.broadcast_to(cols, keep.shape)[keep]
    np.maximum.at(heatmap, (ch, rr, cc), g[keep].astype(heatmap.dtype))


def build_targets(
    boxes: np.ndarray,
    labels: np.ndarray,
    quadrant: int | None,
    grid: GridSpec,
    head_stride: int,
    config: TargetConfig = TargetConfig(),
    num_classes: int = len(CLASS_NAMES),
) -> MapTargets:
    """Targets of quadrant ``quadrant``'s head map from boxes (M, 9) in the LiDAR frame and labels (M,);
    ``quadrant`` None: the head map of the whole grid (a net without the crop).

    Boxes with a label outside [0, num_classes) or a centre outside the map are not targets. The head map
    has (Yq / head_stride, Xq / head_stride) cells of ``grid.voxel_xy_m * head_stride`` metres ((ny, nx) / head_stride
    for the whole grid).
    """
    boxes = np.asarray(boxes, dtype=np.float64)
    labels = np.asarray(labels)
    if boxes.ndim != 2 or boxes.shape[1] != BOX_DIM:
        raise ValueError(f"boxes must be (M, {BOX_DIM}) x, y, z, w, l, h, yaw, vx, vy; got shape {boxes.shape}")
    if labels.shape != (len(boxes),) or (len(labels) and not np.issubdtype(labels.dtype, np.integer)):
        raise ValueError(f"labels must be ({len(boxes)},) integers to match boxes, got shape {labels.shape} dtype {labels.dtype}")
    if not np.all(np.isfinite(boxes)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(boxes), axis=1))[0])
        raise ValueError(f"boxes must be finite; row {bad} is {boxes[bad].tolist()}")
    if np.any(boxes[:, [W, L, H]] <= 0):
        bad = int(np.flatnonzero(np.any(boxes[:, [W, L, H]] <= 0, axis=1))[0])
        raise ValueError(f"box sizes w, l, h must be > 0; row {bad} has {boxes[bad, [W, L, H]].tolist()}")
    if isinstance(head_stride, bool) or not isinstance(head_stride, int) or head_stride < 1 or grid.quadrant_ny % head_stride or grid.quadrant_nx % head_stride:
        raise ValueError(f"head_stride must be a positive integer dividing the {grid.quadrant_ny} x {grid.quadrant_nx} quadrant, got {head_stride!r}")
    crop = quadrant is not None
    # the map's minimum corner: the quadrant's (validates quadrant), or the whole grid's (calibration/slice_maps.py)
    x0, y0 = grid.quadrant_origin_m(quadrant) if crop else slice_maps(grid, (0,), crop=False).origins_m[0]
    rows, cols = map_cells(grid, crop)
    hh, wh = rows // head_stride, cols // head_stride
    cell_m = grid.voxel_xy_m * head_stride

    row, col, reg_x, reg_y = encode_center(boxes[:, X] - x0, boxes[:, Y] - y0, cell_m)  # the decode's inverse
    ok = (labels >= 0) & (labels < num_classes) & (row >= 0) & (row < hh) & (col >= 0) & (col < wh)
    sel = np.flatnonzero(ok)
    num_dropped = max(0, sel.size - config.max_objects)
    sel = sel[: config.max_objects]
    b, r, c, lab = boxes[sel], row[sel], col[sel], labels[sel].astype(np.int64)

    heatmap = np.zeros((num_classes, hh, wh), np.float32)
    radius = gaussian_radius(b[:, L] / cell_m, b[:, W] / cell_m, config.min_overlap)
    radius = np.maximum(config.min_radius_cells, radius.astype(np.int64))  # int() truncation, as CenterPoint
    draw_gaussians(heatmap, lab, r, c, radius)

    k = config.max_objects
    n = sel.size
    index = np.zeros(k, np.int64)
    mask = np.zeros(k, bool)
    label = np.zeros(k, np.int64)
    box = np.zeros((k, BOX_CODE_SIZE), np.float32)
    index[:n] = r * wh + c
    mask[:n] = True
    label[:n] = lab
    box[:n, 0] = reg_x[sel]
    box[:n, 1] = reg_y[sel]
    box[:n, 2] = b[:, Z]
    box[:n, 3:6] = np.log(b[:, [W, L, H]])
    box[:n, 6] = np.sin(b[:, YAW])
    box[:n, 7] = np.cos(b[:, YAW])
    box[:n, 8] = b[:, VX]
    box[:n, 9] = b[:, VY]
    return MapTargets(heatmap=heatmap, index=index, mask=mask, label=label, box=box, num_dropped=num_dropped)
