"""int8 building blocks against naive references: relative L2, box pairing and agreement, which nodes stay float,
which ops are int8, dataset discovery and bad input. No export here (see test_int8_export.py)."""

from __future__ import annotations

import math

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from streamdet.core.classes import CLASS_NAMES
from streamdet.export import int8 as q8
from streamdet.runtime_ort.manifest_records import BoxAgreement

SEEDS = (0, 1, 2)


# ---- relative L2 ----------------------------------------------------------------------------------------------


def _naive_rel_l2(a: np.ndarray, b: np.ndarray) -> float:
    num = sum((float(x) - float(y)) ** 2 for x, y in zip(a.ravel(), b.ravel()))
    den = sum(float(y) ** 2 for y in b.ravel())
    return math.sqrt(num) / math.sqrt(den)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("dtype", [np.float32, np.float16, np.float64])
def test_relative_l2_matches_naive(seed, dtype):
    rng = np.random.default_rng(seed)
    ref = rng.normal(size=(3, 4, 5)).astype(dtype)
    got = (ref + rng.normal(scale=0.01, size=ref.shape)).astype(dtype)
    assert q8.relative_l2(got, ref) == pytest.approx(_naive_rel_l2(got, ref), rel=1e-9)


def test_relative_l2_edge_cases():
    assert q8.relative_l2(np.zeros(0), np.zeros(0)) == 0.0
    assert q8.relative_l2(np.zeros(3), np.zeros(3)) == 0.0
    assert q8.relative_l2(np.ones(3), np.zeros(3)) == math.inf
    with pytest.raises(ValueError, match=r"\(3,\).*\(4,\)"):
        q8.relative_l2(np.zeros(3), np.zeros(4))


def test_dense_parity_concatenates_inputs():
    rng = np.random.default_rng(0)
    ref = [rng.normal(size=(2, 3)).astype(np.float32), rng.normal(size=(5,)).astype(np.float32)]
    got = [r + 0.1 for r in ref]
    p = q8.dense_parity("g", "o", "same", got, ref)
    flat_g, flat_r = np.concatenate([g.ravel() for g in got]), np.concatenate([r.ravel() for r in ref])
    assert p.rel_l2_error == pytest.approx(_naive_rel_l2(flat_g, flat_r), rel=1e-6)
    assert p.max_abs_diff == pytest.approx(0.1, rel=1e-5) and p.num_inputs == 2
    empty = q8.dense_parity("g", "o", "same", [], [])
    assert empty.rel_l2_error == 0.0 and empty.num_inputs == 0


# ---- pairing boxes --------------------------------------------------------------------------------------------


def _naive_pairs(ba, la, bb, lb, radius):
    """Repeatedly take the nearest still-free pair of the same label within the radius (first index on ties)."""
    free_a, free_b, out = set(range(len(ba))), set(range(len(bb))), []
    while True:
        best = None
        for i in sorted(free_a):
            for j in sorted(free_b):
                if la[i] != lb[j]:
                    continue
                d = math.hypot(float(ba[i, 0]) - float(bb[j, 0]), float(ba[i, 1]) - float(bb[j, 1]))
                if d <= radius and (best is None or d < best[0]):
                    best = (d, i, j)
        if best is None:
            return out
        out.append((best[1], best[2]))
        free_a.discard(best[1])
        free_b.discard(best[2])


def _boxes(rng, n):
    b = np.zeros((n, 9), dtype=np.float32)
    b[:, :2] = rng.uniform(0, 10, size=(n, 2))
    b[:, 3:6] = 1.0
    return b, rng.integers(0, 3, size=n)


@pytest.mark.parametrize("seed", SEEDS)
def test_pair_boxes_matches_naive(seed):
    rng = np.random.default_rng(seed)
    ba, la = _boxes(rng, 12)
    bb, lb = _boxes(rng, 9)
    ia, ib, d = q8.pair_boxes(ba, la, bb, lb, radius_m=3.0)
    assert sorted(zip(ia.tolist(), ib.tolist())) == sorted(_naive_pairs(ba, la, bb, lb, 3.0))
    assert np.all(la[ia] == lb[ib]) and np.all(d <= 3.0)
    assert np.allclose(d, np.linalg.norm(ba[ia, :2] - bb[ib, :2], axis=1))


