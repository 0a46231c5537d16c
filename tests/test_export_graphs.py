"""One tiny export with fp16 siblings: files, checks, manifest, dynamic sizes, a calibration change, streamdet-calib lut.

References: the PyTorch modules rebuilt from the same seed (``load_detector``), and ORT fp32 for the fp16 graphs.
"""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
import torch
from click.testing import CliRunner

from streamdet.calibration.camera import Rig
from streamdet.calibration.compact_lut import lifter_feeds
from streamdet.runtime_ort.calib_cli import main as calib_main
from streamdet.calibration.lut import Lut
from streamdet.calibration.perturb import perturb_rig
from streamdet.core.lut_layout import lut_inputs
from streamdet.data.sample import load_bundled_sample
from streamdet.data.slicing import slice_sample
from streamdet.export.exporter import ExportOptions, run_export
from streamdet.export.fp16 import check_model
from streamdet.export.onnx_export import SLICE_HEAD_IO, slice_decoder
from streamdet.export.parity import ort_session
from streamdet.export.weights import load_detector
from streamdet.models.presets import get_preset
from streamdet.runtime_ort.manifest import read_manifest, sha256_file
from streamdet.runtime_ort.pillarize import pillarize

TINY = get_preset("tiny")


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    out = tmp_path_factory.mktemp("exports") / "tiny"
    lines: list[str] = []
    result = run_export(ExportOptions(preset="tiny", fp16=True, out_dir=str(out)), report=lines.append)
    return result, lines


@pytest.fixture(scope="module")
def detector():
    det, _ = load_detector(TINY, None)
    return det


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


def _session(result, name, precision="fp32"):
    return ort_session(str(result.out_dir / result.manifest.graph(name, precision).file))


def test_files_checks_and_parity(export):
    result, lines = export
    names = sorted(p.name for p in result.out_dir.iterdir())
    assert names == sorted([
        "image_encoder.onnx", "volumetric_lifter.onnx", "slice_head.onnx",
        "image_encoder.fp16.onnx", "volumetric_lifter.fp16.onnx", "slice_head.fp16.onnx", "lut.npz", "manifest.json",
    ])
    assert not list(result.out_dir.parent.glob(".tiny.*"))  # staging directories are gone
    for f in result.out_dir.glob("*.onnx"):
        check_model(str(f))  # checker + strict full shape inference
    assert result.parity_passed
    m = result.manifest
    # per precision: features, image BEV, the five det_boxes groups (export/parity.py), det_scores, det_labels
    assert len(m.parity) == 2 * 9 and all(p.passed for p in m.parity)
    assert m.pipeline_parity is not None and m.pipeline_parity.passed
    assert any(line.startswith("[14/14]") for line in lines)  # the progress display numbers every step


def test_manifest_contents(export):
    result, _ = export
    m = read_manifest(result.out_dir)  # verifies every sha256
    d = json.loads((result.out_dir / "manifest.json").read_text())
    assert d["version"] == 1 and d["preset_name"] == "tiny" and d["preset"] == TINY.to_dict()
    assert d["grid"] == TINY.grid.to_dict()
    assert tuple(d["class_names"])[:2] == ("car", "truck") and len(d["class_names"]) == 10
    assert d["normalisation"]["mean_rgb"] == [0.485, 0.456, 0.406]
    assert (m.image.width, m.image.height, m.image.feature_width, m.image.feature_height) == (128, 72, 32, 18)
    assert m.image.camera_names[0] == "CAM_FRONT" and len(m.image.camera_names) == 6
    for g in m.graphs:
        assert g.sha256 == sha256_file(result.out_dir / g.file) and g.opset == 17 and g.gmac > 0
        model = onnx.load(str(result.out_dir / g.file))
        assert [i.name for i in model.graph.input] == [t.name for t in g.inputs]
        assert [o.name for o in model.graph.output] == [t.name for t in g.outputs]
        assert all(t.dtype in ("float32", "int32", "int64", "uint8") for t in (*g.inputs, *g.outputs))  # fp16 io stays fp32
    slice_head = m.graph("slice_head")
    assert {t.name: t.shape for t in slice_head.outputs}["det_boxes"] == ("Q", TINY.top_k, 9)
    assert {t.name: t.shape for t in slice_head.inputs}["pillar_features"] == ("P", 8, 11)
    lifter_dtypes = {t.name: t.dtype for t in m.graph("volumetric_lifter").inputs}
    assert [lifter_dtypes[n] for n in lut_inputs(m.lut_layout) if n.endswith("_index")] in (["int32"], ["int32", "int32"])
    assert m.lut.sha256 == sha256_file(result.out_dir / "lut.npz")


