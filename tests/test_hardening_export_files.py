"""An export's files as the runtime loads them (audit 3): each read once, bounded, hashed from the bytes that are
loaded; no graph keeps weights in another file; graphs of another opset or precision, inputs fixed where the runtime
varies them, a grid edited apart from its preset, a LUT of another calibration, a manifest symlinked out: all
refused with a ManifestError naming the file. Plus ``core.file_input``, the bounded reader under all of it."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import external_data_helper

from streamdet.core.file_input import InputFileError, describe_bytes, read_regular_file
from streamdet.runtime_ort import sessions
from streamdet.runtime_ort import manifest as manifest_mod
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.graph_files import external_tensors, graph_precision
from streamdet.runtime_ort.manifest import ManifestError, read_manifest, sha256_file


@pytest.fixture
def export_copy(tiny_export, tmp_path) -> Path:
    out = tmp_path / "box" / "tiny"
    shutil.copytree(tiny_export, out)
    return out



def _edit_manifest(export_dir: Path, change) -> None:
    path = export_dir / "manifest.json"
    d = json.loads(path.read_text())
    change(d)
    path.write_text(json.dumps(d))


def _rehash(export_dir: Path, name: str) -> None:
    """Record ``name``'s current sha256 in the manifest: what a broken re-export (or a hostile writer) does."""
    sha = sha256_file(export_dir / name)
    _edit_manifest(export_dir, lambda d: [e.update(sha256=sha) for e in d["graphs"] + [d["lut"]] if e["file"] == name])


# ---- external data: weights in a file no sha256 covers ------------------------------------------------------------
@pytest.mark.parametrize("location", ["w.bin", "../outside.bin"])
def test_a_graph_with_external_data_is_refused(export_copy, location):
    path = export_copy / "slice_head.onnx"
    model = onnx.load(path)
    tensor = model.graph.initializer[0]
    external_data_helper.set_external_data(tensor, location)
    (export_copy / location).resolve().write_bytes(tensor.raw_data or np.zeros(1, np.float32).tobytes())
    tensor.ClearField("raw_data")
    tensor.data_location = onnx.TensorProto.EXTERNAL
    path.write_bytes(model.SerializeToString())
    _rehash(export_copy, path.name)
    assert external_tensors(onnx.load(path, load_external_data=False)) == [(tensor.name, location)]
    with pytest.raises(ManifestError, match=rf"slice_head.onnx: 1 tensor\(s\) keep their data in another file \({tensor.name!r} in {location!r}\)"):
        StreamingDetector(export_copy)


def test_the_shipped_graphs_keep_every_weight_inside(tiny_export):
    for f in sorted(tiny_export.glob("*.onnx")):
        assert external_tensors(onnx.load(f, load_external_data=False)) == [], f.name


# ---- one read: the bytes hashed are the bytes loaded --------------------------------------------------------------
def test_sessions_and_the_lut_load_the_bytes_that_were_hashed(export_copy, monkeypatch):
    """No loader opens a graph or the LUT by path after its check: a file swapped in between is never loaded."""
    opened = []
    real = sessions.ort.InferenceSession

    def spy(src, *a, **k):
        opened.append(type(src))
        return real(src, *a, **k)

    monkeypatch.setattr(sessions.ort, "InferenceSession", spy)
    from streamdet.calibration import lut as lut_mod

    loads = []
    real_load = lut_mod.Lut.load.__func__
    monkeypatch.setattr(lut_mod.Lut, "load", classmethod(lambda cls, *a, **k: loads.append(k.get("data")) or real_load(cls, *a, **k)))
    det = StreamingDetector(export_copy, DetectorConfig(camera_terms=False))
    assert opened and set(opened) == {bytes}
    assert len(loads) == 1 and isinstance(loads[0], bytes)
    assert det.lut.index.size > 0


def test_a_graph_changed_after_its_check_is_not_what_runs(export_copy, monkeypatch):
    """The race the audit showed: the file replaced between the sha256 check and onnxruntime's open."""
    path = export_copy / "slice_head.onnx"
    good = path.read_bytes()
    real = manifest_mod.read_regular_file
    reads = []

    def read_then_swap(p, limit):
        raw = real(p, limit)
        if Path(p).name == "slice_head.onnx":
            reads.append(p)
            if len(reads) == 2:  # read_manifest's check, then the load's read: swap right after the latter
                path.write_bytes(b"swapped after the check")  # whoever opens by path now gets this
        return raw

    monkeypatch.setattr(manifest_mod, "read_regular_file", read_then_swap)
    det = StreamingDetector(export_copy, DetectorConfig(camera_terms=False, verify_sha256=True))
    assert len(reads) == 2 and path.read_bytes() != good
    assert det.slice_head.session.get_inputs()[0].name == "pillar_features"  # the good graph loaded


