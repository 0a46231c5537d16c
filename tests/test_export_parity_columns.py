"""The det_boxes parity per column group (export/parity.py): each group against its own scale, taken from the boxes
above the score threshold; yaw modulo 2 pi (the ONNX decode's -pi for PyTorch's +pi); the whole-pipeline check
compares the same groups; and a check that compared few detections says so.

Review 38 (M1): one tolerance for all nine columns, set by the centres' metres across a quadrant, let an fp16 graph
whose every yaw was off by 0.5 rad, or every z or height by 0.5 m, pass both fp16 checks."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from streamdet.core.boxes import H, L, VX, VY, W, X, Y, YAW, Z
from streamdet.export.parity import (
    BOX_COLUMN_GROUPS,
    BOX_SCORE_THRESHOLD,
    FEW_COMPARED,
    FP16_SCALE_FLOOR,
    FP16_TOL_REL,
    MIN_BOX_SCALE,
    MIN_COMPARED,
    TORCH_SCALE_FLOOR,
    TORCH_TOL_REL,
    YAW_SCALE,
    compare_detections,
    pipeline_parity,
    value_scale,
    wrap_angle,
)

SEEDS = [0, 1, 2]
GROUP_OF = {c: name for name, cols in BOX_COLUMN_GROUPS for c in cols}
PIPELINE_KW = dict(slice_index=5, num_slices=8, num_points=100, num_pillars=50, cell_m=0.8)


def _scene(rng: np.random.Generator, q: int = 1, k: int = 60, confident: int = 20):
    """Top-K outputs shaped like a trained small preset's: centres over a 51.2 m quadrant on distinct cells, z around
    the ground below the sensor, sizes of cars and people, any heading; ``confident`` scores above the threshold."""
    boxes = np.zeros((q, k, 9), np.float32)
    cells = np.stack([rng.permutation(64 * 64)[:k] for _ in range(q)])
    boxes[..., X] = (cells % 64 + 0.5) * 0.8
    boxes[..., Y] = (cells // 64 + 0.5) * 0.8
    boxes[..., Z] = rng.uniform(-2.0, 0.5, (q, k))
    boxes[..., W] = rng.uniform(0.5, 2.5, (q, k))
    boxes[..., L] = rng.uniform(0.5, 5.0, (q, k))
    boxes[..., H] = rng.uniform(1.0, 2.5, (q, k))
    boxes[..., YAW] = rng.uniform(-math.pi, math.pi, (q, k))
    boxes[..., VX:] = rng.normal(0.0, 2.0, (q, k, 2))
    scores = np.concatenate([np.linspace(0.9, 0.2, confident), np.linspace(0.09, 0.02, k - confident)])
    scores = np.repeat(scores[None], q, 0).astype(np.float32)
    labels = rng.integers(0, 10, (q, k)).astype(np.int64)
    return boxes, scores, labels


def _fp16_like(dets, rng: np.random.Generator):
    """The same detections with fp16-sized noise: a few mm on lengths, mrad on yaw, 1e-4 on scores."""
    boxes, scores, labels = (a.copy() for a in dets)
    boxes[..., X:YAW] += rng.normal(0.0, 1e-3, boxes[..., X:YAW].shape).astype(np.float32)
    boxes[..., YAW] += rng.normal(0.0, 3e-3, boxes[..., YAW].shape).astype(np.float32)
    boxes[..., VX:] += rng.normal(0.0, 1e-3, boxes[..., VX:].shape).astype(np.float32)
    scores += rng.normal(0.0, 1e-4, scores.shape).astype(np.float32)
    return boxes, scores, labels


def _run(dets):
    return dict(zip(("det_boxes", "det_scores", "det_labels"), dets))


def _shifted(dets, col: int, delta: float):
    boxes = dets[0].copy()
    boxes[..., col] += delta
    return boxes, dets[1].copy(), dets[2].copy()


def _failed(records) -> set[str]:
    return {r.output for r in records if not r.passed}


@pytest.mark.parametrize("seed", SEEDS)
def test_each_group_has_its_own_record_and_fp16_noise_passes(seed):
    rng = np.random.default_rng(seed)
    ref = _scene(rng)
    records = compare_detections("slice_head", "fp16", "onnx-fp32", _fp16_like(ref, rng), ref, FP16_TOL_REL, None,
                                 FP16_SCALE_FLOOR)  # fmt: skip
    assert [r.output for r in records] == [f"det_boxes.{name}" for name, _ in BOX_COLUMN_GROUPS] + ["det_scores", "det_labels"]
    assert all(r.passed for r in records), [(r.output, r.max_abs_diff, r.output_scale) for r in records]
    # naive scales: each group's range and magnitude over the boxes above the threshold only, at least 1; yaw 2 pi
    above = ref[0][ref[1] >= BOX_SCORE_THRESHOLD]
    for r, (name, cols) in zip(records, BOX_COLUMN_GROUPS):
        vals = [float(v) for row in above for v in row[list(cols)]]
        naive = YAW_SCALE if name == "yaw" else max(max(vals) - min(vals), FP16_SCALE_FLOOR * max(map(abs, vals)), MIN_BOX_SCALE)
        assert r.output_scale == pytest.approx(naive), name
        assert r.output_range == pytest.approx(max(vals) - min(vals)), name


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize(
    "col, delta",
    [(YAW, 0.5), (Z, 0.5), (H, 0.5), (W, 0.2), (L, -0.3), (VX, 0.3), (VY, -0.3), (YAW, -0.1), (Z, 0.05)],
)
def test_a_shift_of_one_column_fails_its_group_in_both_fp16_checks(seed, col, delta):
    """What the single tolerance let through (0.5 rad, 0.5 m: its 1e-2 x 51 m), and less: only that group fails."""
    rng = np.random.default_rng(seed)
    ref = _scene(rng)
    got = _shifted(_fp16_like(ref, rng), col, delta)
    records = compare_detections("slice_head", "fp16", "onnx-fp32", got, ref, FP16_TOL_REL, None, FP16_SCALE_FLOOR)
    assert _failed(records) == {f"det_boxes.{GROUP_OF[col]}"}
    res = pipeline_parity(_run(ref), _run(got), **PIPELINE_KW)
    assert not res.passed and res.count_fp32 == res.count_fp16
    if GROUP_OF[col] != "centre":  # the note holds each group's max difference of the pairs above the threshold
        noted = float(re.search(rf"{GROUP_OF[col]} ([0-9.e+-]+) \(tolerance", res.note).group(1))
        assert noted == pytest.approx(abs(delta), abs=0.02)


@pytest.mark.parametrize("seed", SEEDS)
def test_fp32_tolerances_per_group(seed):
    rng = np.random.default_rng(seed)
    ref = _scene(rng)
    got = tuple(a.copy() for a in ref)
    got[0][..., YAW] += np.float32(1e-5)  # float32 rounding of an atan2 passes
    assert not _failed(compare_detections("slice_head", "fp32", "torch", got, ref, TORCH_TOL_REL, None, TORCH_SCALE_FLOOR))
    got[0][..., YAW] += np.float32(4e-3)  # 4 mrad is no rounding (the single tolerance allowed 5e-3 in any unit)
    assert _failed(compare_detections("slice_head", "fp32", "torch", got, ref, TORCH_TOL_REL, None,
                                      TORCH_SCALE_FLOOR)) == {"det_boxes.yaw"}  # fmt: skip


def test_scales_and_comparison_come_from_the_boxes_above_the_threshold():
    """A far-off low-score box neither widens a group's tolerance nor fails it: no one reads it."""
    rng = np.random.default_rng(3)
    ref = _scene(rng)
    ref[0][0, -1, Z] = 40.0  # a junk box below the threshold with an absurd z
    got = tuple(a.copy() for a in ref)
    got[0][0, -1, YAW] += 1.0  # and its yaw is off in the other output (an ill-conditioned atan2 of a weak peak)
    records = {r.output: r for r in compare_detections("slice_head", "fp16", "onnx-fp32", got, ref, FP16_TOL_REL, None,
                                                       FP16_SCALE_FLOOR)}  # fmt: skip
    above_z = ref[0][ref[1] >= BOX_SCORE_THRESHOLD][:, Z]
    assert records["det_boxes.z"].output_scale == pytest.approx(max(value_scale(above_z, FP16_SCALE_FLOOR), MIN_BOX_SCALE))
    assert records["det_boxes.yaw"].passed and records["det_boxes.yaw"].max_abs_diff == 0.0
    got[0][0, 0, YAW] += 1.0  # the best box's yaw: a failure
    assert not compare_detections("slice_head", "fp16", "onnx-fp32", got, ref, FP16_TOL_REL, None, FP16_SCALE_FLOOR)[3].passed


