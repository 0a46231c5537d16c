"""streamdet-export --int8 on the tiny preset (bundled calibration sample): valid QDQ graphs, the decode still
float, the manifest's int8 record, the runtime at precision int8, and one-line errors for bad calibration data."""

from __future__ import annotations

import math

import numpy as np
import onnx
import pytest
from click.testing import CliRunner

from streamdet.data.sample import load_bundled_sample
from streamdet.export.cli import main
from streamdet.export.int8 import BUNDLED_SOURCE, INPUT_NORM_NOTE, LIFTER_POOL_NOTE, relative_l2
from streamdet.runtime_ort.manifest import GRAPH_NAMES, graph_file_name, read_manifest
from streamdet.export.onnx_export import heatmap_producers, is_decode_node
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector


def _invoke(args: list[str]):
    return CliRunner().invoke(main, args)


def _assert_one_line_error(result, *needles: str) -> None:
    assert result.exit_code not in (0, None), result.output
    assert "Traceback" not in result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, result.output
    for needle in needles:
        assert needle in errors[0], errors[0]


@pytest.fixture(scope="module")
def export_dir(tiny_int8_export):
    # fp32 + int8 (conftest), calibrated on the bundled sample's six images
    assert "int8 calibrated on 6 images" in tiny_int8_export.output and "relative L2 error" in tiny_int8_export.output
    return tiny_int8_export.path


def _load(export_dir, name: str) -> onnx.ModelProto:
    return onnx.load(str(export_dir / graph_file_name(name, "int8")))


@pytest.mark.parametrize("name", GRAPH_NAMES)
def test_int8_graphs_are_valid_qdq(export_dir, name):
    model = _load(export_dir, name)
    onnx.checker.check_model(model, full_check=True)
    ops = [n.op_type for n in model.graph.node]
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    # every Conv that reads int8 weights reads them through a DequantizeLinear of an int8 initializer
    inits = {t.name: t for t in model.graph.initializer}
    producer = {o: n for n in model.graph.node for o in n.output}
    int8_convs = 0
    for conv in (n for n in model.graph.node if n.op_type == "Conv"):
        w = producer.get(conv.input[1])
        if w is not None and w.op_type == "DequantizeLinear":
            assert inits[w.input[0]].data_type == onnx.TensorProto.INT8
            int8_convs += 1
    assert int8_convs > 0
    # inputs and outputs keep the fp32 graph's types
    fp32 = onnx.load(str(export_dir / graph_file_name(name, "fp32")))
    io = lambda m: [(v.name, v.type.tensor_type.elem_type) for v in (*m.graph.input, *m.graph.output)]  # noqa: E731
    assert io(model) == io(fp32)


def test_decode_and_head_outputs_stay_float(export_dir):
    model = _load(export_dir, "slice_head")
    decode = [n for n in model.graph.node if is_decode_node(n)]
    assert {"Sigmoid", "MaxPool", "Equal", "TopK"} <= {n.op_type for n in decode}  # (constants are folded)
    producer = {o: n for n in model.graph.node for o in n.output}
    consumers = {}
    for n in model.graph.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    qdq = ("DequantizeLinear", "QuantizeLinear")
    for node in decode:  # decode nodes read and write float tensors only
        assert all(producer.get(i) is None or producer[i].op_type not in qdq for i in node.input), node.name
        assert all(u.op_type not in qdq for o in node.output for u in consumers.get(o, [])), node.name
    inits = {t.name: t for t in model.graph.initializer}
    heat = [n for n in model.graph.node if n.name in set(heatmap_producers(model)) and n.op_type == "Conv"]
    assert heat and all(inits[c.input[1]].data_type == onnx.TensorProto.FLOAT for c in heat)  # float heatmap logits
    feeders = [producer[i] for n in decode for i in n.input if i in producer and not is_decode_node(producer[i])]
    assert feeders and all(f.op_type not in qdq for f in feeders)  # the head outputs are float...
    convs = [f for f in feeders if f.op_type == "Conv"]
    assert convs and all(inits[c.input[1]].data_type == onnx.TensorProto.FLOAT for c in convs)  # ...from float weights


