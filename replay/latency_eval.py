"""Latency-aware nuScenes scores of a replay: every output matched against the world at the moment it is emitted.

Queries are the ends of the drive's LiDAR rotations (from the second on, so every mode could have emitted
something). At a query time ``t`` the ground truth is the world at ``t`` (``truth.py``), seen from the ego pose
at ``t``, and two prediction sets are scored with the project's devkit-identical evaluation
(``streamdet.evaluation.evaluate``):

- **streaming**: what the vehicle knows at ``t``: for every sector, the newest slice emitted by ``t`` (a full-sweep
  mode has one sector: its newest emitted sweep). Each slice's boxes are placed in the world with the ego pose of
  its own rotation (as a planner would), brought into the LiDAR frame of the newest rotation among them and merged
  by the runtime's per-class sweep NMS (``aggregate_sweep``), so an object seen in two sectors counts once;
- **offline**: the rotation ending at ``t``, every slice of it that was emitted (dropped ones are missing), whenever
  it was emitted: the same detections scored at their scan time, so the gap between the two is the cost of latency
  alone.

Moving and static objects are also scored apart: the ground truth of the other kind is removed, and so is every
prediction whose nearest same-class ground truth within 2 m is of the other kind (it is neither right nor wrong
here).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from streamdet.evaluation.config import DetectionConfig
from streamdet.evaluation.detection_eval import evaluate
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.results import boxes_to_results, global_to_lidar, lidar_to_global
from streamdet.replay.record import Recording, SliceRecord
from streamdet.replay.source import Drive
from streamdet.replay.truth import GroundTruth, count_points
from streamdet.runtime_ort.nms import NmsConfig
from streamdet.runtime_ort.postprocess import Detections, aggregate_sweep

SPLIT_RADIUS_M = 2.0
# A late box of a moving object lies behind it, by its speed times the latency: the moving / static split measures
# the distance to where each object was over this long (a static object: where it is), so such a box is the moving
# object's and not a false positive of the static split. Past the replay reports' worst p99 latencies.
SPLIT_LAG_S = 0.5


@dataclass(frozen=True, eq=False)
class QueryTruth:
    """The ground truth of one drive at every query time (shared by all modes)."""

    drive: str
    source: str  # GroundTruth.source
    sweeps: tuple[int, ...]  # the sweep whose end is each query time
    tokens: tuple[str, ...]
    entries: dict[str, list[dict]]  # token -> ground-truth entries (global frame)
    moving: dict[str, np.ndarray]  # token -> (M,) bool, per entry
    ego_xyz: dict[str, list[float]]


def query_truth(drive: Drive, truth: GroundTruth, config: DetectionConfig = DetectionConfig(), first_sweep: int = 1) -> QueryTruth:
    max_range = max(config.class_range_m.values())
    sweeps, tokens, entries, moving, ego = [], [], {}, {}, {}
    for sweep in drive.sweeps[first_sweep:]:
        token = f"{drive.name}@{sweep.index:05d}"
        t_us = float(drive.time_us(sweep.end_s))
        if not truth.covers(t_us):  # outside the annotated key frames: no ground truth to score against
            continue
        boxes = truth.at(t_us)
        keep = np.isin(boxes.names, config.class_names)
        boxes = boxes.select(keep)
        lidar2global = sweep.ego2global @ sweep.lidar2ego
        pts = sweep.points[:, :3].astype(np.float64) @ lidar2global[:3, :3].T + lidar2global[:3, 3]  # (N, 3)
        ego_xyz = sweep.ego2global[:3, 3]
        num_pts = count_points(boxes, pts, max_range + 5.0, ego_xyz[:2])
        entries[token] = [_gt_entry(token, b, str(n), str(a), int(p), ego_xyz)
                          for b, n, a, p in zip(boxes.boxes, boxes.names, boxes.attribute_names(), num_pts)]  # fmt: skip
        moving[token] = boxes.moving
        ego[token] = ego_xyz.tolist()
        sweeps.append(sweep.index)
        tokens.append(token)
    return QueryTruth(drive.name, truth.source, tuple(sweeps), tuple(tokens), entries, moving, ego)


def _gt_entry(token: str, box: np.ndarray, name: str, attribute: str, num_pts: int, ego_xyz: np.ndarray) -> dict:
    return {
        "sample_token": token, "translation": box[0:3].tolist(), "size": box[3:6].tolist(),
        "rotation": [float(np.cos(box[6] / 2)), 0.0, 0.0, float(np.sin(box[6] / 2))], "velocity": box[7:9].tolist(),
        "detection_name": name, "detection_score": -1.0, "attribute_name": attribute,
        "ego_translation": (box[0:3] - ego_xyz).tolist(), "num_pts": num_pts,
    }  # fmt: skip


def prediction_entries(
    drive: Drive, recording: Recording, queries: QueryTruth, nms: NmsConfig, max_boxes: int
) -> tuple[dict[str, list[dict]], dict[str, list[dict]]]:
    """(streaming, offline) prediction entries per query token."""
    emitted = sorted((s for s in recording.slices if s.emitted and s.detections is not None), key=lambda s: s.emit_s)
    by_sweep: dict[int, list[SliceRecord]] = {}
    for s in emitted:
        by_sweep.setdefault(s.sweep, []).append(s)
    latest: dict[int, SliceRecord] = {}
    streaming, offline = {}, {}
    i = 0
    for sweep_index, token in zip(queries.sweeps, queries.tokens):
        t = drive.sweeps[sweep_index].end_s
        while i < len(emitted) and emitted[i].emit_s <= t + 1e-9:
            held = latest.get(emitted[i].slice_index)
            if held is None or emitted[i].sweep >= held.sweep:  # a slice finishing after its next rotation's is older
                latest[emitted[i].slice_index] = emitted[i]
            i += 1
        streaming[token] = _merged_entries(drive, list(latest.values()), token, nms, max_boxes)
        offline[token] = _merged_entries(drive, by_sweep.get(sweep_index, []), token, nms, max_boxes)
    return streaming, offline


def _merged_entries(drive: Drive, records: Sequence[SliceRecord], token: str, nms: NmsConfig, max_boxes: int) -> list[dict]:
    if not records:
        return []
    ref = drive.sweeps[max(r.sweep for r in records)]
    parts = []
    for r in records:
        dets = r.detections
        if r.sweep != ref.index and len(dets):
            own = drive.sweeps[r.sweep]
            g = lidar_to_global(dets.boxes.astype(np.float64), own.lidar2ego, own.ego2global)
            boxes = global_to_lidar(*g, ref.lidar2ego, ref.ego2global).astype(np.float32)
            dets = Detections(boxes, dets.scores, dets.labels)
        parts.append(dets)
    merged = aggregate_sweep(parts, nms)
    order = np.argsort(-merged.scores, kind="stable")[:max_boxes]
    return boxes_to_results(token, merged.boxes[order].astype(np.float64), merged.scores[order], merged.labels[order],
                            ref.lidar2ego, ref.ego2global)  # fmt: skip


@dataclass(frozen=True)
class Scores:
    """nuScenes scores of one prediction set against the query-time ground truth."""

    map: float
    nds: float
    per_class_ap: dict[str, float]
    map_moving: float | None  # None where no scored object of that kind exists
    map_static: float | None
    classes: tuple[str, ...]
    num_queries: int

    def to_dict(self) -> dict:
        return {"map": self.map, "nds": self.nds, "per_class_ap": self.per_class_ap, "map_moving": self.map_moving,
                "map_static": self.map_static, "classes": list(self.classes), "num_queries": self.num_queries}  # fmt: skip


@dataclass(frozen=True)
class ModeScores:
    streaming: Scores  # at emission time
    offline: Scores  # at scan time
    per_scene_streaming_map: dict[str, float] = field(default_factory=dict)


def score(
    truths: Sequence[QueryTruth], predictions: Sequence[dict[str, list[dict]]], config: DetectionConfig = DetectionConfig()
) -> Scores:
    """One Scores over all queries of all drives (``predictions[i]`` answers ``truths[i]``)."""
    gt_results, pred_results, ego, moving = {}, {}, {}, []
    for q, pred in zip(truths, predictions):
        for token in q.tokens:
            gt_results[token] = q.entries[token]
            pred_results[token] = pred[token]
            ego[token] = q.ego_xyz[token]
            moving.append(q.moving[token])
    gt = EvalBoxes.from_results(gt_results, source="ground truth")
    pred = EvalBoxes.from_results(pred_results, source="predictions").with_ego_position(ego)
    moving_mask = np.concatenate(moving) if moving else np.zeros(0, bool)
    metrics = _evaluate(gt, pred, config)
    if metrics is None:
        return Scores(float("nan"), float("nan"), {}, None, None, (), len(gt_results))
    split = {}
    for name, mask in (("moving", moving_mask), ("static", ~moving_mask)):
        m = _evaluate(gt.select(mask), _without_other_kind(pred, gt, mask), config)
        split[name] = None if m is None else float(m.mean_ap)
    return Scores(float(metrics.mean_ap), float(metrics.nd_score), {c: float(v) for c, v in metrics.mean_dist_aps.items()},
                  split["moving"], split["static"], tuple(metrics.classes), len(gt_results))  # fmt: skip


def _evaluate(gt: EvalBoxes, pred: EvalBoxes, config: DetectionConfig):
    in_range = gt.ego_dist < np.array([config.class_range_m[str(n)] for n in gt.detection_name], dtype=np.float64)
    present = set(gt.detection_name[(gt.num_pts > 0) & in_range].tolist())  # the classes the devkit would score
    classes = tuple(c for c in config.class_names if c in present)
    if not classes:
        return None
    return evaluate(gt, pred, config=config, classes=classes)


def trail_distance(points_xy: np.ndarray, centres_xy: np.ndarray, velocity_xy: np.ndarray, lag_s: float) -> np.ndarray:
    """(P, G) distance of each point to each object's trail: the segment from where the object was ``lag_s`` ago
    (its centre minus velocity x lag) to its centre. An unknown (NaN) velocity counts as standing still."""
    v = np.nan_to_num(np.asarray(velocity_xy, dtype=np.float64))  # (G, 2)
    b = np.asarray(centres_xy, dtype=np.float64)  # (G, 2) now
    seg = v * lag_s  # (G, 2): from b - seg to b
    rel = np.asarray(points_xy, dtype=np.float64)[:, None, :] - b[None, :, :]  # (P, G, 2) point - now
    length2 = (seg * seg).sum(axis=-1)  # (G,)
    # position along the trail, 0 = now, 1 = lag_s ago; a static object's trail is its centre
    along = np.where(length2 > 0, -(rel * seg[None]).sum(axis=-1) / np.where(length2 > 0, length2, 1.0), 0.0)  # (P, G)
    along = np.clip(along, 0.0, 1.0)
    return np.linalg.norm(rel + along[..., None] * seg[None], axis=-1)


def _without_other_kind(pred: EvalBoxes, gt: EvalBoxes, kind: np.ndarray) -> EvalBoxes:
    """Predictions minus those nearest to a same-class ground truth not of ``kind``: nearest by the distance to its
    trail over SPLIT_LAG_S (``trail_distance``), within SPLIT_RADIUS_M of it. A prediction near no same-class object
    stays in both splits (a false positive of each)."""
    keep = np.ones(len(pred), dtype=bool)
    gt_rank = {t: i for i, t in enumerate(gt.sample_tokens)}
    for s, token in enumerate(pred.sample_tokens):
        rows = np.flatnonzero(pred.sample_index == s)
        g = np.flatnonzero(gt.sample_index == gt_rank.get(token, -1))
        if rows.size == 0 or g.size == 0:
            continue
        d = trail_distance(pred.translation[rows, :2], gt.translation[g, :2], gt.velocity[g], SPLIT_LAG_S)  # (p, g)
        d[pred.detection_name[rows, None] != gt.detection_name[None, g]] = np.inf
        nearest = np.argmin(d, axis=1)
        close = d[np.arange(len(rows)), nearest] < SPLIT_RADIUS_M
        keep[rows[close & ~kind[g[nearest]]]] = False
    return pred.select(keep)


def score_mode(
    drives: Sequence[Drive], recordings: Sequence[Recording], truths: Sequence[QueryTruth], nms: NmsConfig,
    config: DetectionConfig = DetectionConfig(),
) -> ModeScores:
    """Streaming and offline scores of one mode over its drives, and the streaming mAP of each drive alone."""
    streaming, offline = [], []
    for drive, rec, q in zip(drives, recordings, truths):
        s, o = prediction_entries(drive, rec, q, nms, config.max_boxes_per_sample)
        streaming.append(s)
        offline.append(o)
    per_scene = {q.drive: score([q], [s], config).map for q, s in zip(truths, streaming)} if len(truths) > 1 else {}
    return ModeScores(score(truths, streaming, config), score(truths, offline, config), per_scene)
