"""streamdet.studies: the paper's robustness studies (Sec. IV) of a streaming export, one module per study.

Each study runs an export through the onnxruntime runtime (``runtime_ort.pipeline`` feeds it the samples) over a
dataset split and returns a frozen result with ``to_dict()`` (every figure) and ``format_table()``:

- ``slices``: mAP at 1, 4, 8, 16, 32 slices per sweep, the fused model beside a LiDAR-only baseline
- ``drop_camera``: mAP and per-class AP with a named camera missing at inference
- ``calib_noise``: mAP under uniform extrinsic noise, the LUT rebuilt for every noisy rig, the graphs untouched
- ``resolution``: mAP and image-lane latency with the images fed at other sizes than the export's

``common`` holds what they share (data, runtime options, scoring); ``checkpoints`` is the only part that needs
PyTorch (a LiDAR-only baseline evaluated with PyTorch, a checkpoint exported first), imported when called; ``cli``
is ``streamdet-study``. This package sits above evaluation/ and runtime_ort/, which never import it.
"""

from streamdet.studies.calib_noise import DEFAULT_NOISE_LEVELS, CalibNoiseResult, NoiseLevel, calib_noise_study, noise_seed
from streamdet.studies.checkpoints import export_checkpoint, torch_sliced_detector
from streamdet.studies.common import (
    SHORT_CLASS,
    Progress,
    RuntimeOptions,
    Score,
    StudyData,
    StudyError,
    open_detector,
    open_image_detector,
    score_variants,
)
from streamdet.studies.drop_camera import DEFAULT_DROPPED_CAMERA, DropCameraResult, check_cameras, drop_camera_study
from streamdet.studies.resolution import DEFAULT_RESOLUTIONS, ResolutionResult, ResolutionRow, resolution_study
from streamdet.studies.slices import DEFAULT_SLICE_COUNTS, OnnxSlicedDetector, SlicedDetector, SlicesResult, slices_study

__all__ = [
    "DEFAULT_DROPPED_CAMERA",
    "DEFAULT_NOISE_LEVELS",
    "DEFAULT_RESOLUTIONS",
    "DEFAULT_SLICE_COUNTS",
    "SHORT_CLASS",
    "CalibNoiseResult",
    "DropCameraResult",
    "NoiseLevel",
    "OnnxSlicedDetector",
    "Progress",
    "ResolutionResult",
    "ResolutionRow",
    "RuntimeOptions",
    "Score",
    "SlicedDetector",
    "SlicesResult",
    "StudyData",
    "StudyError",
    "calib_noise_study",
    "check_cameras",
    "drop_camera_study",
    "export_checkpoint",
    "noise_seed",
    "open_detector",
    "open_image_detector",
    "resolution_study",
    "score_variants",
    "slices_study",
    "torch_sliced_detector",
]
