"""Robustness studies of a streaming export, as in the paper's Sec. IV (numpy + onnxruntime, no torch).

Four studies, each a function that runs the onnxruntime runtime (``runtime_ort.detector.StreamingDetector``)
over a dataset split and returns a frozen result with ``to_dict()`` (every figure) and ``format_table()``:

- ``slices_study``: mAP at 1, 4, 8, 16, 32 slices per sweep, the fused model beside a LiDAR-only baseline
  (the paper's Table 2 layout). One cached image BEV per sample serves every slice count.
- ``drop_camera_study``: mAP and per-class AP with a named camera missing at inference (its features are zeros,
  as ``update_images`` does for any camera not given).
- ``calib_noise_study``: mAP under uniform extrinsic noise (``calibration.perturb.perturb_rig``), several seeds
  per level, the LUT rebuilt through ``set_calibration`` for every noisy rig and the graphs untouched.
- ``resolution_study``: mAP and image-lane latency with the images fed at other sizes than the export's
  (``DetectorConfig.image_size``: the graphs are dynamic in H and W, the LUT is rebuilt for the size).

Every variant of a study is scored against the same ground truth with the same classes: the classes with
points in the split's ground truth (``DatasetEvaluation``'s rule), named in every result.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from streamdet.calibration.perturb import perturb_rig
from streamdet.core.sectors import check_num_slices
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.sample import Sample
from streamdet.evaluation.config import DetectionConfig
from streamdet.evaluation.dataset_eval import ground_truth_entries, prediction_entries, split_tokens
from streamdet.evaluation.detection_eval import evaluate
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.metrics import DetectionMetrics
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector, lane_precision_label
from streamdet.runtime_ort.manifest import read_manifest, sha256_file
from streamdet.runtime_ort.postprocess import Detections

DEFAULT_SLICE_COUNTS = (1, 4, 8, 16, 32)
DEFAULT_NOISE_LEVELS = ((0.5, 0.05), (1.0, 0.10), (2.0, 0.20), (3.0, 0.30), (5.0, 0.50))  # (max deg, max m)
DEFAULT_RESOLUTIONS = ((1600, 900), (1200, 675), (800, 450))  # (W, H) px
DEFAULT_DROPPED_CAMERA = "CAM_BACK"  # the paper's "without the back camera" row
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
    version: str = "v1.0-synth"  # table folder
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
    tokens = split_tokens(reader, data.root, data.split)[: data.max_samples]
    gt_results: dict[str, list[dict]] = {}
    pred_results: dict[str, dict[str, list[dict]]] = {}
    ego: dict[str, list[float]] = {}
    for i, token in enumerate(tokens):
        sample = reader.get(token)
        dets = detect(i, sample)
        if pred_results and set(dets) != set(pred_results):
            raise RuntimeError(f"sample {i} gave variants {sorted(dets)}, earlier samples {sorted(pred_results)}")
        gt_results[token] = ground_truth_entries(sample)
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
        scores[name] = Score(evaluate(gt, pred, config=config, classes=classes))
    return scores, len(tokens)


def open_detector(export_dir: str | Path, runtime: RuntimeOptions, image_size: tuple[int, int] | None = None) -> StreamingDetector:
    """A StreamingDetector of the export; a bad export or precision raises StudyError (one line)."""
    try:
        # A LiDAR-only export (the baseline) has no image lane for runtime.image_precision to apply to.
        use_image = runtime.image_precision is not None and read_manifest(export_dir, verify_files=False).use_image
        cfg = DetectorConfig(precision=runtime.precision, image_lane_precision=runtime.image_precision if use_image else None,
                             image_lane_threads=runtime.threads, slice_lane_threads=runtime.threads,
                             image_size=image_size)  # fmt: skip
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


def _sweep(sample: Sample) -> np.ndarray:
    return np.asarray(sample.points, np.float32)  # (N, 5)


def _classes(score: Score) -> tuple[str, ...]:
    return tuple(score.metrics.classes)


def _class_header(classes: Sequence[str], width: int = 8) -> str:
    return "".join(f"{SHORT_CLASS.get(c, c)[:width - 1]:>{width}}" for c in classes)


def _class_row(score: Score, classes: Sequence[str], width: int = 8) -> str:
    aps = score.class_aps
    return "".join(f"{100 * aps[c]:>{width}.1f}" for c in classes)


def _classes_line(classes: Sequence[str], num_samples: int) -> str:
    return (f"mAP and AP in %, nuScenes centre-distance AP; mAP averages {len(classes)} classes: {', '.join(classes)} "
            f"({num_samples} samples)")


# ---- slices ------------------------------------------------------------------------------------------------


class SlicedDetector(Protocol):
    """Detections of a sample at several slice counts (the fused model and the baselines alike)."""

    description: str

    def __call__(self, sample: Sample, slice_counts: Sequence[int]) -> dict[int, Detections]: ...


class OnnxSlicedDetector:
    """An export through the runtime: the sample's images once (if the model reads images), then every count."""

    def __init__(self, export_dir: str | Path, runtime: RuntimeOptions = RuntimeOptions(), label: str | None = None) -> None:
        self.detector = open_detector(export_dir, runtime)
        # The LiDAR-only baseline's export has the slice graph alone: no image lane at all.
        self.uses_images = self.detector.uses_images
        kind = "camera + LiDAR" if self.uses_images else "LiDAR only"
        precision = runtime.label if self.uses_images else runtime.precision
        self.description = label or f"ONNX export {export_dir} ({kind}, {precision}, onnxruntime)"

    def __call__(self, sample: Sample, slice_counts: Sequence[int]) -> dict[int, Detections]:
        det = self.detector
        ts = sample.timestamp_us * 1e-6
        if self.uses_images:
            det.update_images(_load_images(det, sample), timestamp=ts)
        return {n: det.detect_sweep(_sweep(sample), timestamp=ts, num_slices=n) for n in slice_counts}


