"""Rotated BEV IoU, per-class NMS and slice post-processing against slow, independent references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from streamdet.calibration.grid import GridSpec
from streamdet.core.boxes import bev_iou, box_corners_bev, paired_bev_iou
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.sectors import quadrants_of_sector, sector_bounds_deg
from streamdet.runtime_ort.nms import CENTERPOINT_CIRCLE_RADIUS_M, NmsConfig, NmsKind, nms, overlapping_pairs
from streamdet.runtime_ort.postprocess import (
    Detections,
    PostprocessConfig,
    aggregate_sweep,
    in_sector,
    EDGE_MARGIN_M,
    postprocess_slice,
    top_k_reached,
    uncrop_boxes,
)

PAPER = GridSpec()


def box(x, y, w, l, yaw, z=0.0, h=1.5):
    return [x, y, z, w, l, h, yaw, 0.0, 0.0]


# ---- reference rotated IoU: plain Sutherland-Hodgman clipping, one pair at a time ------------------------
def _clip(polygon, start, end):
    """The part of `polygon` left of the directed line start -> end (inclusive)."""

    def side(p):
        return (end[0] - start[0]) * (p[1] - start[1]) - (end[1] - start[1]) * (p[0] - start[0])

    out = []
    for k in range(len(polygon)):
        cur, nxt = polygon[k], polygon[(k + 1) % len(polygon)]
        s_cur, s_nxt = side(cur), side(nxt)
        if s_cur >= 0:
            out.append(cur)
        if (s_cur >= 0) != (s_nxt >= 0):
            t = s_cur / (s_cur - s_nxt)
            out.append((cur[0] + t * (nxt[0] - cur[0]), cur[1] + t * (nxt[1] - cur[1])))
    return out


def reference_iou(a, b):
    pa = [tuple(map(float, c)) for c in box_corners_bev(np.array([a], np.float64))[0]]
    pb = [tuple(map(float, c)) for c in box_corners_bev(np.array([b], np.float64))[0]]
    polygon = pa
    for k in range(4):
        if polygon:
            polygon = _clip(polygon, pb[k], pb[(k + 1) % 4])
    inter = 0.0
    if len(polygon) >= 3:
        nxt = polygon[1:] + polygon[:1]
        inter = 0.5 * abs(sum(p[0] * q[1] - q[0] * p[1] for p, q in zip(polygon, nxt)))
    return inter / (a[3] * a[4] + b[3] * b[4] - inter)


def random_boxes(rng, n, spread_m=6.0, num_classes=3):
    boxes = np.zeros((n, 9), np.float32)
    boxes[:, :2] = rng.uniform(-spread_m, spread_m, (n, 2))
    boxes[:, 2] = rng.uniform(-1, 1, n)
    boxes[:, 3:6] = rng.uniform(0.3, 4.0, (n, 3))
    boxes[:, 6] = rng.uniform(-math.pi, math.pi, n)
    boxes[:, 7:] = rng.normal(0, 2, (n, 2))
    scores = rng.uniform(0, 1, n).astype(np.float32)
    labels = rng.integers(0, num_classes, n).astype(np.int64)
    return boxes, scores, labels


# ---- bev_iou -----------------------------------------------------------------------------------------------
def test_bev_iou_known_cases():
    boxes = np.array(
        [
            box(0, 0, 2, 4, 0.3),  # 0
            box(0, 0, 2, 4, 0.3),  # 1 identical to 0
            box(30, 0, 2, 4, 0.0),  # 2 far away
            box(0, 0, 1, 1, 0.0),  # 3 unit square
            box(0, 0, 1, 1, math.pi / 4),  # 4 unit square turned 45 deg: IoU with 3 is 1 / sqrt(2)
            box(0.5, 0, 1, 1, 0.0),  # 5 half overlap with 3: IoU 1/3
            box(0, 0, 0.5, 0.5, 1.0),  # 6 contained in 0: IoU = area ratio
            box(1, 0, 1, 1, 0.0),  # 7 touches 3 along an edge only
            box(0, 0, 2, 4, 0.3 + math.pi),  # 8 same footprint as 0, heading reversed
        ],
        np.float64,
    )
    iou = bev_iou(boxes, boxes)
    assert iou.shape == (9, 9) and iou.dtype == np.float64
    np.testing.assert_allclose(np.diag(iou), 1.0, atol=1e-12)
    np.testing.assert_allclose(iou, iou.T, atol=1e-12)
    assert iou[0, 1] == pytest.approx(1.0) and iou[0, 8] == pytest.approx(1.0)
    assert iou[0, 2] == 0.0 and iou[3, 7] == pytest.approx(0.0, abs=1e-12)
    assert iou[3, 4] == pytest.approx(1 / math.sqrt(2), abs=1e-12)
    assert iou[3, 5] == pytest.approx(1 / 3, abs=1e-12)
    assert iou[0, 6] == pytest.approx(0.25 / 8, abs=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bev_iou_collinear_edges(seed):
    """Shifting a box along or across its heading makes edges collinear: the degenerate case of clipping."""
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-math.pi, math.pi, 20)
    w, l, shift = rng.uniform(0.5, 3, 20), rng.uniform(1, 5, 20), rng.uniform(0, 0.9, 20)
    centre = rng.uniform(-40, 40, (20, 2))
    heading = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    across = np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)
    base = np.array([box(c[0], c[1], wi, li, y) for c, wi, li, y in zip(centre, w, l, yaw)])
    along = base.copy()
    along[:, :2] += (shift * l)[:, None] * heading
    side = base.copy()
    side[:, :2] += (shift * w)[:, None] * across
    np.testing.assert_allclose(paired_bev_iou(base, base), 1.0, atol=1e-12)
    np.testing.assert_allclose(paired_bev_iou(base, along), (1 - shift) / (1 + shift), atol=1e-9)
    np.testing.assert_allclose(paired_bev_iou(side, base), (1 - shift) / (1 + shift), atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_bev_iou_matches_reference(seed, dtype):
    rng = np.random.default_rng(seed)
    a, _, _ = random_boxes(rng, 25, spread_m=3.0)
    b, _, _ = random_boxes(rng, 20, spread_m=3.0)
    a, b = a.astype(dtype), b.astype(dtype)
    iou = bev_iou(a, b)
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    ref = np.array([[reference_iou(x, y) for y in b64] for x in a64])
    assert (ref > 0).mean() > 0.3  # the test exercises real overlaps
    np.testing.assert_allclose(iou, ref, atol=1e-9)
    np.testing.assert_allclose(paired_bev_iou(a[:20], b), np.diag(ref[:20]), atol=1e-9)


def test_bev_iou_matches_sampling_estimate():
    rng = np.random.default_rng(7)
    a, b = np.array([box(0.3, -0.2, 2.0, 4.5, 0.7)]), np.array([box(-0.4, 0.5, 1.8, 3.9, -0.4)])
    samples = rng.uniform(-4, 4, (400_000, 2))

    def inside(bx, p):
        c, s = math.cos(bx[6]), math.sin(bx[6])
        dx, dy = p[:, 0] - bx[0], p[:, 1] - bx[1]
        return (np.abs(c * dx + s * dy) <= bx[4] / 2) & (np.abs(-s * dx + c * dy) <= bx[3] / 2)

    ia, ib = inside(a[0], samples), inside(b[0], samples)
    estimate = (ia & ib).sum() / (ia | ib).sum()
    assert bev_iou(a, b)[0, 0] == pytest.approx(estimate, abs=5e-3)


def test_bev_iou_empty_degenerate_and_malformed():
    assert bev_iou(np.zeros((0, 9)), np.zeros((3, 9))).shape == (0, 3)
    assert bev_iou(np.zeros((2, 9)), np.zeros((0, 9))).shape == (2, 0)
    flat = np.array([box(0, 0, 0.0, 4, 0), box(0, 0, 2, 4, 0)])
    assert bev_iou(flat, flat)[0].tolist() == [0.0, 0.0]
    with pytest.raises(ValueError, match=r"boxes_a must be \(N, 9\).*\(3, 7\)"):
        bev_iou(np.zeros((3, 7)), np.zeros((3, 9)))
    with pytest.raises(ValueError, match="boxes_b"):
        bev_iou(np.zeros((3, 9)), np.zeros(9))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_overlapping_pairs_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    lo = rng.uniform(0, 10, (200, 2))
    hi = lo + rng.uniform(0, 1.5, (200, 2))
    hi[:5] = lo[:5]  # empty extents overlap nothing
    i, j = overlapping_pairs(lo, hi)
    got = set(zip(i.tolist(), j.tolist()))
    want = {
        (p, q)
        for p in range(200)
        for q in range(p + 1, 200)
        if all(lo[p, d] < hi[q, d] and lo[q, d] < hi[p, d] for d in (0, 1))
    }
    assert got == want and len(got) == len(i)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("num", [0, 1, 2, 40, 128])
def test_dense_same_class_pairs_equal_the_per_class_sweeps(seed, num):
    from streamdet.runtime_ort import nms as nms_module

    rng = np.random.default_rng(seed)
    lo = rng.uniform(0, 6, (num, 2))
    hi = lo + rng.uniform(0, 1.5, (num, 2))
    hi[: num // 8] = lo[: num // 8]  # empty extents overlap nothing
    if num >= 6:  # exact duplicates: equal extents overlap (open intervals of positive width)
        lo[num // 2 : num // 2 + 3], hi[num // 2 : num // 2 + 3] = lo[3:6], hi[3:6]
    labels = rng.integers(0, 4, num)
    dense = nms_module._dense_same_class_pairs(lo, hi, labels)
    firsts, seconds = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for label in np.unique(labels).tolist():  # the sweeps, as _same_class_pairs runs them above DENSE_PAIRS_MAX
        members = np.flatnonzero(labels == label)
        i, j = overlapping_pairs(lo[members], hi[members])
        firsts.append(members[i])
        seconds.append(members[j])
    swept = set(zip(np.concatenate(firsts).tolist(), np.concatenate(seconds).tolist()))
    assert set(zip(dense[0].tolist(), dense[1].tolist())) == swept and dense[0].size == len(swept)
    assert dense[0].dtype == dense[1].dtype == np.int64 and np.all(dense[0] < dense[1])


# ---- NMS ---------------------------------------------------------------------------------------------------
def naive_nms(boxes, scores, labels, config):
    """CenterPoint's loop: best first, a kept box suppresses same-class boxes it overlaps."""
    order = sorted(range(len(scores)), key=lambda k: (-float(scores[k]), k))
    suppressed = set()
    keep = []
    for a_pos, i in enumerate(order):
        if i in suppressed:
            continue
        keep.append(i)
        for j in order[a_pos + 1 :]:
            if j in suppressed or labels[j] != labels[i]:
                continue
            if config.kind is NmsKind.CIRCLE:
                d2 = float(boxes[i, 0] - boxes[j, 0]) ** 2 + float(boxes[i, 1] - boxes[j, 1]) ** 2
                hit = d2 <= config.circle_radius_m[labels[i]] ** 2
            else:
                hit = reference_iou(boxes[i].astype(np.float64), boxes[j].astype(np.float64)) > config.iou_threshold
            if hit:
                suppressed.add(j)
    return keep[: config.max_out]


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(
    "config",
    [
        NmsConfig(kind=NmsKind.CIRCLE),
        NmsConfig(kind=NmsKind.CIRCLE, circle_radius_m=(1.5,) * 10, max_out=20),
        NmsConfig(kind=NmsKind.ROTATED, iou_threshold=0.2),
        NmsConfig(kind=NmsKind.ROTATED, iou_threshold=0.05, max_out=15),
    ],
    ids=["circle-centerpoint", "circle-1.5m-max20", "rotated-0.2", "rotated-0.05-max15"],
)
@pytest.mark.parametrize("num", [12, 120, 300])  # up to DENSE_PAIRS_MAX: the dense pair test; above: the sweeps
def test_nms_matches_naive_loop(seed, config, num):
    rng = np.random.default_rng(seed)
    boxes, scores, labels = random_boxes(rng, num, spread_m=8.0 * (num / 120) ** 0.5)
    scores[::10] = scores[1::10]  # ties: the lower index goes first
    keep = nms(boxes, scores, labels, config)
    assert keep.dtype == np.int64
    assert keep.tolist() == naive_nms(boxes, scores, labels, config)


