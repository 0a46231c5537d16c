"""streamdet.calibration: cameras, rig, projection, grid / quadrants / sectors, projection LUT, perturbation.

numpy only: a vehicle process imports it without PyTorch.
"""

from streamdet.calibration.camera import (
    CalibrationError,
    Camera,
    Rig,
    invert_transform,
    make_transform,
    matrix_to_quaternion,
    quaternion_to_matrix,
)
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut import Lut
from streamdet.calibration.lut_build import build_lut
from streamdet.calibration.perturb import euler_to_matrix, matrix_to_euler, perturb_rig
from streamdet.calibration.projection import project_points, visible_mask
from streamdet.calibration.sectors import (
    camera_sees_sector,
    cameras_overlapping_sector,
    intervals_overlap_deg,
    sector_camera_table,
)
from streamdet.core.sectors import (
    NUM_QUADRANTS,
    azimuth_deg,
    check_num_slices,
    quadrants_of_sector,
    sector_bounds_deg,
    slice_index_of,
)

__all__ = [
    "CalibrationError",
    "Camera",
    "GridSpec",
    "Lut",
    "NUM_QUADRANTS",
    "Rig",
    "azimuth_deg",
    "build_lut",
    "camera_sees_sector",
    "cameras_overlapping_sector",
    "check_num_slices",
    "euler_to_matrix",
    "intervals_overlap_deg",
    "invert_transform",
    "make_transform",
    "matrix_to_euler",
    "matrix_to_quaternion",
    "perturb_rig",
    "project_points",
    "quadrants_of_sector",
    "quaternion_to_matrix",
    "sector_bounds_deg",
    "sector_camera_table",
    "slice_index_of",
    "visible_mask",
]
