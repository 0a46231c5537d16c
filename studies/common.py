"""What every study shares: which samples it scores, how the export runs, scoring variants against one ground truth.

Every variant of a study is scored against the same ground truth with the same classes: the classes with points in
the split's ground truth (``DatasetEvaluation``'s rule), named in every result.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.core.sectors import check_num_slices
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.sample import Sample
from streamdet.data.splits import split_sample_tokens
from streamdet.evaluation.config import DetectionConfig
from streamdet.evaluation.dataset_eval import bike_racks_of, ground_truth_entries, prediction_entries
from streamdet.evaluation.detection_eval import evaluate
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.metrics import DetectionMetrics
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector, lane_precision_label
from streamdet.runtime_ort.manifest import read_manifest
from streamdet.runtime_ort.postprocess import Detections

SHORT_CLASS = {
    "car": "car", "truck": "truck", "trailer": "trailer", "bus": "bus", "construction_vehicle": "c.veh",
    "bicycle": "bicycle", "motorcycle": "motor", "pedestrian": "ped", "traffic_cone": "cone", "barrier": "barrier",
}  # fmt: skip

Progress = Callable[[int, int], None]  # (samples done, samples in all)


class StudyError(ValueError):
    """A study cannot run with these inputs; the message says why in one line."""


@dataclass(frozen=True)
class StudyData:
    """Which samples a study scores."""

    root: Path  # dataset root (nuScenes layout, with splits.json for a named split)
    version: str = DEFAULT_TABLE_VERSION  # table folder
    split: str | None = "val"  # a split of root/splits.json; None: every sample
    max_samples: int | None = None  # the first N samples of the split; None: all

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))
        if self.max_samples is not None and (isinstance(self.max_samples, bool) or not isinstance(self.max_samples, int)
                                             or self.max_samples < 1):  # fmt: skip
            raise StudyError(f"StudyData.max_samples must be a positive integer or None, got {self.max_samples!r}")


@dataclass(frozen=True)
class RuntimeOptions:
    """How the export runs."""

    precision: str = "fp32"  # fp32 | fp16 | int8; the export must hold graphs of that precision
    threads: int = 1  # intra-op threads of each lane's sessions (the studies' machines are shared)
    image_precision: str | None = None  # the image lane's graphs of a camera + LiDAR export; None: precision
    providers: tuple[str, ...] | None = None  # onnxruntime's execution providers; None: the runtime's default

    @property
    def label(self) -> str:
        """``"fp32"``, or ``"int8 image lane + fp32 slices"`` when the lanes differ."""
        return lane_precision_label(self.precision, self.image_precision)


@dataclass(frozen=True, eq=False)
class Score:
    """nuScenes detection metrics of one variant of a study."""

    metrics: DetectionMetrics

    @property
    def mean_ap(self) -> float:
        return self.metrics.mean_ap

    @property
    def class_aps(self) -> dict[str, float]:
        """AP of each averaged class, mean over the distance thresholds."""
        return self.metrics.mean_dist_aps

    def to_dict(self) -> dict:
        return {"mAP": self.mean_ap, "NDS": self.metrics.nd_score, "AP": self.class_aps}


# ---- the shared loop ---------------------------------------------------------------------------------------


def score_variants(
    data: StudyData,
    detect: Callable[[int, Sample], Mapping[str, Detections]],
    progress: Progress | None = None,
    config: DetectionConfig = DetectionConfig(),
) -> tuple[dict[str, Score], int]:
    """Run ``detect(i, sample) -> {variant: detections}`` over the samples and score each variant.

    Every call must return the same variant names. Returns the scores by variant and the number of samples.
    """
    reader = NuScenesReader(data.root, data.version)
    tokens = split_sample_tokens(reader, data.root, data.split)[: data.max_samples]
    gt_results: dict[str, list[dict]] = {}
    pred_results: dict[str, dict[str, list[dict]]] = {}
    ego: dict[str, list[float]] = {}
    racks: dict[str, np.ndarray] = {}  # the devkit's bike-rack rule, as evaluate_dataset applies it
    for i, token in enumerate(tokens):
        sample = reader.get(token)
        dets = detect(i, sample)
        if pred_results and set(dets) != set(pred_results):
            raise RuntimeError(f"sample {i} gave variants {sorted(dets)}, earlier samples {sorted(pred_results)}")
        gt_results[token] = ground_truth_entries(sample)
        if len(sample_racks := bike_racks_of(sample)):
            racks[token] = sample_racks
        for name, d in dets.items():
            pred_results.setdefault(name, {})[token] = prediction_entries(sample, d, config.max_boxes_per_sample)
        ego[token] = sample.ego2global[:3, 3].tolist()
        if progress is not None:
            progress(i + 1, len(tokens))
    gt = EvalBoxes.from_results(gt_results, source="ground truth")
    present = set(gt.detection_name[gt.num_pts > 0].tolist())
    classes = tuple(c for c in config.class_names if c in present)
    if not classes:
        raise StudyError(f"the ground truth of {len(tokens)} samples holds no box with points: nothing to score")
    scores = {}
    for name, results in pred_results.items():
        pred = EvalBoxes.from_results(results, source=f"predictions ({name})").with_ego_position(ego)
        scores[name] = Score(evaluate(gt, pred, config=config, classes=classes, bike_racks=racks))
    return scores, len(tokens)


def open_detector(export_dir: str | Path, runtime: RuntimeOptions, image_size: tuple[int, int] | None = None) -> StreamingDetector:
    """A StreamingDetector of the export; a bad export or precision raises StudyError (one line)."""
    try:
        # A LiDAR-only export (the baseline) has no image lane for runtime.image_precision to apply to.
        use_image = runtime.image_precision is not None and read_manifest(export_dir, verify_files=False).use_image
        cfg = DetectorConfig(precision=runtime.precision, image_lane_precision=runtime.image_precision if use_image else None,
                             image_lane_threads=runtime.threads, slice_lane_threads=runtime.threads,
                             image_size=image_size, providers=runtime.providers)  # fmt: skip
        return StreamingDetector(export_dir, cfg)
    except (OSError, ValueError) as e:  # ManifestError and CalibrationError are ValueErrors
        raise StudyError(f"export {export_dir}: {e}") from None


def open_image_detector(export_dir: str | Path, runtime: RuntimeOptions, study: str,
                        image_size: tuple[int, int] | None = None) -> StreamingDetector:  # fmt: skip
    """``open_detector`` for a study that varies the image lane: a LiDAR-only export raises StudyError (one line)."""
    try:
        use_image = read_manifest(export_dir, verify_files=False).use_image
    except (OSError, ValueError) as e:  # ManifestError is a ValueError
        raise StudyError(f"export {export_dir}: {e}") from None
    if not use_image:
        raise StudyError(f"export {export_dir} is LiDAR-only (preset use_image=false): the {study} study needs an image lane")
    return open_detector(export_dir, runtime, image_size)


def sweep_points(sample: Sample) -> np.ndarray:
    return np.asarray(sample.points, np.float32)  # (N, 5)


def score_classes(score: Score) -> tuple[str, ...]:
    return tuple(score.metrics.classes)


def class_header(classes: Sequence[str], width: int = 8) -> str:
    return "".join(f"{SHORT_CLASS.get(c, c)[:width - 1]:>{width}}" for c in classes)


def class_row(score: Score, classes: Sequence[str], width: int = 8) -> str:
    aps = score.class_aps
    return "".join(f"{100 * aps[c]:>{width}.1f}" for c in classes)


def classes_line(classes: Sequence[str], num_samples: int) -> str:
    return (f"mAP and AP in %, nuScenes centre-distance AP; mAP averages {len(classes)} classes: {', '.join(classes)} "
            f"({num_samples} samples)")


def resolve_num_slices(det: StreamingDetector, num_slices: int | None) -> int:
    n = det.num_slices if num_slices is None else num_slices
    try:
        check_num_slices(n)
    except ValueError as e:
        raise StudyError(f"slices: {e}") from None
    return int(n)


def describe_export(export_dir: str | Path, runtime: RuntimeOptions) -> str:
    return f"ONNX export {export_dir} ({runtime.label}, onnxruntime)"