@dataclass(frozen=True, eq=False)
class SlicesResult:
    slice_counts: tuple[int, ...]
    fused: tuple[Score, ...]  # per slice count
    fused_source: str
    baseline: tuple[Score, ...] | None  # per slice count; None: no baseline was given
    baseline_source: str | None
    num_samples: int
    notes: tuple[str, ...]

    @property
    def classes(self) -> tuple[str, ...]:
        return _classes(self.fused[0])

    def to_dict(self) -> dict:
        rows = lambda scores: None if scores is None else {str(n): s.to_dict() for n, s in zip(self.slice_counts, scores)}  # noqa: E731
        return {
            "study": "slices", "slice_counts": list(self.slice_counts), "classes": list(self.classes),
            "num_samples": self.num_samples, "fused": rows(self.fused), "fused_source": self.fused_source,
            "baseline": rows(self.baseline), "baseline_source": self.baseline_source, "notes": list(self.notes),
        }  # fmt: skip

    def format_table(self) -> str:
        head = f"{'model':<26}{'modality':<10}" + "".join(f"{n:>8}" for n in self.slice_counts)
        lines = ["mAP by slices per sweep (the paper's Table 2 layout)", head, "-" * len(head)]
        models = [("LiDAR-only baseline", "PC", self.baseline), ("fused (ours)", "PC+RGB", self.fused)]
        for name, modality, scores in models:
            if scores is not None:
                lines.append(f"{name:<26}{modality:<10}" + "".join(f"{100 * s.mean_ap:>8.1f}" for s in scores))
        for name, _, scores in models:
            if scores is None:
                continue
            lines += ["", f"{name}: AP per class", f"{'slices':<10}{'mAP':>8}" + _class_header(self.classes)]
            for n, s in zip(self.slice_counts, scores):
                lines.append(f"{n:<10}{100 * s.mean_ap:>8.1f}" + _class_row(s, self.classes))
        lines += ["", _classes_line(self.classes, self.num_samples), f"fused: {self.fused_source}"]
        lines.append(f"baseline: {self.baseline_source}" if self.baseline is not None else "baseline: none given, fused column only")
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)


