"""streamdet boxes <-> nuScenes results JSON: frame conversion, submission files, ground-truth files.

streamdet boxes are ``(N, 9)`` rows of ``streamdet.core.boxes`` in the LiDAR frame of a sweep with
labels indexing ``CLASS_NAMES``; a results entry is a box in the nuScenes global frame (see
``eval_boxes``). ``lidar2ego`` and ``ego2global`` are 4x4 ``[[R, t], [0, 1]]`` matrices mapping points from
the first frame to the second (``data/nuscenes_sample/calibration.json``: ``lidar.sensor2ego.matrix`` and
``lidar.ego2global.matrix``).

Lidar to global, as mmdetection3d formats nuScenes submissions: the centre and the box rotation
``Rz(yaw)`` go through ``ego2global @ lidar2ego`` (so the global quaternion carries the LiDAR's small tilt),
and the velocity ``(vx, vy, 0)`` is rotated and its global xy kept. Global to lidar inverts this exactly:
yaw is the heading of the rotated box x axis, and the lidar ``(vx, vy)`` solves the 2x2 system whose
forward map gave the global xy velocity, so lidar -> global -> lidar is the identity up to rounding.

Files: ``{"meta": {...}, "results": {sample_token: [entry, ...]}}`` (the official submission format);
a ground-truth file has the same layout, its entries carrying ``ego_translation`` and ``num_pts``, plus an
optional ``"ego_positions": {sample_token: [x, y, z]}`` (ego position at the sample's LiDAR time, global),
which the evaluation needs for samples without any ground-truth box, and an optional
``"bike_racks": {sample_token: [[x, y, z, w, l, h, qw, qx, qy, qz], ...]}`` (the sample's
``static_object.bicycle_rack`` annotations, global frame), with which the evaluation applies the devkit's bike-rack
rule; a sample not listed has no rack, and a file without the key (one written before racks were saved) skips the
rule. NaN velocities are written as null.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from streamdet.core.boxes import BOX_DIM, VX, VY, YAW
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.file_output import atomic_write_file
from streamdet.core.json_input import is_finite_number, read_json, short_repr
from streamdet.core.rotations import matrix_to_quaternion, quaternion_to_matrix
from streamdet.evaluation.detection_eval import check_prediction_samples
from streamdet.evaluation.eval_boxes import EvalBoxes

META_KEYS = ("use_camera", "use_lidar", "use_radar", "use_map", "use_external")
# The largest results or ground-truth file read. The devkit's cap of 500 boxes per sample over the 6019 samples
# of nuScenes val (or the 6008 of test) is about 1.2 GiB of JSON as written here (~420 bytes a box); a larger
# file is not a submission, and it (or /dev/zero) is refused before it is read whole.
MAX_RESULTS_BYTES = 2 << 30

# Speed (m/s) above which mmdetection3d labels a vehicle moving / a cycle ridden, when a model has no attribute head.
_MOVING_SPEED_MPS = 0.2
_VEHICLES = ("car", "construction_vehicle", "bus", "truck", "trailer")


# ---- geometry -----------------------------------------------------------------------------------


def _check_transform(m: np.ndarray, name: str) -> np.ndarray:
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"{name} must be a finite 4x4 matrix, got shape {m.shape}")
    if not np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-5) or not np.allclose(m[3], [0, 0, 0, 1]):
        raise ValueError(f"{name} must be a rigid transform [[R, t], [0, 0, 0, 1]] with R a rotation, got {m.tolist()}")
    return m


def lidar_to_global(
    boxes: np.ndarray, lidar2ego: np.ndarray, ego2global: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(N, 9) LiDAR-frame boxes -> global translation (N, 3), size w, l, h (N, 3), rotation wxyz (N, 4), velocity (N, 2)."""
    boxes = _check_boxes(boxes)
    t = _check_transform(ego2global, "ego2global") @ _check_transform(lidar2ego, "lidar2ego")
    rot, trans = t[:3, :3], t[:3, 3]
    c, s = np.cos(boxes[:, YAW]), np.sin(boxes[:, YAW])
    zeros, ones = np.zeros_like(c), np.ones_like(c)
    rz = np.stack([np.stack([c, -s, zeros], -1), np.stack([s, c, zeros], -1), np.stack([zeros, zeros, ones], -1)], -2)  # (N, 3, 3)
    translation = boxes[:, 0:3] @ rot.T + trans
    rotation = matrix_to_quaternion(_nearest_rotation(rot) @ rz)
    vel_lidar = np.concatenate([boxes[:, [VX, VY]], zeros[:, None]], axis=1)  # (N, 3)
    velocity = (vel_lidar @ rot.T)[:, :2]
    return translation, boxes[:, 3:6].copy(), rotation, velocity


