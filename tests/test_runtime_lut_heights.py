"""The runtime's own LUT rebuild (set_calibration with a rig) builds the model's kind of LUT: its heights per voxel;
a LUT of another kind than the manifest's is refused (export_open.check_lut)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from streamdet.calibration.camera import CalibrationError
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.calib_cli import rebuild_lut
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector

CALIBRATION = Path(__file__).resolve().parents[1] / "data" / "nuscenes_sample" / "calibration.json"


def test_set_calibration_rebuilds_with_the_presets_heights(tiny_export, tmp_path):
    export = tmp_path / "exp"
    shutil.copytree(tiny_export, export)
    manifest = json.loads((export / "manifest.json").read_text())
    manifest["preset"].setdefault("lifter", {})["lut_heights_per_voxel"] = 2
    (export / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(CalibrationError, match=r"heights per voxel 1 != the export's 2"):
        StreamingDetector(export, DetectorConfig())  # the export's own lut.npz, as written: another kind now
    lut, _ = rebuild_lut(CALIBRATION, export)  # streamdet-calib builds the manifest's kind
    assert lut.heights_per_voxel == 2
    det = StreamingDetector(export, DetectorConfig())
    assert det.lut.heights_per_voxel == 2
    det.set_calibration(load_bundled_sample(None).rig)  # a file's LUT is never taken for a rig's: built again
    assert det.lut.heights_per_voxel == 2