def slices_study(
    fused: SlicedDetector,
    data: StudyData,
    slice_counts: Sequence[int] = DEFAULT_SLICE_COUNTS,
    baseline: SlicedDetector | None = None,
    progress: Progress | None = None,
) -> SlicesResult:
    """mAP of the fused model (and the baseline) at each slice count; every model scores the same samples."""
    counts = tuple(slice_counts)
    if not counts:
        raise StudyError("slice_counts is empty")
    for n in counts:
        try:
            check_num_slices(n)
        except ValueError as e:
            raise StudyError(f"slice count {n!r}: {e}") from None

    def detect(_i: int, sample: Sample) -> dict[str, Detections]:
        out = {f"fused/{n}": d for n, d in fused(sample, counts).items()}
        if baseline is not None:
            out.update({f"baseline/{n}": d for n, d in baseline(sample, counts).items()})
        return out

    scores, num = score_variants(data, detect, progress)
    notes = []
    if baseline is None:
        notes.append("no LiDAR-only baseline given (--baseline-export-dir / --baseline-checkpoint): fused column only")
    return SlicesResult(
        slice_counts=counts,
        fused=tuple(scores[f"fused/{n}"] for n in counts),
        fused_source=fused.description,
        baseline=None if baseline is None else tuple(scores[f"baseline/{n}"] for n in counts),
        baseline_source=None if baseline is None else baseline.description,
        num_samples=num,
        notes=tuple(notes),
    )


def torch_sliced_detector(checkpoint: str | Path, threads: int = 1, device: str = "cpu") -> SlicedDetector:
    """A checkpoint evaluated with PyTorch (``training.torch_eval``), for a LiDAR-only baseline that has not been
    exported (``streamdet-export --checkpoint`` turns one into its slice graph, for ``--baseline-export-dir``).
    Scored exactly as the ONNX models; needs torch.

    ``threads`` sets torch's intra-op threads for the whole process: on a shared 2-core machine the default (all
    cores) made the 32-slice sweep 20x slower than one thread.
    """
    try:
        torch = importlib.import_module("torch")  # lazily: everything else in this module stays torch-free
        from streamdet.training.checkpoint import load_weights
        from streamdet.training.torch_eval import TorchSweepDetector
    except ImportError as e:
        raise StudyError(f"--baseline-checkpoint needs PyTorch (pip install '.[export]'): {e}") from None
    torch.set_num_threads(threads)
    try:
        model, preset = load_weights(checkpoint)
    except ValueError as e:
        raise StudyError(str(e)) from None
    kind = "camera + LiDAR" if preset.use_image else "LiDAR only"

    class _Torch:
        description = f"checkpoint {checkpoint} ({preset.name}, {kind}, PyTorch fp32 on {device})"

        def __call__(self, sample: Sample, slice_counts: Sequence[int]) -> dict[int, Detections]:
            return {n: TorchSweepDetector(model, num_slices=n, device=device)(sample) for n in slice_counts}

    return _Torch()


def export_checkpoint(
    checkpoint: str | Path, out_dir: str | Path, precision: str = "fp32", image_precision: str | None = None
) -> Path:
    """Export a camera + LiDAR checkpoint into ``out_dir`` with ``streamdet.export`` (needs torch); the export dir."""
    if "int8" in (precision, image_precision):
        raise StudyError("--checkpoint exports fp32 / fp16 only; make the int8 export first and pass --export-dir")
    try:
        from streamdet.export.exporter import ExportError, ExportOptions, run_export  # imports torch
        from streamdet.training.checkpoint import load_checkpoint
    except ImportError as e:
        raise StudyError(f"--checkpoint needs PyTorch to export it (pip install '.[export]'): {e}") from None
    try:
        preset = load_checkpoint(checkpoint)["preset"]
    except ValueError as e:
        raise StudyError(str(e)) from None
    if not preset.get("use_image", True):
        raise StudyError(f"checkpoint {checkpoint} is a LiDAR-only model: pass it as --baseline-checkpoint")
    fp16 = "fp16" in (precision, image_precision)
    opts = ExportOptions(preset=str(preset["name"]), checkpoint=str(checkpoint), fp16=fp16, out_dir=str(out_dir))
    try:
        return run_export(opts).out_dir
    except (ExportError, ValueError) as e:
        raise StudyError(f"exporting {checkpoint}: {e}") from None


# ---- drop a camera -----------------------------------------------------------------------------------------


def _load_images(det: StreamingDetector, sample: Sample) -> dict[str, np.ndarray]:
    """The sample's camera images at the detector's size, by name, and its calibration in the detector."""
    if sample.rig.sha256() != det.lut.calibration_sha256:
        det.set_calibration(sample.rig)  # another rig than the current LUT's: rebuild the LUT, same graphs
    images = sample.load_images((det.image.width, det.image.height))  # (J, H, W, 3) in rig order
    return {n: images[j] for j, n in enumerate(sample.rig.names) if n in det.camera_names}


