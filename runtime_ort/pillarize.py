"""Points of one streaming slice -> the pillar tensors of `slice_head.onnx` (numpy only).

The contract is docs/architecture.md, "Pillar tensors". A point (x, y) falls in the grid cell
``col = floor(x / voxel) + nx / 2``, ``row = floor(y / voxel) + ny / 2``; that is the cell
``[x_min + col * voxel, x_min + (col + 1) * voxel)`` of `calibration/grid.py`, written relative to the
sensor because the grid is symmetric. Dividing x (not x - x_min) keeps the sign of x exact, so a point on an
axis lands in the same quadrant as `GridSpec.quadrant_of_xy` says (the non-negative side) and borders at
whole multiples of the voxel are exact.

Everything is vectorised: points are sorted by their flat pillar index (stable, so input order survives
inside a pillar), the rank inside a pillar comes from the run starts, and the cluster means from
`np.add.reduceat` over the kept points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamdet.calibration.grid import GridSpec
from streamdet.calibration.slice_maps import slice_maps
from streamdet.core.points import MAX_POINT_TIME_S, MAX_SLICE_INDEX, REFLECTANCE_RANGE, SLICE_COLUMNS, SLICE_REFLECTANCE
from streamdet.core.sectors import NUM_QUADRANTS

POINT_DIM = SLICE_COLUMNS  # x, y, z, reflectance, relative time, slice index (streamdet.core.points)
PILLAR_FEATURE_DIM = 11  # the 6 point columns, 3 offsets from the pillar mean, 2 offsets from the cell centre
_INT64_MAX = int(np.iinfo(np.int64).max)
_UINT16_KEYS = 1 << 16  # flat indices below this sort as uint16 (two 128 x 128 quadrants, or a 256 x 256 grid)


@dataclass(frozen=True)
class Pillars:
    """The pillar tensors of one slice plus what was dropped on the way.

    Every input point is counted exactly once:
    ``N = mask.sum() + num_nonfinite_dropped + num_outside_dropped + num_points_dropped``.
    """

    features: np.ndarray  # (P, M, 11) float32, padding rows 0
    mask: np.ndarray  # (P, M) float32, 1 for a real point
    index: np.ndarray  # (P,) int64, qi * Yq * Xq + row * Xq + col, increasing (row * nx + col without the crop)
    num_points_dropped: int  # points inside the quadrants' grid lost to the M or max_pillars caps
    num_pillars_dropped: int  # occupied pillars beyond max_pillars
    num_nonfinite_dropped: int  # points with a NaN or inf in any column
    # finite points outside the x, y, z range or the slice's quadrants, or with a reflectance, time or slice index
    # outside its range (core/points.py)
    num_outside_dropped: int
    # of num_outside_dropped: points inside the grid and the quadrants with a reflectance, time or slice index outside
    num_out_of_range_dropped: int = 0

    @property
    def num_pillars(self) -> int:
        return self.features.shape[0]

    def as_feeds(self, quadrants: tuple[int, ...] | None = None) -> dict[str, np.ndarray]:
        """The pillar inputs of `slice_head.onnx`, by graph input name; with `quadrants` (the slice's, as given to
        `pillarize`) also the `quadrants` (Q,) int64 input of a LiDAR-only slice graph, which has no image_bev (a
        LiDAR-only graph without the crop takes the pillar tensors alone: give None)."""
        feeds = {"pillar_features": self.features, "pillar_mask": self.mask, "pillar_index": self.index}
        if quadrants is not None:
            feeds["quadrants"] = np.asarray(quadrants, dtype=np.int64)
        return feeds


def _check_inputs(
    points: np.ndarray, quadrants: tuple[int, ...], max_points_per_pillar: int, max_pillars: int
) -> None:
    if not isinstance(points, np.ndarray) or points.ndim != 2 or points.shape[1] != POINT_DIM:
        shape = getattr(points, "shape", type(points).__name__)
        raise ValueError(f"points must be (N, {POINT_DIM}) float32 (x, y, z, r, t, s), got shape {shape}")
    if points.dtype != np.float32:
        raise ValueError(f"points must be float32, got dtype {points.dtype} for shape {points.shape}")
    qs = tuple(quadrants)
    if (
        not qs
        or not all(isinstance(q, (int, np.integer)) and 0 <= q < NUM_QUADRANTS for q in qs)
        or any(a >= b for a, b in zip(qs, qs[1:]))
    ):
        raise ValueError(f"quadrants must be a non-empty, strictly increasing tuple of 0..3, got {quadrants!r}")
    for name, value in (("max_points_per_pillar", max_points_per_pillar), ("max_pillars", max_pillars)):
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")


# the ranges of the r, t, s columns (core/points.py), as the (3,) bounds _features_in_range compares with
_FEATURE_LO = np.array([REFLECTANCE_RANGE[0], 0.0, 0.0], dtype=np.float32)
_FEATURE_HI = np.array([REFLECTANCE_RANGE[1], MAX_POINT_TIME_S, MAX_SLICE_INDEX], dtype=np.float32)


def _features_in_range(pts: np.ndarray) -> np.ndarray | None:
    """(N,) bool: the point's reflectance, time and slice index lie in their ranges; None when every point's do."""
    lo, hi = _FEATURE_LO, _FEATURE_HI
    # (3, N) r, t, s rows: numpy reduces a row of a contiguous copy 20x faster than a column of the (N, 6) points
    rows = np.ascontiguousarray(pts[:, SLICE_REFLECTANCE:].T)
    # Row minima and maxima first: the per-point test costs more than everything else when nothing is out of range.
    if pts.shape[0] == 0 or ((rows.min(axis=1) >= lo).all() and (rows.max(axis=1) <= hi).all()):
        return None
    return ((rows >= lo[:, None]) & (rows <= hi[:, None])).all(axis=0)


def _cell(coord: np.ndarray, voxel_m: float, num_cells: int) -> np.ndarray:
    cell = np.floor(coord.astype(np.float64) / voxel_m) + num_cells // 2
    return np.clip(cell, -1, num_cells).astype(np.int64)


def pillarize(
    points: np.ndarray,
    grid: GridSpec,
    quadrants: tuple[int, ...],
    max_points_per_pillar: int,
    max_pillars: int,
    crop: bool = True,
) -> Pillars:
    """Group the (N, 6) float32 points of a slice into at most `max_pillars` pillars of `max_points_per_pillar`.

    Points with a non-finite value, outside the grid's x / y / z range or outside `quadrants` are dropped and
    counted. Inside a pillar the first M points in input order are kept; when more than `max_pillars` pillars
    are occupied, those with the most points win (ties: lower flat index). Pillars come out in increasing
    flat index. Pillar means are over the kept (first M) points, the ones the PointNet sees.

    `crop` False (a net without the quadrant crop, `calibration/slice_maps.py`): the same points, indexed into one
    (ny, nx) map of the whole grid, ``row * nx + col``.

    Points whose reflectance, time or slice index lies outside its range (``core/points.py``: reflectance 0..1, time
    0..MAX_POINT_TIME_S, slice index 0..MAX_SLICE_INDEX) are dropped and counted too, as outside
    (``num_out_of_range_dropped`` says how many of those).
    """
    _check_inputs(points, quadrants, max_points_per_pillar, max_pillars)
    maps = slice_maps(grid, tuple(quadrants), crop)
    m_max = int(max_points_per_pillar)
    xq, yq = grid.quadrant_nx, grid.quadrant_ny

    # Whole-array check first: the per-row reduction costs more than everything else when nothing is bad.
    if np.isfinite(points).all():
        pts, num_nonfinite = points, 0
    else:
        finite = np.isfinite(points).all(axis=1)
        pts, num_nonfinite = points[finite], int(points.shape[0] - np.count_nonzero(finite))

    # Cells in float64: a float32 quotient can round a point near a border into the neighbour cell.
    col = _cell(pts[:, 0], grid.voxel_xy_m, grid.nx)
    row = _cell(pts[:, 1], grid.voxel_xy_m, grid.ny)
    z = pts[:, 2]
    inside = (col >= 0) & (col < grid.nx) & (row >= 0) & (row < grid.ny)
    inside &= (z >= grid.z_range_m[0]) & (z < grid.z_range_m[1])

    # Quadrant from the cell (the numbering of GridSpec), then its position in `quadrants` (-1: not ours).
    quadrant_of_code = np.array([2, 3, 1, 0])  # code = 2 * (y >= 0) + (x >= 0)
    slot = np.full(NUM_QUADRANTS, -1, dtype=np.int64)
    slot[list(quadrants)] = np.arange(len(quadrants)) if crop else 0  # without the crop every quadrant is map 0
    upper_row, upper_col = row >= yq, col >= xq  # (N,) the half of the grid a cell lies in (nx, ny are even)
    qi = slot[quadrant_of_code][2 * upper_row + upper_col]
    inside &= qi >= 0
    in_range = _features_in_range(pts)
    num_out_of_range = 0
    if in_range is not None:
        num_out_of_range = int(np.count_nonzero(inside & ~in_range))  # those the grid and quadrants would keep
        inside &= in_range

    kept_rows = np.flatnonzero(inside)
    num_outside = int(pts.shape[0] - kept_rows.size)
    n = kept_rows.size
    if n == 0:
        return Pillars(
            features=np.zeros((0, m_max, PILLAR_FEATURE_DIM), np.float32),
            mask=np.zeros((0, m_max), np.float32),
            index=np.zeros((0,), np.int64),
            num_points_dropped=0,
            num_pillars_dropped=0,
            num_nonfinite_dropped=num_nonfinite,
            num_outside_dropped=num_outside,
            num_out_of_range_dropped=num_out_of_range,
        )
    # Flat indices of every point, then one gather of the kept ones: cheaper than gathering row, col and qi apart.
    if crop:  # row and column inside the quadrant: quadrant maps start at 0 or at the half-size
        flat = (qi * (yq * xq) + (row - yq * upper_row) * xq + (col - xq * upper_col))[kept_rows]  # (n,)
    else:  # the whole grid is the one map
        flat = (row * grid.nx + col)[kept_rows]  # (n,)

    if maps.count * maps.cells <= _UINT16_KEYS:
        # numpy's stable sort of 16-bit integers is a radix sort: linear, several times faster than the key below
        order = np.argsort(flat.astype(np.uint16), kind="stable")
        sorted_flat = flat[order]
    elif maps.count * maps.cells < _INT64_MAX // max(n, 1):
        # Sorting the unique key (flat, position) equals a stable argsort of flat, at a third of the cost.
        key = np.sort(flat * n + np.arange(n))
        order, sorted_flat = key % n, key // n
    else:
        order = np.argsort(flat, kind="stable")
        sorted_flat = flat[order]
    src = kept_rows[order]  # rows of `pts`, grouped by pillar, input order inside a pillar
    new_run = np.empty(n, dtype=bool)  # (n,) a point opens a pillar's run
    new_run[0] = True
    np.not_equal(sorted_flat[1:], sorted_flat[:-1], out=new_run[1:])
    starts = np.flatnonzero(new_run)  # (U,) run starts
    counts = np.empty_like(starts)  # (U,) points per occupied pillar
    np.subtract(starts[1:], starts[:-1], out=counts[:-1])
    counts[-1] = n - starts[-1]
    pillar_of = np.repeat(np.arange(starts.size), counts)  # (n,) run of each sorted point
    rank = np.arange(n) - starts[pillar_of]  # position inside its pillar, in input order

    num_occupied = starts.size
    if num_occupied > max_pillars:
        # Most points first, then lower flat index (runs are in increasing flat index already).
        winners = np.sort(np.lexsort((np.arange(num_occupied), -counts))[:max_pillars])
        new_id = np.full(num_occupied, -1, dtype=np.int64)
        new_id[winners] = np.arange(winners.size)
        take = (rank < m_max) & (new_id[pillar_of] >= 0)
    else:
        winners = new_id = np.arange(num_occupied)
        take = rank < m_max
    num_pillars = winners.size

    pid = new_id[pillar_of[take]]  # (k,) output pillar of each kept point, non-decreasing
    kept = np.take(pts, src[take], axis=0)  # (k, 6)
    kept_per_pillar = np.minimum(counts[winners], m_max)  # (P,)
    # Per-pillar sums in float64 (bincount), read back per point: 1-D gathers beat 2-D fancy indexing.
    offset_from_mean = [
        kept[:, c] - (np.bincount(pid, weights=kept[:, c], minlength=num_pillars) / kept_per_pillar)[pid]
        for c in range(3)
    ]

    pillar_flat = sorted_flat[starts[winners]]  # (P,)
    origin = np.array(maps.origins_m)  # (Q, 2) minimum corners of the maps
    q_slot, local = np.divmod(pillar_flat, maps.cells)
    centre_x = origin[q_slot, 0] + (local % maps.cols + 0.5) * grid.voxel_xy_m  # (P,)
    centre_y = origin[q_slot, 1] + (local // maps.cols + 0.5) * grid.voxel_xy_m

    point_features = np.empty((kept.shape[0], PILLAR_FEATURE_DIM), np.float32)  # (k, 11)
    point_features[:, :POINT_DIM] = kept
    for c in range(3):
        point_features[:, POINT_DIM + c] = offset_from_mean[c]
    point_features[:, 9] = kept[:, 0] - centre_x[pid]
    point_features[:, 10] = kept[:, 1] - centre_y[pid]

    # Scatter whole 44-byte rows as single void items: several times faster than 2-D fancy indexing.
    # `kept` is in (pillar, rank) order, so the first kept_per_pillar slots of each pillar are the real ones.
    row_item = np.dtype((np.void, PILLAR_FEATURE_DIM * point_features.itemsize))
    features = np.zeros((num_pillars * m_max, PILLAR_FEATURE_DIM), np.float32)  # (P * M, 11)
    features.view(row_item)[pid * m_max + rank[take], 0] = point_features.view(row_item)[:, 0]
    mask = (np.arange(m_max) < kept_per_pillar[:, None]).astype(np.float32)  # (P, M)
    return Pillars(
        features=features.reshape(num_pillars, m_max, PILLAR_FEATURE_DIM),  # (P, M, 11)
        mask=mask,
        index=pillar_flat.astype(np.int64),
        num_points_dropped=int(n - pid.size),
        num_pillars_dropped=int(num_occupied - num_pillars),
        num_nonfinite_dropped=num_nonfinite,
        num_outside_dropped=num_outside,
        num_out_of_range_dropped=num_out_of_range,
    )
