"""Run a detector over a nuScenes-format dataset split and score it (numpy + onnxruntime, no torch).

A *sweep detector* is any callable ``sample -> Detections`` (boxes in the sample's LiDAR frame). The ONNX one,
``OnnxSweepDetector``, feeds the runtime through ``runtime_ort.pipeline.detect_sample`` the way a vehicle would:
all camera images of the sample through the image lane, then every slice of the sweep through the slice lane,
merged with per-class NMS (the paper's per-sweep aggregation). The training side plugs a
PyTorch sweep detector into the same ``evaluate_dataset``, so both are scored identically.

The split's samples come from ``root/splits.json`` (``data.splits``). Ground truth: the boxes of the 10 detection classes, with LiDAR + radar point counts (boxes without points are
ignored by the evaluation, as the devkit does). The mAP averages the classes present in the ground truth unless
``classes`` is given; the result names them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.data.nuscenes import NuScenesReader
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

    def to_dict(self) -> dict:
        return {**self.metrics.to_dict(), "classes": list(self.classes), "num_samples": self.num_samples,
                "seconds": self.seconds}  # fmt: skip


def ground_truth_entries(sample: Sample) -> list[dict]:
    keep = sample.gt_labels >= 0
    return boxes_to_gt(
        sample.token, sample.gt_boxes[keep], sample.gt_labels[keep],
        (sample.num_lidar_pts + sample.num_radar_pts)[keep].astype(np.int64), sample.lidar2ego, sample.ego2global,
    )  # fmt: skip


def prediction_entries(sample: Sample, dets: Detections, max_boxes: int) -> list[dict]:
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
    """Detect every sample of the split and compute nuScenes detection metrics in the global frame."""
    reader = NuScenesReader(root, version)
    tokens = split_sample_tokens(reader, root, split)
    if max_samples is not None:
        tokens = tokens[:max_samples]
    gt_results: dict[str, list[dict]] = {}
    pred_results: dict[str, list[dict]] = {}
    ego: dict[str, list[float]] = {}
    scenes: dict[str, str] = {}
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    t0 = time.perf_counter()
    for i, token in enumerate(tokens):
        sample = reader.get(token)
        gt_results[token] = ground_truth_entries(sample)
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
    metrics = evaluate(gt, pred, config=config, classes=classes)
    return DatasetEvaluation(metrics=metrics, classes=tuple(metrics.classes), num_samples=len(tokens), seconds=seconds,
                             predictions=pred_results, ground_truth=gt_results, ego_positions=ego,
                             scenes=scenes, poses=poses)  # fmt: skip


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
