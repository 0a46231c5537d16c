"""CompactLifter (models/compact_lifter.py) against the K-slot lifter it wraps (the naive reference), tiny preset;
the compact LUT layout of an export against the slots layout through the runtime."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from streamdet.calibration.compact_lut import compact_lut, lifter_feeds
from streamdet.core.lut_layout import COMPACT_INPUTS, LUT_COMPACT, LUT_SLOTS, lut_inputs
from streamdet.data.sample import load_bundled_sample
from streamdet.export.options import DEFAULT_LUT_LAYOUT, LUT_AUTO, resolve_lut_layout
from streamdet.models.compact_lifter import CompactLifter
from streamdet.models.detector import build_detector
from streamdet.models.export_form import to_export_form
from streamdet.models.lifter_fold import FoldedLifter
from streamdet.models.presets import get_preset
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.manifest import ManifestError, read_manifest

N_SLICES = 8


def _lut(rng: np.random.Generator, shape: tuple[int, ...], sentinel: int, multi_share: float):
    """A K = 2 LUT: every voxel's first slot valid or empty, its second valid for ``multi_share`` of the voxels."""
    index = rng.integers(0, sentinel, shape).astype(np.int32)  # (Q, K, Z, Yq, Xq)
    index[:, 0][rng.random(index[:, 0].shape) < 0.2] = sentinel  # seen by no camera
    index[:, 1][rng.random(index[:, 1].shape) >= multi_share] = sentinel
    weight = (rng.random(shape).astype(np.float32) + 0.1) * (index < sentinel)
    return index, weight


def _compact_args(index: np.ndarray, weight: np.ndarray, sentinel: int) -> tuple[torch.Tensor, ...]:
    lut = compact_lut(index, weight, sentinel)
    voxels = lut.voxel_shape  # (Q, Z, Yq, Xq)
    arrays = (lut.multi_index, lut.multi_weight, lut.final_index.reshape(voxels), lut.final_weight.reshape(voxels))
    return tuple(torch.from_numpy(a) for a in arrays)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("folded", [True, False])
@pytest.mark.parametrize("multi_share", [0.0, 0.3])  # 0.0: no voxel seen by two cameras (M = 0)
@pytest.mark.parametrize("q", [1, 2])
def test_compact_lifter_is_the_k_slot_lifter(seed, folded, multi_share, q):
    torch.manual_seed(seed)
    det = build_detector(get_preset("tiny")).eval()
    lifter = to_export_form(det).volumetric_lifter if folded else det.lifter
    assert isinstance(lifter, FoldedLifter) == folded
    g = det.preset.grid
    rng = np.random.default_rng(seed)
    j, hf, wf = 3, 5, 7
    sentinel = j * hf * wf
    index, weight = _lut(rng, (q, 2, g.nz, g.quadrant_ny, g.quadrant_nx), sentinel, multi_share)
    features = torch.randn(j, det.preset.channels, hf, wf)
    with torch.no_grad():
        want = lifter(features, torch.from_numpy(index), torch.from_numpy(weight))
        got = CompactLifter(lifter)(features, *_compact_args(index, weight, sentinel))
    assert got.shape == want.shape == (q, det.preset.channels, g.quadrant_ny, g.quadrant_nx)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("trace_share,run_share", [(0.0, 0.3), (0.3, 0.0), (0.0, 0.0)])
def test_the_compact_graph_takes_any_number_of_multi_voxels(trace_share, run_share):
    """Traced and run on LUTs with and without voxels seen by two cameras (M = 0: a rig whose cameras do not
    overlap, or a quadrant they do not share): one graph for every M."""
    from streamdet.export.onnx_export import VOLUMETRIC_LIFTER_IO, compact_lifter_io, export_module
    from streamdet.export.parity import ort_session

    torch.manual_seed(0)
    det = build_detector(get_preset("tiny")).eval()
    lifter = to_export_form(det).volumetric_lifter
    g = det.preset.grid
    rng = np.random.default_rng(0)
    j, hf, wf = 2, 5, 7
    sentinel = j * hf * wf
    shape = (1, 2, g.nz, g.quadrant_ny, g.quadrant_nx)  # (Q, K, Z, Yq, Xq)
    features = torch.randn(j, det.preset.channels, hf, wf)
    traced = _compact_args(*_lut(rng, shape, sentinel, trace_share), sentinel)
    model = export_module(CompactLifter(lifter), (features, *traced), compact_lifter_io(VOLUMETRIC_LIFTER_IO))
    index, weight = _lut(rng, shape, sentinel, run_share)
    feeds = lifter_feeds(features.numpy(), index, weight, LUT_COMPACT)
    assert (feeds["multi_index"].shape[1] == 0) == (run_share == 0.0)
    (got,) = ort_session(model.SerializeToString()).run(None, feeds)
    with torch.no_grad():
        want = lifter(features, torch.from_numpy(index), torch.from_numpy(weight)).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_compact_lifter_refuses_another_module():
    with pytest.raises(TypeError, match="Linear"):
        CompactLifter(torch.nn.Linear(2, 2))


# ---- the compact LUT layout through the export and the runtime ------------------------------------------------


@pytest.fixture(scope="module")
def slots_export(tmp_path_factory) -> Path:
    """A tiny fp32 export in the K-slot layout (``--lut-layout slots``; compact is the default)."""
    from click.testing import CliRunner

    from streamdet.export.cli import main as export_main

    out = tmp_path_factory.mktemp("tiny_slots_lut") / "tiny"
    args = ["--preset", "tiny", "--slices", str(N_SLICES), "--lut-layout", LUT_SLOTS, "--out", str(out)]
    result = CliRunner().invoke(export_main, args)
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="module")
def compact_export(tiny_int8_export) -> Path:
    """The shared tiny fp32 + int8 export, in the default layout: compact."""
    return tiny_int8_export.path