# ---- files that are no regular file, or too large -----------------------------------------------------------------
@pytest.mark.parametrize("name", ["slice_head.onnx", "lut.npz"])
def test_a_fifo_in_the_export_never_blocks_even_unhashed(export_copy, alarm, name):
    (export_copy / name).unlink()
    os.mkfifo(export_copy / name)
    with pytest.raises(ManifestError, match=rf"{name}: not a regular file"):
        StreamingDetector(export_copy, DetectorConfig(verify_sha256=False))


def test_a_graph_over_its_limit_is_refused_before_reading(export_copy, monkeypatch):
    monkeypatch.setattr(manifest_mod, "MAX_GRAPH_BYTES", 1000)
    with pytest.raises(ManifestError, match=r"image_encoder.onnx: is \d+ bytes, over the 1000 bytes limit; refused before reading"):
        StreamingDetector(export_copy, DetectorConfig(verify_sha256=False))
    with pytest.raises(ManifestError, match=r"over the 1000 bytes limit"):
        read_manifest(export_copy)


def test_the_manifest_itself_is_confined(export_copy, tmp_path):
    outside = tmp_path / "elsewhere.json"
    shutil.move(export_copy / "manifest.json", outside)
    (export_copy / "manifest.json").symlink_to(outside)
    with pytest.raises(ManifestError, match=r"outside the export directory \(a symlink\?\)"):
        read_manifest(export_copy)


# ---- recorded facts the graphs must match -------------------------------------------------------------------------
def test_a_graph_of_another_precision_is_refused(export_copy):
    shutil.copy(export_copy / "slice_head.fp16.onnx", export_copy / "slice_head.onnx")
    _rehash(export_copy, "slice_head.onnx")
    with pytest.raises(ManifestError, match=r"slice_head.onnx: the graph holds a fp16 model, the manifest records fp32"):
        StreamingDetector(export_copy)


def test_precision_of_the_shipped_graphs(tiny_export, tiny_int8_export):
    for d in (tiny_export, tiny_int8_export.path):
        for g in read_manifest(d).graphs:
            assert graph_precision(onnx.load(d / g.file)) == g.precision, g.file


def test_a_graph_of_another_opset_than_recorded_is_refused(export_copy):
    _edit_manifest(export_copy, lambda d: [g.update(opset=g["opset"] + 1) for g in d["graphs"] if g["file"] == "slice_head.onnx"])
    with pytest.raises(ManifestError, match=r"slice_head.onnx: the graph is opset \d+, the manifest records opset \d+"):
        StreamingDetector(export_copy)


def test_an_input_fixed_where_the_runtime_varies_it_is_refused(export_copy):
    path = export_copy / "slice_head.onnx"
    model = onnx.load(path)
    dim = model.graph.input[0].type.tensor_type.shape.dim[0]  # pillar_features (P, M, 11): P varies per slice
    dim.Clear()
    dim.dim_value = 7
    path.write_bytes(model.SerializeToString())
    _rehash(export_copy, path.name)
    _edit_manifest(export_copy, lambda d: [g["inputs"][0]["shape"].__setitem__(0, 7) for g in d["graphs"] if g["file"] == path.name])
    with pytest.raises(ManifestError, match=r"input 'pillar_features' fixes dimension 0 at 7, which the runtime varies"):
        StreamingDetector(export_copy)


def test_a_grid_edited_apart_from_its_preset_is_refused(export_copy):
    def halve(d):  # the same cell counts over half the ranges: every graph check would pass
        g = d["grid"]
        g.update(x_range_m=[v / 2 for v in g["x_range_m"]], y_range_m=[v / 2 for v in g["y_range_m"]], voxel_xy_m=g["voxel_xy_m"] / 2)

    _edit_manifest(export_copy, halve)
    with pytest.raises(ManifestError, match=r"manifest grid .* differs from the grid its preset was trained on"):
        StreamingDetector(export_copy, DetectorConfig(verify_sha256=False))


def test_a_lut_of_another_calibration_than_recorded_is_refused(export_copy):
    _edit_manifest(export_copy, lambda d: d["lut"].update(calibration_sha256="0" * 64))
    with pytest.raises(ManifestError, match=r"lut.npz was built from calibration [0-9a-f]{12}\.\.\., the manifest records 000000000000"):
        StreamingDetector(export_copy)