def check_cameras(det: StreamingDetector, cameras: Sequence[str]) -> tuple[str, ...]:
    names = tuple(cameras)
    if not names:
        raise StudyError("no camera to drop given")
    unknown = [c for c in names if c not in det.camera_names]
    if unknown:
        raise StudyError(f"unknown camera {unknown[0]!r}; the export has {', '.join(det.camera_names)}")
    if len(set(names)) != len(names):
        raise StudyError(f"camera names repeat: {list(names)}")
    return names


@dataclass(frozen=True, eq=False)
class DropCameraResult:
    cameras: tuple[str, ...]  # each dropped on its own
    all_cameras: Score
    without: tuple[Score, ...]  # per dropped camera
    num_slices: int
    source: str
    num_samples: int
    no_cameras: Score | None = None  # every camera missing (image BEV zeros); None: not asked for

    @property
    def classes(self) -> tuple[str, ...]:
        return _classes(self.all_cameras)

    def to_dict(self) -> dict:
        return {
            "study": "drop-camera", "dropped_cameras": list(self.cameras), "classes": list(self.classes),
            "num_samples": self.num_samples, "num_slices": self.num_slices, "source": self.source,
            "all_cameras": self.all_cameras.to_dict(),
            "without": {c: s.to_dict() for c, s in zip(self.cameras, self.without)},
            "no_cameras": None if self.no_cameras is None else self.no_cameras.to_dict(),
        }  # fmt: skip

    def format_table(self) -> str:
        head = f"{'cameras':<22}{'mAP':>8}" + _class_header(self.classes)
        lines = [f"mAP with a camera missing at inference ({self.num_slices} slices; its features are zeros)", head, "-" * len(head)]
        lines.append(f"{'all':<22}{100 * self.all_cameras.mean_ap:>8.1f}" + _class_row(self.all_cameras, self.classes))
        rows = list(zip(self.cameras, self.without))
        if self.no_cameras is not None:
            rows.append(("every camera", self.no_cameras))
        for cam, s in rows:
            lines.append(f"{'without ' + cam:<22}{100 * s.mean_ap:>8.1f}" + _class_row(s, self.classes))
            delta = {c: s.class_aps[c] - self.all_cameras.class_aps[c] for c in self.classes}
            lines.append(f"{'  change':<22}{100 * (s.mean_ap - self.all_cameras.mean_ap):>+8.1f}"
                         + "".join(f"{100 * delta[c]:>+8.1f}" for c in self.classes))  # fmt: skip
        lines += ["", _classes_line(self.classes, self.num_samples), f"model: {self.source}"]
        return "\n".join(lines)


def drop_camera_study(
    export_dir: str | Path,
    data: StudyData,
    cameras: Sequence[str] = (DEFAULT_DROPPED_CAMERA,),
    runtime: RuntimeOptions = RuntimeOptions(),
    num_slices: int | None = None,
    progress: Progress | None = None,
    no_cameras: bool = False,
) -> DropCameraResult:
    """mAP with all cameras, and with each named camera removed from the image lane (same model, same LUT).

    ``no_cameras`` also scores the model with every camera missing: a detector that never gets an image update
    reads a zero image BEV, so the gap to "all" says how much the model leans on its cameras at all.
    """
    det = open_image_detector(export_dir, runtime, "drop-camera")
    names = check_cameras(det, cameras)
    n = _num_slices(det, num_slices)
    blind = open_detector(export_dir, runtime) if no_cameras else None

    def detect(_i: int, sample: Sample) -> dict[str, Detections]:
        images = _load_images(det, sample)
        ts = sample.timestamp_us * 1e-6
        out = {}
        for drop in (None, *names):
            det.update_images({c: a for c, a in images.items() if c != drop}, timestamp=ts)
            out["all" if drop is None else drop] = det.detect_sweep(_sweep(sample), timestamp=ts, num_slices=n)
        if blind is not None:
            out[_NO_CAMERAS] = blind.detect_sweep(_sweep(sample), timestamp=ts, num_slices=n)
        return out

    scores, num = score_variants(data, detect, progress)
    return DropCameraResult(names, scores["all"], tuple(scores[c] for c in names), n,
                            _describe(export_dir, runtime), num, scores.get(_NO_CAMERAS))  # fmt: skip


