"""What an export run is asked to do (``ExportOptions``), its one-line error, and the checks made before any work."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from streamdet.export import onnx_export as ox
from streamdet.export.int8_data import DEFAULT_CALIBRATION_SAMPLES
from streamdet.export.weights import DEFAULT_SEED
from streamdet.core.image_layout import IMAGE_BEV
from streamdet.core.constants import DEFAULT_PRESET  # noqa: F401 (the exporter and its CLI read it here)
from streamdet.core.constants import MAX_RESOLUTION_PX, MIN_RESOLUTION_PX, STEM_STRIDE
from streamdet.core.lut_layout import LUT_COMPACT, LUT_SLOTS

DEFAULT_IMAGE_LAYOUT = IMAGE_BEV  # measured in docs/replay.md ("Less work per lift")
# how the lifter reads the LUT: "auto" picks compact for one height per voxel (the same BEV for less lift time) and
# slots for several, where nearly every voxel has two or more slots and compacting costs more than it saves
# (measured: docs/replay.md, "Less work per lift" and "The flat lifter on a quiet machine")
LUT_AUTO = "auto"
DEFAULT_LUT_LAYOUT = LUT_AUTO


def resolve_lut_layout(layout: str | None, heights_per_voxel: int) -> str:
    """The layout an export writes: ``layout`` itself, or for "auto" (and None, not given) compact (one height) /
    slots (several)."""
    if layout is not None and layout != LUT_AUTO:
        return layout
    return LUT_COMPACT if heights_per_voxel == 1 else LUT_SLOTS



class ExportError(Exception):
    """A problem with the export's inputs or target, stated in one line."""


class ExportUsageError(ExportError):
    """Options that do not go together, e.g. one this export would ignore (streamdet-export: a usage error, exit 2)."""


@dataclass(frozen=True)
class ExportOptions:
    preset: str | None = None  # None: the preset the checkpoint names, else DEFAULT_PRESET
    checkpoint: str | None = None  # None: the bundled fused checkpoint of the preset (export/weights.py bundled_checkpoint), else fixed-seed weights
    calibration: str | None = None  # calibration.json path; None: the bundled nuScenes sample's
    resolution: tuple[int, int] | None = None  # (W, H) px of the camera images; None: the preset's
    num_slices: int = 8  # slices per sweep (the paper's headline model); picks the parity slice
    fp16: bool = False  # also write *.fp16.onnx siblings
    int8: bool = False  # also write *.int8.onnx siblings (static QDQ, calibrated on real samples)
    calibration_data: str | None = None  # nuScenes-format dataset for the int8 calibration; None: the bundled sample
    # samples drawn from calibration_data (its train split); None (not given): DEFAULT_CALIBRATION_SAMPLES. Given
    # without int8 it is refused: nothing is calibrated
    calibration_samples: int | None = None
    opset: int = ox.DEFAULT_OPSET
    out_dir: str | None = None  # None: ./exports/<preset>
    # torch seed of the fixed-seed initial weights (no checkpoint) and of the parity check's noise images (a
    # calibration of cameras the bundled sample lacks); None (not given): DEFAULT_SEED. Given where the export uses
    # neither, it is refused (exporter._check_seed)
    seed: int | None = None
    # which map the lifter hands the slice graph (models/image_half.py): the image BEV, or the BEV encoder's image
    # half computed in the lifter graph; recorded in the manifest's image_layout. None (not given):
    # DEFAULT_IMAGE_LAYOUT. A LiDAR-only export (no lifter) refuses one given, as it does resolution and calibration
    image_layout: str | None = None
    # how the lifter graph reads the LUT (core/lut_layout.py): K slots, or the compacted valid pairs; "auto" (and
    # None, not given): resolve_lut_layout (run_export records the resolved one). A LiDAR-only export refuses one given
    lut_layout: str | None = None
    # detections per quadrant the slice graph decodes (PostConfig.top_k); None: the preset's (the paper's 500). The
    # runtime's score threshold keeps far fewer; the detector counts runs whose K-th score passed it (cut by the cap)
    top_k: int | None = None

    def with_defaults(self, heights_per_voxel: int) -> "ExportOptions":
        """These options with every one not given (None) at its default and the LUT layout resolved for a model
        sampling ``heights_per_voxel`` heights per voxel: what the export steps read."""
        return dataclasses.replace(
            self,
            calibration_samples=DEFAULT_CALIBRATION_SAMPLES if self.calibration_samples is None else self.calibration_samples,
            seed=DEFAULT_SEED if self.seed is None else self.seed,
            image_layout=DEFAULT_IMAGE_LAYOUT if self.image_layout is None else self.image_layout,
            lut_layout=resolve_lut_layout(self.lut_layout, heights_per_voxel),
        )

    @property
    def precisions(self) -> tuple[str, ...]:
        """The precisions written, fp32 first."""
        return ("fp32",) + (("fp16",) if self.fp16 else ()) + (("int8",) if self.int8 else ())


def check_resolution(width: int, height: int) -> None:
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or not MIN_RESOLUTION_PX <= v <= MAX_RESOLUTION_PX or v % STEM_STRIDE:
            raise ExportError(
                f"resolution {width}x{height}: {name} {v!r} must be an even number of pixels in "
                f"{MIN_RESOLUTION_PX}..{MAX_RESOLUTION_PX} (the ResNet stem has stride {STEM_STRIDE}; features are "
                "ceil(size / 4); core/constants.py)"
            )
