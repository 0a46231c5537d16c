"""The int8 column of streamdet-bench: int8 siblings of the Table 3 row graphs, their targets, table, JSON and plot."""

from __future__ import annotations

import numpy as np
import onnx
import pytest

from streamdet.benchmarks.modules import build_rows, export_row
from streamdet.benchmarks.plot import plot_rows
from streamdet.benchmarks.probe import ProbeResult, row_session_config
from streamdet.benchmarks.report import INT8_SPEEDUP_MIN, evaluate_targets, format_rows, row_to_dict
from streamdet.benchmarks.table import RowResult
from streamdet.benchmarks.timing import summarize
from streamdet.export.int8 import relative_l2
from streamdet.models.presets import get_preset
from streamdet.runtime_ort.sessions import GraphSession


@pytest.fixture(scope="module")
def rows():
    return build_rows(get_preset("tiny"), [(128, 72)])


@pytest.mark.parametrize("index", [2, 3, 5])  # cropped slice row, 3D-conv row, image row
def test_rows_get_int8_siblings(rows, tmp_path, index):
    row = rows[index]
    graphs = export_row(row, tmp_path, fp16=False, int8=True)
    assert graphs.int8_error is None and graphs.int8 == tmp_path / f"{row.graph_stem}.int8.onnx"
    model = onnx.load(str(graphs.int8))
    assert any(n.op_type == "QuantizeLinear" for n in model.graph.node)
    out32 = GraphSession(graphs.fp32, row_session_config(1)).run(row.feeds())
    out8 = GraphSession(graphs.int8, row_session_config(1)).run(row.feeds())
    assert [o.shape for o in out8] == [o.shape for o in out32]
    if row.kind != "slice":  # dense outputs; the slice row's are top-K detections
        assert relative_l2(out8[0], out32[0]) < 0.3
    assert export_row(row, tmp_path, fp16=False).int8 is None  # only when asked for


def _row(key, kind, fp32_ms, int8_ms):
    t = summarize([fp32_ms])
    return RowResult(key, key, kind, 1.0, 1.0, t, None, None, int8=None if int8_ms is None else summarize([int8_ms]))


def test_int8_targets():
    peak = ProbeResult((100.0,), 2048, 2)
    rows = [
        _row("image_800x450", "image", 100.0, 30.0),  # 3.3x: met
        _row("image_1600x900", "image", 400.0, 200.0),  # 2.0x: missed
        _row("conv3d_cropped", "conv3d", 100.0, 25.0),  # 4.0x
        _row("slice_single_head_cropped", "slice", 10.0, 9.0),  # faster
    ]
    by_name = {t.name: t for t in evaluate_targets(rows, peak, None)}
    image = by_name[f"int8 >= {INT8_SPEEDUP_MIN['image']}x fp32, image encoder"]
    assert image.met is False and "image_800x450 3.33x" in image.detail and "image_1600x900 2.00x" in image.detail
    assert by_name[f"int8 >= {INT8_SPEEDUP_MIN['conv3d']}x fp32, lifter convolutions"].met is True
    assert by_name["int8 faster than fp32, slice graph"].met is True
    slower = [_row("slice_single_head_cropped", "slice", 10.0, 10.0)]
    assert {t.name: t for t in evaluate_targets(slower, peak, None)}["int8 faster than fp32, slice graph"].met is False
    without = [_row("image_800x450", "image", 100.0, None)]
    assert not any(t.name.startswith("int8") for t in evaluate_targets(without, peak, None))


def test_int8_column_in_table_json_and_plot(tmp_path):
    peak = ProbeResult((100.0,), 2048, 2)
    rows = [_row("image_800x450", "image", 100.0, 40.0), _row("conv3d", "conv3d", 50.0, None)]
    text = format_rows(rows, peak)
    header, first, second = text.splitlines()[:3]
    assert "ms int8 (p95)" in header and "fp32/int8" in header
    assert "40.0 (n/a)" in first and "2.50" in first  # one sample: no p95 printed (fewer than 20)
    d = row_to_dict(rows[0], peak)
    assert d["ms_int8"] == 40.0 and d["int8_speedup"] == 2.5 and d["int8"]["median_ms"] == 40.0
    assert row_to_dict(rows[1], peak)["ms_int8"] is None and row_to_dict(rows[1], peak)["int8_speedup"] is None
    png = plot_rows(rows, tmp_path / "rows.png", "int8")
    assert png.stat().st_size > 0 and np.frombuffer(png.read_bytes()[:8], np.uint8)[1:4].tobytes() == b"PNG"
    wide = plot_rows(rows, tmp_path / "rows_peak.png", "int8", peak_gflops_per_s=peak.gflops_per_s)  # % of peak panel
    assert wide.read_bytes()[1:4] == b"PNG" and wide.stat().st_size > png.stat().st_size
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="peak_gflops_per_s must be a positive number"):
            plot_rows(rows, tmp_path / "bad.png", "int8", peak_gflops_per_s=bad)


def test_stream_precision_needs_its_graphs(tiny_export_fp32):
    from click.testing import CliRunner

    from streamdet.benchmarks.cli import main as bench

    out = tiny_export_fp32  # fp32 graphs alone (conftest)
    result = CliRunner().invoke(bench, ["--preset", "tiny", "--export-dir", str(out), "--stream-precision", "int8"])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert "has no int8 graphs" in result.output and "--int8" in result.output