def test_pair_boxes_empty():
    ia, ib, d = q8.pair_boxes(np.zeros((0, 9)), np.zeros(0, int), np.zeros((4, 9)), np.zeros(4, int), 1.0)
    assert ia.size == ib.size == d.size == 0


def _dets(rng, q=2, k=6):
    boxes = np.zeros((q, k, 9), dtype=np.float32)
    boxes[..., :2] = rng.uniform(0, 20, size=(q, k, 2))
    scores = np.sort(rng.uniform(0.0, 1.0, size=(q, k)).astype(np.float32), axis=1)[:, ::-1].copy()
    labels = rng.integers(0, len(CLASS_NAMES), size=(q, k))
    return boxes, scores, labels


@pytest.mark.parametrize("seed", SEEDS)
def test_box_agreement_identical_and_shifted(seed):
    rng = np.random.default_rng(seed)
    slices = [_dets(rng) for _ in range(3)]
    same = q8.box_agreement(slices, slices, cell_m=0.8, score_threshold=0.1)
    above = sum(int((s >= 0.1).sum()) for _, s, _ in slices)
    assert isinstance(same, BoxAgreement)
    assert same.count_fp32 == same.count_int8 == same.matched == above
    assert same.max_centre_diff_m == 0.0 and same.max_score_diff == 0.0 and same.num_slices == 3
    shifted = [(b + np.array([0.3, 0.4, 0, 0, 0, 0, 0, 0, 0], np.float32), s, l) for b, s, l in slices]
    moved = q8.box_agreement(slices, shifted, cell_m=0.8, score_threshold=0.1)
    assert moved.matched == above and moved.max_centre_diff_m == pytest.approx(0.5, abs=1e-5)


def test_box_agreement_counts_unpaired_and_empty():
    rng = np.random.default_rng(0)
    b, s, l = _dets(rng, q=1, k=4)
    s[:] = [0.9, 0.8, 0.7, 0.05]
    s8 = s.copy()
    s8[0, 1] = 0.01  # dropped below the threshold in the int8 run
    agree = q8.box_agreement([(b, s, l)], [(b, s8, l)], cell_m=0.8, score_threshold=0.1)
    assert (agree.count_fp32, agree.count_int8, agree.matched) == (3, 2, 2)
    none = q8.box_agreement([(b, s * 0, l)], [(b, s * 0, l)], cell_m=0.8)
    assert none.matched == 0 and math.isnan(none.max_centre_diff_m)
    with pytest.raises(ValueError, match="1 fp32 slices but 0 int8"):
        q8.box_agreement([(b, s, l)], [], cell_m=0.8)


# ---- which nodes stay float -----------------------------------------------------------------------------------


def _model(nodes, inputs, outputs, inits=()) -> onnx.ModelProto:
    graph = helper.make_graph(nodes, "g", inputs, outputs, list(inits))
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def _weight(name, shape):
    return helper.make_tensor(name, TensorProto.FLOAT, shape, np.ones(shape, np.float32).ravel().tolist())


def _encoder_like() -> onnx.ModelProto:
    nodes = [
        helper.make_node("Cast", ["images"], ["x0"], to=TensorProto.FLOAT, name="/Cast"),
        helper.make_node("Mul", ["x0", "s"], ["x1"], name="/Mul"),
        helper.make_node("Add", ["x1", "m"], ["x2"], name="/Add"),
        helper.make_node("Conv", ["x2", "w1"], ["x3"], name="/backbone/conv1/Conv"),
        helper.make_node("Relu", ["x3"], ["x4"], name="/backbone/relu/Relu"),
        helper.make_node("Conv", ["x4", "w2"], ["features"], name="/fpn/Conv"),
    ]
    inits = [_weight("s", [1]), _weight("m", [1]), _weight("w1", [2, 3, 1, 1]), _weight("w2", [2, 2, 1, 1])]
    return _model(nodes, [helper.make_tensor_value_info("images", TensorProto.UINT8, [1, 3, 4, 4])],
                  [helper.make_tensor_value_info("features", TensorProto.FLOAT, [1, 2, 4, 4])], inits)  # fmt: skip


