"""The int8 graphs' ONNX rewrites (export/int8_rewrites.py) against naive references: the transposed convolution
as a 1x1 convolution + DepthToSpace on hand-built graphs and on an exported slice graph, what is left alone, and
that the quantizer then runs the upsampling in int8. The input normalisation rewrite is in test_int8_ops.py."""

from __future__ import annotations

import dataclasses

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from onnx import TensorProto, helper, numpy_helper

from streamdet.export import int8 as q8
from streamdet.export.onnx_export import export_slice_head
from streamdet.models.detector import StreamDetector
from streamdet.models.presets import get_preset

from bn_helpers import random_bn

SEEDS = (0, 1, 2)


def _run(model: onnx.ModelProto, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return sess.run(None, feeds)


def _naive_transposed_conv(x: np.ndarray, w: np.ndarray, b: np.ndarray | None, f: int) -> np.ndarray:
    """ConvTranspose(kernel = stride = f), loop by loop: input pixel (y, x) adds w[:, :, i, j] at (f y + i, f x + j)."""
    n, ci, h, wd = x.shape
    co = w.shape[1]
    out = np.zeros((n, co, h * f, wd * f), np.float64)
    for y in range(h):
        for xx in range(wd):
            for i in range(f):
                for j in range(f):
                    out[:, :, f * y + i, f * xx + j] += x[:, :, y, xx].astype(np.float64) @ w[:, :, i, j].astype(np.float64)
    return out if b is None else out + b[None, :, None, None]


def _transposed(ci: int, co: int, f: int, seed: int, bias: bool, relu: bool, shape=(2, None, 3, 5), **attrs) -> onnx.ModelProto:
    rng = np.random.default_rng(seed)
    k = attrs.pop("kernel", f)
    inits = [numpy_helper.from_array(rng.standard_normal((ci, co // attrs.get("group", 1), k, k)).astype(np.float32), "w")]
    inputs = ["x", "w"]
    if bias:
        inits.append(numpy_helper.from_array(rng.standard_normal(co).astype(np.float32), "b"))
        inputs.append("b")
    nodes = [helper.make_node("ConvTranspose", inputs, ["up"], name="up", strides=[f, f], **attrs)]
    out = "up"
    if relu:
        nodes.append(helper.make_node("Relu", ["up"], ["y"], name="relu"))
        out = "y"
    n, _, h, w = shape
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [n, ci, h, w])
    y = helper.make_tensor_value_info(out, TensorProto.FLOAT, [None] * 4)
    graph = helper.make_graph(nodes, "g", [x], [y], inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("relu", [False, True])
@pytest.mark.parametrize("bias", [False, True])
@pytest.mark.parametrize("f", [1, 2, 4])
def test_transposed_conv_as_depth_to_space_is_exact(f, bias, relu, seed):
    model = _transposed(6, 4, f, seed, bias, relu)
    rewritten = _transposed(6, 4, f, seed, bias, relu)
    assert q8.transposed_convs_as_depth_to_space(rewritten) == 1
    onnx.checker.check_model(rewritten, full_check=True)
    ops = [n.op_type for n in rewritten.graph.node]
    assert ops == (["Conv", "Relu", "DepthToSpace"] if relu else ["Conv", "DepthToSpace"])  # the Relu moved before
    assert [o.name for o in rewritten.graph.output] == [o.name for o in model.graph.output]
    assert {t.name for t in rewritten.graph.initializer}.isdisjoint({"w", "b"})  # the transposed weights are gone
    x = np.random.default_rng(seed + 10).standard_normal((2, 6, 3, 5)).astype(np.float32)
    (got,), (ref,) = _run(rewritten, {"x": x}), _run(model, {"x": x})
    w = numpy_helper.to_array(model.graph.initializer[0])
    b = numpy_helper.to_array(model.graph.initializer[1]) if bias else None
    naive = _naive_transposed_conv(x, w, b, f)
    naive = np.maximum(naive, 0) if relu else naive
    assert got.shape == (2, 4, 3 * f, 5 * f)
    np.testing.assert_allclose(got, naive, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)


def test_transposed_conv_as_depth_to_space_of_an_empty_batch():
    rewritten = _transposed(3, 2, 2, 0, True, True, shape=(None, None, 4, 4))
    assert q8.transposed_convs_as_depth_to_space(rewritten) == 1
    (got,) = _run(rewritten, {"x": np.zeros((0, 3, 4, 4), np.float32)})
    assert got.shape == (0, 2, 8, 8)


@pytest.mark.parametrize(
    "attrs",
    [
        dict(kernel=3, pads=[1, 1, 1, 1]),  # overlapping taps
        dict(kernel=4),  # kernel twice the stride
        dict(group=2),
        dict(output_padding=[1, 1]),
        dict(pads=[0, 0, 1, 1]),
        dict(dilations=[2, 2]),
        dict(output_shape=[6, 10]),
        dict(auto_pad="SAME_UPPER"),
    ],
)
def test_other_transposed_convs_are_left_alone(attrs):
    model = _transposed(4, 4, 2, 0, True, True, **attrs)
    before = model.SerializeToString()
    assert q8.transposed_convs_as_depth_to_space(model) == 0
    assert model.SerializeToString() == before


def test_a_weight_computed_in_the_graph_is_left_alone():
    model = _transposed(4, 4, 2, 0, False, False)
    model.graph.node[0].input[1] = "w2"  # the weight now comes from a node, not an initializer
    model.graph.node.insert(0, helper.make_node("Identity", ["w"], ["w2"]))
    before = model.SerializeToString()
    assert q8.transposed_convs_as_depth_to_space(model) == 0 and model.SerializeToString() == before


def test_a_relu_with_company_stays_after_the_shuffle():
    """A ConvTranspose output read by a Relu and something else: the Relu cannot move, the function stays."""
    model = _transposed(4, 3, 2, 1, True, True)
    model.graph.node.append(helper.make_node("Neg", ["up"], ["z"], name="neg"))
    model.graph.output.append(helper.make_tensor_value_info("z", TensorProto.FLOAT, [None] * 4))
    x = np.random.default_rng(1).standard_normal((2, 4, 3, 5)).astype(np.float32)
    ref = _run(model, {"x": x})
    assert q8.transposed_convs_as_depth_to_space(model) == 1
    assert [n.op_type for n in model.graph.node] == ["Conv", "DepthToSpace", "Relu", "Neg"]
    for got, want in zip(_run(model, {"x": x}), ref):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def _upsampling_preset():
    """The tiny preset with a stage at half the head's resolution: its deblock is a ConvTranspose(k=2, s=2)."""
    tiny = get_preset("tiny")
    return dataclasses.replace(tiny, bev=dataclasses.replace(tiny.bev, upsample_strides=(1.0, 2.0), layer_strides=(2, 2)))


def _slice_inputs(preset, q: int, num_pillars: int, seed: int):
    g, pc = preset.grid, preset.pillars
    gen = torch.Generator().manual_seed(seed)
    counts = torch.randint(1, pc.max_points_per_pillar + 1, (num_pillars,), generator=gen)
    mask = (torch.arange(pc.max_points_per_pillar)[None] < counts[:, None]).float()  # (P, M)
    feats = torch.randn(num_pillars, pc.max_points_per_pillar, 11, generator=gen) * mask[..., None]
    index = torch.randperm(q * g.quadrant_ny * g.quadrant_nx, generator=gen)[:num_pillars].sort().values  # (P,)
    bev = torch.randn(q, preset.channels, g.quadrant_ny, g.quadrant_nx, generator=gen)
    return feats, mask, index, bev


@pytest.mark.parametrize("seed", [0, 1])
def test_exported_slice_graph_keeps_its_detections(seed):
    preset = _upsampling_preset()
    torch.manual_seed(seed)
    det = StreamDetector(preset).eval()
    random_bn(det.slice_net, seed)
    model = export_slice_head(det, _slice_inputs(preset, 2, 60, seed))
    assert sum(n.op_type == "ConvTranspose" for n in model.graph.node) == 1
    rewritten = onnx.ModelProto()
    rewritten.CopyFrom(model)
    assert q8.transposed_convs_as_depth_to_space(rewritten) == 1
    assert not [n for n in rewritten.graph.node if n.op_type == "ConvTranspose"]
    for q, p in ((1, 40), (2, 100), (3, 0)):
        feats, mask, index, bev = _slice_inputs(preset, q, p, seed + 5)
        feeds = {"pillar_features": feats.numpy(), "pillar_mask": mask.numpy(), "pillar_index": index.numpy(), "image_bev": bev.numpy()}
        for got, want in zip(_run(rewritten, feeds), _run(model, feeds)):
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def test_quantized_slice_graph_runs_the_upsampling_in_int8(tmp_path):
    """After the rewrite the quantizer makes the 1x1 convolution a QDQ unit and hands the DepthToSpace quantized
    tensors on both sides (what onnxruntime runs on uint8); the fp32 graph keeps its ConvTranspose."""
    preset = _upsampling_preset()
    # seed 1: seed 0's random weights give some peak sin = cos = 0, whose exported atan2 is NaN (torch's is 0), and
    # the calibrator cannot scale a NaN range; a trained head does not output exact zeros
    torch.manual_seed(1)
    det = StreamDetector(preset).eval()
    random_bn(det.slice_net, 1)
    src = tmp_path / "slice_head.onnx"
    onnx.save_model(export_slice_head(det, _slice_inputs(preset, 2, 60, 1)), str(src))
    feeds = []
    for seed in range(1, 4):
        feats, mask, index, bev = _slice_inputs(preset, 2, 60, seed)
        feeds.append({"pillar_features": feats.numpy(), "pillar_mask": mask.numpy(), "pillar_index": index.numpy(), "image_bev": bev.numpy()})
    graph = q8.quantize_graph("slice_head", src, tmp_path / "slice_head.int8.onnx", feeds)
    model = onnx.load(str(graph.path))
    assert not [n for n in model.graph.node if n.op_type == "ConvTranspose"]
    assert graph.quantized_ops.get("DepthToSpace") == 1
    producer = {o: n for n in model.graph.node for o in n.output}
    (shuffle,) = [n for n in model.graph.node if n.op_type == "DepthToSpace"]
    relu_or_dq = producer[shuffle.input[0]]
    assert relu_or_dq.op_type == "DequantizeLinear"  # the 1x1 conv (and its Relu) quantized before the shuffle
    assert sum(n.op_type == "ConvTranspose" for n in onnx.load(str(src)).graph.node) == 1  # the source is untouched
