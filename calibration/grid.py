"""BEV grid and quadrants: the metric conventions of streamdet, defined once (sectors: ``streamdet.core.sectors``).

Frames and axes
---------------
Everything here is in the LiDAR frame of the sweep (nuScenes LIDAR_TOP: x right, y forward, z up).
BEV maps are indexed ``[row, col] = [y_index, x_index]`` with row 0 at ``y_min`` and col 0 at ``x_min``;
a cell ``(row, col)`` covers ``x in [x_min + col * voxel, x_min + (col + 1) * voxel)`` and the same for y.
Image volumes are ``(C, Z, Y, X)`` with z index 0 at ``z_min``.

Quadrants
---------
The BEV plane is split at the sensor origin into four quadrants, numbered counter-clockwise by azimuth::

    q = 0: x >= 0, y >= 0   (azimuth [0, 90) deg)        q = 1: x < 0, y >= 0   ([90, 180))
    q = 2: x < 0,  y < 0    ([180, 270))                  q = 3: x >= 0, y < 0   ([270, 360))

Cropped maps of the touched quadrants are stacked along the batch dimension ``Q`` in increasing q.
A quadrant map of shape ``(Yq, Xq)`` sits in the full map at ``quadrant_offset_cells(q)`` (row0, col0).

Sectors (slices)
----------------
Azimuth, the quadrant numbering by azimuth and the streaming sectors are defined in ``streamdet.core.sectors``
(the functions are importable from here as before).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from streamdet.core.json_input import short_repr
from streamdet.core.sectors import (  # noqa: F401 (public here too)
    NUM_QUADRANTS,
    azimuth_deg,
    check_num_slices,
    quadrant_of_xy,
    quadrants_of_sector,
    sector_bounds_deg,
    slice_index_of,
)

# The most image-volume voxels (nx * ny * nz) a grid may have: 16x the largest shipped grid (the paper's 512 x 512
# x 16 = 4.2 M, GridSpec()). A LUT holds 8 bytes per voxel and slot, so this keeps even a one-slot LUT at 512 MiB,
# under the 1 GiB a lut.npz may declare (calibration.lut_file.MAX_LUT_BYTES); a corrupt grid (+-3000 m, a 1e-300 m
# voxel) is refused here rather than by the allocator.
MAX_GRID_VOXELS = 1 << 26


@dataclass(frozen=True)
class GridSpec:
    """Metric extent and resolution of the BEV grid and of the image volume."""

    x_range_m: tuple[float, float] = (-51.2, 51.2)  # must be symmetric: quadrants split at the sensor
    y_range_m: tuple[float, float] = (-51.2, 51.2)
    z_range_m: tuple[float, float] = (-3.0, 5.0)  # pillars span all of it; the image volume slices it
    voxel_xy_m: float = 0.2  # pillar and image-voxel footprint
    voxel_z_m: float = 0.5  # image-volume voxel height

    def __post_init__(self) -> None:
        # normalised first: a list or numpy range would make two equal grids compare unequal, break hashing (the
        # caches keyed by grid) and JSON (Lut.save); a bool voxel would read as 1 m
        for name in _RANGE_FIELDS:
            object.__setattr__(self, name, _as_range(name, getattr(self, name)))
        for name in ("x_range_m", "y_range_m"):
            lo, hi = getattr(self, name)
            if abs(lo + hi) > 1e-9:
                raise ValueError(f"GridSpec.{name} must be symmetric about 0 (quadrants split at the sensor), got {(lo, hi)}")
        for name in _VOXEL_FIELDS:
            object.__setattr__(self, name, _as_voxel_size(name, getattr(self, name)))
        for name, extent, voxel in (
            ("x_range_m", self.x_range_m[1] - self.x_range_m[0], self.voxel_xy_m),
            ("y_range_m", self.y_range_m[1] - self.y_range_m[0], self.voxel_xy_m),
            ("z_range_m", self.z_range_m[1] - self.z_range_m[0], self.voxel_z_m),
        ):
            _check_cells(name, extent, voxel)
        if self.nx % 2 or self.ny % 2:
            raise ValueError(f"grid {self.nx} x {self.ny} cells must be even in x and y to split into quadrants")
        voxels = self.nx * self.ny * self.nz
        if voxels > MAX_GRID_VOXELS:
            raise ValueError(
                f"grid {self.nx} x {self.ny} x {self.nz} = {voxels} voxels (x_range_m {self.x_range_m}, voxel_xy_m "
                f"{self.voxel_xy_m}, z_range_m {self.z_range_m}, voxel_z_m {self.voxel_z_m}) is over the "
                f"{MAX_GRID_VOXELS}-voxel cap (MAX_GRID_VOXELS)"
            )  # fmt: skip

    # ---- sizes in cells -------------------------------------------------------------------------
    @property
    def nx(self) -> int:
        return round((self.x_range_m[1] - self.x_range_m[0]) / self.voxel_xy_m)

    @property
    def ny(self) -> int:
        return round((self.y_range_m[1] - self.y_range_m[0]) / self.voxel_xy_m)

    @property
    def nz(self) -> int:
        """Number of image-volume voxels along z."""
        return round((self.z_range_m[1] - self.z_range_m[0]) / self.voxel_z_m)

    @property
    def quadrant_nx(self) -> int:
        return self.nx // 2

    @property
    def quadrant_ny(self) -> int:
        return self.ny // 2

    # ---- quadrant placement ---------------------------------------------------------------------
    def quadrant_offset_cells(self, q: int) -> tuple[int, int]:
        """(row0, col0) of quadrant q's top-left cell in the full BEV map."""
        _check_quadrant(q)
        row0 = self.quadrant_ny if q in (0, 1) else 0
        col0 = self.quadrant_nx if q in (0, 3) else 0
        return row0, col0

    def quadrant_origin_m(self, q: int) -> tuple[float, float]:
        """(x, y) in metres of quadrant q's minimum corner (cell (0, 0) lower edges)."""
        row0, col0 = self.quadrant_offset_cells(q)
        return (self.x_range_m[0] + col0 * self.voxel_xy_m, self.y_range_m[0] + row0 * self.voxel_xy_m)

    def quadrant_of_xy(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Quadrant index (int64) of each (x, y); points on an axis go to the non-negative side
        (``core.sectors.quadrant_of_xy``, the rule the slices follow too)."""
        return quadrant_of_xy(x, y)

    def voxel_center_axes(self, q: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Quadrant q's voxel-centre coordinates per axis, (Xq,), (Yq,), (Z,) float64 in metres.

        ``voxel_centers(q)[z, y, x] == (xs[x], ys[y], zs[z])``; the separable form lets callers avoid the
        (Z, Yq, Xq, 3) array.
        """
        x0, y0 = self.quadrant_origin_m(q)
        xs = x0 + (np.arange(self.quadrant_nx) + 0.5) * self.voxel_xy_m
        ys = y0 + (np.arange(self.quadrant_ny) + 0.5) * self.voxel_xy_m
        zs = self.z_range_m[0] + (np.arange(self.nz) + 0.5) * self.voxel_z_m
        return xs, ys, zs

    def voxel_centers(self, q: int) -> np.ndarray:
        """Centres of quadrant q's image-volume voxels, (Z, Yq, Xq, 3) float64 in metres."""
        x0, y0 = self.quadrant_origin_m(q)
        xs = x0 + (np.arange(self.quadrant_nx) + 0.5) * self.voxel_xy_m
        ys = y0 + (np.arange(self.quadrant_ny) + 0.5) * self.voxel_xy_m
        zs = self.z_range_m[0] + (np.arange(self.nz) + 0.5) * self.voxel_z_m
        zz, yy, xx = np.meshgrid(zs, ys, xs, indexing="ij")  # (Z, Yq, Xq) each
        return np.stack([xx, yy, zz], axis=-1)  # (Z, Yq, Xq, 3)

    def to_dict(self) -> dict:
        return {
            "x_range_m": list(self.x_range_m),
            "y_range_m": list(self.y_range_m),
            "z_range_m": list(self.z_range_m),
            "voxel_xy_m": self.voxel_xy_m,
            "voxel_z_m": self.voxel_z_m,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "GridSpec":
        """The grid of ``to_dict``; KeyError (a missing field), TypeError (``d`` not a mapping) or ValueError (naming
        the field and the value: a range that is no (min, max) pair of numbers, a voxel size that is no number; a
        string or a bool is never read as one)."""
        return cls(**{name: d[name] for name in _RANGE_FIELDS + _VOXEL_FIELDS})


_RANGE_FIELDS = ("x_range_m", "y_range_m", "z_range_m")
_VOXEL_FIELDS = ("voxel_xy_m", "voxel_z_m")


def _is_real(value: object) -> bool:
    """A real number (int, float, numpy's), not a bool, a string or anything else."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _as_float(value: numbers.Real) -> float:
    """``float(value)``; NaN (refused as not finite) for an integer past float range."""
    try:
        return float(value)
    except OverflowError:
        return math.nan


def _as_range(name: str, value: object) -> tuple[float, float]:
    """``value`` (a list, tuple or 1-d array of two real numbers, finite, max > min) as a tuple of two floats."""
    pair = list(value) if isinstance(value, (list, tuple)) or (isinstance(value, np.ndarray) and value.ndim == 1) else None
    if pair is None or len(pair) != 2 or not all(_is_real(v) for v in pair):
        raise ValueError(f"GridSpec.{name} must be a (min, max) pair of numbers, got {short_repr(value)}")
    lo, hi = _as_float(pair[0]), _as_float(pair[1])
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise ValueError(f"GridSpec.{name} must be a finite (min, max) with max > min, got {short_repr(value)}")
    return lo, hi


def _as_voxel_size(name: str, value: object) -> float:
    """``value`` (a real number, finite and > 0) as a float."""
    size = _as_float(value) if _is_real(value) else math.nan  # type: ignore[arg-type]
    if not (math.isfinite(size) and size > 0):
        raise ValueError(f"GridSpec.{name} must be a finite number > 0 (voxel sizes must be finite and > 0, in metres), "
                         f"got {short_repr(value)}")  # fmt: skip
    return size


def _check_cells(name: str, extent: float, voxel: float) -> None:
    """``extent`` must be a whole number >= 1 of ``voxel``s, and not astronomically many (a 1e-300 m voxel)."""
    cells = extent / voxel
    if not math.isfinite(cells) or cells > MAX_GRID_VOXELS:
        raise ValueError(f"GridSpec.{name} extent {extent} m holds {cells:.3g} voxels of {voxel} m, over the "
                         f"{MAX_GRID_VOXELS}-voxel cap (MAX_GRID_VOXELS)")  # fmt: skip
    if abs(cells - round(cells)) > 1e-6:
        raise ValueError(f"GridSpec.{name} extent {extent} m is not a whole number of {voxel} m voxels")
    if round(cells) < 1:
        raise ValueError(f"GridSpec.{name} extent {extent} m holds 0 voxels of {voxel} m: a grid needs at least one cell per axis")


def _check_quadrant(q: int) -> None:
    if not (isinstance(q, (int, np.integer)) and 0 <= q < NUM_QUADRANTS):
        raise ValueError(f"quadrant index must be 0..3, got {q!r}")