def test_fp16_graphs_keep_decode_in_fp32(export):
    result, _ = export
    model = onnx.load(str(result.out_dir / "slice_head.fp16.onnx"))
    ops = {n.name: n.op_type for n in model.graph.node}
    decode = [n for n in ops if n.startswith("/decode/")]
    assert {"Sigmoid", "MaxPool", "Equal", "TopK"} <= {ops[n] for n in decode}
    inferred = onnx.shape_inference.infer_shapes(model)
    elem = {v.name: v.type.tensor_type.elem_type for v in inferred.graph.value_info}
    checked = 0
    for node in model.graph.node:
        if node.op_type in ("Sigmoid", "MaxPool", "TopK", "Equal", "Conv") and (
            node.name.startswith("/decode/") or node.output[0] in {n.input[0] for n in model.graph.node if n.op_type == "Sigmoid"}
        ):
            inputs = [elem[i] for i in node.input[:2] if i in elem]
            assert all(t in (onnx.TensorProto.FLOAT, onnx.TensorProto.INT64) for t in inputs), node.name
            checked += 1
    assert checked >= 5  # sigmoid, max-pool, equal, top-k and the heatmap conv feeding the sigmoid


@pytest.mark.parametrize("num_images", [1, 6])
def test_encoder_dynamic_cameras(export, detector, sample, num_images):
    result, _ = export
    images = sample.load_images((128, 72))[:num_images]  # (J, H, W, 3)
    (got,) = _session(result, "image_encoder").run(None, {"images": images})
    with torch.no_grad():
        ref = detector.image_encoder(torch.from_numpy(images)).numpy()
    assert got.shape == (num_images, TINY.channels, 18, 32)
    np.testing.assert_allclose(got, ref, atol=1e-4 * np.ptp(ref))
    (got16,) = _session(result, "image_encoder", "fp16").run(None, {"images": images})
    assert got16.dtype == np.float32
    np.testing.assert_allclose(got16, got, atol=1e-2 * np.ptp(got))


def _slice_inputs(sample, n: int, num_pillars: int, seed: int):
    """Real pillars of the busiest slice of n (Q = 1, 2 or 4), cut to num_pillars, and a seeded image BEV."""
    slices = slice_sample(sample, n)
    sl = max(slices, key=lambda s: len(s.points))
    pl = pillarize(sl.points, TINY.grid, sl.quadrants, TINY.pillars.max_points_per_pillar, TINY.pillars.max_pillars)
    keep = np.random.default_rng(seed).permutation(pl.num_pillars)[:num_pillars]
    q = len(sl.quadrants)
    bev = np.random.default_rng(seed).uniform(0, 1, (q, TINY.channels, TINY.grid.quadrant_ny, TINY.grid.quadrant_nx))
    return {"pillar_features": pl.features[keep], "pillar_mask": pl.mask[keep], "pillar_index": pl.index[keep],
            "image_bev": bev.astype(np.float32)}


def _assert_same_detections(got, ref, tol_rel):
    """Naive set comparison: each reference detection clearly inside the top K has a twin (same label, nearest
    centre) whose box and score agree within tol_rel of the ranges."""
    gb, gs, gl = got
    rb, rs, rl = ref
    assert gb.shape == rb.shape and gl.dtype == np.int64
    box_tol, score_tol = tol_rel * np.ptp(rb), tol_rel * max(np.ptp(rs), 1e-6)
    for qi in range(rb.shape[0]):
        for i in range(rb.shape[1]):
            if rs[qi, i] <= rs[qi].min() + score_tol:
                continue  # at the top-K boundary: may be out of the other top K
            d = [abs(gb[qi, j, :2] - rb[qi, i, :2]).max() if gl[qi, j] == rl[qi, i] else np.inf for j in range(gb.shape[1])]
            j = int(np.argmin(d))
            assert d[j] <= box_tol, f"quadrant {qi} detection {i} has no twin"
            assert abs(gs[qi, j] - rs[qi, i]) <= score_tol
            assert np.abs(gb[qi, j] - rb[qi, i]).max() <= box_tol


