"""What an export asks of the runtime beyond its graphs: its NMS, its image spec at another size, and the rig its
LUT was built from (read only from where the runtime may read)."""

from __future__ import annotations

import importlib.resources
import math
from pathlib import Path

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.core.constants import BUNDLED_PREFIX
from streamdet.runtime_ort.manifest import ImageSpec, Manifest
from streamdet.runtime_ort.nms import NmsConfig


def export_nms(manifest: Manifest) -> NmsConfig:
    """The NMS the export asks for in its post settings: max_detections kept, the per-class rotated IoU thresholds."""
    post = manifest.post
    ious = tuple(float(v) for v in post.get("nms_iou_threshold", ()))
    default = NmsConfig()
    return NmsConfig(
        iou_threshold=ious[0] if ious and len(set(ious)) == 1 else default.iou_threshold,
        iou_threshold_per_class=ious if len(set(ious)) > 1 else None,
        max_out=int(post.get("max_detections", default.max_out)),
    )


def image_spec_at(exported: ImageSpec, size: tuple[int, int] | None) -> ImageSpec:
    """The export's image spec, or the same cameras and stride at another (W, H)."""
    if size is None or size == (exported.width, exported.height):
        return exported
    w, h = size
    s = exported.feature_stride
    return ImageSpec(w, h, s, math.ceil(w / s), math.ceil(h / s), exported.camera_names)  # the encoder's feature size


def export_rig(manifest: Manifest, export_dir: Path) -> Rig:
    """The rig the export's LUT was built from (manifest.lut.calibration_source), read only from where the runtime
    may read: a file bundled with streamdet.data, or a file inside the export directory (copy it there when the
    export was made from a calibration elsewhere). Its hash must still be the LUT's calibration_sha256."""
    source = manifest.lut.calibration_source
    if source.startswith(BUNDLED_PREFIX):
        root = Path(str(importlib.resources.files("streamdet.data"))).resolve()
        path = (root / source[len(BUNDLED_PREFIX):]).resolve()
        allowed = root in path.parents
    else:
        path = (export_dir / source).resolve()  # an absolute source stays absolute
        allowed = path.parent == export_dir.resolve()
    if not (allowed and path.is_file()):
        raise ValueError(
            f"{export_dir}: DetectorConfig.image_size needs the export's calibration to rebuild the LUT, but "
            f"{source!r} is not a bundled file or a file inside the export directory; copy it into the export, "
            "re-export at that size, or keep image_size=None"
        )
    rig = Rig.from_calibration_json(path)
    if rig.sha256() != manifest.lut.calibration_sha256:
        raise CalibrationError(f"{path}: this calibration changed since the export (its hash is not the LUT's calibration_sha256)")
    return rig
