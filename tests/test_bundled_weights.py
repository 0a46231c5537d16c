"""Every shipped checkpoint (models/weights/*.pt, the package data) comes with its record: a JSON beside it whose
file name, hash, size, preset and use of the cameras are the checkpoint's own (scripts/ship_weights.py writes it)."""

from __future__ import annotations

import importlib.resources
import json
from pathlib import Path

import pytest

from streamdet.export.weights import SHIPPED_MAX_BYTES as MAX_BYTES
from streamdet.export.weights import bundled_checkpoint, checkpoint_preset
from streamdet.runtime_ort.manifest import sha256_file

WEIGHTS = Path(str(importlib.resources.files("streamdet.models"))) / "weights"
SHIPPED = sorted(WEIGHTS.glob("*.pt"))


def test_the_shipped_models_are_there():
    assert {p.name for p in SHIPPED} >= {"small.pt", "small_lidar_only.pt", "small_lite.pt", "small_v3_swift.pt"}


@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_each_shipped_checkpoint_matches_its_record(path):
    record_path = path.with_suffix(".json")
    assert record_path.is_file(), f"{path.name} is shipped without {record_path.name}"
    record = json.loads(record_path.read_text())
    assert record["file"] == path.name
    assert record["size_bytes"] == path.stat().st_size <= MAX_BYTES
    assert record["sha256"] == sha256_file(path)
    saved = checkpoint_preset(path)
    assert saved is not None and saved["name"] == record["preset"]
    assert saved.get("use_image", True) == record["use_image"]
    assert record["scores_val"] and record["trained_on"]["not_real_data"]
    if record["use_image"]:  # a fused checkpoint is some preset's default (the first by file name)
        assert bundled_checkpoint(record["preset"]) is not None
