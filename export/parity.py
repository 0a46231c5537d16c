"""Parity checks the export runs on itself, recorded in the manifest (numpy + onnxruntime; no torch here).

Tolerances (of the reference output's scale: its range, max - min, but never less than a fraction of its magnitude,
max |value|):

- onnxruntime fp32 against PyTorch: max |a - b| <= 1e-4 * scale, the scale at least 0.1 * magnitude.
- onnxruntime fp16 graph against the fp32 graph on the same inputs: <= 1e-2 * scale, the scale at least the magnitude.

Why the floor: the scores of a nearly untrained head, or the few of a small ``--top-k``, can span a band far narrower
than their size (a range of 5e-4 at scores near 0.3), where 1e-4 x range falls to a float32 ulp of the scores and
rounding alone failed the export. With the floor the fp32 tolerance is never under about 80 float32 ulps of the
largest value, the fp16 one about 10 fp16 ulps; a trained model's outputs span most of their magnitude, and there the
range decides as before.

Dense outputs (features, image BEV) are compared element-wise. Decoded detections (det_boxes, det_scores,
det_labels) are compared as *sets*: top-K keeps the K best peaks of classes x cells, and two peaks whose scores
differ by less than the rounding error may swap ranks, or one may fall out of the top K for the other. So each
reference detection whose score clears the best score left out of the top K (the reference's (K+1)-th, decoded
for the purpose: export/graph_steps.py ``reference_decode``) by more than the score tolerance is matched to the
detection of the same label with the nearest centre in the other output; its score must agree within the
tolerance, and a detection with no partner there is a failure. Detections at the top-K boundary are not
compared, and how many were left out is recorded in the record's note. Without the (K+1)-th score the K-th
stands in, which leaves the K-th detection itself out: with K = 1 nothing at all would be compared.

Box columns: the nine columns of det_boxes hold five quantities of unrelated size (core/boxes.py), so each group
has its own record and scale (``BOX_COLUMN_GROUPS``): centre x, y; z; size w, l, h; yaw; velocity. One scale for
all nine was set by the widest column, the centres' metres across a quadrant, and let an fp16 yaw or height be
off by half a radian or metre. The scale of a group is that of the reference boxes that matter, those with score
>= ``BOX_SCORE_THRESHOLD`` (the low-score rest of the top K spans the whole map and holds boxes no one reads),
floored as above and at ``MIN_BOX_SCALE``; the columns are compared on the matched detections above the
threshold. Yaw is an angle: compared modulo 2 pi (+pi and -pi are one heading, and the ONNX atan2 gives -pi where
PyTorch's gives +pi, models/decode.py), against a fixed scale of 2 pi, since its error comes from the sin and cos
the head regresses, not from which headings the boxes have.

How many were compared: a check that left out nearly every detection (an untrained head's flat heatmap is mostly
near-ties) says little. The note starts with the count, and below ``MIN_COMPARED`` it says so as a warning, which
the exporter prints. It is not a failure: the fixed-seed untrained export (the default of a preset without a
checkpoint) can legitimately leave only one or none clear of the near-ties, and its graphs are still the ones the
dense checks and the decode check covered. A record that compared nothing at all (no detection, or no box above
the threshold for a box group) holds NaN as its max |diff|, never a 0 that reads as exact agreement, and its note
starts with ``NOT_COMPARED`` (after ``NON_FINITE`` where the output holds NaN or inf, a failure).

Near-ties: peak picking keeps a cell that equals the max of its 3x3 neighbourhood (same class). Where a cell and
a neighbour differ by less than the other precision's error, the peak may move to the neighbour or vanish (the
neighbour now beats it, but is itself beaten by another peak), or a non-peak may become one. Which cells are
that close is read off the reference heatmap: ``peak_margins`` gives every cell's score minus the best of its
eight neighbours. A detection whose cell's |margin| is within the score tolerance is a near-tie: left out of the
comparison and counted. A trained model's confident peaks stand clear of their neighbours; an untrained model's
flat heatmap is full of near-ties.

The whole-pipeline check (fp16 graphs against fp32 graphs on the real sample) lives in ``pipeline_parity``: counts
and centres (in metres), and the other box groups of the paired boxes with the fp16 tolerances above.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from streamdet.core.boxes import BOX_DIM, H, L, VX, VY, W, X, Y, YAW, Z, pair_boxes
from streamdet.core.classes import CLASS_NAMES
from streamdet.runtime_ort.manifest_records import ParityRecord, PipelineParity
from streamdet.runtime_ort.sessions import ort_session  # noqa: F401 (the parity run's sessions; imported from here too)

TORCH_TOL_REL = 1e-4  # onnxruntime fp32 vs PyTorch
FP16_TOL_REL = 1e-2  # onnxruntime fp16 vs onnxruntime fp32
# the scale a tolerance is relative to is at least this fraction of the reference's magnitude (module doc)
TORCH_SCALE_FLOOR = 0.1
FP16_SCALE_FLOOR = 1.0
PIPELINE_SCORE_THRESHOLD = 0.1
PIPELINE_CENTRE_TOL_M = 0.1
# det_boxes column groups, each with its own tolerance (module doc)
BOX_COLUMN_GROUPS: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("centre", (X, Y)), ("z", (Z,)), ("size", (W, L, H)), ("yaw", (YAW,)), ("velocity", (VX, VY)))
YAW_GROUP = "yaw"
# Labels whose boxes have no heading to compare: a cone's predicted heading vector is near zero, so fp16 rounding may
# turn it by anything up to pi on a genuine export. The devkit scores no orientation for them either
# (evaluation/config.py).
NO_HEADING_LABELS = (CLASS_NAMES.index("traffic_cone"),)
YAW_SCALE = 2.0 * math.pi  # an angle's scale is the full turn, whatever headings the boxes have
# The boxes whose columns set the scales and are compared: the runtime's default score threshold (PostConfig).
BOX_SCORE_THRESHOLD = PIPELINE_SCORE_THRESHOLD
# A group's scale is never under 1 (metre, m/s): the velocities of a model trained without them, or the z of a single
# box at the LiDAR's height (z = 0), have neither range nor magnitude, yet their error is that of the features behind.
MIN_BOX_SCALE = 1.0
# Below this many detections compared (as sets, or pipeline boxes above the threshold) the record warns (module doc).
MIN_COMPARED = 5
FEW_COMPARED = "WARNING: few compared"  # how such a note starts (the exporter prints it)
NOT_COMPARED = "nothing compared"  # how the note of a record that compared nothing starts (max_abs_diff NaN)
NON_FINITE = "non-finite values in the output"  # a failure's reason, first in its note


def value_range(x: np.ndarray) -> float:
    """max - min of a float array (0 for an empty one)."""
    if x.size == 0:
        return 0.0
    x = x.astype(np.float64)
    return float(x.max() - x.min())


def value_scale(x: np.ndarray, floor: float = 0.0) -> float:
    """What a tolerance is relative to: the range of ``x``, but at least ``floor`` x max |x| (module doc)."""
    if x.size == 0:
        return 0.0
    return max(value_range(x), floor * float(np.abs(x.astype(np.float64)).max()))


def compare_dense(
    graph: str, precision: str, reference: str, output: str, got: np.ndarray, ref: np.ndarray, tol_rel: float,
    scale_floor: float = 0.0,
) -> ParityRecord:  # fmt: skip
    """Element-wise max |got - ref| against tol_rel * value_scale(ref, scale_floor)."""
    rng, scale = value_range(ref), value_scale(ref, scale_floor)
    if got.shape != ref.shape:
        return ParityRecord(graph, precision, reference, output, math.inf, rng, tol_rel, False,
                            f"shape {got.shape} differs from the reference's {ref.shape}", scale)  # fmt: skip
    diff = float(np.abs(got.astype(np.float64) - ref.astype(np.float64)).max()) if ref.size else 0.0
    finite = bool(np.isfinite(got).all())
    passed = finite and diff <= tol_rel * scale
    note = "" if finite else NON_FINITE
    return ParityRecord(graph, precision, reference, output, diff, rng, tol_rel, passed, note, scale)


# ---- near-ties -------------------------------------------------------------------------------------------


def peak_margins(heatmap_logits: np.ndarray) -> np.ndarray:
    """(Q, C, Hh, Wh) heatmap logits -> each cell's score (sigmoid) minus the largest of its 8 neighbours'.

    > 0 on the decode's peaks, <= 0 elsewhere; the border counts as -inf (the max-pool pads that way).
    """
    with np.errstate(over="ignore"):  # a logit under about -709 overflows exp: its score is 0, as it should be
        heat = 1.0 / (1.0 + np.exp(-heatmap_logits.astype(np.float64)))
    q, c, h, w = heat.shape
    padded = np.full((q, c, h + 2, w + 2), -np.inf)
    padded[:, :, 1:-1, 1:-1] = heat
    best = np.full_like(heat, -np.inf)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy == 1 and dx == 1:
                continue
            best = np.maximum(best, padded[:, :, dy : dy + h, dx : dx + w])
    return heat - best


def cell_centres(reg: np.ndarray, cell_m: float) -> np.ndarray:
    """(Q, 2, Hh, Wh) centre offsets (in cells) -> (Q, 2, Hh, Wh) decoded box centres x, y in metres (decode.py)."""
    _, _, h, w = reg.shape
    col = np.arange(w, dtype=np.float64)[None, None, :]
    row = np.arange(h, dtype=np.float64)[None, :, None]
    x = (col + 0.5 + reg[:, 0].astype(np.float64)) * cell_m  # (Q, Hh, Wh)
    y = (row + 0.5 + reg[:, 1].astype(np.float64)) * cell_m
    return np.stack([x, y], axis=1)


def detection_margins(boxes: np.ndarray, labels: np.ndarray, margins: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(Q, K) peak margin of each detection: that of the cell of its label whose decoded centre is nearest its box's.

    boxes (Q, K, 9), labels (Q, K), margins (Q, C, Hh, Wh) from ``peak_margins``, centres (Q, 2, Hh, Wh).
    """
    q, k = labels.shape
    out = np.zeros((q, k))
    if k == 0:
        return out
    flat_centres = centres.reshape(q, 2, -1).transpose(0, 2, 1)  # (Q, Hh*Wh, 2)
    flat_margins = margins.reshape(q, margins.shape[1], -1)  # (Q, C, Hh*Wh)
    for qi in range(q):
        d = np.abs(boxes[qi, :, None, :2].astype(np.float64) - flat_centres[qi, None]).max(axis=-1)  # (K, Hh*Wh)
        cell = np.argmin(d, axis=1)  # (K,)
        out[qi] = flat_margins[qi, labels[qi], cell]
    return out


