"""Kept for code that imports the box layout from its old home; it is defined in ``streamdet.core.boxes``."""

from streamdet.core.boxes import (  # noqa: F401
    BOX_DIM,
    H,
    L,
    VX,
    VY,
    W,
    X,
    Y,
    YAW,
    Z,
    bev_extent,
    bev_iou,
    box_corners_3d,
    box_corners_bev,
    indexed_bev_iou,
    paired_bev_iou,
)
from streamdet.core.classes import CLASS_NAMES  # noqa: F401