def test_nms_is_per_class_and_uses_the_class_radius():
    boxes = np.array(
        [box(0, 0, 2, 4, 0), box(0.5, 0, 2, 4, 0), box(0.5, 0, 2, 4, 0), box(0.3, 0, 0.6, 0.6, 0)], np.float32
    )
    scores = np.array([0.9, 0.8, 0.7, 0.6], np.float32)
    car, truck, ped = CLASS_NAMES.index("car"), CLASS_NAMES.index("truck"), CLASS_NAMES.index("pedestrian")
    labels = np.array([car, car, truck, ped])
    # Car radius sqrt(4) = 2 m suppresses the car 0.5 m away; the truck and the pedestrian are other classes.
    assert nms(boxes, scores, labels, NmsConfig()).tolist() == [0, 2, 3]
    assert nms(boxes, scores, labels, NmsConfig(kind=NmsKind.ROTATED)).tolist() == [0, 2, 3]
    # A pedestrian 0.3 m from another: CenterPoint's 0.175 is a squared distance, so 0.3 m > sqrt(0.175) survives.
    peds = np.array([box(0, 0, 0.6, 0.6, 0), box(0.3, 0.2, 0.6, 0.6, 0), box(0.5, 0, 0.6, 0.6, 0)], np.float32)
    keep = nms(peds, np.array([0.9, 0.8, 0.7], np.float32), np.full(3, ped), NmsConfig())
    assert keep.tolist() == [0, 2]  # 0.36 m away: suppressed (0.13 <= 0.175); 0.5 m away: kept
    assert CENTERPOINT_CIRCLE_RADIUS_M[car] == pytest.approx(2.0)