def test_float_nodes_encoder_keeps_the_input_normalisation():
    keep = q8.float_nodes("image_encoder", _encoder_like())
    assert set(keep) == {"/Cast", "/Mul", "/Add"} and set(keep.values()) == {q8.INPUT_NORM_NOTE}


def _lifter_like() -> onnx.ModelProto:
    nodes = [
        helper.make_node("Gather", ["table", "idx"], ["g"], axis=0, name="/Gather"),
        helper.make_node("Mul", ["g", "wt"], ["v"], name="/Mul"),
        helper.make_node("Conv", ["v", "w"], ["c"], name="/project/Conv"),
        helper.make_node("AveragePool", ["c"], ["p"], kernel_shape=[2, 1, 1], strides=[2, 1, 1], name="/z_pool/AveragePool"),
        helper.make_node("ReduceMax", ["p"], ["image_bev"], keepdims=0, axes=[2], name="/ReduceMax"),
    ]
    f = TensorProto.FLOAT
    return _model(nodes, [helper.make_tensor_value_info("table", f, [10, 2]), helper.make_tensor_value_info("idx", TensorProto.INT64, [1, 2, 2, 2, 2]),
                          helper.make_tensor_value_info("wt", f, [1])],
                  [helper.make_tensor_value_info("image_bev", f, None)], [_weight("w", [2, 2, 1, 1, 1])])  # fmt: skip


def test_float_nodes_lifter_pooling_and_optional_gather():
    keep = q8.float_nodes("volumetric_lifter", _lifter_like())
    assert set(keep) == {"/Gather", "/Mul", "/z_pool/AveragePool", "/ReduceMax"}
    assert keep["/Gather"] == q8.LIFTER_GATHER_NOTE and keep["/ReduceMax"] == q8.LIFTER_POOL_NOTE
    keep = q8.float_nodes("volumetric_lifter", _lifter_like(), q8.Int8Config(quantize_lifter_gather=True))
    assert set(keep) == {"/z_pool/AveragePool", "/ReduceMax"}


def _slice_like(with_scatter: bool = True) -> onnx.ModelProto:
    f = TensorProto.FLOAT
    nodes = [
        helper.make_node("MatMul", ["pf", "wl"], ["h"], name="/slice_net/pillar_net/MatMul"),
        helper.make_node("ScatterND", ["canvas", "pi", "h"], ["bev"], name="/slice_net/ScatterND")
        if with_scatter else helper.make_node("Identity", ["canvas"], ["bev"], name="/slice_net/Identity"),
        helper.make_node("Conv", ["bev", "wb"], ["b1"], name="/slice_net/bev_encoder/Conv"),
        helper.make_node("Conv", ["b1", "wh"], ["hm"], name="/slice_net/head/heatmap/Conv"),
        helper.make_node("Sigmoid", ["hm"], ["sig"], name="/decode/Sigmoid"),
        helper.make_node("MaxPool", ["sig"], ["mp"], kernel_shape=[3, 3], pads=[1, 1, 1, 1], name="/decode/MaxPool"),
        helper.make_node("Equal", ["sig", "mp"], ["det"], name="/decode/Equal"),
    ]  # fmt: skip
    inputs = [helper.make_tensor_value_info("pf", f, [4, 11]), helper.make_tensor_value_info("canvas", f, [1, 2, 4, 4]),
              helper.make_tensor_value_info("pi", TensorProto.INT64, [4, 4])]  # fmt: skip
    inits = [_weight("wl", [11, 2]), _weight("wb", [2, 2, 1, 1]), _weight("wh", [2, 2, 1, 1])]
    return _model(nodes, inputs, [helper.make_tensor_value_info("det", TensorProto.BOOL, None)], inits)


