"""Candidate pixels of projected boxes, for all boxes at once: the rows and column spans of their convex hulls.

The camera renderer (``synth_render``) intersects each candidate pixel's ray with a part exactly, so the candidates
only need to hold every pixel whose ray can meet the part: the pixels whose centres lie in the convex hull of the
part's projected bounding box. A convex hull of projected box corners is bounded by projected box edges, so the
u-extent of the hull within a horizontal band is the u-extent of the 12 edges clipped to that band; that gives
every row's span without a per-box polygon fill.
"""

from __future__ import annotations

import numpy as np

# The 12 edges of a box as corner pairs of synth_render._CORNERS (corner i = 4 sx + 2 sy + sz, signs as bits).
BOX_EDGES = np.array([(i, i | bit) for bit in (1, 2, 4) for i in range(8) if not i & bit], dtype=np.int64)  # (12, 2)


def hull_span_pixels(uv: np.ndarray, width: int, height: int, margin_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(box index, flat pixel) of every pixel whose centre is within ``margin_px`` (per axis) of the convex hull of
    each box's projected corners; boxes in order, each box's pixels row-major (as ``np.nonzero`` of a mask).

    uv: (R, 8, 2) float64 corners in pixel-centre coordinates (pixel (col, row) is centred at (col, row)), all in
    front of the camera; corner order as ``synth_render._CORNERS``.
    """
    n_box = len(uv)
    if not n_box:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    v_lo = np.maximum(np.ceil(uv[:, :, 1].min(axis=1) - margin_px), 0.0)  # (R,)
    v_hi = np.minimum(np.floor(uv[:, :, 1].max(axis=1) + margin_px), height - 1.0)
    n_rows = np.maximum(v_hi - v_lo + 1.0, 0.0).astype(np.int64)  # (R,)
    row_box = np.repeat(np.arange(n_box), n_rows)  # (N,)
    row_v = v_lo[row_box] + (np.arange(len(row_box)) - np.repeat(np.cumsum(n_rows) - n_rows, n_rows))  # (N,) float

    # Edges with their end points ordered by v: (R, 12) each, then per row (N, 12) (np.take: fast row gathers).
    a, b = uv[:, BOX_EDGES[:, 0]], uv[:, BOX_EDGES[:, 1]]  # (R, 12, 2)
    swap = a[..., 1] > b[..., 1]
    lo_u, lo_v = np.where(swap, b[..., 0], a[..., 0]), np.where(swap, b[..., 1], a[..., 1])
    hi_u, hi_v = np.where(swap, a[..., 0], b[..., 0]), np.where(swap, a[..., 1], b[..., 1])
    rise = hi_v - lo_v
    flat = rise <= 0.0  # a horizontal edge spans its whole u-range
    slope = np.where(flat, 0.0, (hi_u - lo_u) / np.where(flat, 1.0, rise))  # du / dv
    e_min, e_max = np.minimum(lo_u, hi_u), np.maximum(lo_u, hi_u)
    per_edge = (lo_u, lo_v, hi_v, slope, e_min, e_max, flat)
    lo_u, lo_v, hi_v, slope, e_min, e_max, flat = (np.take(x, row_box, axis=0) for x in per_edge)

    # Each row's band [v - margin, v + margin] clipped to each edge's v-range: (N, 12).
    band_lo = np.maximum(row_v[:, None] - margin_px, lo_v)
    band_hi = np.minimum(row_v[:, None] + margin_px, hi_v)
    crosses = band_lo <= band_hi
    u1 = lo_u + (band_lo - lo_v) * slope
    u2 = lo_u + (band_hi - lo_v) * slope
    span_lo = np.where(flat, e_min, np.clip(np.minimum(u1, u2), e_min, e_max))
    span_hi = np.where(flat, e_max, np.clip(np.maximum(u1, u2), e_min, e_max))
    row_u_lo = np.where(crosses, span_lo, np.inf).min(axis=1)  # (N,)
    row_u_hi = np.where(crosses, span_hi, -np.inf).max(axis=1)

    col_lo = np.maximum(np.ceil(row_u_lo - margin_px), 0.0)  # (N,); inf where no edge crosses (no pixels)
    col_hi = np.minimum(np.floor(row_u_hi + margin_px), width - 1.0)
    n_cols = np.where(col_hi >= col_lo, col_hi - col_lo + 1.0, 0.0).astype(np.int64)  # (N,)
    keep = n_cols > 0
    start = (row_v[keep] * width + col_lo[keep]).astype(np.int64)
    n_cols, box_of_row = n_cols[keep], row_box[keep]
    box = np.repeat(box_of_row, n_cols)  # (P,)
    pix = np.repeat(start - (np.cumsum(n_cols) - n_cols), n_cols) + np.arange(len(box))
    return box, pix