# ---- core.file_input ----------------------------------------------------------------------------------------------
def test_read_regular_file(tmp_path, alarm):
    f = tmp_path / "f.bin"
    f.write_bytes(b"x" * 100)
    assert read_regular_file(f, 100) == b"x" * 100
    with pytest.raises(InputFileError, match=r"f.bin: is 100 bytes, over the 99 bytes limit; refused before reading") as e:
        read_regular_file(f, 99)
    assert e.value.too_large
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "dir").mkdir()
    for name, reason in (("fifo", "not a regular file"), ("dir", "not a regular file"), ("nothing", "missing")):
        with pytest.raises(InputFileError) as e:
            read_regular_file(tmp_path / name, 100)
        assert e.value.reason == reason and not e.value.too_large and isinstance(e.value, ValueError)


@pytest.mark.parametrize("n, text", [(0, "0 bytes"), (1023, "1023 bytes"), (1024, "1 KiB"), (64 << 20, "64 MiB"), ((2 << 30) - 1, "2 GiB")])
def test_describe_bytes(n, text):
    assert describe_bytes(n) == text


def test_a_recorded_top_k_other_than_the_graphs_is_refused(export_copy):
    _edit_manifest(export_copy, lambda d: d["post"].update(top_k_per_quadrant=d["post"]["top_k_per_quadrant"] // 2))
    with pytest.raises(ManifestError, match=r"slice_head.onnx .*tensor 'det_boxes' has dimension 1 = \d+ in the graph, the runtime feeds/reads \d+"):
        StreamingDetector(export_copy)


@pytest.mark.parametrize("graph, precision, config", [
    ("slice_head", "fp32", DetectorConfig()),
    ("image_encoder", "fp16", DetectorConfig(image_lane_precision="fp16")),
])  # fmt: skip
def test_graphs_whose_export_parity_failed_are_refused_in_use_only(export_copy, graph, precision, config):
    _edit_manifest(export_copy, lambda d: [p.update(passed=False) for p in d["parity"] if (p["graph"], p["precision"]) == (graph, precision)])
    with pytest.raises(ManifestError, match=rf"parity check FAILED for {graph} {precision} "):
        StreamingDetector(export_copy, config)
    other = DetectorConfig(precision="fp16") if precision == "fp32" else DetectorConfig()
    assert StreamingDetector(export_copy, other).num_slices == 8  # the other precision's graphs run


def test_model_signature_is_what_a_session_reads(tiny_int8_export):
    from streamdet.runtime_ort.graph_files import model_signature
    from streamdet.runtime_ort.sessions import GraphSession

    for f in sorted(tiny_int8_export.path.glob("*.onnx")):
        session = GraphSession(f)
        assert model_signature(onnx.load(f)) == (session.inputs, session.outputs), f.name


def test_a_symlink_loop_or_a_fifo_manifest_is_named(export_copy, alarm):
    (export_copy / "slice_head.onnx").unlink()
    (export_copy / "slice_head.onnx").symlink_to(export_copy / "slice_head.onnx")  # a loop onto itself
    with pytest.raises(ManifestError, match=r"slice_head.onnx' in .* cannot be resolved"):
        StreamingDetector(export_copy, DetectorConfig(verify_sha256=False))
    (export_copy / "manifest.json").unlink()
    os.mkfifo(export_copy / "manifest.json")
    with pytest.raises(ManifestError, match=r"manifest.json is not a regular file"):
        read_manifest(export_copy)
    from click.testing import CliRunner

    from streamdet.evaluation.run_cli import main as run_main

    res = CliRunner().invoke(run_main, ["--export-dir", str(export_copy), "--out", str(export_copy.parent / "run")])
    assert res.exit_code != 0 and "is not a regular file" in res.output and "holds no manifest.json" not in res.output


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to drop to another user")
def test_an_export_directory_that_may_not_be_listed_is_named(export_copy, tmp_path):
    import subprocess
    import sys

    box = export_copy.parent
    box.chmod(0o700)  # nobody else may enter: the export inside cannot be listed
    code = ("import sys\nfrom streamdet.runtime_ort.manifest import read_manifest, ManifestError\n"
            f"try:\n    read_manifest({str(export_copy)!r})\nexcept ManifestError as e:\n    print('NAMED', e)\n")
    run = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable, "-c", code],
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    if run.returncode != 0 and ("setpriv" in run.stderr or "import" in run.stderr.lower()):
        pytest.skip(f"cannot run as another user here: {run.stderr.strip()[-200:]}")
    assert "NAMED" in run.stdout and "cannot be read: Permission denied" in run.stdout, run.stdout + run.stderr


@pytest.mark.parametrize("k", ["500", 0, True, 12.5])
def test_a_malformed_recorded_top_k_is_refused_not_skipped(export_copy, k):
    _edit_manifest(export_copy, lambda d: d["post"].update(top_k_per_quadrant=k))
    with pytest.raises(ManifestError, match=r"post.top_k_per_quadrant must be a positive integer"):
        StreamingDetector(export_copy)