@pytest.mark.parametrize("kind", list(NmsKind))
def test_nms_keeps_one_of_exact_float32_duplicates(kind):
    rng = np.random.default_rng(3)
    boxes, _, _ = random_boxes(rng, 30, spread_m=50.0)
    boxes = np.repeat(boxes, 3, axis=0)  # each box three times, bit-identical, at up to 50 m from the sensor
    scores = rng.uniform(0, 1, len(boxes)).astype(np.float32)
    config = NmsConfig(kind=kind, iou_threshold=0.5, circle_radius_m=(0.0,) * len(CLASS_NAMES))
    keep = nms(boxes, scores, np.zeros(len(boxes), np.int64), config)
    assert sorted((keep // 3).tolist()) == list(range(30))


def test_nms_empty_and_malformed():
    assert nms(np.zeros((0, 9)), np.zeros(0), np.zeros(0, np.int64), NmsConfig()).shape == (0,)
    with pytest.raises(ValueError, match="scores"):
        nms(np.zeros((3, 9)), np.zeros(2), np.zeros(3, np.int64), NmsConfig())
    with pytest.raises(ValueError, match="labels must index CLASS_NAMES.*10"):
        nms(np.zeros((1, 9)), np.zeros(1), np.array([10]), NmsConfig())
    with pytest.raises(ValueError, match="boxes"):
        nms(np.zeros((3, 8)), np.zeros(3), np.zeros(3, np.int64), NmsConfig())


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"kind": "square"}, "kind"),
        ({"iou_threshold": 1.5}, "iou_threshold"),
        ({"circle_radius_m": (1.0,) * 3}, "circle_radius_m"),
        ({"circle_radius_m": (-1.0,) * 10}, "circle_radius_m"),
        ({"max_out": 0}, "max_out"),
    ],
)
def test_nms_config_validation(kwargs, field):
    with pytest.raises(ValueError, match=field):
        NmsConfig(**kwargs)
    assert NmsConfig(kind="rotated").kind is NmsKind.ROTATED  # the enum's value converts, nothing else


