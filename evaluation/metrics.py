"""Metric records: the 101-point curves of one (class, threshold) and the summary (mAP, TP errors, NDS).

These mirror the devkit's ``DetectionMetricData`` and ``DetectionMetrics``; the summaries iterate classes and
thresholds in the config's order so that their floating-point sums are the devkit's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from streamdet.evaluation.config import TP_METRICS, DetectionConfig

NUM_RECALL_POINTS = 101  # recall 0, 0.01, ..., 1


@dataclass(frozen=True, eq=False)
class DetectionMetricData:
    """Precision, confidence and TP errors resampled at the 101 recall points, each (101,) float64."""

    recall: np.ndarray
    precision: np.ndarray
    confidence: np.ndarray  # 0 beyond the highest recall reached
    trans_err: np.ndarray
    vel_err: np.ndarray
    scale_err: np.ndarray
    orient_err: np.ndarray
    attr_err: np.ndarray

    def __post_init__(self) -> None:
        for name in ("recall", "precision", "confidence", *TP_METRICS):
            if np.shape(getattr(self, name)) != (NUM_RECALL_POINTS,):
                raise ValueError(
                    f"DetectionMetricData.{name} must have shape ({NUM_RECALL_POINTS},), got {np.shape(getattr(self, name))}"
                )

    @property
    def max_recall_ind(self) -> int:
        """Index of the highest recall reached: the last operating point with confidence > 0 (0 if none)."""
        nonzero = np.flatnonzero(self.confidence)
        return int(nonzero[-1]) if len(nonzero) else 0

    @classmethod
    def no_predictions(cls) -> DetectionMetricData:
        """The record of a class without ground truth or without a single match: AP 0, every TP error 1."""
        ones = np.ones(NUM_RECALL_POINTS)
        return cls(
            recall=np.linspace(0, 1, NUM_RECALL_POINTS),
            precision=np.zeros(NUM_RECALL_POINTS),
            confidence=np.zeros(NUM_RECALL_POINTS),
            trans_err=ones.copy(),
            vel_err=ones.copy(),
            scale_err=ones.copy(),
            orient_err=ones.copy(),
            attr_err=ones.copy(),
        )


@dataclass(frozen=True, eq=False)
class DetectionMetrics:
    """Per-class AP and TP errors and their summaries over ``classes``."""

    config: DetectionConfig
    classes: tuple[str, ...]  # the classes the means run over, in config order
    label_aps: dict[str, dict[float, float]]  # class -> threshold (m) -> AP
    label_tp_errors: dict[str, dict[str, float]]  # class -> TP metric -> error (NaN: undefined for the class)
    metric_data: dict[tuple[str, float], DetectionMetricData]

    @property
    def mean_dist_aps(self) -> dict[str, float]:
        """AP of each class averaged over the distance thresholds."""
        return {c: float(np.mean(list(self.label_aps[c].values()))) for c in self.classes}

    @property
    def mean_ap(self) -> float:
        return float(np.mean(list(self.mean_dist_aps.values())))

    @property
    def tp_errors(self) -> dict[str, float]:
        """Each TP error averaged over the classes, ignoring classes where it is undefined (NaN if none)."""
        out = {}
        for metric in TP_METRICS:
            errors = np.array([self.label_tp_errors[c][metric] for c in self.classes])
            out[metric] = float(np.nanmean(errors)) if not np.all(np.isnan(errors)) else math.nan
        return out

    @property
    def tp_scores(self) -> dict[str, float]:
        """1 - error, clipped at 0 (an undefined error scores 0, as the devkit's ``max(0.0, nan)`` does)."""
        scores = {}
        for metric, err in self.tp_errors.items():
            score = 1.0 - err
            scores[metric] = score if score > 0.0 else 0.0
        return scores

    @property
    def nd_score(self) -> float:
        """nuScenes detection score: weighted mean of mAP and the five TP scores."""
        w = self.config.mean_ap_weight
        total = float(w * self.mean_ap + np.sum(list(self.tp_scores.values())))
        return total / float(w + len(TP_METRICS))

    def to_dict(self) -> dict:
        """A JSON-ready summary: ``mAP``, ``NDS``, ``classes``, ``tp_errors`` and ``per_class`` (NaN -> None)."""
        mean_dist_aps = self.mean_dist_aps
        per_class = {
            c: {
                "AP": mean_dist_aps[c],
                "AP_by_dist_m": {str(float(t)): ap for t, ap in self.label_aps[c].items()},
                **{m: _none_if_nan(e) for m, e in self.label_tp_errors[c].items()},
            }
            for c in self.classes
        }
        return {
            "mAP": self.mean_ap,
            "NDS": self.nd_score,
            "classes": list(self.classes),
            "tp_errors": {m: _none_if_nan(e) for m, e in self.tp_errors.items()},
            "per_class": per_class,
        }


def _none_if_nan(x: float) -> float | None:
    return None if math.isnan(x) else x
