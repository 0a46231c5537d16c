"""The LiDAR-only net without the quadrant crop (``Preset.slice_crop`` False): one whole-grid map per slice in
pillarization, targets, the slice net, export, the runtime's uncrop and torch eval, checked against the quadrant
maps stitched (a naive reference) and ONNX against PyTorch; the switch recorded only when off."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from streamdet.calibration.slice_maps import map_cells, slice_maps
from streamdet.core.boxes import BOX_DIM
from streamdet.core.sectors import NUM_QUADRANTS
from streamdet.data.sample import load_bundled_sample
from streamdet.data.slicing import slice_sample
from streamdet.export.cli import main as export_main
from streamdet.models.decode import decode_head_maps
from streamdet.models.detector import build_detector
from streamdet.models.presets import Preset, get_preset, preset_names
from streamdet.runtime_ort.detector import StreamingDetector
from streamdet.runtime_ort.manifest import MANIFEST_NAME, ManifestError, read_manifest
from streamdet.runtime_ort.pillarize import pillarize
from streamdet.runtime_ort.postprocess import uncrop_boxes
from streamdet.training.checkpoint import load_checkpoint, load_weights, save_weights
from streamdet.training.targets import build_targets
from streamdet.training.torch_eval import TorchSweepDetector
from streamdet.training.trainer import TrainConfig

TINY = get_preset("tiny")
NO_CROP = dataclasses.replace(TINY, use_image=False, slice_crop=False)
GRID = TINY.grid
N_SLICES = 8


# ---- the switch and its record ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", preset_names())
def test_shipped_presets_serialise_as_before(name):
    preset = get_preset(name)
    assert preset.slice_crop and "slice_crop" not in preset.to_dict()  # written only when off
    assert "slice_crop" not in dataclasses.replace(preset, use_image=False).to_dict()
    assert preset.map_cells == (preset.grid.quadrant_ny, preset.grid.quadrant_nx)


def test_no_crop_round_trips_and_sizes_the_maps():
    d = json.loads(json.dumps(NO_CROP.to_dict()))
    assert d["slice_crop"] is False and Preset.from_dict(d) == NO_CROP
    assert NO_CROP.map_cells == (GRID.ny, GRID.nx) == map_cells(GRID, crop=False)
    assert NO_CROP.head_map_size == (GRID.ny // TINY.head.out_stride, GRID.nx // TINY.head.out_stride)
    assert TrainConfig(preset="tiny", steps=1, use_image=False, slice_crop=False).build_preset() == NO_CROP
    assert "slice_crop" not in TrainConfig(preset="tiny", steps=1).to_dict()


def test_fused_without_crop_is_refused():
    with pytest.raises(ValueError, match="slice_crop=False .* LiDAR-only net only"):
        dataclasses.replace(TINY, slice_crop=False)
    with pytest.raises(ValueError, match="--no-image"):
        TrainConfig(preset="tiny", steps=1, slice_crop=False)
    with pytest.raises(ValueError, match="slice_crop must be True or False"):
        dataclasses.replace(NO_CROP, slice_crop="no")
    with pytest.raises(ValueError, match="crop must be True"):
        slice_maps(GRID, (0,), crop=0)


# ---- pillars and targets: one whole-grid map holds what the four quadrant maps hold ----------------------------


def _points(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 6) float32 slice points over the whole grid and a bit beyond, some on the axes and cell borders."""
    xy = rng.uniform(-14.0, 14.0, (n, 2))
    xy[: n // 10] = np.round(xy[: n // 10] / GRID.voxel_xy_m) * GRID.voxel_xy_m  # on cell borders and axes
    z = rng.uniform(-3.5, 5.5, (n, 1))
    rest = rng.uniform(0.0, 1.0, (n, 3))
    return np.concatenate([xy, z, rest], axis=1).astype(np.float32)


def _dense(pil, rows: int, cols: int, origin_cells: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """Naive reference: every pillar's features and mask written at its cell of the whole (ny, nx) grid."""
    feats = np.zeros((GRID.ny, GRID.nx, *pil.features.shape[1:]), np.float32)
    mask = np.zeros((GRID.ny, GRID.nx, pil.mask.shape[1]), np.float32)
    for p, flat in enumerate(pil.index.tolist()):
        m, local = divmod(flat, rows * cols)
        r, c = divmod(local, cols)
        r0, c0 = origin_cells[m]
        feats[r0 + r, c0 + c] = pil.features[p]
        mask[r0 + r, c0 + c] = pil.mask[p]
    return feats, mask


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("quadrants", [(0, 1, 2, 3), (1, 2), (3,)])
def test_whole_grid_pillars_equal_the_quadrant_maps_stitched(seed, quadrants):
    pts = _points(np.random.default_rng(seed), 4000)
    m, cap = TINY.pillars.max_points_per_pillar, 100_000  # no pillar cap: its ties break by flat index, which differs
    cropped = pillarize(pts, GRID, quadrants, m, cap)
    whole = pillarize(pts, GRID, quadrants, m, cap, crop=False)
    assert whole.num_pillars == cropped.num_pillars > 0
    assert np.all(np.diff(whole.index) > 0) and whole.index.max() < GRID.ny * GRID.nx
    for field in ("num_points_dropped", "num_pillars_dropped", "num_nonfinite_dropped", "num_outside_dropped"):
        assert getattr(whole, field) == getattr(cropped, field), field
    f_crop, m_crop = _dense(cropped, GRID.quadrant_ny, GRID.quadrant_nx, [GRID.quadrant_offset_cells(q) for q in quadrants])
    f_whole, m_whole = _dense(whole, GRID.ny, GRID.nx, [(0, 0)])
    assert np.array_equal(m_whole, m_crop)
    # the cell-centre offsets come from another origin (the grid's corner, not the quadrant's): float rounding only
    np.testing.assert_allclose(f_whole, f_crop, rtol=0, atol=2e-6)
    assert np.array_equal(f_whole[..., :9], f_crop[..., :9])  # the point columns and the pillar-mean offsets exactly


def test_whole_grid_pillars_of_an_empty_slice():
    pil = pillarize(np.zeros((0, 6), np.float32), GRID, (0,), 8, 16, crop=False)
    assert pil.num_pillars == 0 and pil.features.shape == (0, 8, 11)


def _boxes(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Boxes whose Gaussians (radius <= 3 head cells of 0.8 m) stay inside their quadrant: centres 4-10 m off each axis."""
    sign = rng.choice([-1.0, 1.0], (n, 2))
    boxes = np.zeros((n, BOX_DIM))
    boxes[:, :2] = sign * rng.uniform(4.0, 10.0, (n, 2))
    boxes[:, 2] = rng.uniform(-1, 1, n)
    boxes[:, 3:6] = rng.uniform(0.5, 2.0, (n, 3))
    boxes[:, 6] = rng.uniform(-np.pi, np.pi, n)
    boxes[:, 7:] = rng.normal(0, 2, (n, 2))
    return boxes, rng.integers(0, 10, n)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_whole_grid_targets_equal_the_quadrant_maps_stitched(seed):
    boxes, labels = _boxes(np.random.default_rng(seed), 12)
    s = TINY.head.out_stride
    whole = build_targets(boxes, labels, None, GRID, s)
    hh, wh = GRID.quadrant_ny // s, GRID.quadrant_nx // s
    assert whole.heatmap.shape == (10, 2 * hh, 2 * wh) and whole.num_objects == len(boxes)
    stitched = np.zeros_like(whole.heatmap)
    rows = []
    for q in range(NUM_QUADRANTS):
        t = build_targets(boxes, labels, q, GRID, s)
        r0, c0 = (v // s for v in GRID.quadrant_offset_cells(q))
        stitched[:, r0 : r0 + hh, c0 : c0 + wh] = t.heatmap
        for i in np.flatnonzero(t.mask):
            r, c = divmod(int(t.index[i]), wh)
            rows.append(((r0 + r) * 2 * wh + c0 + c, int(t.label[i]), t.box[i]))
    np.testing.assert_array_equal(whole.heatmap, stitched)
    got = sorted((int(whole.index[i]), int(whole.label[i]), whole.box[i]) for i in np.flatnonzero(whole.mask))
    want = sorted(rows, key=lambda r: (r[0], r[1]))
    assert [g[:2] for g in got] == [w[:2] for w in want]
    np.testing.assert_allclose(np.stack([g[2] for g in got]), np.stack([w[2] for w in want]), rtol=0, atol=1e-5)


def test_uncrop_of_the_whole_grid_map():
    local = np.zeros((1, 2, 9), np.float32)
    local[0, :, :2] = [[0.5, 0.5], [20.0, 13.0]]
    out = uncrop_boxes(local, (2, 3), GRID, crop=False)
    np.testing.assert_allclose(out[0, :, :2], [[-12.3, -12.3], [7.2, 0.2]], atol=1e-6)
    with pytest.raises(ValueError, match=r"Q=1, K, 9\) for the whole-grid map"):
        uncrop_boxes(np.zeros((2, 2, 9), np.float32), (2, 3), GRID, crop=False)


# ---- the net, its export and the runtime --------------------------------------------------------------------------


def _model():
    torch.manual_seed(5)
    model = build_detector(NO_CROP).eval()
    with torch.no_grad():  # spread the untrained heatmap logits, so scores are not one flat tie at the prior
        for task in model.slice_net.head.tasks:
            task.branches["heatmap"][-1].weight.normal_(0.0, 0.5)
    return model


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("ckpt") / "no_crop.pt"
    save_weights(path, NO_CROP, _model())
    return path


@pytest.fixture(scope="module")
def export_dir(checkpoint, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export") / "no_crop"
    result = CliRunner().invoke(export_main, ["--checkpoint", str(checkpoint), "--fp16", "--int8", "--slices", str(N_SLICES),
                                              "--out", str(out)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "whole-grid maps (no quadrant crop)" in result.output
    return out


def test_slice_net_runs_one_whole_grid_map():
    pts = slice_sample(load_bundled_sample(), N_SLICES)[0].points
    pil = pillarize(pts, GRID, (0,), TINY.pillars.max_points_per_pillar, TINY.pillars.max_pillars, crop=False)
    with torch.no_grad():
        maps = _model().slice_net(torch.from_numpy(pil.features), torch.from_numpy(pil.mask), torch.from_numpy(pil.index),
                                  num_quadrants=1)  # fmt: skip
    assert maps[0].shape == (1, 10, *NO_CROP.head_map_size)


def test_export_records_the_switch_and_passes_parity(export_dir):
    m = read_manifest(export_dir)
    assert m.preset["slice_crop"] is False and not m.slice_crop and not m.use_image
    assert [t.name for t in m.graph("slice_head").inputs] == ["pillar_features", "pillar_mask", "pillar_index"]
    assert m.precisions == ("fp32", "fp16", "int8")
    assert {(p.precision, p.reference) for p in m.parity} == {("fp32", "torch"), ("fp16", "onnx-fp32")}
    assert all(p.passed for p in m.parity) and m.pipeline_parity.passed
    assert "one whole-grid map" in m.source["parity_input"]


@pytest.mark.parametrize("num_slices", [1, 2, N_SLICES])
def test_sweep_through_onnx_equals_pytorch(export_dir, num_slices):
    sample = load_bundled_sample()
    det = StreamingDetector(export_dir)
    assert not det.slice_crop
    onnx = det.detect_sweep(sample.points, timestamp=0.0, num_slices=num_slices)
    ref = TorchSweepDetector(_model(), num_slices=num_slices)(sample)
    assert len(onnx) == len(ref) > 0
    np.testing.assert_allclose(onnx.scores, ref.scores, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(onnx.boxes, ref.boxes, rtol=1e-4, atol=1e-4)
    assert np.array_equal(onnx.labels, ref.labels)
    # boxes are in the LiDAR frame: the uncrop added the grid's corner, so centres lie inside the grid
    assert np.all(np.abs(onnx.boxes[:, :2]) <= GRID.x_range_m[1] + 1.0)


def test_slice_graph_equals_the_pytorch_decode(export_dir):
    det = StreamingDetector(export_dir)
    model = _model()
    for s in slice_sample(load_bundled_sample(), 2):
        pl = pillarize(s.points, GRID, s.quadrants, TINY.pillars.max_points_per_pillar, TINY.pillars.max_pillars, crop=False)
        got = det.slice_head.run(pl.as_feeds())
        with torch.no_grad():
            maps = model.slice_net(torch.from_numpy(pl.features), torch.from_numpy(pl.mask), torch.from_numpy(pl.index),
                                   num_quadrants=1)  # fmt: skip
            ref = [t.numpy() for t in decode_head_maps(maps, NO_CROP.head_cell_m, NO_CROP.top_k)]
        assert got[0].shape == ref[0].shape == (1, NO_CROP.top_k, 9)
        np.testing.assert_allclose(got[1], ref[1], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(got[0], ref[0], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("precision", ["fp16", "int8"])
def test_other_precisions_run(export_dir, precision):
    from streamdet.runtime_ort.detector import DetectorConfig

    det = StreamingDetector(export_dir, DetectorConfig(precision=precision))
    assert len(det.detect_sweep(load_bundled_sample().points)) > 0


def test_manifest_of_a_fused_preset_without_crop_is_refused(export_dir, tmp_path):
    d = json.loads((export_dir / MANIFEST_NAME).read_text())
    d["preset"]["use_image"] = True
    (tmp_path / MANIFEST_NAME).write_text(json.dumps(d))
    with pytest.raises(ManifestError, match="slice_crop false .* LiDAR-only preset only"):
        read_manifest(tmp_path, verify_files=False)
    d["preset"]["use_image"], d["preset"]["slice_crop"] = False, "no"
    (tmp_path / MANIFEST_NAME).write_text(json.dumps(d))
    with pytest.raises(ManifestError, match="slice_crop"):
        read_manifest(tmp_path, verify_files=False)


# ---- the chain: streamdet-train --no-crop -> streamdet-export -> streamdet-eval ---------------------------------


def test_train_export_eval_chain(tiny_synth_data, tmp_path):
    from streamdet.evaluation.cli import main as eval_main
    from streamdet.training.cli import main as train_main

    run = tmp_path / "run"
    res = CliRunner().invoke(train_main, ["--data", str(tiny_synth_data), "--out", str(run), "--preset", "tiny", "--steps", "2",
                                          "--no-image", "--no-crop", "--num-slices", "8,2", "--cache-dir", str(tmp_path / "c")])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "LiDAR only, no quadrant crop" in res.output
    ckpt = load_checkpoint(run / "last.pt")
    assert ckpt["preset"]["slice_crop"] is False and ckpt["config"]["slice_crop"] is False
    # two steps leave the heatmap near its prior (scores within 1e-4: the exporter's relative parity cannot tell them
    # apart); spread its logits as an untrained export does, the rest is the trained net
    model, preset = load_weights(run / "model.pt")
    assert preset == NO_CROP
    with torch.no_grad():
        for task in model.slice_net.head.tasks:
            task.branches["heatmap"][-1].weight.normal_(0.0, 0.5)
    save_weights(run / "spread.pt", preset, model)
    res = CliRunner().invoke(export_main, ["--checkpoint", str(run / "spread.pt"), "--out", str(tmp_path / "exp")])
    assert res.exit_code == 0, res.output
    assert read_manifest(tmp_path / "exp").preset["slice_crop"] is False
    out = tmp_path / "m.json"
    res = CliRunner().invoke(eval_main, ["--data", str(tiny_synth_data), "--export-dir", str(tmp_path / "exp"), "--split", "all",
                                         "--json", str(out)])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert 0.0 <= json.loads(out.read_text())["mAP"] <= 1.0


def test_train_cli_refuses_no_crop_with_images(tiny_synth_data, tmp_path):
    from streamdet.training.cli import main as train_main

    res = CliRunner().invoke(train_main, ["--data", str(tiny_synth_data), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                          "--steps", "1", "--no-crop"])  # fmt: skip
    assert res.exit_code != 0 and "--no-image" in res.output and "Traceback" not in res.output
