"""Manifest schema (runtime_ort/manifest.py): round trip, validation, file verification, no torch."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest

from streamdet.runtime_ort.manifest import (
    MANIFEST_VERSION,
    GraphEntry,
    ImageSpec,
    LutEntry,
    Manifest,
    ManifestError,
    Normalisation,
    ParityRecord,
    PipelineParity,
    TensorSpec,
    graph_file_name,
    read_manifest,
    sha256_file,
    write_manifest,
)

NAMES = ("image_encoder", "volumetric_lifter", "slice_head")
# the fields of preset and grid the runtime reads (manifest.schema.json requires them)
PRESET = {"name": "tiny", "channels": 8, "pillars": {"max_points_per_pillar": 8, "max_pillars": 1024}}
GRID = {"x_range_m": [-12.8, 12.8], "y_range_m": [-12.8, 12.8], "z_range_m": [-3.0, 5.0], "voxel_xy_m": 0.4, "voxel_z_m": 2.0}


def _manifest(tmp_path, precisions=("fp32",)) -> Manifest:
    graphs = []
    for precision in precisions:
        for name in NAMES:
            f = tmp_path / graph_file_name(name, precision)
            f.write_bytes(f"{name} {precision}".encode())
            graphs.append(GraphEntry(name, precision, f.name, sha256_file(f), 17,
                                     (TensorSpec("x", ("J", 3, 4), "uint8"),), (TensorSpec("y", ("J",), "float32"),), 1.5, {"J": 1}))
    (tmp_path / "lut.npz").write_bytes(b"lut")
    return Manifest(
        preset_name="tiny", preset=PRESET, grid=GRID, class_names=("car", "truck"), num_slices=8,
        image=ImageSpec(128, 72, 4, 32, 18, ("CAM_A", "CAM_B")), normalisation=Normalisation(), post={"top_k": 50, "score_threshold": 0.1},
        graphs=tuple(graphs), lut=LutEntry("lut.npz", sha256_file(tmp_path / "lut.npz"), "ab" * 32, "bundled"),
        parity=(ParityRecord("image_encoder", "fp32", "torch", "features", 1e-6, 3.0, 1e-4, True),),
        pipeline_parity=PipelineParity(0, 8, 100, 10, 0.1, 1e-3, 5, 5, 1, 0, 0, 0.01, 0.1, True, "n"),
        source={"seed": 0},
    )


def test_round_trip_and_lookup(tmp_path):
    m = _manifest(tmp_path, ("fp32", "fp16"))
    write_manifest(m, tmp_path)
    back = read_manifest(tmp_path)
    assert back == m
    assert back.version == MANIFEST_VERSION
    assert back.graph("slice_head", "fp16").file == "slice_head.fp16.onnx"
    assert back.precisions == ("fp32", "fp16")
    d = json.loads((tmp_path / "manifest.json").read_text())
    assert d["graphs"][0]["inputs"][0] == {"name": "x", "shape": ["J", 3, 4], "dtype": "uint8"}
    assert not list(tmp_path.glob(".manifest.*"))  # the atomic write leaves no temp file


def test_missing_graph_and_precision(tmp_path):
    m = _manifest(tmp_path)
    with pytest.raises(ManifestError, match="no fp16 graph 'slice_head'"):
        m.graph("slice_head", "fp16")
    with pytest.raises(ManifestError, match="no fp32 graph 'volumetric_lifter'"):
        dataclasses.replace(m, graphs=tuple(g for g in m.graphs if g.name != "volumetric_lifter"))
    with pytest.raises(ManifestError, match="listed twice"):
        dataclasses.replace(m, graphs=m.graphs + m.graphs[:1])


def test_verify_files(tmp_path):
    write_manifest(_manifest(tmp_path), tmp_path)
    (tmp_path / "slice_head.onnx").write_bytes(b"tampered")
    with pytest.raises(ManifestError, match="slice_head.onnx has sha256"):
        read_manifest(tmp_path)
    read_manifest(tmp_path, verify_files=False)
    (tmp_path / "slice_head.onnx").write_bytes(b"slice_head fp32")
    read_manifest(tmp_path)
    (tmp_path / "lut.npz").unlink()
    with pytest.raises(ManifestError, match="lut.npz is named in the manifest but missing"):
        read_manifest(tmp_path)


@pytest.mark.parametrize(
    "edit,match",
    [
        (lambda d: d.pop("graphs"), "missing the field 'graphs'"),
        (lambda d: d.update(version=99), "version: 99 is not supported"),
        (lambda d: d["graphs"][0].update(precision="int4"), "precision"),
        (lambda d: d["graphs"][0].update(sha256="xyz"), "64 lowercase hex"),
        (lambda d: d["graphs"][0].update(file="../evil.onnx"), "plain file name"),
        (lambda d: d["graphs"][0]["inputs"][0].update(dtype="float64"), r"inputs\[0\].dtype: 'float64' is not one of"),
        (lambda d: d["graphs"][0]["inputs"][0].update(shape=[-1]), r"shape\[0\]: -1 is not allowed \(expected a dimension"),
        (lambda d: d["image"].update(width=0), "image.width"),
        (lambda d: d.update(num_slices=0), "num_slices"),
        (lambda d: d.update(class_names=[]), "class_names"),
        # the preset's parts the runtime reads: the lifter's form and LUT heights, the BEV encoder's first stage
        (lambda d: d["preset"].update(lifter=None), "preset.lifter: expected object, got NoneType None"),
        (lambda d: d["preset"].update(lifter=["flat"]), "preset.lifter: expected object"),
        (lambda d: d["preset"].update(lifter={"form": "bogus"}), "preset.lifter.form: 'bogus' is not one of"),
        (lambda d: d["preset"].update(lifter={"lut_heights_per_voxel": 65}), "preset.lifter.lut_heights_per_voxel"),
        (lambda d: d["preset"].update(bev=[]), "preset.bev: expected object"),
        (lambda d: d["preset"].update(bev={"layer_strides": "x"}), "preset.bev.layer_strides: expected array"),
        (lambda d: d["preset"].update(bev={"num_filters": [0]}), r"preset.bev.num_filters\[0\]"),
        (lambda d: d.update(image_layout="image_half"), "image_layout 'image_half' needs preset.bev.layer_strides"),
        (lambda d: (d.update(image_layout="image_half"), d["preset"].update(bev={"layer_strides": [], "num_filters": [8]})),
         "preset.bev.layer_strides"),
    ],
)
def test_malformed(tmp_path, edit, match):
    d = _manifest(tmp_path).to_dict()
    edit(d)
    with pytest.raises(ManifestError, match=match):
        Manifest.from_dict(d)


def test_unreadable_and_absent(tmp_path):
    with pytest.raises(ManifestError, match="does not exist"):
        read_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(ManifestError, match="not readable JSON"):
        read_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text("[1, 2]")
    with pytest.raises(ManifestError, match="JSON object"):
        read_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text('{"version": 1' + "0" * 5000 + "}")  # past Python's int-parsing limit
    with pytest.raises(ManifestError, match="manifest.json is not readable JSON"):
        read_manifest(tmp_path)


def test_imports_without_torch():
    script = (
        "import sys; sys.modules['torch'] = None; sys.modules['onnxconverter_common'] = None\n"
        "import streamdet.runtime_ort.manifest, streamdet.runtime_ort.calib_cli\n"
        "assert not any(m.split('.')[0] == 'torch' for m, v in sys.modules.items() if v is not None)\n"
        "print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"
