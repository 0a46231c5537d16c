"""streamdet.evaluation: nuScenes detection metrics (mAP, TP errors, NDS) as the official devkit computes them.

numpy only. ``evaluate(gt, pred)`` takes ``EvalBoxes`` in the nuScenes global frame; ``results`` converts
streamdet LiDAR-frame boxes to and from nuScenes results entries and reads / writes results files.
"""

from streamdet.evaluation.config import TP_METRICS, DetectionConfig
from streamdet.evaluation.detection_eval import accumulate, calc_ap, calc_tp, evaluate, filter_eval_boxes
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.metrics import DetectionMetricData, DetectionMetrics
from streamdet.evaluation.results import (
    boxes_to_gt,
    boxes_to_results,
    global_to_lidar,
    lidar_to_global,
    load_eval_inputs,
    load_gt_and_predictions,
    read_results_json,
    results_to_boxes,
    write_results_json,
)

__all__ = [
    "TP_METRICS",
    "DetectionConfig",
    "DetectionMetricData",
    "DetectionMetrics",
    "EvalBoxes",
    "accumulate",
    "boxes_to_gt",
    "boxes_to_results",
    "calc_ap",
    "calc_tp",
    "evaluate",
    "filter_eval_boxes",
    "global_to_lidar",
    "lidar_to_global",
    "load_eval_inputs",
    "load_gt_and_predictions",
    "read_results_json",
    "results_to_boxes",
    "write_results_json",
]
