"""Parity checks the export runs on itself, recorded in the manifest (numpy + onnxruntime; no torch here).

Tolerances (of the reference output's range, max - min):

- onnxruntime fp32 against PyTorch: max |a - b| <= 1e-4 * range.
- onnxruntime fp16 graph against the fp32 graph on the same inputs: <= 1e-2 * range.

Dense outputs (features, image BEV) are compared element-wise. Decoded detections (det_boxes, det_scores,
det_labels) are compared as *sets*: top-K keeps the K best peaks of classes x cells, and two peaks whose scores
differ by less than the rounding error may swap ranks, or one may fall out of the top K for the other. So each
reference detection whose score clears the K-th score by more than the score tolerance is matched to the
detection of the same label with the nearest centre in the other output; its box and score must agree within
the tolerance, and a detection with no partner there is a failure. Detections at the top-K boundary are not
compared, and how many were left out is recorded in the record's note.

The whole-pipeline check (fp16 graphs against fp32 graphs on the real sample) lives in ``pipeline_parity``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import numpy as np
import onnxruntime as ort

from streamdet.export.manifest import ParityRecord, PipelineParity

TORCH_TOL_REL = 1e-4  # onnxruntime fp32 vs PyTorch
FP16_TOL_REL = 1e-2  # onnxruntime fp16 vs onnxruntime fp32
PIPELINE_SCORE_THRESHOLD = 0.1
PIPELINE_CENTRE_TOL_M = 0.1


def ort_session(model: str | os.PathLike | bytes) -> ort.InferenceSession:
    """A CPU session with every graph optimisation on (what the runtime uses)."""
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3  # fp16 graphs on CPU log a warning per wrapped op; errors still raise
    src = model if isinstance(model, bytes) else os.fspath(model)
    return ort.InferenceSession(src, opts, providers=["CPUExecutionProvider"])


def value_range(x: np.ndarray) -> float:
    """max - min of a float array (0 for an empty one)."""
    if x.size == 0:
        return 0.0
    x = x.astype(np.float64)
    return float(x.max() - x.min())


def compare_dense(
    graph: str, precision: str, reference: str, output: str, got: np.ndarray, ref: np.ndarray, tol_rel: float
) -> ParityRecord:
    """Element-wise max |got - ref| against tol_rel * range(ref)."""
    if got.shape != ref.shape:
        return ParityRecord(graph, precision, reference, output, math.inf, value_range(ref), tol_rel, False,
                            f"shape {got.shape} differs from the reference's {ref.shape}")
    diff = float(np.abs(got.astype(np.float64) - ref.astype(np.float64)).max()) if ref.size else 0.0
    rng = value_range(ref)
    finite = bool(np.isfinite(got).all())
    passed = finite and diff <= tol_rel * rng
    note = "" if finite else "non-finite values in the output"
    return ParityRecord(graph, precision, reference, output, diff, rng, tol_rel, passed, note)


def match_detections(
    got: Sequence[np.ndarray], ref: Sequence[np.ndarray], score_tol: float, centre_tol: float
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Pair the reference's safely-in-top-K detections with the other output's (see the module doc).

    got, ref: (det_boxes (Q, K, 9), det_scores (Q, K), det_labels (Q, K)). Returns (box_diff, score_diff) per
    matched pair, each (N_matched,) max-abs, the number of reference detections left out at the top-K boundary,
    and the number with no partner of the same label within ``centre_tol`` of its centre.
    """
    gb, gs, gl = got
    rb, rs, rl = ref
    if gb.shape != rb.shape or gs.shape != rs.shape or gl.shape != rl.shape:
        raise ValueError(f"detection shapes differ: {gb.shape}/{gs.shape}/{gl.shape} vs {rb.shape}/{rs.shape}/{rl.shape}")
    box_diffs, score_diffs = [], []
    boundary = unmatched = 0
    for qi in range(rb.shape[0]):
        if rs.shape[1] == 0:
            continue
        kth = float(rs[qi].min())
        safe = rs[qi] > kth + score_tol  # (K,)
        boundary += int((~safe).sum())
        idx = np.flatnonzero(safe)
        if idx.size == 0:
            continue
        # (n_safe, K) centre distance to every candidate of the same label
        dist = np.abs(gb[qi, None, :, :2] - rb[qi, idx, None, :2]).max(axis=-1).astype(np.float64)
        dist[gl[qi, None, :] != rl[qi, idx, None]] = np.inf
        j = np.argmin(dist, axis=1)  # (n_safe,)
        ok = dist[np.arange(idx.size), j] <= centre_tol
        unmatched += int((~ok).sum())
        box_diffs.append(np.abs(gb[qi, j[ok]] - rb[qi, idx[ok]]).max(axis=1))
        score_diffs.append(np.abs(gs[qi, j[ok]] - rs[qi, idx[ok]]))
    cat = lambda xs: np.concatenate(xs).astype(np.float64) if xs else np.zeros(0)  # noqa: E731
    return cat(box_diffs), cat(score_diffs), boundary, unmatched


