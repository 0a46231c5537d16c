"""Crop / uncrop: every quadrant lands where GridSpec says it belongs, at any stride, for maps and volumes."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from streamdet.calibration.grid import GridSpec
from streamdet.models.crop import crop_quadrants, uncrop_quadrants

GRID = GridSpec(x_range_m=(-12.8, 12.8), y_range_m=(-12.8, 12.8), voxel_xy_m=0.4, voxel_z_m=2.0)  # 64 x 64
ALL_SUBSETS = [qs for n in range(1, 5) for qs in itertools.combinations(range(4), n)]


def quadrant_of_cells(grid: GridSpec, stride: int) -> np.ndarray:
    """(Y, X) map of the quadrant each cell centre lies in, by the metric definition (quadrant_of_xy)."""
    cell = grid.voxel_xy_m * stride
    xs = grid.x_range_m[0] + (np.arange(grid.nx // stride) + 0.5) * cell
    ys = grid.y_range_m[0] + (np.arange(grid.ny // stride) + 0.5) * cell
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return grid.quadrant_of_xy(xx, yy)


@pytest.mark.parametrize("stride", [1, 2, 4])
@pytest.mark.parametrize("quadrants", ALL_SUBSETS)
def test_crop_takes_each_quadrant_from_its_place(stride, quadrants):
    owner = torch.from_numpy(quadrant_of_cells(GRID, stride)).float()  # (Y, X)
    full = owner.expand(2, 3, -1, -1).clone()  # (B, C, Y, X)
    full[1] += 10  # tell the samples apart
    stack = crop_quadrants(full, quadrants, GRID)
    assert stack.shape == (2 * len(quadrants), 3, GRID.ny // stride // 2, GRID.nx // stride // 2)
    for b in range(2):
        for i, q in enumerate(quadrants):
            assert torch.all(stack[b * len(quadrants) + i] == q + 10 * b), (b, q)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("quadrants", ALL_SUBSETS)
def test_uncrop_inverts_crop_and_zeroes_the_rest(seed, quadrants):
    gen = torch.Generator().manual_seed(seed)
    full = torch.randn(2, 3, 4, GRID.ny // 2, GRID.nx // 2, generator=gen)  # a volume at stride 2
    back = uncrop_quadrants(crop_quadrants(full, quadrants, GRID), quadrants, GRID)
    assert back.shape == full.shape
    owner = torch.from_numpy(quadrant_of_cells(GRID, 2))
    keep = torch.zeros_like(owner, dtype=torch.bool)
    for q in quadrants:
        keep |= owner == q
    torch.testing.assert_close(back, torch.where(keep, full, torch.zeros(())), rtol=0, atol=0)


def test_uncrop_places_a_marked_cell_at_its_metric_position():
    g = GRID
    for q in range(4):
        stack = torch.zeros(1, 1, g.quadrant_ny, g.quadrant_nx)
        stack[0, 0, 2, 5] = 1.0  # cell (row 2, col 5) of quadrant q
        full = uncrop_quadrants(stack, [q], g)
        (row, col), = torch.nonzero(full[0, 0]).tolist()
        x0, y0 = g.quadrant_origin_m(q)
        assert g.x_range_m[0] + col * g.voxel_xy_m == pytest.approx(x0 + 5 * g.voxel_xy_m)
        assert g.y_range_m[0] + row * g.voxel_xy_m == pytest.approx(y0 + 2 * g.voxel_xy_m)


@pytest.mark.parametrize("bad", [[], [1, 0], [2, 2], [4], [-1]])
def test_bad_quadrants(bad):
    with pytest.raises(ValueError, match="quadrants must be a non-empty increasing sequence of 0..3"):
        crop_quadrants(torch.zeros(1, 1, 64, 64), bad, GRID)
    with pytest.raises(ValueError, match="quadrants must be a non-empty increasing sequence of 0..3"):
        uncrop_quadrants(torch.zeros(1, 1, 32, 32), bad, GRID)


def test_bad_shapes():
    with pytest.raises(ValueError, match="map of 64 x 48 cells is not the 64 x 64 grid"):
        crop_quadrants(torch.zeros(1, 1, 64, 48), [0], GRID)
    with pytest.raises(ValueError, match="map of 48 x 48 cells"):
        crop_quadrants(torch.zeros(1, 1, 48, 48), [0], GRID)
    with pytest.raises(ValueError, match="expects \\(B, ..., Y, X\\)"):
        crop_quadrants(torch.zeros(64, 64), [0], GRID)
    with pytest.raises(ValueError, match="expects \\(2 \\* B, ..., Yq, Xq\\), got shape \\(3, 1, 32, 32\\)"):
        uncrop_quadrants(torch.zeros(3, 1, 32, 32), [0, 1], GRID)