_NO_CAMERAS = "<no cameras>"  # variant key; cannot clash with a camera name, which check_cameras vets


def _num_slices(det: StreamingDetector, num_slices: int | None) -> int:
    n = det.num_slices if num_slices is None else num_slices
    try:
        check_num_slices(n)
    except ValueError as e:
        raise StudyError(f"slices: {e}") from None
    return int(n)


def _describe(export_dir: str | Path, runtime: RuntimeOptions) -> str:
    return f"ONNX export {export_dir} ({runtime.label}, onnxruntime)"


# ---- calibration noise -------------------------------------------------------------------------------------


def noise_seed(seed: int, sample_index: int) -> int:
    """The perturbation seed of one sample in one seeded run: fresh noise per sample, reproducible per seed."""
    return int(np.random.SeedSequence([seed, sample_index]).generate_state(1)[0])


@dataclass(frozen=True, eq=False)
class NoiseLevel:
    max_angle_deg: float  # every Euler angle uniform in +-this, per camera
    max_translation_m: float  # every translation axis uniform in +-this, per camera
    scores: tuple[Score, ...]  # per seed
    lut_changed_fraction: float  # voxels whose first LUT slot names another feature cell than the true rig's (mean)

    @property
    def mean_ap(self) -> float:
        return float(np.mean([s.mean_ap for s in self.scores]))

    @property
    def std_ap(self) -> float:
        """Sample standard deviation (ddof 1) of the mAP over seeds; 0 with one seed."""
        return float(np.std([s.mean_ap for s in self.scores], ddof=1)) if len(self.scores) > 1 else 0.0

    def class_ap_mean(self) -> dict[str, float]:
        classes = self.scores[0].class_aps
        return {c: float(np.mean([s.class_aps[c] for s in self.scores])) for c in classes}

    def to_dict(self) -> dict:
        return {
            "max_angle_deg": self.max_angle_deg, "max_translation_m": self.max_translation_m,
            "mAP_mean": self.mean_ap, "mAP_std": self.std_ap, "mAP_per_seed": [s.mean_ap for s in self.scores],
            "AP_mean": self.class_ap_mean(), "lut_changed_fraction": self.lut_changed_fraction,
        }  # fmt: skip


@dataclass(frozen=True, eq=False)
class CalibNoiseResult:
    reference: Score  # the true calibration
    levels: tuple[NoiseLevel, ...]
    seeds: tuple[int, ...]
    num_slices: int
    source: str
    num_samples: int
    graphs_sha256: dict[str, str]  # graph file -> sha256, hashed after the study
    graphs_untouched: bool  # every hash still equals the manifest's

    @property
    def classes(self) -> tuple[str, ...]:
        return _classes(self.reference)

    def to_dict(self) -> dict:
        return {
            "study": "calib-noise", "classes": list(self.classes), "num_samples": self.num_samples,
            "num_slices": self.num_slices, "seeds": list(self.seeds), "source": self.source,
            "reference": self.reference.to_dict(), "levels": [lv.to_dict() for lv in self.levels],
            "graphs_sha256": self.graphs_sha256, "graphs_untouched": self.graphs_untouched,
        }  # fmt: skip

    def format_table(self) -> str:
        head = f"{'noise (deg, cm)':<18}{'mAP':>8}{'std':>7}{'change':>8}{'LUT moved':>11}" + _class_header(self.classes)
        title = f"mAP under uniform extrinsic noise, {len(self.seeds)} seed(s) each ({self.num_slices} slices)"
        lines = [title, head, "-" * len(head)]
        ref = self.reference
        lines.append(f"{'none (true)':<18}{100 * ref.mean_ap:>8.1f}{'':>7}{'':>8}{'':>11}" + _class_row(ref, self.classes))
        for lv in self.levels:
            label = f"{lv.max_angle_deg:g} deg, {100 * lv.max_translation_m:g} cm"
            aps = lv.class_ap_mean()
            lines.append(
                f"{label:<18}{100 * lv.mean_ap:>8.1f}{100 * lv.std_ap:>7.1f}{100 * (lv.mean_ap - ref.mean_ap):>+8.1f}"
                f"{100 * lv.lut_changed_fraction:>10.1f}%" + "".join(f"{100 * aps[c]:>8.1f}" for c in self.classes)
            )
        lines += [
            "", _classes_line(self.classes, self.num_samples),
            "mean and sample std over seeds; per sample and seed a fresh draw per camera; the LUT is rebuilt for every "
            "noisy rig, the graphs are untouched"
            + (" (sha256 checked after the run)" if self.graphs_untouched else " (GRAPH SHA256 CHANGED)"),
            "LUT moved: voxels whose first camera slot reads another feature cell than with the true calibration",
            f"model: {self.source}",
        ]  # fmt: skip
        return "\n".join(lines)