def test_float_nodes_slice_graph():
    keep = q8.float_nodes("slice_head", _slice_like())
    assert {"/decode/Sigmoid", "/decode/MaxPool", "/decode/Equal"} <= set(keep)
    assert "/slice_net/head/heatmap/Conv" in keep  # the heatmap logits
    assert {"/slice_net/pillar_net/MatMul", "/slice_net/ScatterND"} <= set(keep) and keep["/slice_net/ScatterND"] == q8.PILLAR_NOTE
    assert "/slice_net/bev_encoder/Conv" not in keep


def test_float_nodes_bad_input():
    with pytest.raises(ValueError, match="'lut'"):
        q8.float_nodes("lut", _encoder_like())
    with pytest.raises(ValueError, match="ScatterND"):
        q8.float_nodes("slice_head", _slice_like(with_scatter=False))
    with pytest.raises(ValueError, match="Conv"):
        q8.float_nodes("image_encoder", _model([], [], []))


# ---- which ops are int8 -----------------------------------------------------------------------------------------


def test_quantized_ops_counts_qdq_units_only():
    f, u8 = TensorProto.FLOAT, TensorProto.UINT8
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "sc", "zp"], ["xq"], name="q0"),
        helper.make_node("DequantizeLinear", ["xq", "sc", "zp"], ["xd"], name="dq0"),
        helper.make_node("DequantizeLinear", ["wq", "sc"], ["wd"], name="dqw"),
        helper.make_node("Conv", ["xd", "wd"], ["c"], name="conv_int8"),  # DQ in, Q out: an int8 unit
        helper.make_node("QuantizeLinear", ["c", "sc", "zp"], ["cq"], name="q1"),
        helper.make_node("DequantizeLinear", ["cq", "sc", "zp"], ["cd"], name="dq1"),
        helper.make_node("Conv", ["cd", "wd"], ["y"], name="conv_float_out"),  # graph output in float: not a unit
        helper.make_node("Relu", ["x"], ["r"], name="relu_float"),
    ]
    inits = [helper.make_tensor("sc", f, [], [0.1]), helper.make_tensor("zp", u8, [], [128]),
             helper.make_tensor("wq", TensorProto.INT8, [1, 1, 1, 1], [3])]  # fmt: skip
    model = _model(nodes, [helper.make_tensor_value_info("x", f, [1, 1, 2, 2])],
                   [helper.make_tensor_value_info("y", f, None), helper.make_tensor_value_info("r", f, None)], inits)  # fmt: skip
    assert q8.quantized_ops(model) == {"Conv": 1}
    assert q8.quantized_ops(_encoder_like()) == {}


def test_quantize_graph_refuses_no_inputs(tmp_path):
    with pytest.raises(ValueError, match="no calibration inputs"):
        q8.quantize_graph("image_encoder", tmp_path / "a.onnx", tmp_path / "b.onnx", [])


# ---- calibration data discovery -------------------------------------------------------------------------------


def test_dataset_version(tmp_path):
    with pytest.raises(q8.Int8CalibrationDataError, match="not a directory"):
        q8.dataset_version(tmp_path / "missing")
    with pytest.raises(q8.Int8CalibrationDataError, match="no nuScenes table folder"):
        q8.dataset_version(tmp_path)
    (tmp_path / "v1.0-test").mkdir()
    (tmp_path / "v1.0-test" / "sample.json").write_text("[]")
    with pytest.raises(q8.Int8CalibrationDataError, match="only the test split"):
        q8.dataset_version(tmp_path)
    for v in ("v1.0-trainval", "v1.0-mini"):
        (tmp_path / v).mkdir()
        (tmp_path / v / "sample.json").write_text("[]")
    assert q8.dataset_version(tmp_path) == "v1.0-mini"  # the first one that is not a test split, by name


def test_bundled_calibration_samples():
    cal = q8.load_calibration_samples(None, 8, ("CAM_FRONT", "CAM_BACK"))
    assert cal.source == q8.BUNDLED_SOURCE and len(cal.samples) == 1 and cal.split == "all"
    with pytest.raises(q8.Int8CalibrationDataError, match=r"cameras \['CAM_X'\]"):
        q8.load_calibration_samples(None, 8, ("CAM_FRONT", "CAM_X"))
    for bad in (0, -1, 2.5, True):
        with pytest.raises(q8.Int8CalibrationDataError, match="positive integer"):
            q8.load_calibration_samples(None, bad, ("CAM_FRONT",))