def test_float_ops_in_encoder_and_lifter(export_dir):
    enc = _load(export_dir, "image_encoder")
    first = next(n for n in enc.graph.node if n.op_type == "Conv")
    producer = {o: n for n in enc.graph.node for o in n.output}
    assert producer[first.input[0]].op_type == "DequantizeLinear"  # the normalised image is quantized once, here
    lifter = _load(export_dir, "volumetric_lifter")
    consumers = {i: n for n in lifter.graph.node for i in n.input}
    pool = next(n for n in lifter.graph.node if n.op_type == "AveragePool")
    assert consumers[pool.output[0]].op_type != "QuantizeLinear"  # pooling and max over z in float
    assert any(n.op_type == "Gather" and "DequantizeLinear" not in n.name for n in lifter.graph.node)


def test_manifest_records_int8(export_dir):
    m = read_manifest(export_dir)
    assert m.precisions == ("fp32", "int8")
    for name in GRAPH_NAMES:
        g, g32 = m.graph(name, "int8"), m.graph(name, "fp32")
        assert g.file == f"{name}.int8.onnx" and g.inputs == g32.inputs and g.outputs == g32.outputs
    r = m.int8
    c = r.calibration
    assert c.source == BUNDLED_SOURCE and c.num_images == 6 and c.num_volumes == 1 and not c.parity_held_out
    assert 0 < c.num_slices <= m.num_slices and c.method == "MinMax" and c.reduce_range
    assert [g.graph for g in r.graphs] == list(GRAPH_NAMES)
    assert r.graphs[0].quantized_ops["Conv"] > 0 and INPUT_NORM_NOTE in r.graphs[0].float_nodes
    assert LIFTER_POOL_NOTE in r.graphs[1].float_nodes
    outputs = {(p.graph, p.output, p.inputs) for p in r.parity}
    assert outputs == {
        ("image_encoder", "features", "same"), ("volumetric_lifter", "image_bev", "same"),
        ("volumetric_lifter", "image_bev", "pipeline"), ("slice_head", "det_scores", "same"),
        ("slice_head", "det_boxes", "same"), ("slice_head", "det_scores", "pipeline"), ("slice_head", "det_boxes", "pipeline"),
    }  # fmt: skip
    for p in r.parity:
        assert math.isfinite(p.rel_l2_error) and 0 <= p.rel_l2_error < 0.5, p
    b = r.boxes
    assert b.num_slices == c.num_slices and b.matched <= min(b.count_fp32, b.count_int8)


def test_runtime_runs_int8(export_dir):
    sample = load_bundled_sample()
    runs = {}
    for precision in ("fp32", "int8"):
        det = StreamingDetector(export_dir, DetectorConfig(precision=precision))
        img = det.manifest.image
        images = sample.load_images((img.width, img.height))
        det.update_images({n: images[j] for j, n in enumerate(sample.rig.names)})
        runs[precision] = (det, det.detect_sweep(sample.points))
    det8, dets8 = runs["int8"]
    assert det8.image_encoder.path.name == "image_encoder.int8.onnx"
    assert len(dets8.scores) > 0 and np.isfinite(dets8.boxes).all()
    assert relative_l2(det8.image_state.bev, runs["fp32"][0].image_state.bev) < 0.5  # the cached image BEV


def test_runtime_refuses_int8_without_int8_graphs(tmp_path):
    out = tmp_path / "exp"
    assert _invoke(["--preset", "tiny", "--out", str(out)]).exit_code == 0
    with pytest.raises(ValueError, match="no int8 graphs.*--int8"):
        StreamingDetector(out, DetectorConfig(precision="int8"))


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--int8", "--calibration-data", "{tmp}/missing"], "is not a directory"),
        (["--int8", "--calibration-data", "{tmp}/data"], "no nuScenes table folder"),
        (["--calibration-data", "{tmp}/data"], "needs --int8"),
        (["--int8", "--calibration-samples", "0"], "--calibration-samples"),
    ],
)
def test_bad_calibration_data_is_a_one_line_error(tmp_path, args, needle):
    out = tmp_path / "exp"
    (tmp_path / "data").mkdir()  # an empty folder, beside --out (an export inside its input is refused first)
    result = _invoke(["--preset", "tiny", "--out", str(out)] + [a.format(tmp=tmp_path) for a in args])
    _assert_one_line_error(result, needle)
    assert not out.exists()
