"""Crop a full BEV map into its stacked quadrants and uncrop back (paper Sec. III-C).

Works on any map whose last two axes are (Y, X) on the BEV grid at some integer stride: pillar maps (B, C, Y, X),
image volumes (B, C, Z, Y, X), head maps at the head stride. Quadrant placement is ``GridSpec.quadrant_offset_cells``
scaled by the stride; stacking order is sample-major: row ``b * Q + i`` holds quadrant ``quadrants[i]`` of sample b.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from streamdet.calibration.grid import NUM_QUADRANTS, GridSpec


def _check_quadrants(quadrants: Sequence[int]) -> tuple[int, ...]:
    qs = tuple(int(q) for q in quadrants)
    if not qs or any(not 0 <= q < NUM_QUADRANTS for q in qs) or any(a >= b for a, b in zip(qs, qs[1:])):
        raise ValueError(f"quadrants must be a non-empty increasing sequence of 0..3, got {tuple(quadrants)!r}")
    return qs


def _stride(grid: GridSpec, y: int, x: int) -> int:
    if y < 2 or x < 2 or grid.ny % y or grid.nx % x or grid.ny // y != grid.nx // x:
        raise ValueError(f"map of {y} x {x} cells is not the {grid.ny} x {grid.nx} grid at one integer stride")
    s = grid.ny // y
    if grid.quadrant_ny % s or grid.quadrant_nx % s:
        raise ValueError(f"stride {s} does not divide the {grid.quadrant_ny} x {grid.quadrant_nx} quadrant")
    return s


def crop_quadrants(full: Tensor, quadrants: Sequence[int], grid: GridSpec) -> Tensor:
    """(B, ..., Y, X) -> (B * Q, ..., Y / 2, X / 2), quadrants stacked sample-major."""
    qs = _check_quadrants(quadrants)
    if full.dim() < 3:
        raise ValueError(f"crop_quadrants expects (B, ..., Y, X), got shape {tuple(full.shape)}")
    y, x = full.shape[-2:]
    s = _stride(grid, y, x)
    hq, wq = y // 2, x // 2
    crops = []
    for q in qs:
        r0, c0 = (v // s for v in grid.quadrant_offset_cells(q))
        crops.append(full[..., r0 : r0 + hq, c0 : c0 + wq])
    stacked = torch.stack(crops, dim=1)  # (B, Q, ..., Yq, Xq)
    return stacked.flatten(0, 1)  # (B * Q, ..., Yq, Xq)


def uncrop_quadrants(stack: Tensor, quadrants: Sequence[int], grid: GridSpec) -> Tensor:
    """(B * Q, ..., Yq, Xq) -> (B, ..., 2 * Yq, 2 * Xq) with zeros in the quadrants not given."""
    qs = _check_quadrants(quadrants)
    if stack.dim() < 3 or stack.shape[0] % len(qs):
        raise ValueError(f"uncrop_quadrants expects ({len(qs)} * B, ..., Yq, Xq), got shape {tuple(stack.shape)}")
    hq, wq = stack.shape[-2:]
    s = _stride(grid, 2 * hq, 2 * wq)
    per_sample = stack.reshape(-1, len(qs), *stack.shape[1:])  # (B, Q, ..., Yq, Xq)
    full = stack.new_zeros(per_sample.shape[0], *stack.shape[1:-2], 2 * hq, 2 * wq)  # (B, ..., Y, X)
    for i, q in enumerate(qs):
        r0, c0 = (v // s for v in grid.quadrant_offset_cells(q))
        full[..., r0 : r0 + hq, c0 : c0 + wq] = per_sample[:, i]
    return full