# ---- the encoder's input normalisation as a BatchNormalization --------------------------------------------------


def _normalising(scale: np.ndarray, shift: np.ndarray) -> onnx.ModelProto:
    f = TensorProto.FLOAT
    nodes = [
        helper.make_node("Cast", ["images"], ["x0"], to=f, name="/Cast"),
        helper.make_node("Mul", ["x0", "scale"], ["x1"], name="/Mul"),
        helper.make_node("Add", ["x1", "shift"], ["x2"], name="/Add"),
        helper.make_node("Conv", ["x2", "w"], ["features"], pads=[1, 1, 1, 1], name="/backbone/conv1/Conv"),
    ]
    inits = [onnx.numpy_helper.from_array(scale.astype(np.float32), "scale"), onnx.numpy_helper.from_array(shift.astype(np.float32), "shift"),
             onnx.numpy_helper.from_array(np.linspace(-1, 1, 2 * 3 * 9, dtype=np.float32).reshape(2, 3, 3, 3), "w")]  # fmt: skip
    return _model(nodes, [helper.make_tensor_value_info("images", TensorProto.UINT8, [2, 3, 5, 6])],
                  [helper.make_tensor_value_info("features", f, [2, 2, 5, 6])], inits)  # fmt: skip


@pytest.mark.parametrize("seed", SEEDS)
def test_normalisation_as_batchnorm_is_exact(seed):
    import onnxruntime as ort

    rng = np.random.default_rng(seed)
    scale, shift = rng.uniform(0.01, 0.02, (1, 3, 1, 1)), rng.uniform(-2.2, -1.8, (1, 3, 1, 1))
    model = _normalising(scale, shift)
    rewritten = _normalising(scale, shift)
    assert q8.normalisation_as_batchnorm(rewritten)
    onnx.checker.check_model(rewritten, full_check=True)
    assert [n.op_type for n in rewritten.graph.node] == ["Cast", "BatchNormalization", "Conv"]
    assert {t.name for t in rewritten.graph.initializer} >= {"w"} and "scale" not in {t.name for t in rewritten.graph.initializer}
    images = rng.integers(0, 256, (2, 3, 5, 6), dtype=np.uint8)
    run = lambda m: ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"images": images})[0]  # noqa: E731
    np.testing.assert_array_equal(run(rewritten), run(model))
    # the naive reference of the normalised image, through a graph that stops before the conv
    naive = images.astype(np.float32) * scale.astype(np.float32) + shift.astype(np.float32)
    cut = _normalising(scale, shift)
    assert q8.normalisation_as_batchnorm(cut)
    cut.graph.node.pop()  # drop the conv: the BatchNormalization's output is the graph's
    cut.graph.output[0].name = "x2"
    got = ort.InferenceSession(cut.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"images": images})[0]
    np.testing.assert_allclose(got, naive, rtol=1e-6, atol=1e-6)


def test_normalisation_as_batchnorm_leaves_other_graphs():
    per_tensor = _normalising(np.full((1, 1, 1, 1), 0.5), np.full((1, 1, 1, 1), 0.1))
    per_tensor.graph.initializer[0].CopyFrom(onnx.numpy_helper.from_array(np.float32([0.5]), "scale"))
    before = per_tensor.SerializeToString()
    assert not q8.normalisation_as_batchnorm(per_tensor) and per_tensor.SerializeToString() == before
    assert not q8.normalisation_as_batchnorm(_lifter_like())  # no Mul -> Add before its first conv


