"""nuScenes detection metrics, computed as nuscenes-devkit 1.2.0 computes them.

The devkit's ``filter_eval_boxes`` (``eval/common/loaders.py``), ``accumulate`` / ``calc_ap`` / ``calc_tp``
(``eval/detection/algo.py``), the pairwise box measures (``eval/common/utils.py``) and ``DetectionEval``'s
summary, rewritten over arrays. Everything that decides a figure is kept exactly: the score sort (descending,
ties broken by *later* box first), greedy matching per sample on the xy centre distance (strict ``<`` for
both the nearest ground truth, so the first of equally near boxes wins, and the threshold), the
101-point precision curve by ``np.interp(..., right=0)``, the confidence-aligned cumulative means of the
TP errors, and the recall / precision clipping. The per-sample greedy loop runs only over predictions
that have some ground truth within the threshold: the others can never match.

The floating-point routes are the devkit's too, so that a distance that lands on a threshold, or two equally near
boxes, fall on the devkit's side: distances and velocity errors go through the BLAS dot product that the devkit's
``np.linalg.norm`` of a 1-D vector calls, and yaws through pyquaternion's rotation matrix (normalisation by
``np.dot``, the 4x4 matrix product, the product with the x axis), batched (``_dot_last``, ``_rotation_matrix``).
A closed form (``sqrt(dx*dx + dy*dy)``, ``atan2`` of the quaternion) differs from those in the last bit for some
inputs, which flips a match at an exact tie.

Differences from the devkit, on purpose:

- The bike-rack rule (bicycles and motorcycles whose centre lies in a ``static_object.bicycle_rack``
  annotation are not evaluated) needs those rack annotations, which results files do not carry; it is
  applied when ``bike_racks`` is given (dataset mode passes the dataset's racks, files mode those of a
  ground-truth file's ``bike_racks``), otherwise skipped.
- The attribute error needs GT ``attribute_name``; GT without attributes gives ``attr_err`` 1 for every
  class (the devkit's value for that case).
- Inputs are validated up front (sizes > 0 for every box, not only matched ones; unknown names rejected).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from streamdet.evaluation.config import TP_METRICS, UNDEFINED_TP_METRICS, DetectionConfig
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.metrics import NUM_RECALL_POINTS, DetectionMetricData, DetectionMetrics

# ---- pairwise box measures (devkit eval/common/utils.py), vectorised over rows --------------------


def center_distance(gt_xy: np.ndarray, pred_xy: np.ndarray) -> np.ndarray:
    """xy distance between box centres, m; broadcasts (..., 2) against (..., 2). Bit for bit the devkit's
    ``np.linalg.norm(pred - gt)``."""
    d = np.asarray(pred_xy, dtype=np.float64) - np.asarray(gt_xy, dtype=np.float64)
    return np.sqrt(_dot_last(d, d))


def velocity_l2(gt_v: np.ndarray, pred_v: np.ndarray) -> np.ndarray:
    """L2 norm of the velocity difference, m/s (NaN where the ground truth has no velocity)."""
    return center_distance(gt_v, pred_v)


def scale_iou(gt_size: np.ndarray, pred_size: np.ndarray) -> np.ndarray:
    """3D IoU of the two boxes aligned (same centre and orientation), from their (w, l, h)."""
    inter = np.minimum(gt_size, pred_size)
    inter_vol = inter[..., 0] * inter[..., 1] * inter[..., 2]
    gt_vol = gt_size[..., 0] * gt_size[..., 1] * gt_size[..., 2]
    pred_vol = pred_size[..., 0] * pred_size[..., 1] * pred_size[..., 2]
    return inter_vol / (gt_vol + pred_vol - inter_vol)


def quaternion_yaw(q_wxyz: np.ndarray) -> np.ndarray:
    """Heading about global z: the box x axis rotated by q, projected onto the xy plane (the devkit's
    ``quaternion_yaw``: ``np.dot(Quaternion(q).rotation_matrix, [1, 0, 0])``, then ``arctan2``)."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    flat = q.reshape(-1, 4)
    yaw = np.empty(len(flat))
    for i in range(0, len(flat), _YAW_CHUNK):
        x_axis = _rotation_matrix(flat[i : i + _YAW_CHUNK]) @ np.array([1.0, 0.0, 0.0])  # the matrix-vector product
        yaw[i : i + _YAW_CHUNK] = np.arctan2(x_axis[:, 1], x_axis[:, 0])
    return yaw.reshape(q.shape[:-1])


