"""The drop-camera study: mAP and per-class AP with a named camera missing at inference (its features are zeros, as
``update_images`` does for any camera not given)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from streamdet.data.sample import Sample
from streamdet.runtime_ort.detector import StreamingDetector
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
    open_detector,
    open_image_detector,
    resolve_num_slices,
    score_classes,
    score_variants,
    sweep_points,
)

DEFAULT_DROPPED_CAMERA = "CAM_BACK"  # the paper's "without the back camera" row


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
        return score_classes(self.all_cameras)

    def to_dict(self) -> dict:
        return {
            "study": "drop-camera", "dropped_cameras": list(self.cameras), "classes": list(self.classes),
            "num_samples": self.num_samples, "num_slices": self.num_slices, "source": self.source,
            "all_cameras": self.all_cameras.to_dict(),
            "without": {c: s.to_dict() for c, s in zip(self.cameras, self.without)},
            "no_cameras": None if self.no_cameras is None else self.no_cameras.to_dict(),
        }  # fmt: skip

    def format_table(self) -> str:
        head = f"{'cameras':<22}{'mAP':>8}" + class_header(self.classes)
        lines = [f"mAP with a camera missing at inference ({self.num_slices} slices; its features are zeros)", head, "-" * len(head)]
        lines.append(f"{'all':<22}{100 * self.all_cameras.mean_ap:>8.1f}" + class_row(self.all_cameras, self.classes))
        rows = list(zip(self.cameras, self.without))
        if self.no_cameras is not None:
            rows.append(("every camera", self.no_cameras))
        for cam, s in rows:
            lines.append(f"{'without ' + cam:<22}{100 * s.mean_ap:>8.1f}" + class_row(s, self.classes))
            delta = {c: s.class_aps[c] - self.all_cameras.class_aps[c] for c in self.classes}
            lines.append(f"{'  change':<22}{100 * (s.mean_ap - self.all_cameras.mean_ap):>+8.1f}"
                         + "".join(f"{100 * delta[c]:>+8.1f}" for c in self.classes))  # fmt: skip
        lines += ["", classes_line(self.classes, self.num_samples), f"model: {self.source}"]
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
    reads the camera-less BEV (``StreamingDetector.blank_image_bev``), so the gap to "all" says how much the model
    leans on its cameras at all.
    """
    det = open_image_detector(export_dir, runtime, "drop-camera")
    names = check_cameras(det, cameras)
    n = resolve_num_slices(det, num_slices)
    blind = open_detector(export_dir, runtime) if no_cameras else None

    def detect(_i: int, sample: Sample) -> dict[str, Detections]:
        images = sample_images(det, sample)
        ts = sample_time_s(sample)
        encoded = det.encode_images(images)  # once per sample: a variant only leaves cameras out of the lift
        out = {}
        for drop in (None, *names):
            kept = {c: a for c, a in images.items() if c != drop}
            det.update_images(kept, timestamp=ts, encoded={c: encoded[c] for c in kept})
            out["all" if drop is None else drop] = det.detect_sweep(sweep_points(sample), timestamp=ts, num_slices=n)
        if blind is not None:
            out[_NO_CAMERAS] = blind.detect_sweep(sweep_points(sample), timestamp=ts, num_slices=n)
        return out

    scores, num = score_variants(data, detect, progress)
    return DropCameraResult(names, scores["all"], tuple(scores[c] for c in names), n,
                            describe_export(export_dir, runtime), num, scores.get(_NO_CAMERAS))  # fmt: skip


_NO_CAMERAS = "<no cameras>"  # variant key; cannot clash with a camera name, which check_cameras vets