def compare_detections(
    graph: str, precision: str, reference: str, got: Sequence[np.ndarray], ref: Sequence[np.ndarray], tol_rel: float
) -> list[ParityRecord]:
    """Set-wise comparison of decoded top-K detections; one record per output (det_boxes, det_scores, det_labels)."""
    rb, rs, rl = ref
    box_rng, score_rng = value_range(rb), value_range(rs)
    box_diff, score_diff, boundary, unmatched = match_detections(got, ref, tol_rel * score_rng, tol_rel * box_rng)
    matched = box_diff.size
    note = f"{matched} detections matched as sets; {boundary} at the top-K boundary not compared; {unmatched} without a partner"
    finite = all(bool(np.isfinite(x).all()) for x in got[:2])
    bd = float(box_diff.max()) if matched else 0.0
    sd = float(score_diff.max()) if matched else 0.0
    ok = finite and unmatched == 0
    return [
        ParityRecord(graph, precision, reference, "det_boxes", bd, box_rng, tol_rel, ok and bd <= tol_rel * box_rng, note),
        ParityRecord(graph, precision, reference, "det_scores", sd, score_rng, tol_rel, ok and sd <= tol_rel * score_rng, note),
        ParityRecord(graph, precision, reference, "det_labels", float(unmatched), float(rl.max() - rl.min()) if rl.size else 0.0,
                     tol_rel, ok, "labels must agree on every matched detection; max_abs_diff holds the unmatched count"),
    ]