# Quaternions per pass of quaternion_yaw: the (n, 4, 4) temporaries of a whole set of matches at once outgrow the
# caches, and a single pass then costs several times the chunked ones.
_YAW_CHUNK = 1 << 14


def yaw_diff(gt_q: np.ndarray, pred_q: np.ndarray, period: float = 2 * np.pi) -> np.ndarray:
    """Absolute yaw difference in [0, pi], modulo ``period`` (pi for barriers, whose front is ambiguous)."""
    diff = np.mod(quaternion_yaw(gt_q) - quaternion_yaw(pred_q) + period / 2, period) - period / 2
    diff = np.where(diff > np.pi, diff - 2 * np.pi, diff)
    return np.abs(diff)


def attr_acc(gt_attr: np.ndarray, pred_attr: np.ndarray) -> np.ndarray:
    """1 where the attributes agree, 0 where not, NaN where the ground truth has none (ignored later)."""
    return np.where(gt_attr == "", np.nan, (gt_attr == pred_attr).astype(np.float64))


def cummean(x: np.ndarray) -> np.ndarray:
    """NaN-ignoring running mean; all-NaN input gives ones (an undefined error counts as the worst)."""
    if np.all(np.isnan(x)):
        return np.ones(len(x))
    sums = np.nancumsum(x.astype(float))
    counts = np.cumsum(~np.isnan(x))
    return np.divide(sums, counts, out=np.zeros_like(sums), where=counts != 0)


