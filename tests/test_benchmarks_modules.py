"""Row modules (the lifter's convolutions alone vs the whole lifter, row inputs), profile summaries, target verdicts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from streamdet.benchmarks.modules import build_rows, export_row, pillar_inputs
from streamdet.benchmarks.prepost import real_sweep_points
from streamdet.benchmarks.sweep_pillars import busiest_quadrant_pillars, whole_grid_pillars
from streamdet.benchmarks.ort_profile import summarize_events, summarize_profile
from streamdet.benchmarks.probe import ProbeConfig, ProbeResult, matmul_model, measure_peak, row_session_config
from streamdet.benchmarks.report import evaluate_targets
from streamdet.benchmarks.table import RowResult
from streamdet.benchmarks.timing import summarize
from streamdet.models.lifter import VolumetricLifter, gather_volume
from streamdet.models.lifter_fold import LifterConvs
from streamdet.models.presets import get_preset
from streamdet.runtime_ort.pillarize import pillarize
from streamdet.runtime_ort.sessions import GraphSession

TINY = get_preset("tiny")
SMALL = get_preset("small")


@pytest.mark.parametrize("seed", range(3))
def test_lifter_convs_equal_lifter_after_gather(seed):
    torch.manual_seed(seed)
    g, c = TINY.grid, TINY.channels
    lifter = VolumetricLifter(TINY.lifter, c).eval()
    with torch.no_grad():  # non-trivial BN statistics so the eval path matters
        for m in lifter.modules():
            if isinstance(m, torch.nn.BatchNorm3d):
                m.running_mean.normal_()
                m.running_var.uniform_(0.5, 2.0)
    j, hf, wf = 2, 5, 7
    shape = (2, 2, g.nz, g.quadrant_ny, g.quadrant_nx)  # (Q, K, Z, Yq, Xq)
    gen = torch.Generator().manual_seed(seed)
    features = torch.randn(j, c, hf, wf, generator=gen)
    index = torch.randint(0, j * hf * wf + 1, shape, dtype=torch.int32, generator=gen)
    weight = torch.rand(shape, generator=gen)
    with torch.no_grad():
        ref = lifter(features, index, weight)
        got = LifterConvs(lifter)(gather_volume(features, index, weight))
    torch.testing.assert_close(got, ref)


@pytest.mark.parametrize("cropped", [False, True])
def test_pillar_inputs_follow_the_contract(cropped):
    feats, mask, index, bev = pillar_inputs(TINY, cropped, seed=0)
    g = TINY.grid
    ny, nx = (g.quadrant_ny, g.quadrant_nx) if cropped else (g.ny, g.nx)
    p, m = mask.shape
    assert 0 < p <= TINY.pillars.max_pillars and m == TINY.pillars.max_points_per_pillar
    assert feats.shape == (p, m, TINY.pillars.num_point_features)
    assert torch.all(mask.sum(1) >= 1)
    assert torch.all(feats[mask == 0] == 0)  # zero padding rows, as the eval pillar net requires
    assert torch.all(index[1:] > index[:-1]) and index.min() >= 0 and index.max() < ny * nx
    assert bev.shape == (1, TINY.channels, ny, nx)


def test_sweep_pillars_on_the_whole_grid_are_the_quadrants_pillars():
    """The whole-grid map holds each quadrant's pillars at that quadrant's place, with the same points."""
    g, pc = SMALL.grid, SMALL.pillars
    full = whole_grid_pillars(g, pc.max_points_per_pillar, pc.max_pillars)
    busiest = busiest_quadrant_pillars(g, pc.max_points_per_pillar, pc.max_pillars)
    counts = []
    for q in range(4):
        quad = pillarize(real_sweep_points(), g, (q,), pc.max_points_per_pillar, pc.max_pillars)
        counts.append(quad.num_pillars)
        row0, col0 = g.quadrant_offset_cells(q)
        row, col = np.divmod(quad.index, g.quadrant_nx)
        where = np.searchsorted(full.index, (row0 + row) * g.nx + col0 + col)
        np.testing.assert_array_equal(full.index[where], (row0 + row) * g.nx + col0 + col)
        np.testing.assert_array_equal(full.features[where], quad.features)
    assert full.num_pillars == sum(counts) and full.quadrant is None
    assert busiest.num_pillars == max(counts) and busiest.quadrant == int(np.argmax(counts))
    assert (full.map_ny, full.map_nx, busiest.map_ny, busiest.map_nx) == (g.ny, g.nx, g.quadrant_ny, g.quadrant_nx)


def test_rows_layout_and_export(tmp_path):
    rows = build_rows(TINY, [(128, 72), (64, 36)])
    assert [r.kind for r in rows] == ["slice"] * 3 + ["conv3d"] * 2 + ["image"] * 2
    assert rows[5].graph_stem == rows[6].graph_stem == "image_encoder"  # one dynamic-size encoder graph
    graphs = export_row(rows[2], tmp_path)
    assert graphs.fp32.is_file() and graphs.fp16 is not None and graphs.fp16.is_file() and graphs.fp16_error is None
    fp16 = onnx.load(graphs.fp16)
    assert any(i.data_type == onnx.TensorProto.FLOAT16 for i in fp16.graph.initializer)
    out32 = GraphSession(graphs.fp32, row_session_config(1)).run(rows[2].feeds())
    out16 = GraphSession(graphs.fp16, row_session_config(1)).run(rows[2].feeds())
    assert [o.shape for o in out32] == [o.shape for o in out16]
    assert export_row(rows[3], tmp_path, fp16=False).fp16 is None


def test_profile_summary_from_events():
    events = [
        {"cat": "Session", "name": "model_run", "dur": 1000},
        {"cat": "Session", "name": "model_run", "dur": 3000},
        {"cat": "Node", "name": "a_kernel_time", "dur": 600, "args": {"op_name": "Conv"}},
        {"cat": "Node", "name": "b_kernel_time", "dur": 200, "args": {"op_name": "Conv"}},
        {"cat": "Node", "name": "a_kernel_time", "dur": 600, "args": {"op_name": "Conv"}},
        {"cat": "Node", "name": "c_kernel_time", "dur": 400, "args": {"op_name": "Relu"}},
        {"cat": "Node", "name": "c_fence_before", "dur": 99, "args": {"op_name": "Relu"}},
    ]
    s = summarize_events(events)
    assert s.runs == 2 and s.run_ms == pytest.approx(3.0)
    assert [o.op_type for o in s.ops] == ["Conv", "Relu"]
    assert s.ops[0].ms_per_run == pytest.approx(0.7) and s.ops[0].nodes == 2
    assert s.ops[0].share == pytest.approx(1400 / 1800)
    assert s.kernel_ms == pytest.approx(0.9)
    with pytest.raises(ValueError, match="no model_run event"):
        summarize_events([{"cat": "Node", "name": "x_kernel_time", "dur": 1}])
    with pytest.raises(ValueError, match="JSON list of events"):
        summarize_events({"traceEvents": []})


def test_profile_summary_of_a_real_session(tmp_path):
    path = tmp_path / "mm.onnx"
    onnx.save_model(matmul_model(64), str(path))
    session = GraphSession(path, row_session_config(1, profile=True, profile_dir=tmp_path / "prof"))
    feeds = {"a": np.ones((64, 64), np.float32), "b": np.ones((64, 64), np.float32)}
    for _ in range(3):
        session.run(feeds)
    written = Path(session.end_profiling())
    assert written.parent == tmp_path / "prof" and written.name.startswith("mm.profile")  # where it was asked to go
    s = summarize_profile(written)
    assert s.runs == 3 and s.ops[0].op_type == "MatMul"
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="cannot read onnxruntime profile"):
        summarize_profile(bad)


def test_probe_runs_and_merges():
    a = measure_peak(1, ProbeConfig(size=64, runs=2, warmup=0))
    assert a.runs == 2 and a.gflops_per_s >= a.median_gflops_per_s > 0
    b = ProbeResult((1e9,), 64, 1)
    assert a.merged(b).gflops_per_s == 1e9 and a.merged(b).runs == 3
    with pytest.raises(ValueError, match="cannot merge"):
        a.merged(ProbeResult((1.0,), 128, 1))
    with pytest.raises(ValueError, match="ProbeConfig.size"):
        ProbeConfig(size=0)


def _row(key, gmac, fp32_ms, torch_ms, kind="slice"):
    t = summarize([fp32_ms])
    return RowResult(key, key, kind, gmac, gmac, t, t, None if torch_ms is None else summarize([torch_ms]))


def test_target_verdicts():
    peak = ProbeResult((100.0,), 2048, 2)  # GFLOP/s
    rows = [
        _row("slice_single_head", 4.0, 100.0, 200.0),  # 80 GFLOP/s, torch 2x
        _row("slice_single_head_cropped", 1.0, 30.0, 36.0),  # 66.7 GFLOP/s, torch 1.2x: misses 1.3x
        _row("conv3d", 8.0, 400.0, None, "conv3d"),  # 40 GFLOP/s: misses 60 %
        _row("conv3d_cropped", 2.0, 100.0, 200.0, "conv3d"),
    ]
    torch_t, crop_slice, crop_conv, peak_t, stream_t = evaluate_targets(rows, peak, None)
    assert torch_t.met is False and "slice_single_head_cropped 1.20x" in torch_t.detail and "1 row(s) without PyTorch" in torch_t.detail
    assert crop_slice.met is False and "fp32 3.33x" in crop_slice.detail
    assert crop_conv.met is True and "fp32 4.00x" in crop_conv.detail
    assert peak_t.met is False and "conv3d 40%" in peak_t.detail and "slice_single_head 80%" not in peak_t.detail
    assert stream_t.met is None