def global_to_lidar(
    translation: np.ndarray,
    size: np.ndarray,
    rotation: np.ndarray,
    velocity: np.ndarray,
    lidar2ego: np.ndarray,
    ego2global: np.ndarray,
) -> np.ndarray:
    """Global boxes -> (N, 9) LiDAR-frame boxes (pitch and roll relative to the LiDAR are dropped)."""
    t = _check_transform(ego2global, "ego2global") @ _check_transform(lidar2ego, "lidar2ego")
    rot, trans = t[:3, :3], t[:3, 3]
    translation = np.asarray(translation, dtype=np.float64).reshape(-1, 3)
    n = len(translation)
    rotation = np.asarray(rotation, dtype=np.float64).reshape(n, 4)
    velocity = np.asarray(velocity, dtype=np.float64).reshape(n, 2)
    # The exact inverse, not R^T: calibration matrices stored in float32 are orthonormal only to ~1e-7.
    inv_rot = np.linalg.inv(rot)
    heading = _nearest_rotation(rot).T @ quaternion_to_matrix(rotation)[:, :, 0].T  # (3, N): box x axis, lidar frame
    out = np.empty((n, BOX_DIM), dtype=np.float64)
    out[:, 0:3] = (translation - trans) @ inv_rot.T
    out[:, 3:6] = np.asarray(size, dtype=np.float64).reshape(n, 3)
    out[:, YAW] = np.arctan2(heading[1], heading[0])
    out[:, [VX, VY]] = np.linalg.solve(rot[:2, :2], velocity.T).T  # inverse of "rotate (vx, vy, 0), keep xy"
    return out


def _nearest_rotation(rot: np.ndarray) -> np.ndarray:
    """The rotation closest to ``rot`` (polar decomposition): box orientations need an exactly orthonormal R."""
    u, _, vt = np.linalg.svd(rot)
    return u @ vt


def _check_boxes(boxes: np.ndarray) -> np.ndarray:
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != BOX_DIM:
        raise ValueError(f"boxes must have shape (N, {BOX_DIM}), got {boxes.shape}")
    if not np.all(np.isfinite(boxes[:, :7])):
        raise ValueError("boxes must have finite centre, size and yaw (columns 0..6)")
    return boxes


def _check_labels(labels: np.ndarray, n: int) -> np.ndarray:
    labels = np.asarray(labels)
    if labels.shape != (n,) or not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"labels must be ({n},) integers, got shape {labels.shape} dtype {labels.dtype}")
    bad = (labels < 0) | (labels >= len(CLASS_NAMES))
    if np.any(bad):
        raise ValueError(f"labels must index CLASS_NAMES (0..{len(CLASS_NAMES) - 1}), got {labels[bad][0]}")
    return labels


def default_attribute(name: str, velocity_xy: Sequence[float]) -> str:
    """mmdetection3d's attribute for a model without an attribute head, from class and speed."""
    speed = math.hypot(velocity_xy[0], velocity_xy[1])
    if speed > _MOVING_SPEED_MPS:
        if name in _VEHICLES:
            return "vehicle.moving"
        if name in ("bicycle", "motorcycle"):
            return "cycle.with_rider"
        return "pedestrian.moving" if name == "pedestrian" else ""
    if name == "pedestrian":
        return "pedestrian.standing"
    if name == "bus":
        return "vehicle.stopped"
    if name in _VEHICLES:
        return "vehicle.parked"
    return "cycle.without_rider" if name in ("bicycle", "motorcycle") else ""


# ---- entries ------------------------------------------------------------------------------------


