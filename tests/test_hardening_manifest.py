"""The manifest checked completely before anything runs: manifest.schema.json (one definition, the runtime's own
validator agreeing with jsonschema), the graphs' real signatures, and the post settings the runtime now honours."""

from __future__ import annotations

import json
import shutil
try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the dev extra installs tomli
    import tomli as tomllib
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from streamdet.core.classes import CLASS_NAMES
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.manifest import ManifestError, read_manifest, sha256_file
from streamdet.runtime_ort.nms import NmsConfig, NmsKind, nms
from streamdet.runtime_ort.schema import KEYWORDS, SCHEMA_FILE, SchemaViolation, manifest_schema, validate

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def export_copy(tiny_export, tmp_path) -> Path:
    out = tmp_path / "tiny"
    shutil.copytree(tiny_export, out)
    return out


def _edit(export_dir: Path, change) -> None:
    path = export_dir / "manifest.json"
    d = json.loads(path.read_text())
    change(d)
    path.write_text(json.dumps(d))


def test_the_schema_is_valid_json_schema_and_uses_only_implemented_keywords():
    schema = manifest_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    used = set()

    def walk(node, parent_key=None):
        if isinstance(node, dict):
            if parent_key not in ("properties", "$defs"):
                used.update(node)
            for k, v in node.items():
                walk(v, k)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(schema)
    assert used <= KEYWORDS


def test_the_schema_ships_with_the_package():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert SCHEMA_FILE in cfg["tool"]["setuptools"]["package-data"]["streamdet.runtime_ort"]
    assert (ROOT / "runtime_ort" / SCHEMA_FILE).is_file()


def test_every_export_validates_against_the_schema(tiny_export):
    d = json.loads((tiny_export / "manifest.json").read_text())
    jsonschema.validate(d, manifest_schema(), cls=jsonschema.Draft202012Validator)
    validate(d)
    # the LiDAR-only form: the image fields null, the slice graph alone (as test_export_lidar_only's exports)
    lidar = {**d, "image": None, "normalisation": None, "lut": None, "preset": {**d["preset"], "use_image": False},
             "graphs": [g for g in d["graphs"] if g["name"] == "slice_head"]}  # fmt: skip
    jsonschema.validate(lidar, manifest_schema(), cls=jsonschema.Draft202012Validator)
    validate(lidar)


@pytest.mark.parametrize(
    "change,match",
    [
        (lambda d: d["preset"].pop("pillars"), "preset is missing the field 'pillars'"),
        (lambda d: d["preset"].pop("channels"), "preset is missing the field 'channels'"),
        (lambda d: d["post"].pop("score_threshold"), "post is missing the field 'score_threshold'"),
        (lambda d: d["preset"]["pillars"].update(max_pillars=0), r"preset.pillars.max_pillars: 0 is below the minimum 1"),
        (lambda d: d["graphs"][0].update(gmac="lots"), r"graphs\[0\].gmac: expected number, got str"),
        (lambda d: d["graphs"][0]["gmac_at"].update(J="x"), r"graphs\[0\].gmac_at.J: expected number, got str"),
        (lambda d: d["lut"].update(calibration_source=7), r"lut.calibration_source: expected string, got int"),
        (lambda d: d["image"].update(camera_names=["A", "A"]), r"image.camera_names: item 'A' is repeated"),
        (lambda d: d["post"].update(score_threshold=float("inf")), r"post.score_threshold: inf is above the maximum 1"),
        (lambda d: d["grid"].update(voxel_xy_m=0), r"grid.voxel_xy_m: 0 must be above 0"),
        (lambda d: d.update(num_slices=1e9), r"num_slices: 1000000000.0 is above the maximum 4096"),
    ],
)
def test_malformed_fields_are_named_errors(export_copy, change, match):
    _edit(export_copy, change)
    with pytest.raises(ManifestError, match=match):
        read_manifest(export_copy, verify_files=False)


@pytest.mark.parametrize("names", [CLASS_NAMES[::-1], CLASS_NAMES[:9], (*CLASS_NAMES[:9], "zebra")])
def test_class_names_must_be_the_runtimes_label_table(export_copy, names):
    _edit(export_copy, lambda d: d.update(class_names=list(names)))
    with pytest.raises(ManifestError, match="differ from the runtime's label table"):
        StreamingDetector(export_copy)


