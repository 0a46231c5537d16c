"""Run a detector over a nuScenes-format dataset split and score it (numpy + onnxruntime, no torch).

A *sweep detector* is any callable ``sample -> Detections`` (boxes in the sample's LiDAR frame). The ONNX one,
``OnnxSweepDetector``, feeds the runtime through ``runtime_ort.pipeline.detect_sample`` the way a vehicle would:
all camera images of the sample through the image lane, then every slice of the sweep through the slice lane,
merged with per-class NMS (the paper's per-sweep aggregation). The training side plugs a
PyTorch sweep detector into the same ``evaluate_dataset``, so both are scored identically.

The split's samples come from ``root/splits.json`` (``data.splits``). Ground truth: the boxes of the 10 detection
classes, as the devkit's ``load_gt`` gives them: LiDAR + radar point counts (boxes without points are ignored by the
evaluation, as the devkit does), the annotation's attribute, and NaN velocity where the annotation has none
(``Sample.velocity_valid``; the reader's 0 there would be scored as standing still). The sample's
``static_object.bicycle_rack`` annotations, in the global frame as annotated, drive the devkit's bike-rack rule.
The mAP averages the classes present in the ground truth unless ``classes`` is given; the result names them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from streamdet.core.classes import CLASS_NAMES
from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.data.nuscenes import GLOBAL_ANNOTATIONS, NuScenesReader
from streamdet.data.sample import Sample
from streamdet.data.splits import split_sample_tokens
from streamdet.evaluation.config import DetectionConfig
from streamdet.evaluation.detection_eval import evaluate
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.metrics import DetectionMetrics
from streamdet.evaluation.results import boxes_to_gt, boxes_to_results
from streamdet.runtime_ort.pipeline import detect_sample
from streamdet.runtime_ort.postprocess import Detections

SweepDetector = Callable[[Sample], Detections]


@dataclass(frozen=True)
class DatasetEvaluation:
    metrics: DetectionMetrics
    classes: tuple[str, ...]  # the classes the mAP averages
    num_samples: int
    seconds: float  # detection time over the split (reading the data included)
    # what was scored, in the nuScenes results format (global frame), for write_results_json / files mode
    predictions: dict[str, list[dict]] = field(default_factory=dict, repr=False)
    ground_truth: dict[str, list[dict]] = field(default_factory=dict, repr=False)
    ego_positions: dict[str, list[float]] = field(default_factory=dict, repr=False)
    # per sample: its scene and (lidar2ego, ego2global), for the scene bootstrap and slice subsets of --compare
    scenes: dict[str, str] = field(default_factory=dict, repr=False)
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)
    # per sample with a bicycle rack: its racks (R, 10), global frame (evaluate's bike_racks; gt.json's bike_racks)
    bike_racks: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        return {**self.metrics.to_dict(), "classes": list(self.classes), "num_samples": self.num_samples,
                "seconds": self.seconds}  # fmt: skip


BIKE_RACK_CATEGORY = "static_object.bicycle_rack"


def ground_truth_entries(sample: Sample) -> list[dict]:
    """The sample's boxes of the 10 classes as ground-truth entries (global frame), as the devkit's ``load_gt``
    builds them: the annotated box, ``box_velocity``'s xy (NaN where unknown), the attribute ("" = none) and the
    LiDAR + radar point count.

    A sample of ``NuScenesReader`` carries the annotations as the table holds them (``GLOBAL_ANNOTATIONS``), and those
    are the entries, exactly. Another sample's LiDAR-frame boxes are mapped back instead, which recovers the global
    centre and velocity to rounding but not the annotation's pitch and roll, so its yaw is the LiDAR-plane heading.
    """
    keep = sample.gt_labels >= 0
    labels = sample.gt_labels[keep]
    num_pts = (sample.num_lidar_pts + sample.num_radar_pts)[keep].astype(np.int64)
    attributes = [a for a, k in zip(sample.attribute_names, keep.tolist()) if k]
    valid = np.asarray(sample.velocity_valid, dtype=bool)[keep]
    annotated = sample.extras.get(GLOBAL_ANNOTATIONS)
    if annotated is not None:
        ego = sample.ego2global[:3, 3]
        translation = np.asarray(annotated["translation"], dtype=np.float64)[keep]
        velocity = np.asarray(annotated["velocity"], dtype=np.float64)[keep, :2]
        velocity[~valid] = np.nan  # box_velocity's NaN: the TP error ignores it, where the reader's 0 would count
        return [
            {"sample_token": sample.token, "translation": t.tolist(), "size": size.tolist(), "rotation": r.tolist(),
             "velocity": v.tolist(), "detection_name": CLASS_NAMES[label], "detection_score": -1.0,
             "attribute_name": attribute, "ego_translation": (t - ego).tolist(), "num_pts": n}
            for t, size, r, v, label, attribute, n in zip(
                translation, np.asarray(annotated["size"], dtype=np.float64)[keep],
                np.asarray(annotated["rotation"], dtype=np.float64)[keep], velocity, labels.tolist(), attributes,
                num_pts.tolist())
        ]  # fmt: skip
    boxes = sample.gt_boxes[keep]
    entries = boxes_to_gt(sample.token, boxes, labels, num_pts, sample.lidar2ego, sample.ego2global,
                          attribute_names=attributes)  # fmt: skip
    # The velocity back as box_velocity gave it (global xy). The LiDAR-frame velocity is (vx, vy, 0) put through the
    # global -> LiDAR rotation, xy kept (NuScenesReader, and mmdetection3d's info files the bundled sample comes
    # from); rotating (vx, vy, 0) back, boxes_to_gt's convention for predictions, is not the inverse of that when the
    # LiDAR is tilted (an error of the order of the tilt squared): solve the 2x2 block applied instead. NaN where the
    # velocity is unknown, as above.
    global2lidar = sample.lidar2global[:3, :3].T  # NuScenesReader's rotation (calibration.invert_transform: R^T)
    velocity = np.full((len(boxes), 2), np.nan)
    velocity[valid] = np.linalg.solve(global2lidar[:2, :2], boxes[valid, 7:9].T).T
    for entry, v in zip(entries, velocity.tolist()):
        entry["velocity"] = v
    return entries


def bike_racks_of(sample: Sample) -> np.ndarray:
    """(R, 10) the sample's bicycle racks as annotated (global translation, size w l h, rotation w x y z), the boxes
    the devkit's ``filter_eval_boxes`` builds; none for a sample that does not carry its annotations
    (``GLOBAL_ANNOTATIONS``): the LiDAR-frame boxes keep the yaw only."""
    annotated = sample.extras.get(GLOBAL_ANNOTATIONS)
    racks = np.array([name == BIKE_RACK_CATEGORY for name in sample.gt_names], dtype=bool)
    if annotated is None or not racks.any():
        return np.zeros((0, 10))
    return np.concatenate([np.asarray(annotated[k], dtype=np.float64)[racks] for k in ("translation", "size", "rotation")],
                          axis=1)  # fmt: skip


def prediction_entries(sample: Sample, dets: Detections, max_boxes: int) -> list[dict]:
    if not isinstance(dets, Detections):  # a caller's sweep detector: name what it gave, not an attribute it lacks
        raise TypeError(f"the sweep detector must return Detections, got {type(dets).__name__} for sample {sample.token}")
    order = np.argsort(-dets.scores, kind="stable")[:max_boxes]  # the evaluation refuses more per sample
    return boxes_to_results(sample.token, dets.boxes[order].astype(np.float64), dets.scores[order], dets.labels[order],
                            sample.lidar2ego, sample.ego2global)  # fmt: skip


def evaluate_dataset(
    detect: SweepDetector,
    root: str | Path,
    version: str = DEFAULT_TABLE_VERSION,
    split: str | None = "val",
    classes: Sequence[str] | None = None,
    max_samples: int | None = None,
    config: DetectionConfig = DetectionConfig(),
    progress: Callable[[int, int], None] | None = None,
) -> DatasetEvaluation:
    """Detect every sample of the split and compute nuScenes detection metrics in the global frame.
    ``max_samples``: the split's first samples only (None: all of them), an int >= 1."""
    if max_samples is not None and (isinstance(max_samples, bool) or not isinstance(max_samples, (int, np.integer)) or max_samples < 1):
        # a slice bound: -1 would drop the last sample silently, 0 score nothing
        raise ValueError(f"max_samples must be None or an int >= 1, got {max_samples!r}")
    reader = NuScenesReader(root, version)
    tokens = split_sample_tokens(reader, root, split)
    if max_samples is not None:
        tokens = tokens[:max_samples]
    gt_results: dict[str, list[dict]] = {}
    pred_results: dict[str, list[dict]] = {}
    ego: dict[str, list[float]] = {}
    scenes: dict[str, str] = {}
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    racks: dict[str, np.ndarray] = {}
    t0 = time.perf_counter()
    for i, token in enumerate(tokens):
        sample = reader.get(token)
        gt_results[token] = ground_truth_entries(sample)
        sample_racks = bike_racks_of(sample)
        if len(sample_racks):
            racks[token] = sample_racks
        pred_results[token] = prediction_entries(sample, detect(sample), config.max_boxes_per_sample)
        ego[token] = sample.ego2global[:3, 3].tolist()
        scenes[token] = reader.scene_name(token)
        poses[token] = (sample.lidar2ego, sample.ego2global)
        if progress is not None:
            progress(i + 1, len(tokens))
    seconds = time.perf_counter() - t0
    gt = EvalBoxes.from_results(gt_results, source="ground truth")
    pred = EvalBoxes.from_results(pred_results, source="predictions").with_ego_position(ego)
    if classes is None:
        present = set(gt.detection_name[gt.num_pts > 0].tolist())
        classes = tuple(c for c in config.class_names if c in present)
        if not classes:
            raise ValueError(f"the ground truth of {len(tokens)} samples holds no box with points: nothing to score")
    metrics = evaluate(gt, pred, config=config, classes=classes, bike_racks=racks)
    return DatasetEvaluation(metrics=metrics, classes=tuple(metrics.classes), num_samples=len(tokens), seconds=seconds,
                             predictions=pred_results, ground_truth=gt_results, ego_positions=ego,
                             scenes=scenes, poses=poses, bike_racks=racks)  # fmt: skip


class OnnxSweepDetector:
    """``sample -> Detections`` through an export directory with onnxruntime (all cameras, then every slice; a
    LiDAR-only export: every slice, no image read)."""

    def __init__(
        self, export_dir: str | Path, precision: str = "fp32", num_slices: int | None = None, threads: int = 1,
        image_precision: str | None = None, providers: tuple[str, ...] | None = None,
    ) -> None:
        from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector

        cfg = DetectorConfig(precision=precision, image_lane_precision=image_precision, num_slices=num_slices,
                             image_lane_threads=threads, slice_lane_threads=threads, providers=providers)  # fmt: skip
        self.detector = StreamingDetector(export_dir, cfg)

    def __call__(self, sample: Sample) -> Detections:
        # a LiDAR-only export (the streaming baseline) has no image lane; detect_sample then reads the sweep alone
        return detect_sample(self.detector, sample).detections
