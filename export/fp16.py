"""fp16 siblings of exported graphs: weights and activations in float16, inputs and outputs kept float32.

Wraps onnxconverter-common's ``convert_float_to_float16`` and works around its traps:

- It retypes the outputs of ``ConstantOfShape`` and ``Cast`` to float16 even where the node still writes float32
  (or an integer type), which yields a graph that fails type checking or silently mis-reads a buffer. Those nodes
  are blocked: they keep their own types, and the converter inserts casts around them. They are blocked *by node
  name*, not through ``op_block_list``: the casts the converter inserts are themselves ``Cast`` nodes appended to
  the list it is iterating, so a blocked ``Cast`` op type makes it wrap its own casts forever (onnxconverter-common
  1.16 hangs).
- ``op_block_list`` is left at the converter's default (TopK, Resize, Range, Min, Max, ...).
- ``keep_io_types`` does not hold for a graph output written by a blocked node: the converter casts it to float16
  and retypes the output. ``_restore_float_outputs`` turns that trailing cast back into a float32 one (the value
  was float32 before it), so outputs stay float32 without a lossy float32 -> float16 -> float32 round trip.
- Each blocked node gets its own casts: a float16 cast after it and a float32 cast before the next blocked node,
  so a chain of blocked nodes (the whole decode) would round its intermediates to float16 between every op.
  ``_drop_cast_round_trips`` rewires float32 -> float16 -> float32 cast pairs to the float32 value.
- The exporter shares identical initializers through ``Identity`` nodes (e.g. every head's heatmap bias starts at the
  same prior, and untrained heads have equal weights). When the sharing nodes straddle the fp32 / fp16 border, the
  converter keeps the initializer float32 but retypes the ``Identity`` output float16, and the graph fails type
  checking. ``_materialize_shared_initializers`` gives each such output its own copy of the initializer first.
- Peak picking on an fp16 heatmap creates ties: neighbouring cells that round to the same half-precision value are
  all "local maxima" of a 3x3 max-pool, so one object yields several peaks. The caller passes the decode nodes
  (sigmoid, max-pool, equality, top-k and the head layer that makes the heatmap logits) in ``keep_fp32`` and they
  run in float32.

The converted model is checked again (``onnx.checker`` with full shape inference): the converter's own shape
inference is no guarantee that the result is valid.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterable

import onnx
from onnxconverter_common import float16

# Ops whose outputs the converter types wrongly (see the module doc); kept as they are.
FP16_UNSAFE_OPS: tuple[str, ...] = ("ConstantOfShape", "Cast")


def convert_model_to_fp16(
    model: onnx.ModelProto,
    keep_fp32: Callable[[onnx.NodeProto], bool] | Iterable[str] = (),
) -> tuple[onnx.ModelProto, list[str]]:
    """The fp16 version of ``model`` and the names of the nodes kept in fp32 by ``keep_fp32``.

    ``keep_fp32`` is either a predicate on nodes or an iterable of node names.
    """
    model = onnx.shape_inference.infer_shapes(model, check_type=True, strict_mode=True, data_prop=True)
    model = _materialize_shared_initializers(model)
    if callable(keep_fp32):
        kept = [n.name for n in model.graph.node if keep_fp32(n)]
    else:
        kept = list(keep_fp32)
        missing = sorted(set(kept) - {n.name for n in model.graph.node})
        if missing:
            raise ValueError(f"keep_fp32 names nodes that are not in the graph: {missing[:5]}")
    unnamed = [i for i, n in enumerate(model.graph.node) if not n.name]
    if unnamed:
        # The converter names its casts after the node; an unnamed node would give colliding cast names.
        raise ValueError(f"every node needs a name for fp16 conversion; nodes {unnamed[:5]} have none")
    unsafe = [n.name for n in model.graph.node if n.op_type in FP16_UNSAFE_OPS and n.name not in kept]
    with warnings.catch_warnings():
        # One warning per weight below float16's range (clamped to +-1e-7, harmless); the parity checks judge.
        warnings.filterwarnings("ignore", message="the float32 number .* will be truncated to", category=UserWarning)
        converted = float16.convert_float_to_float16(
            model,
            keep_io_types=True,  # the runtime feeds and reads float32 whatever the precision inside
            op_block_list=list(float16.DEFAULT_OP_BLOCK_LIST),
            node_block_list=kept + unsafe,
        )
    _restore_float_outputs(converted, io_types(model))
    _drop_cast_round_trips(converted)
    return converted, kept


def check_model(model_or_path: onnx.ModelProto | str | os.PathLike) -> onnx.ModelProto:
    """onnx.checker (full check) plus strict full shape inference; returns the shape-inferred model."""
    model = model_or_path if isinstance(model_or_path, onnx.ModelProto) else onnx.load(os.fspath(model_or_path))
    onnx.checker.check_model(model, full_check=True)
    return onnx.shape_inference.infer_shapes(model, check_type=True, strict_mode=True, data_prop=True)


def io_types(model: onnx.ModelProto) -> dict[str, int]:
    """Element type of every graph input and output, by name."""
    return {v.name: v.type.tensor_type.elem_type for v in (*model.graph.input, *model.graph.output)}


def _restore_float_outputs(model: onnx.ModelProto, original: dict[str, int]) -> None:
    """Give back float32 to every graph output the converter turned into float16 (in place)."""
    producer = {out: n for n in model.graph.node for out in n.output}
    for out in model.graph.output:
        was, now = original.get(out.name), out.type.tensor_type.elem_type
        if was != onnx.TensorProto.FLOAT or now != onnx.TensorProto.FLOAT16:
            continue
        node = producer.get(out.name)
        if node is not None and node.op_type == "Cast":
            # The converter's trailing float32 -> float16 cast after a blocked node: make it a float32 no-op.
            for a in node.attribute:
                if a.name == "to":
                    a.i = onnx.TensorProto.FLOAT
        else:
            # A genuinely float16 value: cast it up under the output's name.
            inner = f"{out.name}_fp16"
            if node is None:
                raise ValueError(f"graph output {out.name!r} has no producing node")
            node.output[list(node.output).index(out.name)] = inner
            model.graph.node.append(
                onnx.helper.make_node("Cast", [inner], [out.name], to=onnx.TensorProto.FLOAT, name=f"{out.name}_to_fp32")
            )
        out.type.tensor_type.elem_type = onnx.TensorProto.FLOAT


def _materialize_shared_initializers(model: onnx.ModelProto) -> onnx.ModelProto:
    """A copy of ``model`` where every ``Identity`` of an initializer is replaced by its own initializer."""
    model_copy = onnx.ModelProto()
    model_copy.CopyFrom(model)
    g = model_copy.graph
    inits = {t.name: t for t in g.initializer}
    graph_outputs = {o.name for o in g.output}
    shared = [n for n in g.node if n.op_type == "Identity" and n.input[0] in inits and n.output[0] not in graph_outputs]
    for node in shared:
        copy = onnx.TensorProto()
        copy.CopyFrom(inits[node.input[0]])
        copy.name = node.output[0]
        g.initializer.append(copy)
        g.node.remove(node)
    return model_copy


def _drop_cast_round_trips(model: onnx.ModelProto) -> None:
    """Replace ``Cast(to=fp32)(Cast(to=fp16)(x))`` with ``x`` where x is float32 (in place; exact, not lossy)."""
    g = model.graph
    inferred = onnx.shape_inference.infer_shapes(model)
    elem = {v.name: v.type.tensor_type.elem_type for v in (*inferred.graph.value_info, *g.input, *g.output)}
    elem.update({t.name: t.data_type for t in g.initializer})
    producer = {out: n for n in g.node for out in n.output}
    graph_outputs = {o.name for o in g.output}

    def cast_to(node: onnx.NodeProto) -> int | None:
        if node.op_type != "Cast":
            return None
        return next((a.i for a in node.attribute if a.name == "to"), None)

    rename: dict[str, str] = {}  # output of a redundant float32 cast -> the original float32 tensor
    for node in g.node:
        if cast_to(node) != onnx.TensorProto.FLOAT or node.output[0] in graph_outputs:
            continue
        down = producer.get(node.input[0])
        if down is None or cast_to(down) != onnx.TensorProto.FLOAT16:
            continue
        if elem.get(down.input[0]) == onnx.TensorProto.FLOAT:
            rename[node.output[0]] = down.input[0]
    if not rename:
        return
    for node in g.node:
        for i, name in enumerate(node.input):
            if name in rename:
                node.input[i] = rename[name]
    # Drop the bypassed casts, then float16 casts nobody reads any more.
    keep = [n for n in g.node if not (n.op_type == "Cast" and n.output[0] in rename)]
    used = {i for n in keep for i in n.input} | graph_outputs
    keep = [n for n in keep if not (cast_to(n) == onnx.TensorProto.FLOAT16 and n.output[0] not in used)]
    del g.node[:]
    g.node.extend(keep)
    names = {o for n in keep for o in n.output}
    kept_info = [v for v in g.value_info if v.name in names]
    del g.value_info[:]
    g.value_info.extend(kept_info)