# ---- detections as sets ----------------------------------------------------------------------------------


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles (radians) mapped to [-pi, pi): a difference of headings, +pi and -pi being the same one."""
    return (np.asarray(a, dtype=np.float64) + math.pi) % (2.0 * math.pi) - math.pi


def box_differences(got: np.ndarray, ref: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
    """(N, 9) |got - ref| per column, float64, yaw modulo 2 pi; 0 for the yaw of boxes whose ``labels`` (N,) (the
    pairs' label) have no heading (NO_HEADING_LABELS)."""
    diff = np.abs(got.astype(np.float64) - ref.astype(np.float64))
    diff[:, YAW] = np.abs(wrap_angle(diff[:, YAW]))
    if labels is not None:
        diff[np.isin(np.asarray(labels), NO_HEADING_LABELS), YAW] = 0.0
    return diff


def box_group_scales(boxes: np.ndarray, scale_floor: float) -> dict[str, float]:
    """Each group's scale (module doc) from the (N, 9) reference boxes that matter: ``value_scale`` floored at
    ``MIN_BOX_SCALE``, yaw's fixed at ``YAW_SCALE``."""
    boxes = boxes.reshape(-1, BOX_DIM)
    return {name: YAW_SCALE if name == YAW_GROUP else max(value_scale(boxes[:, list(cols)], scale_floor), MIN_BOX_SCALE)
            for name, cols in BOX_COLUMN_GROUPS}  # fmt: skip


def box_group_max(diff: np.ndarray) -> dict[str, float]:
    """(N, 9) per-column differences -> each group's max (0 with no rows)."""
    return {name: float(diff[:, list(cols)].max()) if diff.size else 0.0 for name, cols in BOX_COLUMN_GROUPS}


@dataclass(frozen=True)
class DetectionMatch:
    """What ``match_detections`` found: per matched pair, the per-column box differences (N, 9) (yaw modulo 2 pi),
    the score difference (N,) and the reference's score (N,); how many reference detections were left out at the
    top-K boundary, how many have no partner (failures), how many were left out as near-ties."""

    box_diff: np.ndarray
    score_diff: np.ndarray
    ref_score: np.ndarray
    boundary: int
    unmatched: int
    ties: int

    @property
    def compared(self) -> int:
        return int(self.score_diff.size)


def match_detections(
    got: Sequence[np.ndarray],
    ref: Sequence[np.ndarray],
    score_tol: float,
    centre_tol: float,
    near_tie: np.ndarray | None = None,
    first_left_out: np.ndarray | None = None,
) -> DetectionMatch:
    """Pair the reference's safely-in-top-K detections with the other output's (see the module doc).

    got, ref: (det_boxes (Q, K, 9), det_scores (Q, K), det_labels (Q, K)); near_tie (Q, K) bool flags reference
    detections left out as near-ties. first_left_out (Q,): each quadrant's best reference score left out of its top
    K (the (K+1)-th; -inf where the top K holds every cell); a detection is safely in the top K when its score
    clears it by more than ``score_tol``. None: not known, the K-th score stands in (the K-th detection itself is
    then never compared). A reference detection with no partner of the same label within ``centre_tol`` of its
    centre is counted as unmatched (a failure).
    """
    gb, gs, gl = got
    rb, rs, rl = ref
    if gb.shape != rb.shape or gs.shape != rs.shape or gl.shape != rl.shape:
        raise ValueError(f"detection shapes differ: {gb.shape}/{gs.shape}/{gl.shape} vs {rb.shape}/{rs.shape}/{rl.shape}")
    if near_tie is None:
        near_tie = np.zeros(rs.shape, dtype=bool)
    if near_tie.shape != rs.shape:
        raise ValueError(f"near_tie has shape {near_tie.shape}, the detections {rs.shape}")
    cut = _boundary_scores(rs, first_left_out)
    box_diffs, score_diffs, ref_scores = [], [], []
    boundary = unmatched = ties = 0
    for qi in range(rb.shape[0]):
        if rs.shape[1] == 0:
            continue
        safe = rs[qi] > cut[qi] + score_tol  # (K,)
        boundary += int((~safe).sum())
        ties += int((safe & near_tie[qi]).sum())
        idx = np.flatnonzero(safe & ~near_tie[qi])
        if idx.size == 0:
            continue
        # (n, K) centre distance to every candidate of the same label
        dist = np.abs(gb[qi, None, :, :2] - rb[qi, idx, None, :2]).max(axis=-1).astype(np.float64)
        dist[gl[qi, None, :] != rl[qi, idx, None]] = np.inf
        j = np.argmin(dist, axis=1)  # (n,)
        ok = dist[np.arange(idx.size), j] <= centre_tol
        unmatched += int((~ok).sum())
        box_diffs.append(box_differences(gb[qi, j[ok]], rb[qi, idx[ok]], rl[qi, idx[ok]]))
        score_diffs.append(np.abs(gs[qi, j[ok]].astype(np.float64) - rs[qi, idx[ok]]))
        ref_scores.append(rs[qi, idx[ok]])
    cat = lambda xs: np.concatenate(xs).astype(np.float64) if xs else np.zeros(0)  # noqa: E731
    return DetectionMatch(np.concatenate(box_diffs) if box_diffs else np.zeros((0, BOX_DIM)), cat(score_diffs),
                          cat(ref_scores), boundary, unmatched, ties)  # fmt: skip


def _boundary_scores(scores: np.ndarray, first_left_out: np.ndarray | None) -> np.ndarray:
    """(Q,) float64 score each quadrant's detections must clear (by the tolerance) to be compared: the best one left
    out of the top K, or where that is not known (None) the K-th score."""
    q, k = scores.shape
    if first_left_out is None:
        return scores.astype(np.float64).min(axis=1) if k else np.full(q, -np.inf)
    cut = np.asarray(first_left_out)
    if cut.shape != (q,) or not np.issubdtype(cut.dtype, np.number):
        raise ValueError(f"first_left_out must hold one score per quadrant, shape ({q},), got {cut.dtype} {cut.shape}")
    if np.isnan(cut).any() or (cut == np.inf).any():
        raise ValueError(f"first_left_out must hold scores (or -inf where nothing was left out), got {cut.tolist()[:8]}")
    return cut.astype(np.float64)


def compare_detections(
    graph: str,
    precision: str,
    reference: str,
    got: Sequence[np.ndarray],
    ref: Sequence[np.ndarray],
    tol_rel: float,
    ref_margins: np.ndarray | None = None,
    scale_floor: float = 0.0,
    score_threshold: float = BOX_SCORE_THRESHOLD,
    first_left_out: np.ndarray | None = None,
) -> list[ParityRecord]:
    """Set-wise comparison of decoded top-K detections: one record per box column group (``det_boxes.centre``,
    ``.z``, ``.size``, ``.yaw``, ``.velocity``), then det_scores and det_labels, each against tol_rel x its scale.

    The box groups' scales come from the reference boxes with score >= ``score_threshold`` (``box_group_scales``;
    all reference boxes when none clears it, for the centre tolerance that pairs them), and their columns are
    compared on the matched detections above the threshold; the scores' scale is ``value_scale(reference scores,
    scale_floor)``. ``ref_margins`` (Q, K): the reference detections' peak margins (``detection_margins``); those
    within the score tolerance are near-ties, left out and counted. ``first_left_out`` (Q,): the reference's best
    score left out of each quadrant's top K (``match_detections``). A record that compared nothing holds NaN as its
    max |diff| and a note starting with ``NOT_COMPARED`` (module doc); non-finite values in the output fail every
    record, the note starting with ``NON_FINITE``.
    """
    rb, rs, rl = ref
    matter = rb[rs >= score_threshold]  # (n, 9)
    scales = box_group_scales(matter if len(matter) else rb, scale_floor)
    score_rng, score_scale = value_range(rs), value_scale(rs, scale_floor)
    score_tol = tol_rel * score_scale
    near_tie = None if ref_margins is None else np.abs(ref_margins) <= score_tol
    m = match_detections(got, ref, score_tol, tol_rel * scales["centre"], near_tie, first_left_out)
    total = int(rs.size)
    confident = m.ref_score >= score_threshold
    finite = all(bool(np.isfinite(x).all()) for x in got[:2])
    bad = "" if finite else f"{NON_FINITE}; "
    few = f"{FEW_COMPARED}: only {m.compared} of {total} detections; " if total and m.compared < MIN_COMPARED else ""
    note = (
        f"{few}{m.compared} of {total} detections compared as sets; {m.boundary} at the top-K boundary and {m.ties} "
        f"near-tie peaks (margin over a neighbour <= {score_tol:.3g}) not compared; {m.unmatched} without a partner"
    )
    box_note = (
        f"{note}; box columns compared on the {int(confident.sum())} of them with score >= {score_threshold:g}, scaled by "
        + (f"the {len(matter)} reference boxes there" if len(matter) else "all reference boxes (none above it)")
    )
    ok = finite and m.unmatched == 0
    group_diff = box_group_max(m.box_diff[confident])

    def record(output: str, diff: float, compared: int, rng: float, passed: bool, text: str, scale: float | None) -> ParityRecord:
        if not compared:  # a 0 would read as exact agreement
            diff, text = math.nan, f"{NOT_COMPARED}: {text}"
        return ParityRecord(graph, precision, reference, output, diff, rng, tol_rel, passed, bad + text, scale)

    records = []
    for name, cols in BOX_COLUMN_GROUPS:
        rng = value_range(matter[:, list(cols)]) if len(matter) else 0.0
        records.append(record(f"det_boxes.{name}", group_diff[name], int(confident.sum()), rng,
                              ok and group_diff[name] <= tol_rel * scales[name], box_note, scales[name]))  # fmt: skip
    sd = float(m.score_diff.max()) if m.compared else 0.0
    labels_rng = float(rl.max() - rl.min()) if rl.size else 0.0
    return records + [
        record("det_scores", sd, m.compared, score_rng, ok and sd <= score_tol, note, score_scale),
        record("det_labels", float(m.unmatched), m.compared + m.unmatched, labels_rng, ok,
               "labels must agree on every matched detection; max_abs_diff holds the unmatched count", None),
    ]


def pipeline_parity(
    fp32: Mapping[str, np.ndarray],
    fp16: Mapping[str, np.ndarray],
    *,
    slice_index: int,
    num_slices: int,
    num_points: int,
    num_pillars: int,
    cell_m: float,
    margins32: np.ndarray | None = None,
    margins16: np.ndarray | None = None,
    score_threshold: float = PIPELINE_SCORE_THRESHOLD,
    centre_tol_m: float = PIPELINE_CENTRE_TOL_M,
) -> PipelineParity:
    """fp16 pipeline against fp32 pipeline: decoded boxes with score >= threshold.

    ``fp32`` / ``fp16``: det_boxes (Q, K, 9), det_scores (Q, K), det_labels (Q, K) of the slice graph, each fed by
    its own precision's encoder and lifter. ``margins32`` / ``margins16`` (Q, K): each box's peak margin in the
    fp32 reference heatmap (``detection_margins``), None for no near-tie test.

    Boxes of the two runs are paired greedily by centre distance (``core.boxes.pair_boxes``: same quadrant and label,
    within two head cells, ``2 * cell_m``). Left out of the count, and counted instead: a pair or unpaired box whose score lies within the
    band ``FP16_TOL_REL * value_scale(fp32 scores, FP16_SCALE_FLOOR)`` of the threshold in either run (it may land on either side,
    ``excluded_in_band``); an unpaired box within the band of its run's K-th score (its partner may have dropped
    out of the other top K, ``excluded_at_top_k``); a pair or unpaired box whose peak margin is within the band
    (a near-tie, see the module doc, ``excluded_near_ties``). Every other box above the threshold must be paired
    with a box above the threshold in the other run, centres within ``centre_tol_m``: then both counts agree. The
    other box groups of those pairs (z, size, yaw modulo 2 pi, velocity) must agree within ``FP16_TOL_REL`` x their
    scale (``box_group_scales`` of the fp32 boxes above the threshold, floor ``FP16_SCALE_FLOOR``); PipelineParity
    has no field for them, so the note holds each group's max difference and tolerance. Fewer than
    ``MIN_COMPARED`` pairs compared: the note starts with a warning (module doc).
    """
    band = FP16_TOL_REL * value_scale(fp32["det_scores"], FP16_SCALE_FLOOR)
    pair_radius_m = 2.0 * cell_m
    runs = []
    for run, margins in ((fp32, margins32), (fp16, margins16)):
        s = run["det_scores"]
        q = np.broadcast_to(np.arange(s.shape[0])[:, None], s.shape)
        tie = np.zeros(s.shape, dtype=bool) if margins is None else np.abs(margins) <= band
        runs.append((run["det_boxes"].reshape(-1, 9).astype(np.float64), s.reshape(-1), run["det_labels"].reshape(-1),
                     q.reshape(-1), tie.reshape(-1)))
    (b32, s32, l32, q32, t32), (b16, s16, l16, q16, t16) = runs
    # Only boxes that may be above the threshold take part; a pair needs one of them.
    a32 = np.flatnonzero(s32 >= score_threshold - band)
    a16 = np.flatnonzero(s16 >= score_threshold - band)
    keys32 = np.stack([l32[a32], q32[a32]], axis=1)  # (n32, 2): a pair shares its label and its quadrant
    keys16 = np.stack([l16[a16], q16[a16]], axis=1)
    ia, ib, dist = pair_boxes(b32[a32], keys32, b16[a16], keys16, pair_radius_m)
    pair16 = np.full(a32.size, -1)  # position in a16 of each fp32 box's partner
    pair16[ia] = ib
    taken = np.zeros(a16.size, dtype=bool)
    taken[ib] = True
    pair_dist = np.full(a32.size, np.nan)  # centre distance to the partner
    pair_dist[ia] = dist

    def in_band(s: np.ndarray, around: np.ndarray | float) -> np.ndarray:
        return np.abs(s - around) <= band

    paired = pair16 >= 0
    i32, i16 = a32[paired], a16[pair16[paired]]
    ps32, ps16 = s32[i32], s16[i16]
    pair_tie = t32[i32] | t16[i16]
    pair_band = ~pair_tie & (in_band(ps32, score_threshold) | in_band(ps16, score_threshold))
    counted = ~pair_tie & ~pair_band
    pair_above = counted & (ps32 >= score_threshold) & (ps16 >= score_threshold)
    pair_split = counted & ((ps32 >= score_threshold) != (ps16 >= score_threshold))  # one above, one clearly below

    lone = []
    for idx, s, t, run in ((a32[~paired], s32, t32, fp32), (a16[~taken], s16, t16, fp16)):
        q = (q32 if run is fp32 else q16)[idx]
        kth = run["det_scores"].min(axis=1)[q] if idx.size else np.zeros(0)
        tie, band_thr = t[idx], in_band(s[idx], score_threshold)
        at_k = ~tie & ~band_thr & in_band(s[idx], kth)
        above = ~tie & ~band_thr & ~at_k & (s[idx] >= score_threshold)
        lone.append((tie, band_thr & ~tie, at_k, above))
    (lt32, lb32, lk32, la32), (lt16, lb16, lk16, la16) = lone

    excluded_ties = int(pair_tie.sum() + lt32.sum() + lt16.sum())
    excluded_band = int(pair_band.sum() + lb32.sum() + lb16.sum())
    excluded_top_k = int(lk32.sum() + lk16.sum())
    count32 = int(pair_above.sum() + (pair_split & (ps32 >= score_threshold)).sum() + la32.sum())
    count16 = int(pair_above.sum() + (pair_split & (ps16 >= score_threshold)).sum() + la16.sum())
    centre = pair_dist[paired][pair_above]
    max_d = float(centre.max()) if centre.size else math.nan
    # the other columns of the pairs counted above the threshold, each group against its own tolerance
    scales = box_group_scales(b32[s32 >= score_threshold], FP16_SCALE_FLOOR)
    group_diff = box_group_max(box_differences(b16[i16[pair_above]], b32[i32[pair_above]], l32[i32[pair_above]]))
    groups = [name for name, _ in BOX_COLUMN_GROUPS if name != "centre"]
    groups_ok = all(group_diff[g] <= FP16_TOL_REL * scales[g] for g in groups)
    passed = bool(
        count32 == count16 and not pair_split.any() and not la32.any() and not la16.any()
        and (centre.size == 0 or max_d <= centre_tol_m) and groups_ok
    )
    compared = int(pair_above.sum())
    few = f"{FEW_COMPARED}: only {compared} boxes above the threshold compared; " if compared < MIN_COMPARED else ""
    note = (
        f"{few}band = {FP16_TOL_REL:g} x fp32 score scale = {band:.3g}; {compared} boxes above in both runs; "
        f"{int(pair_split.sum())} pairs split by the threshold, {int(la32.sum())} fp32 and {int(la16.sum())} fp16 "
        f"boxes above it without a partner within {pair_radius_m:g} m; max diff of the pairs above: "
        + ", ".join(f"{g} {group_diff[g]:.3g} (tolerance {FP16_TOL_REL * scales[g]:.3g})" for g in groups)
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
        excluded_in_band=excluded_band,
        excluded_at_top_k=excluded_top_k,
        excluded_near_ties=excluded_ties,
        max_centre_diff_m=max_d,
        centre_tolerance_m=centre_tol_m,
        passed=passed,
        note=note,
    )
