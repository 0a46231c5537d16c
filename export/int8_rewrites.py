"""The int8 graphs' ONNX rewrites: each keeps the fp32 graph's function and makes the QDQ quantizer's output run faster.

Applied to a pre-processed fp32 graph before ``quantize_static`` (export/int8_quantize.py: ``quantize_graph``); the
fp32 graphs of an export never see them. What each buys is measured in benchmarks/RESULTS.md.

- ``normalisation_as_batchnorm`` (image encoder): the input normalisation as one float BatchNormalization
  (export/int8_quantize.py's module doc says why).
- ``transposed_convs_as_depth_to_space`` (slice graph): a ConvTranspose whose kernel tiles its output (kernel =
  stride = f, no padding, one group) computes, for every input pixel, an f x f block of output pixels, each a 1x1
  convolution of that pixel with its own tap. That is a 1x1 Conv to ``Co * f * f`` channels, tap (i, j) of output
  channel c in channel ``c * f * f + i * f + j``, followed by DepthToSpace in CRD order, which puts that channel at
  pixel (f * y + i, f * x + j). onnxruntime has no int8 ConvTranspose (it runs float, NCHW, between a
  DequantizeLinear and a QuantizeLinear); the 1x1 Conv quantizes to a QLinearConv and DepthToSpace runs on uint8.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import numpy_helper


def first_node(model: onnx.ModelProto, op_type: str) -> onnx.NodeProto:
    """The first node of ``op_type`` (graphs are topologically sorted), or a clear error."""
    nodes = [n for n in model.graph.node if n.op_type == op_type]
    if not nodes:
        raise ValueError(f"the graph has no {op_type} node")
    return nodes[0]


def _constant(model: onnx.ModelProto, name: str) -> np.ndarray | None:
    for t in model.graph.initializer:
        if t.name == name:
            return numpy_helper.to_array(t)
    for n in model.graph.node:
        if n.op_type == "Constant" and n.output[0] == name:
            return numpy_helper.to_array(n.attribute[0].t)
    return None


def normalisation_as_batchnorm(model: onnx.ModelProto) -> bool:
    """Rewrite the encoder's input normalisation ``Add(Mul(x, scale), shift)`` with (1, C, 1, 1) constants before
    the first Conv into one BatchNormalization (mean 0, variance 1, epsilon 0: the same arithmetic). In place;
    False when there is no such pair. See the module doc for why."""
    first = first_node(model, "Conv")
    producer = {o: n for n in model.graph.node for o in n.output}
    add = producer.get(first.input[0])
    mul = producer.get(add.input[0]) if add is not None and add.op_type == "Add" else None
    if mul is None or mul.op_type != "Mul":
        return False
    scale, shift = _constant(model, mul.input[1]), _constant(model, add.input[1])
    per_channel = lambda a: a is not None and a.ndim == 4 and a.shape[0] == a.shape[2] == a.shape[3] == 1  # noqa: E731
    if not (per_channel(scale) and per_channel(shift) and scale.shape == shift.shape):
        return False
    users = [n for n in model.graph.node if mul.output[0] in n.input]
    if users != [add]:
        return False
    c = scale.shape[1]  # (1, C, 1, 1)
    names = [f"{first.name}/input_norm_{k}" for k in ("scale", "shift", "mean", "var")]
    values = [scale.reshape(c), shift.reshape(c), np.zeros(c), np.ones(c)]
    model.graph.initializer.extend(numpy_helper.from_array(v.astype(np.float32), n) for n, v in zip(names, values))
    bn = onnx.helper.make_node("BatchNormalization", [mul.input[0], *names], [add.output[0]], epsilon=0.0,
                               name=f"{first.name}/input_norm")  # fmt: skip
    nodes = [bn if n is mul else n for n in model.graph.node if n is not add]
    used = {i for n in nodes for i in n.input}
    nodes = [n for n in nodes if not (n.op_type == "Constant" and n.output[0] not in used)]
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    inits = [t for t in model.graph.initializer if t.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(inits)
    return True


def _ints(node: onnx.NodeProto, name: str) -> list[int] | None:
    for a in node.attribute:
        if a.name == name:
            return list(a.ints)
    return None


def _int(node: onnx.NodeProto, name: str, default: int) -> int:
    for a in node.attribute:
        if a.name == name:
            return int(a.i)
    return default


def _tiling_factor(node: onnx.NodeProto, weight: np.ndarray | None) -> int | None:
    """f when the 2-D ConvTranspose ``node`` has kernel = stride = (f, f), no padding, dilation or output padding,
    one group and an explicit output size; else None."""
    if weight is None or weight.ndim != 4 or weight.shape[2] != weight.shape[3]:
        return None
    f = weight.shape[2]
    if (_ints(node, "kernel_shape") or [f, f]) != [f, f] or (_ints(node, "strides") or [1, 1]) != [f, f]:
        return None
    zeros = lambda name: all(v == 0 for v in _ints(node, name) or [])  # noqa: E731
    ones = all(v == 1 for v in _ints(node, "dilations") or [])
    auto_pad = next((a.s for a in node.attribute if a.name == "auto_pad"), b"NOTSET")
    if not (zeros("pads") and zeros("output_padding") and ones and auto_pad == b"NOTSET"):
        return None
    if _int(node, "group", 1) != 1 or _ints(node, "output_shape") is not None:
        return None
    return f


def transposed_convs_as_depth_to_space(model: onnx.ModelProto) -> int:
    """Rewrite every ConvTranspose with kernel = stride (f x f tiles, see the module doc) as ``Conv(1x1, Co * f * f)``
    + ``DepthToSpace(f, CRD)``, the same function. In place; returns how many were rewritten (0: the graph is
    untouched). The DepthToSpace writes the tensor the rewritten part wrote, so its readers and shapes stay.

    A Relu that is the ConvTranspose's only reader moves before the DepthToSpace (elementwise, so it commutes with
    the shuffle): onnxruntime fuses it into the int8 convolution, and the DepthToSpace then moves uint8 values
    between two quantized tensors instead of running in float between a DequantizeLinear and a QuantizeLinear.
    """
    inits = {t.name: t for t in model.graph.initializer}
    readers: dict[str, list[onnx.NodeProto]] = {}
    for n in model.graph.node:
        for i in n.input:
            readers.setdefault(i, []).append(n)
    graph_outputs = {o.name for o in model.graph.output}
    nodes: list[onnx.NodeProto] = []
    dropped: set[int] = set()  # ids of the Relus moved before a DepthToSpace
    count = 0
    for node in model.graph.node:
        if id(node) in dropped:
            continue
        weight = numpy_helper.to_array(inits[node.input[1]]) if node.op_type == "ConvTranspose" and node.input[1] in inits else None
        f = _tiling_factor(node, weight) if weight is not None else None
        bias_name = node.input[2] if len(node.input) > 2 and node.input[2] else None
        if f is None or (bias_name is not None and bias_name not in inits):
            nodes.append(node)
            continue
        ci, co = weight.shape[:2]  # ConvTranspose keeps (Ci, Co, f, f)
        taps = weight.transpose(1, 2, 3, 0).reshape(co * f * f, ci, 1, 1)  # (Co * f * f, Ci, 1, 1), channel c * f * f + i * f + j
        prefix = node.name or node.output[0]
        names = [f"{prefix}/as_conv_weight"]
        model.graph.initializer.append(numpy_helper.from_array(np.ascontiguousarray(taps), names[0]))
        if bias_name is not None:
            bias = numpy_helper.to_array(inits[bias_name]).repeat(f * f)  # (Co * f * f,)
            names.append(f"{prefix}/as_conv_bias")
            model.graph.initializer.append(numpy_helper.from_array(bias, names[1]))
        blocks = f"{node.output[0]}/blocks"  # (N, Co * f * f, H, W)
        nodes.append(onnx.helper.make_node("Conv", [node.input[0], *names], [blocks], kernel_shape=[1, 1], name=f"{prefix}/as_conv"))
        out = node.output[0]
        relu = readers.get(out, [])
        if len(relu) == 1 and relu[0].op_type == "Relu" and out not in graph_outputs:
            dropped.add(id(relu[0]))
            out = relu[0].output[0]
            nodes.append(onnx.helper.make_node("Relu", [blocks], [f"{blocks}/relu"], name=f"{prefix}/as_conv_relu"))
            blocks = f"{blocks}/relu"
        nodes.append(onnx.helper.make_node("DepthToSpace", [blocks], [out], blocksize=f, mode="CRD", name=f"{prefix}/depth_to_space"))
        count += 1
    if count:
        del model.graph.node[:]
        model.graph.node.extend(nodes)
        used = {i for n in nodes for i in n.input}
        kept = [t for t in model.graph.initializer if t.name in used]
        del model.graph.initializer[:]
        model.graph.initializer.extend(kept)
    return count
