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

# One colour per class (CLASS_NAMES order), RGB 0..255, for every picture the project draws (preview PNGs, the
# bird's-eye views, the ROS 2 markers): a pedestrian is the same colour in a PNG and in Foxglove.
CLASS_COLORS_RGB: tuple[tuple[int, int, int], ...] = (
    (255, 180, 60),  # car
    (255, 120, 0),  # truck
    (200, 80, 0),  # trailer
    (255, 200, 0),  # bus
    (140, 140, 0),  # construction_vehicle
    (255, 80, 255),  # bicycle
    (200, 60, 200),  # motorcycle
    (80, 255, 80),  # pedestrian
    (255, 40, 40),  # traffic_cone
    (60, 200, 200),  # barrier
)
OTHER_COLOR_RGB = (160, 160, 160)  # a label outside CLASS_NAMES


def class_color_rgb(label: int) -> tuple[int, int, int]:
    """The RGB 0..255 colour of ``label``; OTHER_COLOR_RGB for one outside CLASS_NAMES (-1, or a custom class)."""
    return CLASS_COLORS_RGB[label] if 0 <= label < NUM_CLASSES else OTHER_COLOR_RGB
