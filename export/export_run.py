"""The state one export run carries from step to step (export/steps.py lists the steps)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from streamdet.calibration.camera import Rig
from streamdet.calibration.lut import Lut
from streamdet.export import onnx_export as ox
from streamdet.export.options import ExportOptions
from streamdet.export.parity_inputs import ParityInputs
from streamdet.export.record import Gmacs
from streamdet.export.weights import WeightsSource
from streamdet.models.detector import StreamDetector
from streamdet.models.presets import Preset
from streamdet.runtime_ort.manifest import Manifest
from streamdet.runtime_ort.manifest_records import Int8Record, ParityRecord, PipelineParity
from streamdet.runtime_ort.recording import Feeds


@dataclass(eq=False)
class ExportRun:
    """Inputs of the run (first block), then what the steps produce, in step order."""

    tmp: Path  # the staging directory (export/staging.py)
    out_dir: Path
    preset: Preset  # with the export's image size and use_image
    size: tuple[int, int]  # (W, H) px of the camera images
    opts: ExportOptions
    note: Callable[[str], None]  # a line under the current step
    det: StreamDetector | None = None
    source: WeightsSource | None = None
    rig: Rig | None = None  # None: LiDAR-only
    lut: Lut | None = None
    calibration_source: str | None = None
    inputs: ParityInputs | None = None
    feeds32: dict[str, Feeds] = field(default_factory=dict)  # each graph's parity feeds (fp32 upstream)
    outputs32: dict[str, list[np.ndarray]] = field(default_factory=dict)  # each graph's fp32 outputs on them
    margins_of: Callable[[list[np.ndarray]], Any] | None = None  # near-tie margins of decoded detections
    parity: list[ParityRecord] = field(default_factory=list)
    gmacs: Gmacs = field(default_factory=dict)
    pipeline: PipelineParity | None = None
    int8_work: Any = None  # export/int8_steps.py: Int8Work between its steps
    int8_record: Int8Record | None = None
    manifest: Manifest | None = None
    committed_dir: Path | None = None  # where the export went: out_dir, or beside it when its parity failed

    @property
    def parity_passed(self) -> bool:
        """Every parity record of the manifest passed (and the fp16 pipeline check where there is one)."""
        return manifest_parity_passed(self.manifest)

    @property
    def graphs(self) -> tuple[str, ...]:
        """The graphs this export writes, in pipeline order."""
        return tuple(ox.graph_ios(self.preset.use_image, self.preset.slice_crop, self.opts.image_layout, self.opts.lut_layout))

    def graph_io(self, name: str) -> ox.GraphIO:
        """The names and dynamic axes of graph ``name`` of this export."""
        return ox.graph_ios(self.preset.use_image, self.preset.slice_crop, self.opts.image_layout, self.opts.lut_layout)[name]


def manifest_parity_passed(manifest: Manifest) -> bool:
    """Every parity record of ``manifest`` passed, and its fp16 pipeline check where there is one."""
    pipeline_ok = manifest.pipeline_parity is None or manifest.pipeline_parity.passed
    return pipeline_ok and all(p.passed for p in manifest.parity)