def calib_noise_study(
    export_dir: str | Path,
    data: StudyData,
    levels: Sequence[tuple[float, float]] = DEFAULT_NOISE_LEVELS,
    seeds: int | Sequence[int] = 3,
    runtime: RuntimeOptions = RuntimeOptions(),
    num_slices: int | None = None,
    progress: Progress | None = None,
) -> CalibNoiseResult:
    """mAP with each sample's camera extrinsics perturbed (``perturb_rig``) at each level and seed.

    Per sample the images are encoded once; every noisy rig only rebuilds the LUT and re-lifts the cached
    features (``set_calibration``), so the graphs and their inputs other than the LUT stay as they are.
    """
    seed_list = tuple(range(seeds)) if isinstance(seeds, int) else tuple(seeds)
    if not seed_list or any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in seed_list):
        raise StudyError(f"seeds must be a positive count or non-negative integers, got {seeds!r}")
    level_list = tuple((float(a), float(t)) for a, t in levels)
    for a, t in level_list:
        if not (0 <= a < 180 and 0 <= t < math.inf):
            raise StudyError(f"noise level ({a} deg, {t} m): angle must be in [0, 180), translation >= 0 and finite")
    det = open_image_detector(export_dir, runtime, "calib-noise")
    n = _num_slices(det, num_slices)
    changed = np.zeros(len(level_list))

    def detect(i: int, sample: Sample) -> dict[str, Detections]:
        ts = sample.timestamp_us * 1e-6
        det.update_images(_load_images(det, sample), timestamp=ts)
        true_index = det.lut.index[:, 0]  # (4, Z, Yq, Xq) first slot
        out = {"reference": det.detect_sweep(_sweep(sample), timestamp=ts, num_slices=n)}
        for li, (angle, shift) in enumerate(level_list):
            for s in seed_list:
                det.set_calibration(perturb_rig(sample.rig, angle, shift, noise_seed(s, i)))  # re-lifts the cached features
                changed[li] += float(np.mean(det.lut.index[:, 0] != true_index))
                out[f"{li}/{s}"] = det.detect_sweep(_sweep(sample), timestamp=ts, num_slices=n)
        return out

    scores, num = score_variants(data, detect, progress)
    graph_files = sorted({g.file for g in det.manifest.graphs})
    hashes = {f: sha256_file(det.export_dir / f) for f in graph_files}
    untouched = all(hashes[g.file] == g.sha256 for g in det.manifest.graphs)
    result_levels = tuple(
        NoiseLevel(a, t, tuple(scores[f"{li}/{s}"] for s in seed_list), float(changed[li] / (num * len(seed_list))))
        for li, (a, t) in enumerate(level_list)
    )
    return CalibNoiseResult(scores["reference"], result_levels, seed_list, n, _describe(export_dir, runtime), num, hashes, untouched)


# ---- image resolution --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ResolutionRow:
    width: int
    height: int
    score: Score
    image_lane_p50_ms: float  # median of image_total (encoder + lifter, all cameras) at this size
    image_lane_count: int  # updates timed (after one untimed warm-up)
    encoder_p50_ms: float
    upsampled: bool  # the dataset's images are smaller than this size in some dimension

    def to_dict(self) -> dict:
        return {
            "width": self.width, "height": self.height, **self.score.to_dict(),
            "image_lane_p50_ms": self.image_lane_p50_ms, "image_lane_count": self.image_lane_count,
            "image_encoder_p50_ms": self.encoder_p50_ms, "upsampled": self.upsampled,
        }  # fmt: skip