def _dot_last(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product over the last axis, one BLAS dot per row.

    A stacked (1, n) @ (n, 1) product is the BLAS routine that ``np.dot`` of two 1-D vectors calls (and so
    ``np.linalg.norm``, and pyquaternion's sum of squares). An elementwise ``sum(a * b)`` rounds differently (the
    BLAS kernel fuses multiply and add), so it would not give the devkit's last bit."""
    return (a[..., None, :] @ b[..., :, None])[..., 0, 0]


def _normalised(q: np.ndarray) -> np.ndarray:
    # pyquaternion normalises only quaternions off unit length by 1e-14 or more, by its norm sqrt(np.dot(q, q)):
    # the same test and division, for the same rounding.
    q = np.asarray(q, dtype=np.float64)
    sq = _dot_last(q, q)[..., None]
    return np.where(np.abs(1.0 - sq) < 1e-14, q, q / np.sqrt(sq))


def _rotation_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation of quaternions (normalised here) by pyquaternion's route: the 4x4 product
    ``Q @ Qbar^T``, lower-right 3x3 block. A closed form of the entries rounds differently in the last bit."""
    q = _normalised(q_wxyz)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    q_matrix = np.stack([np.stack(row, axis=-1) for row in
                         ([w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w])], axis=-2)  # fmt: skip
    q_bar = np.stack([np.stack(row, axis=-1) for row in
                      ([w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w])], axis=-2)  # fmt: skip
    # Q_bar transposed as a view, as pyquaternion's .conj().transpose(): the same BLAS product (B transposed).
    return (q_matrix @ np.swapaxes(q_bar, -1, -2))[..., 1:, 1:]


# ---- filtering (devkit eval/common/loaders.py filter_eval_boxes) --------------------------------


def points_in_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(P, B) bool: point p lies in box b, boundary included (devkit ``points_in_box`` via box corners).

    points: (P, 3); boxes: (B, 10) rows of translation (3), size w, l, h (3), rotation w, x, y, z (4).
    """
    signs = np.array(
        [[1, 1, 1, 1, -1, -1, -1, -1], [1, -1, -1, 1, 1, -1, -1, 1], [1, 1, -1, -1, 1, 1, -1, -1]], dtype=np.float64
    )  # (3, 8) corner pattern of the devkit's Box.corners: x along l, y along w, z along h
    half = np.stack([boxes[:, 4], boxes[:, 3], boxes[:, 5]], axis=-1)[:, :, None] / 2  # (B, 3, 1) l, w, h
    corners = _rotation_matrix(boxes[:, 6:10]) @ (half * signs) + boxes[:, 0:3, None]  # (B, 3, 8)
    p1 = corners[:, :, 0]  # (B, 3)
    axes = np.stack([corners[:, :, 4], corners[:, :, 1], corners[:, :, 3]], axis=1) - p1[:, None, :]  # (B, 3 axes, 3)
    rel = points[:, None, :] - p1[None, :, :]  # (P, B, 3)
    # np.dot of an axis with a point and with itself, as the devkit's points_in_box: the same BLAS dot
    proj = np.stack([_dot_last(rel, axes[None, :, a, :]) for a in range(3)], axis=-1)  # (P, B, 3 axes)
    extent = _dot_last(axes, axes)  # (B, 3 axes)
    return np.all((proj >= 0) & (proj <= extent[None]), axis=-1)


def filter_eval_boxes(
    boxes: EvalBoxes,
    class_range_m: Mapping[str, float],
    bike_racks: Mapping[str, np.ndarray] | None = None,
) -> EvalBoxes:
    """Drop boxes beyond their class range, boxes with no points (``num_pts == 0``) and, where ``bike_racks``
    ({sample_token: (R, 10) rack boxes, global frame, rows as in ``points_in_boxes``}) is given, bicycles and
    motorcycles standing in a rack."""
    names, name_index = np.unique(boxes.detection_name, return_inverse=True)
    unknown = [str(n) for n in names if n not in class_range_m]
    if unknown:
        raise ValueError(f"no class range for detection_name {unknown[0]!r} (class_range_m has {list(class_range_m)})")
    max_dist = np.array([class_range_m[str(n)] for n in names], dtype=np.float64)[name_index.reshape(-1)]
    keep = (boxes.ego_dist < max_dist) & (boxes.num_pts != 0)
    if bike_racks:
        for token, racks in bike_racks.items():
            racks = np.asarray(racks, dtype=np.float64)
            if racks.ndim != 2 or racks.shape[1] != 10:
                raise ValueError(f"bike_racks[{token!r}] must have shape (R, 10), got {racks.shape}")
        cycles = np.flatnonzero(np.isin(boxes.detection_name, ("bicycle", "motorcycle")))
        for s in np.unique(boxes.sample_index[cycles]).tolist():
            racks = np.asarray(bike_racks.get(boxes.sample_tokens[s], np.zeros((0, 10))), dtype=np.float64)
            rows = cycles[boxes.sample_index[cycles] == s]
            if len(racks):
                keep[rows] &= ~points_in_boxes(boxes.translation[rows], racks).any(axis=1)
    return boxes.select(keep)


# ---- accumulate / calc_ap / calc_tp (devkit eval/detection/algo.py) -----------------------------


def score_order(scores: np.ndarray) -> np.ndarray:
    """Indices of the predictions in the devkit's order: descending score, equal scores the later box first (the
    devkit reverses an ascending (score, index) sort)."""
    return np.lexsort((np.arange(len(scores)), scores))[::-1]


def greedy_match(gt: EvalBoxes, pred: EvalBoxes, order: np.ndarray, dist_th_m: float) -> np.ndarray:
    """GT row matched by each prediction taken in ``order`` (-1 = none), the devkit's greedy loop per sample."""
    matched = np.full(len(order), -1, dtype=np.int64)
    if len(order) == 0 or len(gt) == 0:
        return matched
    # Samples are matched by token: the two box sets may list their samples in different orders.
    gt_rank = {t: i for i, t in enumerate(gt.sample_tokens)}
    pred_to_gt = np.array([gt_rank.get(t, -1) for t in pred.sample_tokens], dtype=np.int64)
    ordered_sample = pred_to_gt[pred.sample_index[order]]
    by_sample = np.argsort(ordered_sample, kind="stable")  # positions in `order`, grouped by sample, order kept
    grouped = ordered_sample[by_sample]
    starts = np.flatnonzero(np.r_[True, grouped[1:] != grouped[:-1]])
    ends = np.r_[starts[1:], len(grouped)]
    gt_lo = np.searchsorted(gt.sample_index, grouped[starts], side="left")
    gt_hi = np.searchsorted(gt.sample_index, grouped[starts], side="right")
    for p0, p1, g0, g1 in zip(starts.tolist(), ends.tolist(), gt_lo.tolist(), gt_hi.tolist()):
        if g0 == g1:
            continue
        positions = by_sample[p0:p1]
        dist = center_distance(gt.translation[None, g0:g1, :2], pred.translation[order[positions], None, :2])  # (p, g)
        # A prediction with no ground truth within the threshold is a false positive whatever was taken before.
        candidates = np.flatnonzero(np.any(dist < dist_th_m, axis=1))
        rows = dist[candidates].tolist()  # plain floats: the loop is sequential and its rows are short
        taken = [False] * (g1 - g0)
        for r, row in zip(candidates.tolist(), rows):
            best, j_best = math.inf, -1
            for j, d in enumerate(row):
                if d < best and not taken[j]:  # strict '<': the first of equally near boxes wins, as in the devkit
                    best, j_best = d, j
            if best < dist_th_m:
                taken[j_best] = True
                matched[positions[r]] = g0 + j_best
    return matched


def tp_errors(gt: EvalBoxes, pred: EvalBoxes, g: np.ndarray, p: np.ndarray, class_name: str) -> dict[str, np.ndarray]:
    """The five TP errors of the matched pairs (ground-truth row ``g[i]``, prediction row ``p[i]``), the devkit's
    definitions: one place for ``accumulate`` and the bootstrap, so the two cannot drift apart."""
    period = np.pi if class_name == "barrier" else 2 * np.pi  # a barrier's front is ambiguous
    return {
        "trans_err": center_distance(gt.translation[g, :2], pred.translation[p, :2]),
        "vel_err": velocity_l2(gt.velocity[g], pred.velocity[p]),
        "scale_err": 1 - scale_iou(gt.size[g], pred.size[p]),
        "orient_err": yaw_diff(gt.rotation[g], pred.rotation[p], period=period),
        "attr_err": 1 - attr_acc(gt.attribute_name[g], pred.attribute_name[p]),
    }


def metric_curves(is_tp: np.ndarray, conf: np.ndarray, npos: float, errors: Mapping[str, np.ndarray]) -> DetectionMetricData:
    """``accumulate``'s 101-point curves from the predictions in score order: ``is_tp`` (P,) their outcome, ``conf``
    (P,) their scores, ``npos`` the ground-truth count, ``errors`` each TP metric's (T,) errors of the true
    positives in that order. No ground truth or no true positive: ``DetectionMetricData.no_predictions()``."""
    if npos == 0 or not np.any(is_tp):
        return DetectionMetricData.no_predictions()
    tp = np.cumsum(is_tp).astype(float)
    fp = np.cumsum(~is_tp).astype(float)
    prec = tp / (fp + tp)
    rec = tp / float(npos)

    rec_interp = np.linspace(0, 1, NUM_RECALL_POINTS)
    prec = np.interp(rec_interp, rec, prec, right=0)
    conf_interp = np.interp(rec_interp, rec, conf, right=0)

    match_conf = conf[is_tp]
    # Each TP error at an operating point is the running mean over the matches of at least that confidence;
    # np.interp needs increasing x, hence the reversals.
    resampled = {
        key: np.interp(conf_interp[::-1], match_conf[::-1], cummean(errors[key])[::-1])[::-1] for key in TP_METRICS
    }
    return DetectionMetricData(recall=rec_interp, precision=prec, confidence=conf_interp, **resampled)


def accumulate(gt: EvalBoxes, pred: EvalBoxes, class_name: str, dist_th_m: float) -> DetectionMetricData:
    """Match the predictions of ``class_name`` to the ground truth at ``dist_th_m`` and build the 101-point curves."""
    gt = gt.select(gt.detection_name == class_name)
    npos = len(gt)
    if npos == 0:
        return DetectionMetricData.no_predictions()
    pred = pred.select(pred.detection_name == class_name)
    order = score_order(pred.detection_score)
    matched = greedy_match(gt, pred, order, dist_th_m)
    is_tp = matched >= 0
    if not np.any(is_tp):
        return DetectionMetricData.no_predictions()
    errors = tp_errors(gt, pred, matched[is_tp], order[is_tp], class_name)  # matched pairs, in score order
    return metric_curves(is_tp, pred.detection_score[order], npos, errors)


def calc_ap(md: DetectionMetricData, min_recall: float, min_precision: float) -> float:
    """Mean precision over the recall points above ``min_recall``, precision clipped at ``min_precision``, in [0, 1]."""
    if not (0 <= min_precision < 1 and 0 <= min_recall <= 1):
        raise ValueError(f"calc_ap needs 0 <= min_precision < 1 and 0 <= min_recall <= 1, got {min_precision}, {min_recall}")
    prec = np.copy(md.precision)[round(100 * min_recall) + 1 :] - min_precision
    prec[prec < 0] = 0
    return float(np.mean(prec)) / (1.0 - min_precision)


def calc_tp(md: DetectionMetricData, min_recall: float, metric_name: str) -> float:
    """Mean of a TP error over the recall points above ``min_recall`` up to the highest recall reached (1 if none)."""
    if metric_name not in TP_METRICS:
        raise ValueError(f"metric_name must be one of {TP_METRICS}, got {metric_name!r}")
    first = round(100 * min_recall) + 1
    last = md.max_recall_ind
    if last < first:
        return 1.0
    return float(np.mean(getattr(md, metric_name)[first : last + 1]))


# ---- the whole evaluation (devkit DetectionEval.evaluate) ---------------------------------------


def check_prediction_samples(gt: EvalBoxes, pred: EvalBoxes, config: DetectionConfig = DetectionConfig()) -> None:
    """The devkit's two checks of a submission against its ground truth (ValueError): the predictions cover exactly
    the ground-truth samples, with at most ``config.max_boxes_per_sample`` boxes each. ``evaluate`` makes them; a
    reader of files makes them too, to name the files."""
    if set(gt.sample_tokens) != set(pred.sample_tokens):
        only_gt = sorted(set(gt.sample_tokens) - set(pred.sample_tokens))
        only_pred = sorted(set(pred.sample_tokens) - set(gt.sample_tokens))
        raise ValueError(
            "predictions must cover exactly the ground-truth samples: "
            f"{len(only_gt)} only in the ground truth (e.g. {only_gt[:1]}), {len(only_pred)} only in the predictions (e.g. {only_pred[:1]})"
        )
    counts = np.bincount(pred.sample_index, minlength=len(pred.sample_tokens))
    if len(counts) and counts.max() > config.max_boxes_per_sample:
        worst = int(np.argmax(counts))
        raise ValueError(
            f"sample {pred.sample_tokens[worst]!r} has {counts[worst]} predictions, more than "
            f"max_boxes_per_sample={config.max_boxes_per_sample}"
        )


def evaluate(
    gt: EvalBoxes,
    pred: EvalBoxes,
    config: DetectionConfig = DetectionConfig(),
    classes: Iterable[str] | None = None,
    bike_racks: Mapping[str, np.ndarray] | None = None,
    filter_boxes: bool = True,
) -> DetectionMetrics:
    """Per-class AP and TP errors, mAP and NDS of ``pred`` against ``gt`` (both in the global frame).

    ``classes`` restricts the classes evaluated and averaged (default: all of ``config``). Like the devkit,
    the predictions must cover exactly the ground-truth samples (an empty list for a sample without
    detections) with at most ``config.max_boxes_per_sample`` boxes each. ``bike_racks`` ({sample_token: (R, 10)
    rack boxes, global frame}, see ``filter_eval_boxes``) applies the devkit's bike-rack rule; without it the rule is
    skipped. ``filter_boxes=False`` skips ``filter_eval_boxes`` for inputs already filtered.
    """
    check_prediction_samples(gt, pred, config)
    classes = config.class_names if classes is None else ordered_classes(classes, config)
    if filter_boxes:
        gt = filter_eval_boxes(gt, config.class_range_m, bike_racks)
        pred = filter_eval_boxes(pred, config.class_range_m, bike_racks)

    metric_data = {}
    for c in classes:
        gt_c, pred_c = gt.select(gt.detection_name == c), pred.select(pred.detection_name == c)  # split once per class
        metric_data.update({(c, th): accumulate(gt_c, pred_c, c, th) for th in config.dist_ths_m})
    return detection_metrics(metric_data, classes, config)


def detection_metrics(
    metric_data: Mapping[tuple[str, float], DetectionMetricData], classes: Sequence[str], config: DetectionConfig
) -> DetectionMetrics:
    """``DetectionEval``'s summary of the curves of each (class, threshold): AP per class and threshold, the TP
    errors at ``config.dist_th_tp_m`` (NaN where the devkit leaves one undefined for the class)."""
    label_aps = {
        c: {th: calc_ap(metric_data[c, th], config.min_recall, config.min_precision) for th in config.dist_ths_m}
        for c in classes
    }
    label_tp_errors = {
        c: {
            m: math.nan
            if m in UNDEFINED_TP_METRICS.get(c, ())
            else calc_tp(metric_data[c, config.dist_th_tp_m], config.min_recall, m)
            for m in TP_METRICS
        }
        for c in classes
    }
    return DetectionMetrics(config=config, classes=tuple(classes), label_aps=label_aps, label_tp_errors=label_tp_errors,
                            metric_data=dict(metric_data))  # fmt: skip


def ordered_classes(classes: Iterable[str], config: DetectionConfig) -> tuple[str, ...]:
    """``classes`` in the config's (the devkit's) order; ValueError for an empty list or an unknown name."""
    wanted = list(classes)
    unknown = [c for c in wanted if c not in config.class_range_m]
    if unknown or not wanted:
        raise ValueError(f"classes must be a non-empty subset of {config.class_names}, got {wanted}")
    return tuple(c for c in config.class_names if c in wanted)
