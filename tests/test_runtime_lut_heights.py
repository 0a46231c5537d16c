"""The runtime's own LUT rebuild (set_calibration with a rig) builds the model's kind of LUT: its heights per voxel."""

from __future__ import annotations

import json
import shutil

from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector


def test_set_calibration_rebuilds_with_the_presets_heights(tiny_export, tmp_path):
    export = tmp_path / "exp"
    shutil.copytree(tiny_export, export)
    manifest = json.loads((export / "manifest.json").read_text())
    manifest["preset"].setdefault("lifter", {})["lut_heights_per_voxel"] = 2
    (export / "manifest.json").write_text(json.dumps(manifest))
    det = StreamingDetector(export, DetectorConfig())
    assert det.lut.heights_per_voxel == 1  # the export's own lut.npz, as written
    det.set_calibration(load_bundled_sample(None).rig)
    assert det.lut.heights_per_voxel == 2