def boxes_to_results(
    sample_token: str,
    boxes: np.ndarray,
    scores: np.ndarray,
    labels: np.ndarray,
    lidar2ego: np.ndarray,
    ego2global: np.ndarray,
    attribute_names: Sequence[str] | None = None,
) -> list[dict]:
    """Detections of one sample (LiDAR frame) -> results entries (global frame).

    ``attribute_names`` (N,) defaults to ``default_attribute`` of each box's class and global speed.
    """
    boxes = _check_boxes(boxes)
    n = len(boxes)
    scores = np.asarray(scores, dtype=np.float64)
    if scores.shape != (n,) or not np.all(np.isfinite(scores)):
        raise ValueError(f"scores must be ({n},) finite numbers, got shape {scores.shape}")
    labels = _check_labels(labels, n)
    translation, size, rotation, velocity = lidar_to_global(boxes, lidar2ego, ego2global)
    names = [CLASS_NAMES[i] for i in labels.tolist()]
    if attribute_names is None:
        attribute_names = [default_attribute(nm, v) for nm, v in zip(names, velocity.tolist())]
    elif len(attribute_names) != n:
        raise ValueError(f"attribute_names must have {n} entries, got {len(attribute_names)}")
    return [
        {
            "sample_token": sample_token,
            "translation": translation[i].tolist(),
            "size": size[i].tolist(),
            "rotation": rotation[i].tolist(),
            "velocity": velocity[i].tolist(),
            "detection_name": names[i],
            "detection_score": float(scores[i]),
            "attribute_name": attribute_names[i],
        }
        for i in range(n)
    ]


def boxes_to_gt(
    sample_token: str,
    boxes: np.ndarray,
    labels: np.ndarray,
    num_pts: np.ndarray,
    lidar2ego: np.ndarray,
    ego2global: np.ndarray,
    attribute_names: Sequence[str] | None = None,
) -> list[dict]:
    """Ground truth of one sample (LiDAR frame) -> entries with ``ego_translation`` and ``num_pts``.

    ``ego_translation`` is the global centre minus the ego position (``ego2global`` translation), global axes,
    as the devkit's ``add_center_dist``; ``num_pts`` counts LiDAR + radar points (0 = not evaluated).
    ``attribute_names`` default to "" (none: the attribute error is then undefined).
    """
    n = len(_check_boxes(boxes))
    num_pts = np.asarray(num_pts)
    if num_pts.shape != (n,) or not np.issubdtype(num_pts.dtype, np.integer):
        raise ValueError(f"num_pts must be ({n},) integers, got shape {num_pts.shape} dtype {num_pts.dtype}")
    entries = boxes_to_results(
        sample_token, boxes, np.full(n, -1.0), labels, lidar2ego, ego2global,
        attribute_names=[""] * n if attribute_names is None else attribute_names,
    )  # fmt: skip
    ego = _check_transform(ego2global, "ego2global")[:3, 3]
    for entry, pts in zip(entries, num_pts.tolist()):
        entry["ego_translation"] = (np.asarray(entry["translation"]) - ego).tolist()
        entry["num_pts"] = int(pts)
    return entries


