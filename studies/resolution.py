"""The resolution study: mAP and image-lane latency with the images fed at other sizes than the export's
(``DetectorConfig.image_size``: the graphs are dynamic in H and W, the LUT is rebuilt for the size)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from streamdet.data.sample import Sample
from streamdet.runtime_ort.pipeline import sample_images, sample_time_s
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
    describe_export,
    open_image_detector,
    resolve_num_slices,
    score_classes,
    score_variants,
    sweep_points,
)

DEFAULT_RESOLUTIONS = ((1600, 900), (1200, 675), (800, 450))  # (W, H) px


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
        return score_classes(self.rows[0].score)

    def to_dict(self) -> dict:
        return {
            "study": "resolution", "classes": list(self.classes), "num_samples": self.num_samples,
            "num_slices": self.num_slices, "num_cameras": self.num_cameras, "threads": self.threads,
            "export_size": list(self.export_size), "dataset_sizes": [list(s) for s in self.dataset_sizes],
            "source": self.source, "rows": [r.to_dict() for r in self.rows],
        }  # fmt: skip

    def format_table(self) -> str:
        head = f"{'image size':<14}{'mAP':>8}{'image lane ms':>15}{'encoder ms':>12}{'n':>5}  " + class_header(self.classes)
        lines = [f"mAP and image-lane latency by image size ({self.num_slices} slices)", head, "-" * len(head)]
        for r in self.rows:
            size = f"{r.width}x{r.height}" + ("*" if r.upsampled else "")
            lines.append(f"{size:<14}{100 * r.score.mean_ap:>8.1f}{r.image_lane_p50_ms:>15.1f}{r.encoder_p50_ms:>12.1f}"
                         f"{r.image_lane_count:>5}  " + class_row(r.score, self.classes))  # fmt: skip
        native = ", ".join(f"{w}x{h}" for w, h in self.dataset_sizes)
        lines += [
            "", classes_line(self.classes, self.num_samples),
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
    n = resolve_num_slices(dets[0], num_slices)
    native: set[tuple[int, int]] = set()

    def detect(i: int, sample: Sample) -> dict[str, Detections]:
        native.update((c.width, c.height) for c in sample.rig.cameras)
        ts = sample_time_s(sample)
        out = {}
        for (w, h), det in zip(sizes, dets):
            images = sample_images(det, sample)
            if i == 0:  # untimed warm-up: the first run of a session allocates its buffers
                det.update_images(images, timestamp=ts)
                det.stats.reset()
            det.update_images(images, timestamp=ts)
            out[f"{w}x{h}"] = det.detect_sweep(sweep_points(sample), timestamp=ts, num_slices=n)
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
                            runtime.threads, describe_export(export_dir, runtime), num)  # fmt: skip