def test_slice_parity_wraps_yaw():
    rng = np.random.default_rng(0)
    b, s, l = _dets(rng, q=1, k=4)
    s[:] = [0.9, 0.8, 0.7, 0.6]
    b[0, :, 6] = np.float32(np.pi - 1e-3)
    b8 = b.copy()
    b8[0, :, 6] = np.float32(-np.pi + 1e-3)  # the same heading, 2e-3 rad apart
    scores, boxes = q8._slice_parity("same", [(b8, s, l)], [(b, s, l)], cell_m=0.8)  # noqa: SLF001
    assert boxes.max_abs_diff == pytest.approx(2e-3, abs=1e-5) and scores.rel_l2_error == 0.0


def test_float_nodes_slice_graph_stops_at_the_peak_heads_relu():
    # the peak head (models/peak_head.py): the decode reads the regression branches' hidden features (a ReLU's
    # output), so their conv is quantized; the heatmap's output conv still stays float
    f = TensorProto.FLOAT
    nodes = [
        helper.make_node("MatMul", ["pf", "wl"], ["h"], name="/slice_net/pillar_net/MatMul"),
        helper.make_node("ScatterND", ["canvas", "pi", "h"], ["bev"], name="/slice_net/ScatterND"),
        helper.make_node("Conv", ["bev", "wb"], ["hid"], name="/slice_net/peak_head/hidden/Conv"),
        helper.make_node("Relu", ["hid"], ["act"], name="/slice_net/peak_head/relu/Relu"),
        helper.make_node("Conv", ["act", "wh"], ["hm"], name="/slice_net/peak_head/heatmap/Conv"),
        helper.make_node("Sigmoid", ["hm"], ["sig"], name="/decode/Sigmoid"),
        helper.make_node("Mul", ["act", "sig"], ["det"], name="/decode/Mul"),  # the decode reading the features
    ]
    inputs = [helper.make_tensor_value_info("pf", f, [4, 11]), helper.make_tensor_value_info("canvas", f, [1, 2, 4, 4]),
              helper.make_tensor_value_info("pi", TensorProto.INT64, [4, 4])]  # fmt: skip
    inits = [_weight("wl", [11, 2]), _weight("wb", [2, 2, 1, 1]), _weight("wh", [2, 2, 1, 1])]
    model = _model(nodes, inputs, [helper.make_tensor_value_info("det", f, None)], inits)
    keep = q8.float_nodes("slice_head", model)
    assert "/slice_net/peak_head/heatmap/Conv" in keep
    assert "/slice_net/peak_head/hidden/Conv" not in keep and "/slice_net/peak_head/relu/Relu" not in keep


def test_shapes_of_quantized_reads_the_quantized_tensor():
    import onnxruntime as ort

    from streamdet.export.int8_quantize import shapes_of_quantized

    f, u8 = TensorProto.FLOAT, TensorProto.UINT8
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "s", "z"], ["xq"], name="q"),
        helper.make_node("DequantizeLinear", ["xq", "s", "z"], ["xd"], name="dq"),
        helper.make_node("DequantizeLinear", ["xq", "s", "z"], ["xd2"], name="dq_for_shape"),
        helper.make_node("Relu", ["xd"], ["y"], name="relu"),
        helper.make_node("Shape", ["xd2"], ["shape"], name="shape"),
    ]
    inits = [helper.make_tensor("s", f, [], [0.1]), helper.make_tensor("z", u8, [], [128])]
    model = _model(nodes, [helper.make_tensor_value_info("x", f, [2, 3, 5])],
                   [helper.make_tensor_value_info("y", f, [2, 3, 5]), helper.make_tensor_value_info("shape", TensorProto.INT64, [3])],
                   inits)  # fmt: skip
    assert shapes_of_quantized(model) == 1
    names = [n.name for n in model.graph.node]
    assert "dq_for_shape" not in names and "dq" in names  # the copy no one reads is gone, the other stays
    assert next(n for n in model.graph.node if n.name == "shape").input[0] == "xq"
    onnx.checker.check_model(model)
    x = np.random.default_rng(0).normal(size=(2, 3, 5)).astype(np.float32)
    y, shape = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"x": x})
    assert shape.tolist() == [2, 3, 5] and y.shape == (2, 3, 5)
    assert shapes_of_quantized(model) == 0  # nothing left to move
