"""The BEV maps one slice is computed on: its quadrants cropped (the paper's set-up), or the whole grid.

With the crop (paper Sec. III-C, ``Preset.slice_crop`` True) a slice's net runs on one (Yq, Xq) map per quadrant
it touches, stacked in increasing quadrant order; a map's cell (0, 0) sits at ``GridSpec.quadrant_origin_m(q)``.
Without it (``slice_crop`` False, the set-up of the paper's LiDAR-only streaming baselines) the net runs on one
(ny, nx) map of the whole grid for every slice, mostly empty, whose cell (0, 0) is the grid's minimum corner.

Pillar indices (``runtime_ort/pillarize.py``), training targets (``training/targets.py``), the slice net's map
shape (``models/detector.py``) and the uncrop (``runtime_ort/postprocess.py``) all read the layout from here, so
the four agree by construction. numpy only: the runtime uses it without PyTorch.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

from streamdet.calibration.grid import GridSpec
from streamdet.core.sectors import check_quadrants


@dataclass(frozen=True)
class SliceMaps:
    """The stacked maps of one slice: their count, their size in cells and where each one starts."""

    rows: int  # cells of one map along y
    cols: int  # cells of one map along x
    origins_m: tuple[tuple[float, float], ...]  # (x, y) in metres of each map's minimum corner, in stack order

    @property
    def count(self) -> int:
        """Q: the maps stacked along the batch dimension."""
        return len(self.origins_m)

    @property
    def cells(self) -> int:
        """Cells of one map (rows * cols): the stride of a map in a flat pillar index."""
        return self.rows * self.cols


def map_cells(grid: GridSpec, crop: bool = True) -> tuple[int, int]:
    """(rows, cols) of one slice map: a quadrant (Yq, Xq) with the crop, the whole grid (ny, nx) without."""
    _check_crop(crop)
    return (grid.quadrant_ny, grid.quadrant_nx) if crop else (grid.ny, grid.nx)


def slice_maps(grid: GridSpec, quadrants: tuple[int, ...], crop: bool = True) -> SliceMaps:
    """The maps of a slice touching ``quadrants`` (increasing): one per quadrant with the crop, one without."""
    qs = check_quadrants(quadrants)
    _check_crop(crop)
    return _slice_maps(grid, qs, crop)


@functools.lru_cache(maxsize=64)  # the slice lane asks twice per slice; a grid has 15 quadrant sets x 2 layouts
def _slice_maps(grid: GridSpec, qs: tuple[int, ...], crop: bool) -> SliceMaps:
    rows, cols = map_cells(grid, crop)
    if crop:
        origins = tuple(grid.quadrant_origin_m(q) for q in qs)
    else:
        origins = ((grid.x_range_m[0], grid.y_range_m[0]),)
    return SliceMaps(rows, cols, origins)


def _check_crop(crop: object) -> None:
    if not isinstance(crop, bool):
        raise ValueError(f"crop must be True (one map per quadrant) or False (the whole grid), got {crop!r}")
