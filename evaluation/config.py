"""The nuScenes detection-eval configuration ``detection_cvpr_2019``, as a frozen dataclass.

Values are those of nuscenes-devkit's ``nuscenes/eval/detection/configs/detection_cvpr_2019.json``, the
configuration of the official leaderboard. The class order of ``class_range_m`` is the devkit's: every
per-class table and every mean iterates in this order, so floating-point sums match the devkit's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

# The five true-positive metrics, in the devkit's order (TP_METRICS).
TP_METRICS: tuple[str, ...] = ("trans_err", "scale_err", "orient_err", "vel_err", "attr_err")

# TP metrics the devkit does not define for a class (set to NaN, then ignored by the nan-mean over classes):
# cones have no orientation, velocity or attribute; barriers do not move and have no attribute.
UNDEFINED_TP_METRICS: Mapping[str, frozenset[str]] = MappingProxyType(
    {
        "traffic_cone": frozenset({"attr_err", "vel_err", "orient_err"}),
        "barrier": frozenset({"attr_err", "vel_err"}),
    }
)


def _cvpr_2019_class_range() -> Mapping[str, float]:
    # Boxes (GT and predictions) farther than this from the ego vehicle, in the xy plane, are not evaluated.
    return MappingProxyType(
        {
            "car": 50.0,
            "truck": 50.0,
            "bus": 50.0,
            "trailer": 50.0,
            "construction_vehicle": 50.0,
            "pedestrian": 40.0,
            "motorcycle": 40.0,
            "bicycle": 40.0,
            "traffic_cone": 30.0,
            "barrier": 30.0,
        }
    )


@dataclass(frozen=True)
class DetectionConfig:
    """Parameters of the nuScenes detection metrics (defaults: ``detection_cvpr_2019``)."""

    # Per-class evaluation range in metres (xy distance to the ego vehicle, strict <); also fixes the class order.
    class_range_m: Mapping[str, float] = field(default_factory=_cvpr_2019_class_range)
    # Centre-distance (xy) matching thresholds for AP, in metres; a match needs distance < threshold.
    dist_ths_m: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)
    # The matching threshold at which the TP errors are measured, in metres; must be one of dist_ths_m.
    dist_th_tp_m: float = 2.0
    # AP and TP errors ignore the operating points at recall <= min_recall (the curve is unreliable there).
    min_recall: float = 0.1
    # Precision below this counts as 0 and AP is renormalised by 1 / (1 - min_precision).
    min_precision: float = 0.1
    # The devkit refuses result files with more boxes than this in one sample.
    max_boxes_per_sample: int = 500
    # NDS = (mean_ap_weight * mAP + sum of the 5 TP scores) / (mean_ap_weight + 5).
    mean_ap_weight: float = 5.0

    def __post_init__(self) -> None:
        if not isinstance(self.class_range_m, MappingProxyType):
            object.__setattr__(self, "class_range_m", MappingProxyType(dict(self.class_range_m)))
        if not self.class_range_m:
            raise ValueError("DetectionConfig.class_range_m must name at least one class, got {}")
        for name, rng in self.class_range_m.items():
            if not (isinstance(name, str) and name):
                raise ValueError(f"DetectionConfig.class_range_m keys must be class names, got {name!r}")
            if not (isinstance(rng, (int, float)) and rng > 0):
                raise ValueError(f"DetectionConfig.class_range_m[{name!r}] must be a range > 0 m, got {rng!r}")
        object.__setattr__(self, "dist_ths_m", tuple(float(t) for t in self.dist_ths_m))
        if not self.dist_ths_m or any(not (math.isfinite(t) and t > 0) for t in self.dist_ths_m):
            raise ValueError(f"DetectionConfig.dist_ths_m must be finite thresholds > 0 m, got {self.dist_ths_m}")
        if self.dist_th_tp_m not in self.dist_ths_m:
            raise ValueError(
                f"DetectionConfig.dist_th_tp_m must be one of dist_ths_m {self.dist_ths_m}, got {self.dist_th_tp_m}"
            )
        if not 0.0 <= self.min_recall <= 1.0:
            raise ValueError(f"DetectionConfig.min_recall must be in [0, 1], got {self.min_recall}")
        if not 0.0 <= self.min_precision < 1.0:
            raise ValueError(f"DetectionConfig.min_precision must be in [0, 1), got {self.min_precision}")
        if not (isinstance(self.max_boxes_per_sample, int) and self.max_boxes_per_sample > 0):
            raise ValueError(f"DetectionConfig.max_boxes_per_sample must be an int > 0, got {self.max_boxes_per_sample!r}")
        if not self.mean_ap_weight >= 0:
            raise ValueError(f"DetectionConfig.mean_ap_weight must be >= 0, got {self.mean_ap_weight}")

    @property
    def class_names(self) -> tuple[str, ...]:
        """The evaluated classes, in the devkit's order."""
        return tuple(self.class_range_m)
