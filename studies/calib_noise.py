"""The calibration-noise study: mAP under uniform extrinsic noise (``calibration.perturb.perturb_rig``), several seeds
per level, the LUT rebuilt through ``set_calibration`` for every noisy rig and the graphs untouched."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from streamdet.calibration.perturb import perturb_rig
from streamdet.data.sample import Sample
from streamdet.runtime_ort.manifest import sha256_file
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
    describe_export,
    open_image_detector,
    resolve_num_slices,
    score_classes,
    score_variants,
    sweep_points,
)

DEFAULT_NOISE_LEVELS = ((0.5, 0.05), (1.0, 0.10), (2.0, 0.20), (3.0, 0.30), (5.0, 0.50))  # (max deg, max m)


def noise_seed(seed: int, sample_index: int) -> int:
    """The perturbation seed of one sample in one seeded run: fresh noise per sample, reproducible per seed. The level
    is not part of it: every level scales the same unit draw to its bound (common random numbers), so the change
    from one level to the next is the size of the error alone, not another draw of it."""
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
        return score_classes(self.reference)

    def to_dict(self) -> dict:
        return {
            "study": "calib-noise", "classes": list(self.classes), "num_samples": self.num_samples,
            "num_slices": self.num_slices, "seeds": list(self.seeds), "source": self.source,
            "reference": self.reference.to_dict(), "levels": [lv.to_dict() for lv in self.levels],
            "graphs_sha256": self.graphs_sha256, "graphs_untouched": self.graphs_untouched,
        }  # fmt: skip

    def format_table(self) -> str:
        head = f"{'noise (deg, cm)':<18}{'mAP':>8}{'std':>7}{'change':>8}{'LUT moved':>11}" + class_header(self.classes)
        title = f"mAP under uniform extrinsic noise, {len(self.seeds)} seed(s) each ({self.num_slices} slices)"
        lines = [title, head, "-" * len(head)]
        ref = self.reference
        lines.append(f"{'none (true)':<18}{100 * ref.mean_ap:>8.1f}{'':>7}{'':>8}{'':>11}" + class_row(ref, self.classes))
        for lv in self.levels:
            label = f"{lv.max_angle_deg:g} deg, {100 * lv.max_translation_m:g} cm"
            aps = lv.class_ap_mean()
            lines.append(
                f"{label:<18}{100 * lv.mean_ap:>8.1f}{100 * lv.std_ap:>7.1f}{100 * (lv.mean_ap - ref.mean_ap):>+8.1f}"
                f"{100 * lv.lut_changed_fraction:>10.1f}%" + "".join(f"{100 * aps[c]:>8.1f}" for c in self.classes)
            )
        lines += [
            "", classes_line(self.classes, self.num_samples),
            "mean and sample std over seeds; per sample and seed a fresh draw per camera, scaled to each level; the LUT "
            "is rebuilt for every noisy rig, the graphs are untouched"
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
    n = resolve_num_slices(det, num_slices)
    changed = np.zeros(len(level_list))

    def detect(i: int, sample: Sample) -> dict[str, Detections]:
        ts = sample_time_s(sample)
        feed_images(det, sample, ts)
        true_index = det.lut.index[:, 0]  # (4, Z, Yq, Xq) first slot
        out = {"reference": det.detect_sweep(sweep_points(sample), timestamp=ts, num_slices=n)}
        for li, (angle, shift) in enumerate(level_list):
            for s in seed_list:
                det.set_calibration(perturb_rig(sample.rig, angle, shift, noise_seed(s, i)))  # re-lifts the cached features
                changed[li] += float(np.mean(det.lut.index[:, 0] != true_index))
                out[f"{li}/{s}"] = det.detect_sweep(sweep_points(sample), timestamp=ts, num_slices=n)
        return out

    scores, num = score_variants(data, detect, progress)
    graph_files = sorted({g.file for g in det.manifest.graphs})
    hashes = {f: sha256_file(det.export_dir / f) for f in graph_files}
    untouched = all(hashes[g.file] == g.sha256 for g in det.manifest.graphs)
    result_levels = tuple(
        NoiseLevel(a, t, tuple(scores[f"{li}/{s}"] for s in seed_list), float(changed[li] / (num * len(seed_list))))
        for li, (a, t) in enumerate(level_list)
    )
    return CalibNoiseResult(scores["reference"], result_levels, seed_list, n, describe_export(export_dir, runtime), num, hashes, untouched)