@pytest.mark.parametrize("n,num_pillars", [(8, 1), (8, 37), (2, 37), (1, 37), (1, 1)])
def test_slice_head_dynamic_pillars_and_quadrants(export, detector, sample, n, num_pillars):
    result, _ = export
    feeds = _slice_inputs(sample, n, num_pillars, seed=n + num_pillars)
    q = feeds["image_bev"].shape[0]
    assert q == {8: 1, 2: 2, 1: 4}[n] and feeds["pillar_index"].shape == (num_pillars,)
    got = _session(result, "slice_head").run(None, feeds)
    with torch.no_grad():
        ref = [t.numpy() for t in slice_decoder(detector)(*(torch.from_numpy(feeds[k]) for k in SLICE_HEAD_IO.inputs))]
    assert got[0].shape == (q, TINY.top_k, 9)
    _assert_same_detections(got, ref, 1e-4)
    got16 = _session(result, "slice_head", "fp16").run(None, feeds)
    assert [a.dtype for a in got16] == [np.float32, np.float32, np.int64]
    _assert_same_detections(got16, got, 1e-2)


def _lifter_bev(result, features, lut: Lut, quadrants):
    index, weight = lut.for_quadrants(quadrants)
    (bev,) = _session(result, "volumetric_lifter").run(None, lifter_feeds(features, index, weight, result.manifest.lut_layout))
    return bev


def test_calibration_change_changes_lut_and_image_bev(export, sample, tmp_path):
    result, _ = export
    # a copy of the export, so the module's export stays intact for the other tests
    work = tmp_path / "exp"
    work.mkdir()
    for f in result.out_dir.iterdir():
        (work / f.name).write_bytes(f.read_bytes())
    rig = sample.rig
    calib = tmp_path / "perturbed.json"
    calib.write_text(json.dumps(perturb_rig(rig, max_angle_deg=1.0, max_translation_m=0.0, seed=7).to_dict()))
    old_lut = Lut.load(work / "lut.npz")
    out = CliRunner().invoke(calib_main, ["lut", "--calibration", str(calib), "--export-dir", str(work)])
    assert out.exit_code == 0, out.output
    assert out.output.startswith("rebuilt ")
    new_lut = Lut.load(work / "lut.npz")
    m = read_manifest(work)  # the manifest names the new file's sha256
    assert m.lut.calibration_source == str(calib) and m.lut.calibration_sha256 == new_lut.calibration_sha256
    assert m.lut.calibration_sha256 != result.manifest.lut.calibration_sha256
    assert not np.array_equal(old_lut.index, new_lut.index)
    images = sample.load_images((128, 72))
    (features,) = _session(result, "image_encoder").run(None, {"images": images})
    bev_old = _lifter_bev(result, features, old_lut, (0, 1))
    bev_new = _lifter_bev(result, features, new_lut, (0, 1))
    assert bev_old.shape == bev_new.shape == (2, TINY.channels, 32, 32)
    assert np.abs(bev_old - bev_new).max() > 1e-3 * np.ptp(bev_old)
    # the unperturbed calibration gives the exported LUT back, byte for byte
    orig = tmp_path / "orig.json"
    orig.write_text(json.dumps(rig.to_dict()))
    out = CliRunner().invoke(calib_main, ["lut", "--calibration", str(orig), "--export-dir", str(work)])
    assert out.exit_code == 0 and sha256_file(work / "lut.npz") == result.manifest.lut.sha256


@pytest.mark.parametrize(
    "edit,match",
    [
        (lambda d: d.update(cameras=d["cameras"][:5]), "do not match the export's"),
        (lambda d: d.update(cameras=d["cameras"][::-1]), "same names in the same order"),
        (lambda d: [c.update(height=1200) for c in d["cameras"]], "aspect"),
        (lambda d: d.pop("lidar"), "lidar"),
    ],
)
def test_calib_lut_refusals(export, sample, tmp_path, edit, match):
    result, _ = export
    d = sample.rig.to_dict()
    edit(d)
    calib = tmp_path / "bad.json"
    calib.write_text(json.dumps(d))
    before = sha256_file(result.out_dir / "lut.npz"), sha256_file(result.out_dir / "manifest.json")
    out = CliRunner().invoke(calib_main, ["lut", "--calibration", str(calib), "--export-dir", str(result.out_dir)])
    assert out.exit_code != 0
    assert out.output.count("\n") == 1 and out.output.startswith("Error: ") and match in out.output
    assert str(calib) in out.output and "Traceback" not in out.output  # every refusal names the file
    assert (sha256_file(result.out_dir / "lut.npz"), sha256_file(result.out_dir / "manifest.json")) == before


def test_calib_lut_needs_an_export(tmp_path, sample):
    calib = tmp_path / "c.json"
    calib.write_text(json.dumps(sample.rig.to_dict()))
    out = CliRunner().invoke(calib_main, ["lut", "--calibration", str(calib), "--export-dir", str(tmp_path)])
    assert out.exit_code != 0 and "not a (complete) streamdet export" in out.output and out.output.count("\n") == 1
    assert Rig.from_calibration_json(calib) == sample.rig
