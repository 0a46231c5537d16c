"""Parity helpers (export/parity.py) against naive loop references; empty and malformed input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from streamdet.export.parity import (
    FP16_TOL_REL,
    cell_centres,
    compare_dense,
    compare_detections,
    detection_margins,
    match_detections,
    peak_margins,
    pipeline_parity,
)


def _detections(rng: np.random.Generator, q: int, k: int, num_classes: int = 10) -> tuple[np.ndarray, ...]:
    """Top-K-like outputs: distinct positions per quadrant, scores sorted descending."""
    boxes = rng.uniform(0.0, 25.6, size=(q, k, 9)).astype(np.float32)
    boxes[..., :2] = (rng.permutation(64 * 64)[: q * k].reshape(q, k, 1) // np.array([64, 1]) % 64 + 0.5) * 0.4
    scores = -np.sort(-rng.uniform(0.0, 1.0, size=(q, k)), axis=1).astype(np.float32)
    labels = rng.integers(0, num_classes, size=(q, k)).astype(np.int64)
    return boxes, scores, labels


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compare_dense_matches_naive(seed):
    rng = np.random.default_rng(seed)
    ref = rng.normal(size=(2, 3, 5)).astype(np.float32)
    got = ref + rng.normal(scale=1e-5, size=ref.shape).astype(np.float32)
    rec = compare_dense("g", "fp32", "torch", "out", got, ref, 1e-4)
    naive = max(abs(float(a) - float(b)) for a, b in zip(got.ravel(), ref.ravel()))
    assert rec.max_abs_diff == pytest.approx(naive)
    assert rec.output_range == pytest.approx(float(ref.max()) - float(ref.min()))
    assert rec.passed == (naive <= 1e-4 * rec.output_range)
    bad = compare_dense("g", "fp32", "torch", "out", ref + 1.0, ref, 1e-4)
    assert not bad.passed


def test_compare_dense_shape_nan_and_empty():
    ref = np.zeros((2, 3), np.float32)
    assert not compare_dense("g", "fp32", "torch", "o", np.zeros((3, 2), np.float32), ref, 1e-4).passed
    got = ref.copy()
    got[0, 0] = np.nan
    assert not compare_dense("g", "fp32", "torch", "o", got, ref + np.arange(3), 1e-4).passed
    empty = np.zeros((0, 4), np.float32)
    rec = compare_dense("g", "fp32", "torch", "o", empty, empty, 1e-4)
    assert rec.passed and rec.max_abs_diff == 0.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_match_detections_tolerates_rank_swaps(seed):
    rng = np.random.default_rng(seed)
    ref = _detections(rng, 2, 20)
    # a permutation of the same detections with tiny noise: same set, different order
    perm = np.stack([rng.permutation(20) for _ in range(2)])
    got = tuple(np.take_along_axis(a, perm[..., None] if a.ndim == 3 else perm, axis=1).copy() for a in ref)
    got[0][...] += 1e-6
    m = match_detections(got, ref, score_tol=1e-3, centre_tol=1e-3)
    # naive: every reference detection clearly above its quadrant's K-th score has its twin
    naive_safe = sum(int(s > ref[1][q].min() + 1e-3) for q in range(2) for s in ref[1][q])
    assert m.compared == naive_safe and m.box_diff.shape == (naive_safe, 9)
    assert m.unmatched == m.ties == 0 and m.boundary == 40 - naive_safe
    assert m.box_diff.max() <= 2e-6 and m.score_diff.max() == 0.0


@pytest.mark.parametrize("seed", [0, 1])
def test_match_detections_flags_moved_and_relabelled(seed):
    rng = np.random.default_rng(seed)
    ref = _detections(rng, 1, 10)
    got = tuple(a.copy() for a in ref)
    got[0][0, 0, 0] += 1.0  # the best detection moved by a metre
    got[2][0, 1] = (got[2][0, 1] + 1) % 10  # the second changed class
    m = match_detections(got, ref, score_tol=1e-4, centre_tol=0.1)
    assert m.unmatched == 2 and m.ties == 0
    recs = compare_detections("slice_head", "fp16", "onnx-fp32", got, ref, 1e-2)
    assert [r.output for r in recs] == ["det_boxes.centre", "det_boxes.z", "det_boxes.size", "det_boxes.yaw",
                                        "det_boxes.velocity", "det_scores", "det_labels"]
    assert not any(r.passed for r in recs)
    assert recs[-1].max_abs_diff == 2.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_peak_margins_and_centres_match_naive(seed):
    rng = np.random.default_rng(seed)
    logits = rng.normal(size=(2, 3, 5, 6)).astype(np.float32)
    reg = rng.uniform(-0.5, 0.5, size=(2, 2, 5, 6)).astype(np.float32)
    margins = peak_margins(logits)
    centres = cell_centres(reg, 0.8)
    heat = 1.0 / (1.0 + np.exp(-logits.astype(np.float64)))
    for q, c, r, k in np.ndindex(*logits.shape):
        neighbours = [heat[q, c, r + dr, k + dk] for dr in (-1, 0, 1) for dk in (-1, 0, 1)
                      if (dr or dk) and 0 <= r + dr < 5 and 0 <= k + dk < 6]
        assert margins[q, c, r, k] == pytest.approx(heat[q, c, r, k] - max(neighbours))
    for q, r, k in np.ndindex(2, 5, 6):
        assert centres[q, 0, r, k] == pytest.approx((k + 0.5 + reg[q, 0, r, k]) * 0.8)
        assert centres[q, 1, r, k] == pytest.approx((r + 0.5 + reg[q, 1, r, k]) * 0.8)
    # decode's peaks are exactly the cells with a positive margin (no exact ties in random floats)
    pooled = np.max(np.stack([np.pad(heat, ((0, 0), (0, 0), (1, 1), (1, 1)), constant_values=-np.inf)[:, :, dr:dr + 5, dk:dk + 6]
                              for dr in range(3) for dk in range(3)]), axis=0)
    np.testing.assert_array_equal(margins > 0, heat == pooled)
    # each detection finds its own cell's margin
    boxes = np.zeros((2, 4, 9), np.float32)
    labels = rng.integers(0, 3, size=(2, 4))
    cells = rng.integers(0, 30, size=(2, 4))
    for q in range(2):
        boxes[q, :, :2] = centres[q].reshape(2, -1)[:, cells[q]].T
    got = detection_margins(boxes, labels, margins, centres)
    want = np.array([[margins[q, labels[q, i]].ravel()[cells[q, i]] for i in range(4)] for q in range(2)])
    np.testing.assert_allclose(got, want)
    assert detection_margins(boxes[:, :0], labels[:, :0], margins, centres).shape == (2, 0)


def test_near_ties_are_left_out_and_counted():
    """A detection that vanished in the other output is a failure, unless the reference heatmap says its peak
    stood within the score tolerance of a neighbour."""
    boxes, scores, labels = _detections(np.random.default_rng(4), 1, 10)
    scores[0] = np.linspace(0.9, 0.45, 10)
    got = tuple(a.copy() for a in (boxes, scores, labels))
    got[0][0, 2, :2] += 5.0  # detection 2 is gone from where it was
    m = match_detections(got, (boxes, scores, labels), 1e-3, 1e-3)
    assert (m.unmatched, m.ties) == (1, 0)
    tie = np.zeros((1, 10), bool)
    tie[0, 2] = True
    m = match_detections(got, (boxes, scores, labels), 1e-3, 1e-3, tie)
    assert (m.unmatched, m.ties) == (0, 1)
    margins = np.full((1, 10), 0.3)
    margins[0, 2] = 1e-4
    recs = compare_detections("slice_head", "fp16", "onnx-fp32", got, (boxes, scores, labels), 1e-2, margins)
    assert all(r.passed for r in recs) and all("1 near-tie peaks" in r.note for r in recs[:-1])
    margins[0, 2] = 0.05  # a clear peak: its loss is a failure
    assert not any(r.passed for r in compare_detections("slice_head", "fp16", "onnx-fp32", got, (boxes, scores, labels), 1e-2, margins))
    with pytest.raises(ValueError, match="near_tie"):
        match_detections(got, (boxes, scores, labels), 1e-3, 1e-3, tie[:, :3])
    # the pipeline: the moved box pairs with nothing; as a near-tie in either run it is left out
    kwargs = dict(slice_index=0, num_slices=8, num_points=1, num_pillars=1, cell_m=0.4)
    res = pipeline_parity(_run(boxes, scores, labels), _run(*got), **kwargs)
    assert not res.passed and res.count_fp32 == res.count_fp16
    res = pipeline_parity(_run(boxes, scores, labels), _run(*got), margins32=np.where(tie, 0.0, 0.3),
                          margins16=np.where(tie, 0.0, 0.3), **kwargs)
    assert res.passed and res.excluded_near_ties == 2 and res.count_fp32 == res.count_fp16 == 9


def test_match_detections_empty_and_malformed():
    empty = (np.zeros((1, 0, 9), np.float32), np.zeros((1, 0), np.float32), np.zeros((1, 0), np.int64))
    m = match_detections(empty, empty, 1e-4, 1e-4)
    assert m.box_diff.shape == (0, 9) and m.compared == m.boundary == m.unmatched == m.ties == 0
    assert all(r.passed for r in compare_detections("s", "fp32", "torch", empty, empty, 1e-4))
    ref = _detections(np.random.default_rng(0), 1, 5)
    short = (ref[0][:, :4], ref[1][:, :4], ref[2][:, :4])
    with pytest.raises(ValueError, match="shapes differ"):
        match_detections(short, ref, 1e-4, 1e-4)


def _run(boxes, scores, labels):
    return {"det_boxes": boxes, "det_scores": scores, "det_labels": labels}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pipeline_parity_counts_like_naive(seed):
    rng = np.random.default_rng(seed)
    boxes, scores, labels = _detections(rng, 2, 30)
    noisy = scores + rng.normal(scale=1e-4, size=scores.shape).astype(np.float32)
    moved = boxes + rng.normal(scale=0.01, size=boxes.shape).astype(np.float32)
    res = pipeline_parity(_run(boxes, scores, labels), _run(moved, noisy, labels),
                          slice_index=0, num_slices=8, num_points=10, num_pillars=5, cell_m=0.4)
    # the fp32 scores' range, floored at their magnitude (FP16_SCALE_FLOOR = 1: export/parity.py)
    band = FP16_TOL_REL * max(float(scores.max() - scores.min()), float(np.abs(scores).max()))
    assert res.score_band == pytest.approx(band)
    # naive: a box is excluded if either run puts it within the band; otherwise counted if above 0.1
    excluded = counted = 0
    for a, b in zip(scores.ravel(), noisy.ravel()):
        if abs(a - 0.1) <= band or abs(b - 0.1) <= band:
            excluded += 1
        elif a >= 0.1:
            counted += 1
    assert res.excluded_in_band == excluded
    assert res.count_fp32 == res.count_fp16 == counted
    assert res.passed and res.max_centre_diff_m < 0.1


def test_pipeline_parity_fails_on_missing_and_moved_boxes():
    boxes, scores, labels = _detections(np.random.default_rng(5), 1, 10)
    scores[:] = np.linspace(0.9, 0.5, 10)
    low = scores.copy()
    low[0, 0] = 0.01  # the best box vanished in fp16
    res = pipeline_parity(_run(boxes, scores, labels), _run(boxes, low, labels),
                          slice_index=0, num_slices=8, num_points=1, num_pillars=1, cell_m=0.4)
    assert not res.passed and res.count_fp32 == res.count_fp16 + 1
    moved = boxes.copy()
    moved[0, 3, 0] += 0.5  # within the pairing radius (2 cells = 0.8 m), with another score: not a near-tie shift
    other = scores.copy()
    other[0, 3] += 0.02
    res = pipeline_parity(_run(boxes, scores, labels), _run(moved, other, labels),
                          slice_index=0, num_slices=8, num_points=1, num_pillars=1, cell_m=0.4)
    assert not res.passed and res.max_centre_diff_m == pytest.approx(0.5, abs=1e-5)


def test_pipeline_parity_no_boxes_above_threshold():
    boxes, scores, labels = _detections(np.random.default_rng(1), 1, 4)
    scores[:] = 0.01
    res = pipeline_parity(_run(boxes, scores, labels), _run(boxes, scores, labels),
                          slice_index=0, num_slices=8, num_points=1, num_pillars=1, cell_m=0.4)
    assert res.passed and res.count_fp32 == res.count_fp16 == 0 and math.isnan(res.max_centre_diff_m)