def test_no_box_above_the_threshold_compares_no_column_and_still_matches_the_set():
    rng = np.random.default_rng(4)
    ref = _scene(rng, confident=0)
    records = compare_detections("slice_head", "fp16", "onnx-fp32", _shifted(ref, Z, 0.5), ref, FP16_TOL_REL, None,
                                 FP16_SCALE_FLOOR)  # fmt: skip
    assert all(r.passed for r in records) and "none above it" in records[0].note
    moved = _shifted(ref, X, 3.0)  # every box gone from where it was: the set comparison still fails
    assert not any(r.passed for r in compare_detections("slice_head", "fp16", "onnx-fp32", moved, ref, FP16_TOL_REL,
                                                        None, FP16_SCALE_FLOOR))  # fmt: skip


# ---- yaw modulo 2 pi (review 38, L1) -------------------------------------------------------------------------


@pytest.mark.parametrize("a, b, want", [(math.pi, -math.pi, 0.0), (3.1, -3.1, 2 * math.pi - 6.2), (0.2, -0.3, 0.5),
                                        (1.0, 1.0 + 4 * math.pi, 0.0), (-3.0, 3.0, 2 * math.pi - 6.0)])  # fmt: skip
def test_wrap_angle_against_the_definition(a, b, want):
    # naive: the smallest |a - b + 2 pi n| over integers n
    naive = min(abs(a - b + 2 * math.pi * n) for n in range(-3, 4))
    assert abs(float(wrap_angle(np.array([a - b]))[0])) == pytest.approx(naive, abs=1e-12)
    assert naive == pytest.approx(want, abs=1e-12)