# ---- post-processing ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("q", [0, 1, 2, 3])
def test_uncrop_places_every_quadrant(q):
    """A box at the centre of local cell (row, col) lands on the centre of that cell in the full map."""
    yq, xq, v = PAPER.quadrant_ny, PAPER.quadrant_nx, PAPER.voxel_xy_m
    rows, cols = np.array([0, 0, yq - 1, 17]), np.array([0, xq - 1, 0, 200])
    local = np.zeros((1, 4, 9), np.float32)
    local[0, :, 0] = (cols + 0.5) * v
    local[0, :, 1] = (rows + 0.5) * v
    local[0, :, 3:6] = 1.0
    out = uncrop_boxes(local, (q,), PAPER)
    row0, col0 = PAPER.quadrant_offset_cells(q)
    np.testing.assert_allclose(out[0, :, 0], PAPER.x_range_m[0] + (col0 + cols + 0.5) * v, atol=1e-5)
    np.testing.assert_allclose(out[0, :, 1], PAPER.y_range_m[0] + (row0 + rows + 0.5) * v, atol=1e-5)
    assert (PAPER.quadrant_of_xy(out[0, :, 0], out[0, :, 1]) == q).all()
    np.testing.assert_array_equal(out[..., 2:], local[..., 2:])


def test_uncrop_stacks_quadrants_in_order():
    local = np.zeros((2, 1, 9), np.float32)
    local[:, 0, :2] = 0.1
    out = uncrop_boxes(local, (1, 2), PAPER)
    assert PAPER.quadrant_of_xy(out[:, 0, 0], out[:, 0, 1]).tolist() == [1, 2]
    with pytest.raises(ValueError, match=r"det_boxes must be \(Q=2"):
        uncrop_boxes(np.zeros((1, 5, 9), np.float32), (1, 2), PAPER)


