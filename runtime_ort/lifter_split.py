"""The flat lifter graph cut after its first convolution, for per-camera lifts: that convolution's weights and the
``tail`` graph.

The flat lifter (``models/flat_lifter.py``) gathers each voxel's LUT slots from the cameras' feature maps, stacks z
into channels and runs a 1x1 convolution, then the rest (ReLU, a residual k3 convolution, the slice graph's image
half where the export has it). The gather and that first convolution are linear, so the quadrant's pre-activation
map is the convolution's bias plus one term per camera (``calibration/camera_lut.py``). This module builds, from an
export's own lifter graphs (ONNX surgery, no model code), what ``runtime_ort/camera_terms.py`` runs (in onnxruntime,
which releases the GIL: the same work in numpy held it long enough to double the slice lane's latency beside it):

- ``first_conv``: the fp32 lifter's first Conv, its (C_out, Z * C) weight and bias;
- ``term_graph``: one camera's terms from its feature map (that weight applied before the gather);
- ``tail_graph``: the cameras' terms scattered into the quadrant's cells and added to the first convolution's bias,
  then the lifter graph from that convolution's output on. Cut from the int8 lifter too, its QuantizeLinear of the
  cut tensor quantizes the sum (ReLU included, as the int8 graph does it).

Only a lifter whose first Conv is a 1x1 with constant weight and bias splits (``SplitError`` otherwise: the volume
lifter's export form runs its 1x1 per z plane, and what follows reads the graph's inputs again).
``runtime_ort/camera_terms.py`` runs the pieces and checks them against the lifter graph they were cut from.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from streamdet.core.errors import first_line
from streamdet.runtime_ort.onnx_build import make_model

OPSET = 17


class SplitError(ValueError):
    """The lifter graph cannot be cut into per-camera partial lifts (not the flat lifter's form)."""


def first_conv(model: onnx.ModelProto) -> tuple[onnx.NodeProto, np.ndarray, np.ndarray]:
    """The lifter graph's first Conv (the flat lifter's 1x1 over the z-stacked channels), its weight (C_out, Z * C)
    and bias (C_out,), from constant initializers."""
    inits = {t.name: t for t in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type == "Conv":
            if len(node.input) < 3 or node.input[1] not in inits or node.input[2] not in inits:
                raise SplitError(f"the lifter's first Conv {node.name!r} has no constant weight and bias")
            weight = numpy_helper.to_array(inits[node.input[1]])
            if weight.ndim != 4 or weight.shape[2:] != (1, 1):
                raise SplitError(f"the lifter's first Conv has a {weight.shape} weight, not a 2D 1x1: a per-camera lift "
                                 "needs the flat lifter (LifterConfig.form='flat')")  # fmt: skip
            bias = numpy_helper.to_array(inits[node.input[2]])
            return node, weight[:, :, 0, 0].astype(np.float32), bias.astype(np.float32)
    raise SplitError("the lifter graph has no Conv")


def first_conv_output(model: onnx.ModelProto) -> str:
    """The output tensor of the first Conv of ``model`` (the fp32 or the int8 QDQ lifter: its weight may come from a
    DequantizeLinear)."""
    for node in model.graph.node:
        if node.op_type == "Conv":
            return node.output[0]
    raise SplitError("the lifter graph has no Conv")


def term_graph(weight: np.ndarray, channels: int, feature_hw: tuple[int, int], heights: int, *, sparse: bool = True) -> onnx.ModelProto:
    """One camera's terms ``term (N, C_out) = sum_j weights[n, j] * P[slots[n, j]]``, where ``P`` is the map's
    projected table: row ``z * (Hf*Wf + 1) + r`` = row r of the map's (Hf*Wf + 1, C) table (the zero row last) times
    the (C, C_out) block of height z of the first convolution's ``weight`` (C_out, Z * C), Z = ``heights``. The
    convolution applied before the gather: the same sums as gathering the (N, Z * C) rows and multiplying by
    ``weight``, and faster (measured: docs/replay.md, section "Per-camera lifts in the runtime (issue 22, ninth
    session)", "The convolution before the gather"). ``camera_terms.share_slots`` gives a share's slots and
    weights; the rows of several shares of one camera (its quadrants) go through one run, projecting the map once.

    Inputs: ``features (1, C, Hf, Wf)`` and, with ``sparse`` (the default), ``lut``: the (N, Z * (Hf*Wf + 1))
    sparse matrix of the weights (``sparse_lut``; onnxruntime's ``com.microsoft`` SparseToDenseMatMul, which does
    not materialise the (N, J, C_out) gathered rows and is faster than the dense form; measured: docs/replay.md,
    section "Sparse terms and full updates through terms (issue 22, twelfth session)"), else ``slots (N, J) int64``
    and ``weights (N, J) float32`` (Gather, then a batched MatMul)."""
    hf, wf = feature_hw
    c_out, zc = weight.shape
    if zc != heights * channels:
        raise SplitError(f"the lifter's first Conv takes {zc} channels, not the {heights} z planes x {channels} feature "
                         "channels stacked: a per-camera lift needs the flat lifter (LifterConfig.form='flat')")  # fmt: skip
    blocks = weight.reshape(c_out, heights, channels).transpose(1, 2, 0)  # (Z, C, C_out)
    table_rows = heights * (hf * wf + 1)

    def const(name: str, value: np.ndarray) -> onnx.TensorProto:
        return numpy_helper.from_array(np.ascontiguousarray(value), name)

    inits = [
        const("flat", np.array([channels, hf * wf], np.int64)),
        const("zero_row", np.zeros((1, channels), np.float32)),
        const("blocks", blocks.astype(np.float32)),  # (Z, C, C_out)
        const("rows_out", np.array([table_rows, c_out], np.int64)),
    ]
    nodes = [
        helper.make_node("Reshape", ["features", "flat"], ["cf"]),  # (C, Hf*Wf)
        helper.make_node("Transpose", ["cf"], ["rows"], perm=[1, 0]),  # (Hf*Wf, C)
        helper.make_node("Concat", ["rows", "zero_row"], ["table"], axis=0),  # (Hf*Wf + 1, C)
        # broadcast over the heights: the projected table comes out in gather order, no transpose of it
        helper.make_node("MatMul", ["table", "blocks"], ["projected"]),  # (Z, Hf*Wf + 1, C_out)
        helper.make_node("Reshape", ["projected", "rows_out"], ["p"]),  # (Z * (Hf*Wf + 1), C_out)
    ]
    features = helper.make_tensor_value_info("features", TensorProto.FLOAT, [1, channels, hf, wf])
    opsets = [helper.make_opsetid("", OPSET)]
    if sparse:
        nodes.append(helper.make_node("SparseToDenseMatMul", ["lut", "p"], ["term"], domain="com.microsoft"))  # (N, C_out)
        inputs = [features, helper.make_sparse_tensor_value_info("lut", TensorProto.FLOAT, ["N", table_rows])]
        opsets.append(helper.make_opsetid("com.microsoft", 1))
    else:
        inits.append(const("axis1", np.array([1], np.int64)))
        nodes += [
            helper.make_node("Gather", ["p", "slots"], ["g"], axis=0),  # (N, J, C_out)
            helper.make_node("Unsqueeze", ["weights", "axis1"], ["w3"]),  # (N, 1, J)
            helper.make_node("MatMul", ["w3", "g"], ["t3"]),  # (N, 1, C_out)
            helper.make_node("Squeeze", ["t3", "axis1"], ["term"]),  # (N, C_out)
        ]
        inputs = [features, helper.make_tensor_value_info("slots", TensorProto.INT64, ["N", "J"]),
                  helper.make_tensor_value_info("weights", TensorProto.FLOAT, ["N", "J"])]  # fmt: skip
    graph = helper.make_graph(nodes, "lifter_term", inputs, [helper.make_tensor_value_info("term", TensorProto.FLOAT, ["N", c_out])], inits)
    model = make_model(graph, opsets)
    onnx.checker.check_model(model)
    return model


def sparse_lut(slots: np.ndarray, weights: np.ndarray, table_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """(values (nnz,) float32, coo (nnz, 2) int64 (row, table row), row-major order) of the (N, table_rows) matrix
    whose row n holds ``weights[n, j]`` at column ``slots[n, j]``: the sparse ``lut`` of ``term_graph``. Zero
    weights (padding slots) are left out and a slot repeated within a row has its weights summed, so each row's
    product with the projected table is the dense form's sum (up to float order)."""
    if slots.shape != weights.shape or slots.ndim != 2:
        raise ValueError(f"slots and weights must be the same (N, J) shape, got {slots.shape} and {weights.shape}")
    if slots.size and (slots.min() < 0 or slots.max() >= table_rows):
        raise ValueError(f"slots must lie in [0, {table_rows}), got [{slots.min()}, {slots.max()}]")
    n = slots.shape[0]
    keep = weights != 0
    flat = (np.arange(n, dtype=np.int64)[:, None] * table_rows + slots.astype(np.int64))[keep]  # (nnz',)
    cells, inverse = np.unique(flat, return_inverse=True)  # sorted: row-major
    values = np.zeros(cells.size, np.float64)
    np.add.at(values, inverse.reshape(-1), weights[keep].astype(np.float64))
    coo = np.stack([cells // table_rows, cells % table_rows], axis=1)  # (nnz, 2)
    nonzero = values != 0  # weights that cancel exactly
    return np.ascontiguousarray(values[nonzero], np.float32), np.ascontiguousarray(coo[nonzero], np.int64)


def tail_graph(lifter: onnx.ModelProto, cut: str, shape: tuple[int, int, int], bias: np.ndarray) -> onnx.ModelProto:
    """``lifter`` from tensor ``cut`` (its first Conv's output) on, fed the cameras' distinct terms ``terms (U, C_out)``,
    ``rows (M,) int64`` (the term of each of the quadrant's M (cell, camera) pairs: cells whose slots and weights
    are the same share one term) and ``cells (M, 1) int64`` (the quadrant's flat cells ``y * Xq + x`` of those
    pairs, repeats summed), added to the first convolution's ``bias`` (C_out,) in every cell (ScatterND, reduction
    add: the sum happens in onnxruntime, which releases the GIL); ``shape`` = (C_out, Yq, Xq)."""
    from onnx.utils import Extractor

    if max((o.version for o in lifter.opset_import if o.domain in ("", "ai.onnx")), default=0) < 16:
        raise SplitError("the lifter graph's opset is below 16 (ScatterND's add): re-export it")
    outputs = [o.name for o in lifter.graph.output]
    lifter = onnx.shape_inference.infer_shapes(lifter)
    if cut not in {v.name for v in lifter.graph.value_info}:  # the Extractor needs the cut tensor's type
        lifter.graph.value_info.append(helper.make_tensor_value_info(cut, TensorProto.FLOAT, None))
    tail = Extractor(lifter).extract_model([cut], outputs)
    c, yq, xq = shape
    inits = [
        numpy_helper.from_array(np.asarray(bias, np.float32).reshape(c), "tail_bias"),
        numpy_helper.from_array(np.array([yq * xq, c], np.int64), "tail_rows"),
        numpy_helper.from_array(np.array([1, yq, xq, c], np.int64), "tail_shape"),
    ]
    head = [
        helper.make_node("Expand", ["tail_bias", "tail_rows"], ["base"]),  # (Yq*Xq, C_out)
        helper.make_node("Gather", ["terms", "rows"], ["tail_pairs"], axis=0),  # (M, C_out)
        helper.make_node("ScatterND", ["base", "cells", "tail_pairs"], ["summed"], reduction="add"),  # (Yq*Xq, C_out)
        helper.make_node("Reshape", ["summed", "tail_shape"], ["summed4"]),  # (1, Yq, Xq, C_out)
        helper.make_node("Transpose", ["summed4"], [cut], perm=[0, 3, 1, 2]),  # (1, C_out, Yq, Xq)
    ]
    graph = helper.make_graph(
        head + list(tail.graph.node), "lifter_tail",
        [helper.make_tensor_value_info("terms", TensorProto.FLOAT, ["U", c]),
         helper.make_tensor_value_info("rows", TensorProto.INT64, ["M"]),
         helper.make_tensor_value_info("cells", TensorProto.INT64, ["M", 1])], list(tail.graph.output),
        inits + list(tail.graph.initializer),
    )  # fmt: skip
    model = make_model(graph, lifter.opset_import)
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as e:  # e.g. the rest of the graph reads the lifter's inputs again
        raise SplitError(f"the lifter graph after its first Conv is not a graph of that Conv's output alone ({first_line(e)}): "
                         "a per-camera lift needs the flat lifter (LifterConfig.form='flat')") from None
    return model