def _images(det: StreamingDetector, sample) -> dict[str, np.ndarray]:
    img = det.manifest.image
    arr = sample.load_images((img.width, img.height))  # (J, H, W, 3)
    return {n: arr[sample.rig.names.index(n)] for n in det.camera_names}


@pytest.mark.parametrize("quadrants", [None, (0,), (1, 3)])  # the full update, per-quadrant lifts
def test_compact_export_lifts_what_the_slots_export_lifts(slots_export, compact_export, quadrants):
    sample = load_bundled_sample()
    results = []
    for export_dir in (slots_export, compact_export):
        det = StreamingDetector(export_dir)
        det.update_images(_images(det, sample), timestamp=1.0, quadrants=quadrants)
        results.append((det._image.bev, det.detect_sweep_slices(sample.points, timestamp=1.05, num_slices=N_SLICES)))  # noqa: SLF001
    (bev_a, a), (bev_b, b) = results
    np.testing.assert_allclose(bev_b, bev_a, rtol=1e-5, atol=1e-6)
    for sa, sb in zip(a.slices, b.slices):
        assert sa.detections.boxes.shape == sb.detections.boxes.shape
        np.testing.assert_allclose(sb.detections.scores, sa.detections.scores, rtol=1e-4, atol=1e-5)


def test_the_compact_int8_graphs_run(compact_export):
    sample = load_bundled_sample()
    det = StreamingDetector(compact_export, DetectorConfig(precision="int8"))
    det.update_images(_images(det, sample), timestamp=1.0, quadrants=(2,))
    assert len(det.detect_sweep_slices(sample.points, timestamp=1.05, num_slices=N_SLICES).slices) == N_SLICES


def test_the_manifest_names_the_lut_layout(slots_export, compact_export, tmp_path):
    assert DEFAULT_LUT_LAYOUT == LUT_AUTO  # compact for one height per voxel (tiny), slots for several
    assert resolve_lut_layout(LUT_AUTO, 1) == LUT_COMPACT and resolve_lut_layout(LUT_AUTO, 2) == LUT_SLOTS
    assert resolve_lut_layout(LUT_COMPACT, 2) == LUT_COMPACT and resolve_lut_layout(LUT_SLOTS, 1) == LUT_SLOTS
    assert read_manifest(slots_export).lut_layout == LUT_SLOTS
    m = read_manifest(compact_export)
    assert m.lut_layout == LUT_COMPACT
    assert [t.name for t in m.graph("volumetric_lifter").inputs] == ["features", *COMPACT_INPUTS]
    d = json.loads((slots_export / "manifest.json").read_text())
    d["lut_layout"] = LUT_COMPACT  # the graphs read K slots
    copy = tmp_path / "bad"
    shutil.copytree(slots_export, copy)
    (copy / "manifest.json").write_text(json.dumps(d))
    with pytest.raises(ManifestError, match="multi_index|lut_index"):
        StreamingDetector(copy)
    d["lut_layout"] = "sparse"
    (copy / "manifest.json").write_text(json.dumps(d))
    with pytest.raises(ManifestError, match="sparse"):
        StreamingDetector(copy)


def test_a_manifest_without_the_field_still_runs_as_slots(slots_export, tmp_path):
    """Exports written before lut_layout existed: no field, K-slot graphs."""
    d = json.loads((slots_export / "manifest.json").read_text())
    del d["lut_layout"]
    old = tmp_path / "old"
    shutil.copytree(slots_export, old)
    (old / "manifest.json").write_text(json.dumps(d))
    sample = load_bundled_sample()
    results = []
    for export_dir in (slots_export, old):
        det = StreamingDetector(export_dir)
        assert det.manifest.lut_layout == LUT_SLOTS
        det.update_images(_images(det, sample), timestamp=1.0)
        results.append(det.detect_sweep_slices(sample.points, timestamp=1.05, num_slices=N_SLICES))
    a, b = results
    for sa, sb in zip(a.slices, b.slices, strict=True):
        np.testing.assert_array_equal(sb.detections.boxes, sa.detections.boxes)


@pytest.mark.parametrize("layout", [LUT_SLOTS, LUT_COMPACT])
def test_lifter_feeds_name_the_layouts_inputs(layout):
    rng = np.random.default_rng(0)
    j, hf, wf = 2, 3, 4
    index, weight = _lut(rng, (1, 2, 2, 3, 3), j * hf * wf, 0.3)
    features = rng.standard_normal((j, 5, hf, wf)).astype(np.float32)
    feeds = lifter_feeds(features, index, weight, layout)
    assert list(feeds) == ["features", *lut_inputs(layout)]
    assert feeds["features"] is features


@pytest.mark.parametrize("bad,match", [("sparse", "sparse"), (None, "features")])
def test_lifter_feeds_malformed(bad, match):
    index = np.zeros((1, 2, 2, 3, 3), np.int32)
    weight = np.zeros((1, 2, 2, 3, 3), np.float32)
    features = np.zeros((2, 5, 3, 4) if bad else (5, 3, 4), np.float32)
    with pytest.raises(ValueError, match=match):
        lifter_feeds(features, index, weight, bad or LUT_SLOTS)
