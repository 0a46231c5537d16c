"""The slices study: mAP at 1, 4, 8, 16, 32 slices per sweep, the fused model beside a LiDAR-only baseline (the
paper's Table 2 layout). One cached image BEV per sample serves every slice count."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from streamdet.core.sectors import check_num_slices
from streamdet.data.sample import Sample
from streamdet.runtime_ort.pipeline import feed_images, sample_time_s
from streamdet.runtime_ort.postprocess import Detections
from streamdet.studies.common import (
    Progress,
    RuntimeOptions,
    Score,
    StudyData,
    StudyError,
    class_header,
    class_row,
    classes_line,
    open_detector,
    score_classes,
    score_variants,
    sweep_points,
)

DEFAULT_SLICE_COUNTS = (1, 4, 8, 16, 32)


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
        ts = sample_time_s(sample)
        if self.uses_images:
            feed_images(det, sample, ts)
        return {n: det.detect_sweep(sweep_points(sample), timestamp=ts, num_slices=n) for n in slice_counts}


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
        return score_classes(self.fused[0])

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
            lines += ["", f"{name}: AP per class", f"{'slices':<10}{'mAP':>8}" + class_header(self.classes)]
            for n, s in zip(self.slice_counts, scores):
                lines.append(f"{n:<10}{100 * s.mean_ap:>8.1f}" + class_row(s, self.classes))
        lines += ["", classes_line(self.classes, self.num_samples), f"fused: {self.fused_source}"]
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
