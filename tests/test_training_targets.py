"""CenterPoint targets: radius rule and Gaussians vs CenterPoint's own loops, peaks, decode round trip, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from streamdet.calibration.grid import GridSpec
from streamdet.core.classes import CLASS_NAMES
from streamdet.models.decode import decode_head_maps
from streamdet.training.targets import TargetConfig, build_targets, draw_gaussians, gaussian_radius

GRID = GridSpec(x_range_m=(-25.6, 25.6), y_range_m=(-25.6, 25.6), voxel_xy_m=0.4, voxel_z_m=2.0)  # quadrant 64 x 64
STRIDE = 2  # head cells of 0.8 m, 32 x 32 per quadrant


# ---- CenterPoint's reference implementations (det3d/core/utils/center_utils.py), verbatim in spirit -----------
def ref_gaussian_radius(det_size, min_overlap=0.5):
    height, width = det_size
    a1 = 1
    b1 = height + width
    c1 = width * height * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1**2 - 4 * a1 * c1)) / 2
    a2 = 4
    b2 = 2 * (height + width)
    c2 = (1 - min_overlap) * width * height
    r2 = (b2 + math.sqrt(b2**2 - 4 * a2 * c2)) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (height + width)
    c3 = (min_overlap - 1) * width * height
    r3 = (b3 + math.sqrt(b3**2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def ref_gaussian2d(shape, sigma=1):
    m, n = [(ss - 1.0) / 2.0 for ss in shape]
    y, x = np.ogrid[-m : m + 1, -n : n + 1]
    h = np.exp(-(x * x + y * y) / (2 * sigma * sigma))
    h[h < np.finfo(h.dtype).eps * h.max()] = 0
    return h


def ref_draw_gaussian(heatmap, center, radius):
    diameter = 2 * radius + 1
    gaussian = ref_gaussian2d((diameter, diameter), sigma=diameter / 6)
    x, y = int(center[0]), int(center[1])
    height, width = heatmap.shape[0:2]
    left, right = min(x, radius), min(width - x, radius + 1)
    top, bottom = min(y, radius), min(height - y, radius + 1)
    masked_heatmap = heatmap[y - top : y + bottom, x - left : x + right]
    masked_gaussian = gaussian[radius - top : radius + bottom, radius - left : radius + right]
    if min(masked_gaussian.shape) > 0 and min(masked_heatmap.shape) > 0:
        np.maximum(masked_heatmap, masked_gaussian, out=masked_heatmap)
    return heatmap


def ref_targets(boxes, labels, q, cfg):
    """The per-object loop of CenterPoint's AssignLabel, in quadrant-local coordinates and our decode's offset."""
    hh, wh = GRID.quadrant_ny // STRIDE, GRID.quadrant_nx // STRIDE
    cell = GRID.voxel_xy_m * STRIDE
    x0, y0 = GRID.quadrant_origin_m(q)
    heat = np.zeros((len(CLASS_NAMES), hh, wh), np.float32)
    rows = []
    for b, lab in zip(boxes, labels):
        u, v = (b[0] - x0) / cell, (b[1] - y0) / cell
        col, row = math.floor(u), math.floor(v)
        if lab < 0 or not (0 <= row < hh and 0 <= col < wh):
            continue
        radius = max(cfg.min_radius_cells, int(ref_gaussian_radius((b[4] / cell, b[3] / cell), cfg.min_overlap)))
        ref_draw_gaussian(heat[lab], (col, row), radius)
        rows.append((row * wh + col, lab, [u - col - 0.5, v - row - 0.5, b[2], *np.log(b[3:6]), math.sin(b[6]), math.cos(b[6]), b[7], b[8]]))
    return heat, rows


def random_boxes(rng, n, q=0):
    x0, y0 = GRID.quadrant_origin_m(q)
    side = GRID.quadrant_nx * GRID.voxel_xy_m
    boxes = np.zeros((n, 9))
    boxes[:, 0] = x0 + rng.uniform(-2, side + 2, n)  # some centres fall outside the quadrant
    boxes[:, 1] = y0 + rng.uniform(-2, side + 2, n)
    boxes[:, 2] = rng.uniform(-2, 1, n)
    boxes[:, 3:6] = rng.uniform(0.3, 6.0, (n, 3))
    boxes[:, 6] = rng.uniform(-math.pi, math.pi, n)
    boxes[:, 7:9] = rng.normal(0, 3, (n, 2))
    labels = rng.integers(-1, len(CLASS_NAMES), n)
    return boxes, labels


@pytest.mark.parametrize("seed", range(4))
def test_radius_matches_centerpoint(seed):
    rng = np.random.default_rng(seed)
    h, w = rng.uniform(0.2, 30, 50), rng.uniform(0.2, 30, 50)
    for overlap in (0.1, 0.5, 0.7):
        ours = gaussian_radius(h, w, overlap)
        ref = [ref_gaussian_radius((a, b), overlap) for a, b in zip(h, w)]
        np.testing.assert_allclose(ours, ref, rtol=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_gaussians_match_centerpoint_loop(seed):
    rng = np.random.default_rng(seed)
    n = 30
    heat = np.zeros((3, 20, 25), np.float32)
    ref = np.zeros_like(heat)
    ch, row, col = rng.integers(0, 3, n), rng.integers(0, 20, n), rng.integers(0, 25, n)
    radius = rng.integers(0, 7, n)
    draw_gaussians(heat, ch, row, col, radius)
    for c, r, k, rad in zip(ch, row, col, radius):
        ref_draw_gaussian(ref[c], (k, r), int(rad))
    np.testing.assert_allclose(heat, ref, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("q", range(4))
def test_targets_match_reference(seed, q):
    rng = np.random.default_rng(seed)
    boxes, labels = random_boxes(rng, 25, q)
    cfg = TargetConfig()
    t = build_targets(boxes, labels, q, GRID, STRIDE, cfg)
    heat, rows = ref_targets(boxes, labels, q, cfg)
    np.testing.assert_allclose(t.heatmap, heat, rtol=1e-6, atol=1e-7)
    assert t.num_objects == len(rows) and t.num_dropped == 0
    assert t.mask[: len(rows)].all() and not t.mask[len(rows) :].any()
    for i, (idx, lab, code) in enumerate(rows):
        assert t.index[i] == idx and t.label[i] == lab
        np.testing.assert_allclose(t.box[i], code, rtol=1e-5, atol=1e-5)
        assert t.heatmap[lab].reshape(-1)[idx] == 1.0  # the peak sits exactly on the centre cell
    assert np.all(np.abs(t.box[: len(rows), :2]) <= 0.5)


@pytest.mark.parametrize("seed", range(4))
def test_regression_decodes_back_to_the_box(seed):
    """Put the targets into head maps and run models/decode.py: the boxes come back (quadrant-local)."""
    rng = np.random.default_rng(seed)
    q = int(rng.integers(0, 4))
    boxes, labels = random_boxes(rng, 12, q)
    labels = np.abs(labels)
    # keep centres inside the quadrant and at least 3 cells apart so every peak survives the 3x3 max-pool
    x0, y0 = GRID.quadrant_origin_m(q)
    lattice = (np.arange(0, 32, 3)[:, None] * 32 + np.arange(0, 32, 3)[None, :]).reshape(-1)  # 3 cells apart
    cells = rng.choice(lattice, 12, replace=False)
    boxes[:, 0] = x0 + (cells % 32 + rng.uniform(0, 1, 12)) * 0.8
    boxes[:, 1] = y0 + (cells // 32 + rng.uniform(0, 1, 12)) * 0.8
    t = build_targets(boxes, labels, q, GRID, STRIDE)
    n = t.num_objects
    hh = wh = 32
    heat = np.full((1, len(CLASS_NAMES), hh, wh), -20.0, np.float32)
    code = np.zeros((1, 10, hh * wh), np.float32)
    heat.reshape(1, len(CLASS_NAMES), -1)[0, t.label[:n], t.index[:n]] = np.linspace(-3.0, 3.0, n)  # distinct, unsaturated
    code[0, :, t.index[:n]] = t.box[:n]
    code = code.reshape(1, 10, hh, wh)
    maps = tuple(torch.from_numpy(m) for m in (heat, code[:, :2], code[:, 2:3], code[:, 3:6], code[:, 6:8], code[:, 8:10]))
    det, scores, labs = decode_head_maps(maps, 0.8, n)
    det = det[0].numpy()
    order = np.arange(n)[::-1]  # decode returns the highest score first
    expect = boxes[order].copy()
    expect[:, 0] -= x0
    expect[:, 1] -= y0
    np.testing.assert_array_equal(labs[0].numpy(), labels[order])
    np.testing.assert_allclose(det[:, :6], expect[:, :6], rtol=1e-5, atol=1e-4)
    yaw_err = np.angle(np.exp(1j * (det[:, 6] - expect[:, 6])))
    np.testing.assert_allclose(yaw_err, 0, atol=1e-5)
    np.testing.assert_allclose(det[:, 7:], expect[:, 7:], atol=1e-5)


def test_max_objects_drops_and_counts():
    rng = np.random.default_rng(0)
    boxes, labels = random_boxes(rng, 60)
    labels = np.abs(labels)
    inside = build_targets(boxes, labels, 0, GRID, STRIDE).num_objects
    t = build_targets(boxes, labels, 0, GRID, STRIDE, TargetConfig(max_objects=5))
    assert t.num_objects == 5 and t.num_dropped == inside - 5 and t.index.shape == (5,)


def test_empty_input():
    t = build_targets(np.zeros((0, 9)), np.zeros(0, np.int64), 2, GRID, STRIDE)
    assert t.heatmap.shape == (10, 32, 32) and not t.heatmap.any() and t.num_objects == 0
    assert t.box.shape == (128, 10) and t.index.dtype == np.int64


@pytest.mark.parametrize(
    "boxes, labels, q, stride, match",
    [
        (np.zeros((2, 7)), np.zeros(2, np.int64), 0, STRIDE, r"\(M, 9\)"),
        (np.ones((2, 9)), np.zeros(3, np.int64), 0, STRIDE, r"labels must be \(2,\)"),
        (np.ones((1, 9)), np.zeros(1), 0, STRIDE, "integers"),
        (np.full((1, 9), np.nan), np.zeros(1, np.int64), 0, STRIDE, "finite; row 0"),
        (np.r_[np.ones((1, 9)), [[1, 1, 1, 0, 1, 1, 0, 0, 0]]], np.zeros(2, np.int64), 0, STRIDE, "row 1 has"),
        (np.ones((1, 9)), np.zeros(1, np.int64), 4, STRIDE, "quadrant index must be 0..3"),
        (np.ones((1, 9)), np.zeros(1, np.int64), 0, 3, "head_stride"),
    ],
)
def test_malformed_input(boxes, labels, q, stride, match):
    with pytest.raises(ValueError, match=match):
        build_targets(boxes, labels, q, GRID, stride)


@pytest.mark.parametrize("kwargs", [{"min_overlap": 0.0}, {"min_overlap": 1.0}, {"max_objects": 0}, {"min_radius_cells": -1}])
def test_config_validation(kwargs):
    with pytest.raises(ValueError, match="TargetConfig"):
        TargetConfig(**kwargs)