@dataclass(frozen=True, eq=False)
class ResolutionResult:
    rows: tuple[ResolutionRow, ...]
    export_size: tuple[int, int]  # (W, H) the export (and its training) used
    dataset_sizes: tuple[tuple[int, int], ...]  # (W, H) of the dataset's images
    num_slices: int
    num_cameras: int
    threads: int
    source: str
    num_samples: int

    @property
    def classes(self) -> tuple[str, ...]:
        return _classes(self.rows[0].score)

    def to_dict(self) -> dict:
        return {
            "study": "resolution", "classes": list(self.classes), "num_samples": self.num_samples,
            "num_slices": self.num_slices, "num_cameras": self.num_cameras, "threads": self.threads,
            "export_size": list(self.export_size), "dataset_sizes": [list(s) for s in self.dataset_sizes],
            "source": self.source, "rows": [r.to_dict() for r in self.rows],
        }  # fmt: skip

    def format_table(self) -> str:
        head = f"{'image size':<14}{'mAP':>8}{'image lane ms':>15}{'encoder ms':>12}{'n':>5}  " + _class_header(self.classes)
        lines = [f"mAP and image-lane latency by image size ({self.num_slices} slices)", head, "-" * len(head)]
        for r in self.rows:
            size = f"{r.width}x{r.height}" + ("*" if r.upsampled else "")
            lines.append(f"{size:<14}{100 * r.score.mean_ap:>8.1f}{r.image_lane_p50_ms:>15.1f}{r.encoder_p50_ms:>12.1f}"
                         f"{r.image_lane_count:>5}  " + _class_row(r.score, self.classes))  # fmt: skip
        native = ", ".join(f"{w}x{h}" for w, h in self.dataset_sizes)
        lines += [
            "", _classes_line(self.classes, self.num_samples),
            f"latency: median image_total (encoder + lifter) of {self.num_cameras} cameras in one batch, "
            f"{self.threads} thread(s), onnxruntime CPU; n = updates timed after one warm-up",
            f"the dataset's images are {native}" + ("; * = upsampled to that size" if any(r.upsampled for r in self.rows) else ""),
            f"the export was made (and the model trained) for {self.export_size[0]}x{self.export_size[1]}; other sizes "
            "run the same graphs with a LUT built for them",
            f"model: {self.source}",
        ]  # fmt: skip
        return "\n".join(lines)


def resolution_study(
    export_dir: str | Path,
    data: StudyData,
    resolutions: Sequence[tuple[int, int]] = DEFAULT_RESOLUTIONS,
    runtime: RuntimeOptions = RuntimeOptions(),
    num_slices: int | None = None,
    progress: Progress | None = None,
) -> ResolutionResult:
    """mAP and image-lane latency with the images resized to each (W, H); one detector per size, interleaved
    per sample so that machine load falls on every size alike."""
    sizes = tuple((int(w), int(h)) for w, h in resolutions)
    if not sizes or any(w < 16 or h < 16 for w, h in sizes):
        raise StudyError(f"resolutions must be (width, height) pairs of at least 16 px each, got {list(resolutions)!r}")
    if len(set(sizes)) != len(sizes):
        raise StudyError(f"resolutions repeat: {list(sizes)}")
    dets = [open_image_detector(export_dir, runtime, "resolution", image_size=s) for s in sizes]
    n = _num_slices(dets[0], num_slices)
    native: set[tuple[int, int]] = set()

    def detect(i: int, sample: Sample) -> dict[str, Detections]:
        native.update((c.width, c.height) for c in sample.rig.cameras)
        ts = sample.timestamp_us * 1e-6
        out = {}
        for (w, h), det in zip(sizes, dets):
            images = _load_images(det, sample)
            if i == 0:  # untimed warm-up: the first run of a session allocates its buffers
                det.update_images(images, timestamp=ts)
                det.stats.reset()
            det.update_images(images, timestamp=ts)
            out[f"{w}x{h}"] = det.detect_sweep(_sweep(sample), timestamp=ts, num_slices=n)
        return out

    scores, num = score_variants(data, detect, progress)
    rows = []
    for (w, h), det in zip(sizes, dets):
        stats = det.stats.summary()
        rows.append(ResolutionRow(
            w, h, scores[f"{w}x{h}"], stats["image_total"]["p50_ms"], int(stats["image_total"]["count"]),
            stats["image_encoder"]["p50_ms"], any(w > nw or h > nh for nw, nh in native),
        ))  # fmt: skip
    m = dets[0].manifest.image
    return ResolutionResult(tuple(rows), (m.width, m.height), tuple(sorted(native)), n, len(dets[0].camera_names),
                            runtime.threads, _describe(export_dir, runtime), num)  # fmt: skip
