"""The detection classes, defined once: a label is a row index into ``CLASS_NAMES``."""

from __future__ import annotations

# The 10 nuScenes detection classes, in mmdetection3d's order (the `label` of the bundled sample).
CLASS_NAMES: tuple[str, ...] = (
    "car",
    "truck",
    "trailer",
    "bus",
    "construction_vehicle",
    "bicycle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "barrier",
)
NUM_CLASSES = len(CLASS_NAMES)