def pipeline_parity(
    fp32: Mapping[str, np.ndarray],
    fp16: Mapping[str, np.ndarray],
    *,
    slice_index: int,
    num_slices: int,
    num_points: int,
    num_pillars: int,
    score_threshold: float = PIPELINE_SCORE_THRESHOLD,
    centre_tol_m: float = PIPELINE_CENTRE_TOL_M,
    pair_radius_m: float = 2.0,
) -> PipelineParity:
    """fp16 pipeline against fp32 pipeline: decoded boxes with score >= threshold.

    ``fp32`` / ``fp16``: det_boxes (Q, K, 9), det_scores (Q, K), det_labels (Q, K) of the slice graph, each fed by
    its own precision's encoder and lifter. Boxes of the two runs are paired greedily by centre distance (same
    quadrant and label, within ``pair_radius_m``). A pair, or an unpaired box, whose score lies within the band
    ``FP16_TOL_REL * range(fp32 scores)`` of the threshold in either run may legitimately land on either side of
    it: it is excluded from the count (``excluded_in_band``); so is an unpaired box within the band of its run's K-th
    score, whose partner may have dropped out of the other run's top K (``excluded_at_top_k``). Every other box
    above the threshold must be paired
    with a box above the threshold in the other run, with centres within ``centre_tol_m``: then both runs count the
    same boxes.
    """
    band = FP16_TOL_REL * value_range(fp32["det_scores"])
    runs = []
    for run in (fp32, fp16):
        s = run["det_scores"]
        q = np.broadcast_to(np.arange(s.shape[0])[:, None], s.shape)
        runs.append((run["det_boxes"].reshape(-1, 9).astype(np.float64), s.reshape(-1), run["det_labels"].reshape(-1), q.reshape(-1)))
    (b32, s32, l32, q32), (b16, s16, l16, q16) = runs
    # Only boxes that may be above the threshold take part; a pair needs one of them.
    a32 = np.flatnonzero(s32 >= score_threshold - band)
    a16 = np.flatnonzero(s16 >= score_threshold - band)
    d = np.linalg.norm(b32[a32, None, :2] - b16[None, a16, :2], axis=-1)  # (n32, n16)
    d[(l32[a32, None] != l16[None, a16]) | (q32[a32, None] != q16[None, a16])] = np.inf
    pair16 = np.full(a32.size, -1)  # position in a16 of each fp32 box's partner
    taken = np.zeros(a16.size, dtype=bool)
    for flat in np.argsort(d, axis=None, kind="stable"):  # greedy, nearest pairs first
        i, j = divmod(int(flat), a16.size)
        if not d[i, j] <= pair_radius_m:
            break
        if pair16[i] < 0 and not taken[j]:
            pair16[i], taken[j] = j, True

    def in_band(s: np.ndarray) -> np.ndarray:
        return np.abs(s - score_threshold) <= band

    paired = pair16 >= 0
    ps32, ps16 = s32[a32[paired]], s16[a16[pair16[paired]]]
    pair_band = in_band(ps32) | in_band(ps16)
    pair_above = ~pair_band & (ps32 >= score_threshold) & (ps16 >= score_threshold)
    pair_split = ~pair_band & ((ps32 >= score_threshold) != (ps16 >= score_threshold))  # one above, one clearly below
    lone32, lone16 = s32[a32[~paired]], s16[a16[~taken]]
    # A lone box just above its run's K-th score may have a partner that fell out of the other run's top K.
    kth32 = fp32["det_scores"].min(axis=1)[q32[a32[~paired]]] if lone32.size else lone32
    kth16 = fp16["det_scores"].min(axis=1)[q16[a16[~taken]]] if lone16.size else lone16
    at_k32, at_k16 = (lone32 <= kth32 + band) & ~in_band(lone32), (lone16 <= kth16 + band) & ~in_band(lone16)
    lone32_above = ~in_band(lone32) & ~at_k32 & (lone32 >= score_threshold)
    lone16_above = ~in_band(lone16) & ~at_k16 & (lone16 >= score_threshold)
    excluded = int(pair_band.sum() + in_band(lone32).sum() + in_band(lone16).sum())
    excluded_top_k = int(at_k32.sum() + at_k16.sum())
    count32 = int(pair_above.sum() + (pair_split & (ps32 >= score_threshold)).sum() + lone32_above.sum())
    count16 = int(pair_above.sum() + (pair_split & (ps16 >= score_threshold)).sum() + lone16_above.sum())
    # (lone boxes at the top-K boundary are left out of both counts, like those in the threshold band)
    centre = d[np.flatnonzero(paired)[pair_above], pair16[paired][pair_above]]
    max_d = float(centre.max()) if centre.size else math.nan
    passed = bool(
        count32 == count16 and not pair_split.any() and not lone32_above.any() and not lone16_above.any()
        and (centre.size == 0 or max_d <= centre_tol_m)
    )
    note = (
        f"band = {FP16_TOL_REL:g} x fp32 score range = {band:.3g}; {int(pair_above.sum())} boxes above in both runs; "
        f"{int(pair_split.sum())} pairs split by the threshold, {int(lone32_above.sum())} fp32 and "
        f"{int(lone16_above.sum())} fp16 boxes above it without a partner within {pair_radius_m:g} m"
    )
    return PipelineParity(
        slice_index=slice_index,
        num_slices=num_slices,
        num_points=num_points,
        num_pillars=num_pillars,
        score_threshold=score_threshold,
        score_band=band,
        count_fp32=count32,
        count_fp16=count16,
        excluded_in_band=excluded,
        excluded_at_top_k=excluded_top_k,
        max_centre_diff_m=max_d,
        centre_tolerance_m=centre_tol_m,
        passed=passed,
        note=note,
    )