def slice_outputs(rng, quadrants, k_top=60):
    q = len(quadrants)
    det = np.zeros((q, k_top, 9), np.float32)
    det[..., :2] = rng.uniform(0, 51.2, (q, k_top, 2))
    det[..., 3:6] = rng.uniform(0.4, 5.0, (q, k_top, 3))
    det[..., 6] = rng.uniform(-math.pi, math.pi, (q, k_top))
    det[:, 1::2, :2] = det[:, ::2, :2][:, : det[:, 1::2].shape[1]] + rng.normal(0, 0.4, (q, k_top // 2, 2))
    scores = rng.uniform(0, 1, (q, k_top)).astype(np.float32)
    labels = rng.integers(0, 10, (q, k_top)).astype(np.int64)
    return det, scores, labels


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("restrict", [False, True])
def test_postprocess_slice_matches_naive_pipeline(seed, restrict):
    rng = np.random.default_rng(seed)
    k, n = 3, 4 if seed else 2  # n = 2 touches two quadrants
    quadrants = quadrants_of_sector(k % n, n)
    sector = sector_bounds_deg(k % n, n)
    det, scores, labels = slice_outputs(rng, quadrants)
    det[0, 0, 0] = np.nan  # a broken row is dropped, not fatal
    # boxes no net of this grid can mean (plausible_boxes): far away, flat, larger than the grid; and one just past
    # the grid's edge, within EDGE_MARGIN_M, which stays
    det[0, 1, 0] = 1.7e4
    det[0, 2, 3] = 0.0
    det[-1, 3, 5] = 500.0
    det[-1, 4, 1] = -1e-29
    det[0, 5, :2] = 51.2 + 1.5 - np.array(PAPER.quadrant_origin_m(quadrants[0]), np.float32)
    scores[0, :6] = scores[-1, 3:5] = 0.9
    config = PostprocessConfig(score_threshold=0.3, restrict_to_sector=restrict, nms=NmsConfig(kind=NmsKind.ROTATED))
    out = postprocess_slice(det, scores, labels, quadrants, PAPER, config, sector_deg=sector)

    rows = []
    for qi, q in enumerate(quadrants):
        x0, y0 = PAPER.quadrant_origin_m(q)
        for j in range(det.shape[1]):
            b = det[qi, j].astype(np.float64)
            b[0] += x0
            b[1] += y0
            if not np.isfinite(b).all() or scores[qi, j] < 0.3:
                continue
            lo, hi = -51.2 - EDGE_MARGIN_M, 51.2 + EDGE_MARGIN_M
            if not (lo <= b[0] <= hi and lo <= b[1] <= hi and all(0 < v <= 102.4 for v in b[3:6])):
                continue
            azimuth = math.degrees(math.atan2(b[1], b[0])) % 360
            if restrict and not (sector[0] <= azimuth < sector[1]):
                continue
            rows.append((b, scores[qi, j], labels[qi, j]))
    ref_boxes = np.array([r[0] for r in rows], np.float32)
    ref_scores = np.array([r[1] for r in rows], np.float32)
    ref_labels = np.array([r[2] for r in rows])
    keep = naive_nms(ref_boxes, ref_scores, ref_labels, config.nms)
    np.testing.assert_allclose(out.boxes, ref_boxes[keep], atol=1e-5)
    np.testing.assert_array_equal(out.scores, ref_scores[keep])
    np.testing.assert_array_equal(out.labels, ref_labels[keep])
    assert out.boxes.dtype == np.float32 and out.labels.dtype == np.int64
    if restrict:
        assert in_sector(out.boxes, sector).all()


def test_postprocess_slice_malformed_inputs():
    det = np.zeros((1, 5, 9), np.float32)
    scores = np.zeros((1, 5), np.float32)
    labels = np.zeros((1, 5), np.int64)
    with pytest.raises(ValueError, match="det_scores"):
        postprocess_slice(det, scores[:, :3], labels, (0,), PAPER)
    with pytest.raises(ValueError, match="det_labels"):
        postprocess_slice(det, scores, labels.astype(np.float32), (0,), PAPER)
    with pytest.raises(ValueError, match="det_labels must index"):
        postprocess_slice(det, scores + 1, labels - 1, (0,), PAPER)
    with pytest.raises(ValueError, match="sector_deg"):
        postprocess_slice(det, scores, labels, (0,), PAPER, PostprocessConfig(restrict_to_sector=True))
    with pytest.raises(ValueError, match="quadrants"):
        postprocess_slice(det, scores, labels, (5,), PAPER)
    no_rows = np.zeros((1, 0, 9), np.float32)
    empty = postprocess_slice(no_rows, np.zeros((1, 0)), np.zeros((1, 0), np.int64), (0,), PAPER)
    assert len(empty) == 0 and empty.boxes.shape == (0, 9)


def test_in_sector_wraps_and_is_half_open():
    boxes = np.zeros((4, 9), np.float32)
    boxes[:, 0] = [1.0, 0.0, -1.0, 1.0]
    boxes[:, 1] = [0.0, 1.0, 0.0, -0.01]
    assert in_sector(boxes, (0.0, 90.0)).tolist() == [True, False, False, False]
    assert in_sector(boxes, (270.0, 360.0)).tolist() == [False, False, False, True]
    assert in_sector(boxes, (0.0, 360.0)).all()
    with pytest.raises(ValueError, match="sector_deg"):
        in_sector(boxes, (10.0, 10.0))


def test_aggregate_sweep_removes_duplicates_across_slices():
    rng = np.random.default_rng(0)
    a = Detections(np.array([box(10, 0.1, 2, 4, 0)]), np.array([0.9]), np.array([0]))
    b_boxes = np.array([box(10.3, -0.1, 2, 4, 0.05), box(-20, 5, 0.6, 0.6, 0)])
    b = Detections(b_boxes, np.array([0.8, 0.5]), np.array([0, 7]))
    out = aggregate_sweep([a, b], NmsConfig())
    assert len(out) == 2 and out.scores.tolist() == pytest.approx([0.9, 0.5])
    assert len(aggregate_sweep([], NmsConfig())) == 0
    parts = []
    for _ in range(4):
        bx, sc, lb = random_boxes(rng, 30, spread_m=20.0, num_classes=10)
        parts.append(Detections(bx, sc, lb))
    merged = Detections.concatenate(parts)
    out = aggregate_sweep(parts, NmsConfig(kind=NmsKind.ROTATED))
    keep = naive_nms(merged.boxes, merged.scores, merged.labels, NmsConfig(kind=NmsKind.ROTATED))
    np.testing.assert_array_equal(out.boxes, merged.boxes[keep])


def test_detections_container():
    empty = Detections.empty()
    assert len(empty) == 0 and empty.boxes.shape == (0, 9) and empty.labels.dtype == np.int64
    d = Detections(np.ones((3, 9)), np.array([0.1, 0.5, 0.9]), np.array([1, 2, 3], np.int32))
    assert d.boxes.dtype == np.float32 and d.labels.dtype == np.int64
    assert len(d.select(d.scores > 0.3)) == 2 and d.select(np.array([2, 0])).labels.tolist() == [3, 1]
    assert len(Detections.concatenate([d, empty, d])) == 6
    with pytest.raises(ValueError, match="boolean selection"):
        d.select(np.array([True, False]))
    with pytest.raises(ValueError, match=r"Detections.boxes must be \(N, 9\)"):
        Detections(np.ones((3, 7)), np.ones(3), np.ones(3, np.int64))
    with pytest.raises(ValueError, match="Detections.scores"):
        Detections(np.ones((3, 9)), np.ones(2), np.ones(3, np.int64))
    with pytest.raises(ValueError, match="Detections.labels"):
        Detections(np.ones((3, 9)), np.ones(3), np.ones(3))


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("block", [1, 7, 64])
def test_blocked_rotated_nms_matches_naive_loop(seed, block, monkeypatch):
    """The blocked greedy that crowded input takes (nms.BLOCKED_MIN_PAIRS) keeps exactly what the loop keeps."""
    import streamdet.runtime_ort.nms as nms_module

    monkeypatch.setattr(nms_module, "BLOCKED_MIN_PAIRS", 0)
    monkeypatch.setattr(nms_module, "BLOCK_BOXES", block)
    rng = np.random.default_rng(seed)
    boxes, scores, labels = random_boxes(rng, 120, spread_m=4.0)
    config = NmsConfig(kind=NmsKind.ROTATED, iou_threshold=0.2)
    assert nms(boxes, scores, labels, config).tolist() == naive_nms(boxes, scores, labels, config)


def _naive_top_k_reached(scores: np.ndarray, threshold: float) -> bool:
    return any(len(row) > 0 and row[-1] >= threshold for row in scores.tolist())


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [np.float32, np.float16, np.float64])
def test_top_k_reached_matches_reference(seed, dtype):
    rng = np.random.default_rng(seed)
    for q, k in ((1, 5), (2, 3), (4, 500), (3, 0)):
        scores = -np.sort(-rng.uniform(0, 1, (q, k)), axis=1).astype(dtype)  # descending, as the graph's top-K
        for threshold in (0.0, 0.05, 0.5, 0.99, 1.0):
            assert top_k_reached(scores, threshold) == _naive_top_k_reached(scores, threshold)


def test_top_k_reached_nan_and_malformed():
    assert not top_k_reached(np.array([[0.9, np.nan]], np.float32), 0.1)  # a NaN K-th score passes nothing
    assert top_k_reached(np.array([[0.9, 0.2], [0.5, np.nan]], np.float32), 0.1)
    for bad in (np.zeros(5, np.float32), np.zeros((1, 2, 3), np.float32)):
        with pytest.raises(ValueError, match=r"\(Q, K\)"):
            top_k_reached(bad, 0.1)
