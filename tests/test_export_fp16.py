"""fp16 conversion (export/fp16.py) on small hand-built graphs, against the fp32 graph as the reference."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from streamdet.export.fp16 import check_model, convert_model_to_fp16, io_types
from streamdet.export.parity import ort_session


def _run(model: onnx.ModelProto, feeds: dict) -> list[np.ndarray]:
    return ort_session(model.SerializeToString()).run(None, feeds)


def _traps_model() -> onnx.ModelProto:
    """x (N, 4) float -> y = x * W + zeros(shape(x)) + Cast(x > 0); s, idx = TopK(Sigmoid(y)) written by blocked
    nodes straight to graph outputs. Holds every op the converter mistypes or loops on."""
    w = helper.make_tensor("w", TensorProto.FLOAT, [4], [0.5, -1.0, 2.0, 0.25])
    k = helper.make_tensor("k", TensorProto.INT64, [1], [2])
    nodes = [
        helper.make_node("Mul", ["x", "w"], ["xw"], name="mul"),
        helper.make_node("Shape", ["x"], ["shape"], name="shape"),
        helper.make_node("ConstantOfShape", ["shape"], ["zeros"], name="zeros", value=helper.make_tensor("v", TensorProto.FLOAT, [1], [0.0])),
        helper.make_node("Add", ["xw", "zeros"], ["y0"], name="add0"),
        helper.make_node("Greater", ["x", "zeros"], ["pos"], name="greater"),
        helper.make_node("Cast", ["pos"], ["posf"], name="cast_pos", to=TensorProto.FLOAT),
        helper.make_node("Add", ["y0", "posf"], ["y"], name="add1"),
        helper.make_node("Sigmoid", ["y"], ["sig"], name="decode_sigmoid"),
        helper.make_node("Mul", ["sig", "sig"], ["sig2"], name="decode_square"),
        helper.make_node("TopK", ["sig2", "k"], ["s", "idx"], name="decode_topk", axis=1),
    ]
    graph = helper.make_graph(
        nodes,
        "traps",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 4])],
        [
            helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 4]),
            helper.make_tensor_value_info("s", TensorProto.FLOAT, ["N", 2]),
            helper.make_tensor_value_info("idx", TensorProto.INT64, ["N", 2]),
        ],
        [w, k],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_traps_convert_check_and_match_fp32(seed):
    model = _traps_model()
    check_model(model)
    fp16, kept = convert_model_to_fp16(model, lambda n: n.name.startswith("decode_"))
    assert kept == ["decode_sigmoid", "decode_square", "decode_topk"]
    check_model(fp16)
    # inputs and outputs keep their types, also where a blocked node writes a graph output
    assert io_types(fp16) == io_types(model)
    x = np.random.default_rng(seed).normal(size=(5, 4)).astype(np.float32)
    ref = _run(model, {"x": x})
    got = _run(fp16, {"x": x})
    assert [g.dtype for g in got] == [np.float32, np.float32, np.int64]
    np.testing.assert_allclose(got[0], ref[0], atol=1e-2 * np.ptp(ref[0]))
    np.testing.assert_array_equal(got[2], ref[2])


def test_blocked_chain_stays_exact_float32():
    """Decode ops fed by float32 stay float32 end to end: no float16 round trip between blocked nodes."""
    model = _traps_model()
    fp16, _ = convert_model_to_fp16(model, lambda n: n.name.startswith("decode_") or n.name in ("add1",))
    x = np.random.default_rng(3).normal(size=(7, 4)).astype(np.float32)
    # reference: the fp16 graph's own y (its last fp16 op is add1, kept fp32 here) through the decode in float32
    y = _run(fp16, {"x": x})[0]
    sig2 = (1.0 / (1.0 + np.exp(-y.astype(np.float64)))) ** 2
    want = -np.sort(-sig2, axis=1)[:, :2]
    got = _run(fp16, {"x": x})[1]
    np.testing.assert_allclose(got, want, rtol=1e-6)  # float16 rounding would show at ~1e-3
    to = {n.output[0]: n.attribute[0].i for n in fp16.graph.node if n.op_type == "Cast"}
    round_trips = [n.name for n in fp16.graph.node
                   if n.op_type == "Cast" and to[n.output[0]] == TensorProto.FLOAT and to.get(n.input[0]) == TensorProto.FLOAT16]
    assert not round_trips


def test_unknown_keep_names_and_unnamed_nodes_raise():
    model = _traps_model()
    with pytest.raises(ValueError, match="not in the graph"):
        convert_model_to_fp16(model, ["no_such_node"])
    model.graph.node[0].name = ""
    with pytest.raises(ValueError, match="needs a name"):
        convert_model_to_fp16(model)


def test_names_list_equals_predicate():
    model = _traps_model()
    a, _ = convert_model_to_fp16(model, ["decode_sigmoid", "decode_square", "decode_topk"])
    b, _ = convert_model_to_fp16(model, lambda n: n.name.startswith("decode_"))
    assert a.SerializeToString() == b.SerializeToString()


@pytest.mark.parametrize("seed", [0, 1])
def test_identity_shared_initializer_across_the_fp32_border(seed):
    """The exporter shares equal initializers through Identity; one user kept fp32, the other converted
    (the multi-head slice graph's heatmap biases): the converted graph must still type-check and match."""
    b = helper.make_tensor("b", TensorProto.FLOAT, [4], [0.1, -2.19, 0.3, 1.0])
    nodes = [
        helper.make_node("Identity", ["b"], ["b_shared"], name="share_b"),
        helper.make_node("Add", ["x", "b"], ["kept"], name="decode_add"),  # kept fp32: b stays float32
        helper.make_node("Add", ["x", "b_shared"], ["half"], name="head_add"),  # converted: b_shared float16
        helper.make_node("Add", ["kept", "half"], ["y"], name="sum"),
    ]
    graph = helper.make_graph(nodes, "shared", [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 4])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 4])], [b])  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    fp16, _ = convert_model_to_fp16(model, ["decode_add"])
    check_model(fp16)
    assert not [n for n in fp16.graph.node if n.op_type == "Identity" and n.input[0] == "b"]
    x = np.random.default_rng(seed).normal(size=(3, 4)).astype(np.float32)
    np.testing.assert_allclose(_run(fp16, {"x": x})[0], _run(model, {"x": x})[0], atol=1e-2)
