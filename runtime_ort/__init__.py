"""streamdet.runtime_ort: the torch-free onnxruntime runtime a vehicle process embeds.

    from streamdet.runtime_ort import StreamingDetector, DetectorConfig, StreamingRunner

Names are imported lazily, so importing one module of the package (``streamdet.runtime_ort.manifest``) does not
load onnxruntime.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "StreamingDetector": "streamdet.runtime_ort.detector",
    "DetectorConfig": "streamdet.runtime_ort.detector_config",
    "SliceResult": "streamdet.runtime_ort.detector_results",
    "ImageUpdate": "streamdet.runtime_ort.detector_results",
    "SweepResult": "streamdet.runtime_ort.detector_results",
    "NoImageLaneError": "streamdet.runtime_ort.detector_config",
    "DetectorClosed": "streamdet.runtime_ort.detector_config",
    "StreamingRunner": "streamdet.runtime_ort.lanes",
    "LaneConfig": "streamdet.runtime_ort.lanes",
    "SliceDropped": "streamdet.runtime_ort.lanes",
    "ImagesSuperseded": "streamdet.runtime_ort.lanes",
    "CalibrationSuperseded": "streamdet.runtime_ort.lanes",
    "RunnerClosed": "streamdet.runtime_ort.lanes",
    "ManifestError": "streamdet.runtime_ort.manifest",
    "GraphRunError": "streamdet.runtime_ort.sessions",
    "ProviderError": "streamdet.runtime_ort.sessions",
    # what set_calibration raises and warns (defined with the LUT, which the runtime shares with the export)
    "CalibrationError": "streamdet.calibration.camera",
    "BlindCameraWarning": "streamdet.calibration.lut",
    "CameraMovedWarning": "streamdet.calibration.lut",
    # what the ROS 2 adapters (streamdet.runtime_ort.ros) raise for a message they cannot read or write, and the two
    # refusals a node may want to tell apart: a cloud's per-point clock, and a TF lookup with no answer
    "RosMessageError": "streamdet.runtime_ort.ros.header",
    "CloudClockError": "streamdet.runtime_ort.ros.pointcloud2",
    "TfLookupError": "streamdet.runtime_ort.ros.tf",
    "PhaseLockStats": "streamdet.runtime_ort.phase_locked_lane",
    "Detections": "streamdet.runtime_ort.postprocess",
    "PostprocessConfig": "streamdet.runtime_ort.postprocess",
    "NmsConfig": "streamdet.runtime_ort.nms",
    "NmsKind": "streamdet.runtime_ort.nms",
    "CLASS_NAMES": "streamdet.core.classes",
}
# Not here: the ``pillarize`` function (``from streamdet.runtime_ort.pillarize import pillarize``). The package attribute
# of that name is its submodule once anything has imported it, so the function cannot be a package name reliably.

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'streamdet.runtime_ort' has no attribute {name!r}")