@pytest.mark.parametrize("precision, tol_rel, floor", [("fp32", TORCH_TOL_REL, TORCH_SCALE_FLOOR),
                                                       ("fp16", FP16_TOL_REL, FP16_SCALE_FLOOR)])  # fmt: skip
def test_minus_pi_for_plus_pi_is_the_same_heading(precision, tol_rel, floor):
    """atan2(+0, cos < 0): PyTorch gives +pi, the ONNX graph (Atan with quadrant fixes) -pi (models/decode.py)."""
    ref = _scene(np.random.default_rng(5))
    ref[0][0, :5, YAW] = np.float32(math.pi)
    ref[0][0, 5:10, YAW] = np.float32(-math.pi)
    got = tuple(a.copy() for a in ref)
    got[0][0, :10, YAW] *= -1  # every +pi read as -pi and back
    reference = "torch" if precision == "fp32" else "onnx-fp32"
    records = compare_detections("slice_head", precision, reference, got, ref, tol_rel, None, floor)
    assert all(r.passed for r in records) and records[3].max_abs_diff < 1e-6
    assert pipeline_parity(_run(ref), _run(got), **PIPELINE_KW).passed
    got[0][0, :10, YAW] += np.float32(0.5)  # but half a radian off beside the cut is still a failure
    assert _failed(compare_detections("slice_head", precision, reference, got, ref, tol_rel, None, floor)) == {"det_boxes.yaw"}


# ---- how many were compared (review 38, L5) ------------------------------------------------------------------


def test_few_compared_detections_are_flagged_not_failed():
    """Near-ties and the top-K cut can leave almost nothing to compare (an untrained head's flat heatmap): the
    record passes on what it did compare, and its note starts with the warning the exporter prints."""
    rng = np.random.default_rng(6)
    ref = _scene(rng)
    margins = np.zeros(ref[1].shape)  # every peak a near-tie ...
    margins[0, : MIN_COMPARED - 1] = 0.5  # ... but a few
    records = compare_detections("slice_head", "fp16", "onnx-fp32", ref, ref, FP16_TOL_REL, margins, FP16_SCALE_FLOOR)
    assert all(r.passed for r in records)
    assert all(r.note.startswith(f"{FEW_COMPARED}: only {MIN_COMPARED - 1} of 60 detections") for r in records[:-1])
    margins[0, :MIN_COMPARED] = 0.5
    records = compare_detections("slice_head", "fp16", "onnx-fp32", ref, ref, FP16_TOL_REL, margins, FP16_SCALE_FLOOR)
    assert not any(r.note.startswith(FEW_COMPARED) for r in records)
    assert records[0].note.startswith(f"{MIN_COMPARED} of 60 detections compared")


def test_few_pipeline_boxes_are_flagged_not_failed():
    ref = _scene(np.random.default_rng(7), confident=MIN_COMPARED - 1)
    res = pipeline_parity(_run(ref), _run(ref), **PIPELINE_KW)
    assert res.passed and res.note.startswith(f"{FEW_COMPARED}: only {MIN_COMPARED - 1} boxes")
    ref = _scene(np.random.default_rng(7), confident=MIN_COMPARED)
    res = pipeline_parity(_run(ref), _run(ref), **PIPELINE_KW)
    assert res.passed and not res.note.startswith(FEW_COMPARED)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_cone_s_heading_is_not_compared(seed):
    """A cone's heading vector is near zero: fp16 may turn it by anything on a genuine export, and the devkit scores
    no orientation for cones (diff review L2). Every other class's heading still counts."""
    from streamdet.core.classes import CLASS_NAMES
    from streamdet.export.parity import NO_HEADING_LABELS

    rng = np.random.default_rng(seed)
    ref = _scene(rng)
    cone = CLASS_NAMES.index("traffic_cone")
    assert NO_HEADING_LABELS == (cone,)
    for label, fails in ((cone, False), (CLASS_NAMES.index("barrier"), True)):
        ref[2][:] = label
        got = _fp16_like(ref, rng)
        got[0][..., YAW] += math.pi / 2  # every heading turned a quarter
        records = compare_detections("slice_head", "fp16", "onnx-fp32", got, ref, FP16_TOL_REL, None, FP16_SCALE_FLOOR)
        assert _failed(records) == ({"det_boxes.yaw"} if fails else set()), label
        assert pipeline_parity(_run(ref), _run(got), **PIPELINE_KW).passed != fails, label