def results_to_boxes(
    entries: Sequence[Mapping], lidar2ego: np.ndarray, ego2global: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Results entries of one sample -> (boxes (N, 9) LiDAR frame, scores (N,) float32, labels (N,) int64)."""
    tokens = {e.get("sample_token") for e in entries if isinstance(e, Mapping)}
    if len(tokens) > 1:
        raise ValueError(f"results_to_boxes takes the entries of one sample, got sample tokens {sorted(map(str, tokens))}")
    token = tokens.pop() if tokens else ""
    parsed = EvalBoxes.from_results({token: list(entries)}, source="entries")
    boxes = global_to_lidar(parsed.translation, parsed.size, parsed.rotation, parsed.velocity, lidar2ego, ego2global)
    labels = np.array([CLASS_NAMES.index(str(n)) for n in parsed.detection_name], dtype=np.int64)
    return boxes, parsed.detection_score.astype(np.float32), labels


# ---- files --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ResultsFile:
    """A results (or ground-truth) JSON file as read: entries are checked later, by ``EvalBoxes.from_results``."""

    results: dict[str, list]
    meta: dict = field(default_factory=dict)
    ego_positions: dict[str, list[float]] = field(default_factory=dict)
    bike_racks: dict[str, np.ndarray] | None = None  # {sample_token: (R, 10)}; None: the file has no bike_racks
    has_meta: bool = True  # the file has a 'meta' object (a submission must: ``check_submission``)


def write_results_json(
    path: str | os.PathLike,
    results_by_sample: Mapping[str, Sequence[Mapping]],
    meta: Mapping,
    ego_positions: Mapping[str, Sequence[float]] | None = None,
    bike_racks: Mapping[str, np.ndarray | Sequence[Sequence[float]]] | None = None,
) -> None:
    """Write a submission ``{"meta", "results"}`` (plus ``ego_positions`` and ``bike_racks`` for ground truth),
    atomically.

    ``meta`` needs ``use_camera`` and ``use_lidar``; the other official flags default to False. ``bike_racks``
    ({sample_token: (R, 10) rows}, see the module doc) is written even when empty: ``{}`` says "no rack anywhere",
    where a missing key says "racks unknown".
    """
    missing = [k for k in ("use_camera", "use_lidar") if k not in meta]
    if missing:
        raise ValueError(f"meta must say {missing[0]!r} (official keys: {META_KEYS}), got {dict(meta)}")
    full_meta = {k: False for k in META_KEYS} | dict(meta)
    for k in META_KEYS:
        if not isinstance(full_meta[k], bool):
            raise ValueError(f"meta[{k!r}] must be true or false, got {full_meta[k]!r}")
    EvalBoxes.from_results(results_by_sample)  # refuse to write what the evaluation would refuse to read
    doc: dict = {"meta": full_meta, "results": {t: [_json_entry(e) for e in es] for t, es in results_by_sample.items()}}
    if ego_positions is not None:
        doc["ego_positions"] = {t: [float(v) for v in p] for t, p in ego_positions.items()}
    if bike_racks is not None:
        doc["bike_racks"] = {t: rows.tolist() for t, rows in check_bike_racks(bike_racks, "bike_racks").items()}
    text = json.dumps(doc, allow_nan=False)  # before the file: a refused value leaves no file behind
    atomic_write_file(path, lambda f: f.write(text.encode("utf-8")))


def read_results_json(path: str | os.PathLike, what: str = "results file") -> ResultsFile:
    """Read a results or ground-truth file (``what`` names it in errors); ValueError (naming the file) when it is
    not one.

    A file over MAX_RESULTS_BYTES is refused unread, as is input nested too deeply for the JSON parser, and a key
    given twice in one object (a sample listed twice would otherwise keep only its last list of boxes).
    """
    doc = read_json(path, what, MAX_RESULTS_BYTES, unique_keys=True)
    if not isinstance(doc, dict) or not isinstance(doc.get("results"), dict):
        got = sorted(doc) if isinstance(doc, dict) else type(doc).__name__
        raise ValueError(f"{path} must be a JSON object with a 'results' object (sample_token -> boxes), got {got}")
    meta = doc.get("meta", {})
    ego = doc.get("ego_positions", {})
    if not isinstance(meta, dict) or not isinstance(ego, dict):
        raise ValueError(f"{path}: 'meta' and 'ego_positions' must be JSON objects")
    for token, xyz in ego.items():
        # is_finite_number, not math.isfinite: a JSON int such as 10**400 must be refused, not overflow
        if not (isinstance(xyz, list) and len(xyz) == 3 and all(is_finite_number(v) for v in xyz)):
            raise ValueError(f"{path}: ego_positions[{token!r}] must be 3 finite numbers, got {short_repr(xyz)}")
    racks = doc.get("bike_racks")  # absent (or null): a file written before racks were saved
    return ResultsFile(results=doc["results"], meta=meta, ego_positions=ego, has_meta="meta" in doc,
                       bike_racks=None if racks is None else check_bike_racks(racks, f"{path}: bike_racks"))  # fmt: skip


def check_submission(results_file: ResultsFile, pred: EvalBoxes, path: str | os.PathLike) -> list[str]:
    """ValueError naming ``path`` (and the entry) where a results file read as ``results_file`` and parsed as
    ``pred`` is not one the devkit scores: the devkit reads ``meta`` with ``[]`` (a KeyError without it), a missing
    ``detection_score`` is -1 to it, and a negative score breaks its "confidences descending" assert once a precision
    curve is padded with 0. An official ``meta`` key given must be true or false, as ``write_results_json`` writes
    it (``"use_camera": "yes"`` is a serializer's slip); a key left out is not refused, as the devkit does not.
    Not for ground truth: the devkit builds that from its tables (its ``detection_score`` is -1, its ``meta`` absent).

    Returns notes: boxes without ``attribute_name``, which the devkit also reads with ``[]``, are scored as ''
    (no attribute) and said, not refused: this reader has always taken them, and the files mode's tests score the
    bundled devkit oracle (``oracle_detection_eval.json``), whose predictions carry no attribute."""
    if not results_file.has_meta:
        raise ValueError(f"{path} has no 'meta' object; a submission says which inputs it used: "
                         f"{{{', '.join(f'{k!r}: true or false' for k in META_KEYS)}}}")  # fmt: skip
    meta = results_file.meta
    for k in META_KEYS:
        if k in meta and not isinstance(meta[k], bool):
            raise ValueError(f"{path}: meta[{k!r}] must be true or false, got {short_repr(meta[k])}")
    no_attribute, first = 0, ""
    for token, entries in results_file.results.items():
        for i, e in enumerate(entries):  # parsed already: a list of objects
            # from_results gives a missing score ground truth's -1, which the check below would call negative
            if "detection_score" not in e:
                raise ValueError(f"{path}: results[{token!r}][{i}] has no 'detection_score' field (keys: {sorted(e)})")
            if "attribute_name" not in e:
                no_attribute += 1
                first = first or f"results[{token!r}][{i}]"
    negative = np.flatnonzero(pred.detection_score < 0)
    if len(negative):
        row = int(negative[0])
        token = pred.sample_tokens[pred.sample_index[row]]
        index = row - int(np.searchsorted(pred.sample_index, pred.sample_index[row]))  # rows are grouped by sample
        raise ValueError(f"{path}: results[{token!r}][{index}].detection_score must be >= 0, got "
                         f"{float(pred.detection_score[row])!r} ({len(negative)} negative in the file: logits written "
                         "where probabilities belong?)")  # fmt: skip
    if no_attribute:
        return [f"{path}: {no_attribute} of {len(pred)} boxes have no attribute_name (first {first}), scored as '' "
                "(no attribute): the devkit refuses such a file (KeyError 'attribute_name'); give '' where a class "
                "has none"]  # fmt: skip
    return []


def check_bike_racks(racks: object, where: str = "bike_racks") -> dict[str, np.ndarray]:
    """``{sample_token: [[x, y, z, w, l, h, qw, qx, qy, qz], ...]}`` as ``{token: (R, 10) float64}``; ValueError
    (naming ``where``, the sample and the bad value) unless every row is 10 finite numbers with sizes > 0 and a
    non-zero quaternion, the rule every box of the evaluation follows."""
    if not isinstance(racks, Mapping):
        raise ValueError(f"{where} must map sample tokens to lists of rack boxes, got {type(racks).__name__}")
    out = {}
    for token, rows in racks.items():
        if isinstance(rows, np.ndarray):
            rows = rows.tolist()
        if not isinstance(token, str) or not isinstance(rows, (list, tuple)):
            raise ValueError(f"{where}[{short_repr(token)}] must be a list of rack boxes, got {short_repr(rows)}")
        for i, row in enumerate(rows):
            if isinstance(row, np.ndarray):
                row = row.tolist()
            if not (isinstance(row, (list, tuple)) and len(row) == 10 and all(is_finite_number(v) for v in row)):
                raise ValueError(f"{where}[{token!r}][{i}] must be 10 finite numbers (translation, size w l h, "
                                 f"rotation w x y z), got {short_repr(row)}")  # fmt: skip
            if min(row[3:6]) <= 0 or sum(float(v) * float(v) for v in row[6:10]) < 1e-12:
                raise ValueError(f"{where}[{token!r}][{i}] must have sizes > 0 and a non-zero quaternion, "
                                 f"got {short_repr(row)}")  # fmt: skip
        out[token] = np.array(rows, dtype=np.float64).reshape(len(rows), 10)
    return out


@dataclass(frozen=True)
class EvalInputs:
    """A ground-truth file and a results file as the evaluation takes them (``load_eval_inputs``)."""

    gt: EvalBoxes
    pred: EvalBoxes
    bike_racks: dict[str, np.ndarray] | None  # the ground-truth file's (for evaluate's bike_racks); None: it has none
    notes: tuple[str, ...] = ()  # what is scored but would not be by the devkit (``check_submission``)


def load_gt_and_predictions(gt_path: str | os.PathLike, results_path: str | os.PathLike) -> tuple[EvalBoxes, EvalBoxes]:
    """Both files as EvalBoxes (``load_eval_inputs`` without the bike racks)."""
    inputs = load_eval_inputs(gt_path, results_path)
    return inputs.gt, inputs.pred


def load_eval_inputs(gt_path: str | os.PathLike, results_path: str | os.PathLike) -> EvalInputs:
    """Both files as EvalBoxes, predictions' ``ego_translation`` set from each sample's ego position, and the
    ground-truth file's ``bike_racks``.

    The ego position of a sample is the ground-truth file's ``ego_positions`` entry, else ``translation -
    ego_translation`` of its ground-truth boxes; a prediction in a sample with neither keeps its own
    ``ego_translation``, which it must then have. A rack of a sample the ground truth does not hold is refused:
    the file belongs to other data. The results file must be one the devkit scores: its samples those of the
    ground truth with at most 500 boxes each (``check_prediction_samples``), its ``meta`` and scores as
    ``check_submission`` says (whose notes ``notes`` holds).
    """
    gt_file, pred_file = read_results_json(gt_path, "ground-truth file"), read_results_json(results_path)
    for token, entries in gt_file.results.items():
        for i, e in enumerate(entries if isinstance(entries, list) else []):
            if isinstance(e, Mapping) and "ego_translation" not in e and token not in gt_file.ego_positions:
                raise ValueError(f"{gt_path}: ground truth [{token!r}][{i}] has no 'ego_translation' and the file no ego_positions[{token!r}]")
    gt = EvalBoxes.from_results(gt_file.results, source=f"{gt_path}: results")
    gt = gt.with_ego_position(gt_file.ego_positions)
    pred = EvalBoxes.from_results(pred_file.results, source=f"{results_path}: results")
    try:
        check_prediction_samples(gt, pred)  # evaluate makes them too, but cannot name the files
    except ValueError as e:
        raise ValueError(f"{results_path} (against {gt_path}): {e}") from None
    notes = check_submission(pred_file, pred, results_path)
    ego = _ego_positions_from_boxes(gt, gt_path) | dict(gt_file.ego_positions)
    for token, entries in pred_file.results.items():
        if token not in ego and any("ego_translation" not in e for e in entries):
            raise ValueError(
                f"{results_path}: no ego position for sample {token!r} (no ground-truth box or ego_positions entry "
                "in the ground-truth file) and its predictions carry no ego_translation"
            )
    if gt_file.bike_racks is not None:
        stray = [t for t in gt_file.bike_racks if t not in gt_file.results]
        if stray:
            raise ValueError(f"{gt_path}: bike_racks names sample {stray[0]!r}, which its results do not hold")
    return EvalInputs(gt=gt, pred=pred.with_ego_position(ego), bike_racks=gt_file.bike_racks, notes=tuple(notes))


def _ego_positions_from_boxes(gt: EvalBoxes, where: str | os.PathLike) -> dict[str, list[float]]:
    if len(gt) == 0:
        return {}
    ego = gt.translation - gt.ego_translation  # (N, 3), one ego position per sample
    starts = np.flatnonzero(np.r_[True, np.diff(gt.sample_index) != 0])  # rows are grouped by sample
    spread = (np.maximum.reduceat(ego, starts, axis=0) - np.minimum.reduceat(ego, starts, axis=0)).max(axis=1)
    if spread.max() > 1e-3:
        bad = int(np.argmax(spread))
        raise ValueError(
            f"{where}: the ground truth of sample {gt.sample_tokens[gt.sample_index[starts[bad]]]!r} implies ego positions "
            f"(translation - ego_translation) {spread[bad]:.3g} m apart; they must agree"
        )
    return {gt.sample_tokens[gt.sample_index[r]]: ego[r].tolist() for r in starts.tolist()}


def _json_entry(entry: Mapping) -> dict:
    out = dict(entry)
    if "velocity" in out:
        out["velocity"] = [None if v is None or math.isnan(float(v)) else float(v) for v in out["velocity"]]
    return out