def test_a_feature_size_that_does_not_follow_from_the_image_size_is_a_manifest_error(export_copy):
    _edit(export_copy, lambda d: d["image"].update(feature_width=33))
    with pytest.raises(ManifestError, match=r"image.feature_width/height 33x18 do not follow from 128x72 at stride 4"):
        StreamingDetector(export_copy)


def _swap_graph(export_dir: Path, name: str, source: str) -> None:
    shutil.copy(export_dir / source, export_dir / name)
    _edit(export_dir, lambda d: [g.update(sha256=sha256_file(export_dir / name)) for g in d["graphs"] if g["file"] == name])


def test_a_lifter_graph_in_place_of_the_slice_graph_fails_at_load(export_copy):
    _swap_graph(export_copy, "slice_head.onnx", "volumetric_lifter.onnx")
    with pytest.raises(ManifestError, match=r"slice_head.onnx \(slice_head, fp32\): the graph's inputs are \['features'"):
        StreamingDetector(export_copy)


def test_a_declared_io_that_differs_from_the_graph_fails_at_load(export_copy):
    _edit(export_copy, lambda d: d["graphs"][2]["outputs"][0].update(dtype="float16"))
    with pytest.raises(ManifestError, match=r"tensor 'det_boxes' is float32 in the graph, the manifest records float16"):
        StreamingDetector(export_copy)


def test_channels_that_disagree_with_the_graphs_fail_at_load(export_copy):
    _edit(export_copy, lambda d: d["preset"].update(channels=16))
    with pytest.raises(ManifestError, match=r"tensor '(features|image_bev)' has dimension 1 = 8 in the graph"):
        StreamingDetector(export_copy)


def test_the_validator_reports_the_deepest_anyof_failure():
    schema = {"anyOf": [{"type": "null"}, {"type": "object", "required": ["a"], "properties": {"a": {"type": "integer"}}}]}
    with pytest.raises(SchemaViolation, match=r"manifest field a: expected integer, got str"):
        validate({"a": "x"}, schema)
    with pytest.raises(SchemaViolation, match=r"manifest: 3 is not allowed"):
        validate(3, schema)


# ---- post settings: written to every manifest, now honoured ---------------------------------------------------------
def test_nms_follows_the_exports_post_settings(export_copy):
    det = StreamingDetector(export_copy)
    m = det.manifest
    assert det.config.nms.max_out == m.post["max_detections"]
    assert det.config.nms.iou_threshold == m.post["nms_iou_threshold"][0]
    per_class = [0.1 + 0.05 * i for i in range(len(CLASS_NAMES))]
    _edit(export_copy, lambda d: d["post"].update(max_detections=7, nms_iou_threshold=per_class))
    det = StreamingDetector(export_copy)
    assert det.config.nms.max_out == 7 and det.config.nms.iou_threshold_per_class == tuple(per_class)
    own = NmsConfig(max_out=3)
    assert StreamingDetector(export_copy, DetectorConfig(nms=own)).config.nms is own  # the caller's wins


def test_per_class_iou_thresholds_equal_one_nms_per_class():
    rng = np.random.default_rng(0)
    n = 60
    boxes = np.zeros((n, 9), np.float32)
    boxes[:, :2] = rng.uniform(0, 6, (n, 2))
    boxes[:, 3:6] = rng.uniform(1, 3, (n, 3))
    boxes[:, 6] = rng.uniform(-np.pi, np.pi, n)
    scores = rng.uniform(0, 1, n).astype(np.float32)
    labels = rng.integers(0, 3, n)
    per_class = (0.05, 0.3, 0.7) + (0.2,) * (len(CLASS_NAMES) - 3)
    kept = set(nms(boxes, scores, labels, NmsConfig(kind=NmsKind.ROTATED, iou_threshold_per_class=per_class)).tolist())
    expect = set()
    for c in range(3):
        idx = np.flatnonzero(labels == c)
        sub = nms(boxes[idx], scores[idx], labels[idx], NmsConfig(kind=NmsKind.ROTATED, iou_threshold=per_class[c]))
        expect |= set(idx[sub].tolist())
    assert kept == expect
