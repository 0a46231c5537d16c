"""Multiply-accumulates of an ONNX graph, counted from its shapes: the cross-check of the torch counter.

``models/flops.py`` counts MACs while PyTorch runs the module; this counts them on the exported graph, after
onnx shape inference with the benchmark's concrete input shapes. Counted ops (everything else, element-wise work,
pooling, gathers, costs no MACs here as there):

- Conv:          prod(Y.shape) * prod(W.shape[1:])                    (W is (C_out, C_in / group, k...))
- ConvTranspose: prod(X.shape) * prod(W.shape[1:])                    (W is (C_in, C_out / group, k...): each
                 input element meets C_out / group * k... weights, i.e. C_in * C_out / group * k * k * H_in * W_in)
- MatMul:        prod(Y.shape) * K, K = A.shape[-1]                    (numpy broadcasting and 1-D operands alike)
- Gemm:          M * N * K                                            (K from A's shape and transA)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import onnx

MAC_OPS: tuple[str, ...] = ("Conv", "ConvTranspose", "MatMul", "Gemm")


@dataclass(frozen=True)
class GraphMacs:
    total: int  # MACs of the counted nodes
    by_op: dict[str, int] = field(default_factory=dict)  # op type -> MACs
    unresolved: tuple[str, ...] = ()  # MAC nodes whose shapes inference could not fix (not in total)

    @property
    def gmac(self) -> float:
        return self.total / 1e9

    @property
    def complete(self) -> bool:
        return not self.unresolved


def with_input_shapes(model: onnx.ModelProto, input_shapes: Mapping[str, Sequence[int]]) -> onnx.ModelProto:
    """A copy of ``model`` whose named graph inputs have the given fixed shapes (dynamic axes bound)."""
    fixed = onnx.ModelProto()
    fixed.CopyFrom(model)
    inputs = {i.name: i for i in fixed.graph.input}
    unknown = sorted(set(input_shapes) - set(inputs))
    if unknown:
        raise ValueError(f"input_shapes names {unknown}, which are not inputs of the graph (it has {sorted(inputs)})")
    for name, shape in input_shapes.items():
        dims = inputs[name].type.tensor_type.shape.dim
        if len(dims) != len(shape):
            raise ValueError(f"input {name!r} has rank {len(dims)} in the graph, got shape {tuple(shape)}")
        for d, v in zip(dims, shape):
            if int(v) < 0:
                raise ValueError(f"input {name!r}: dimensions must be >= 0, got shape {tuple(shape)}")
            d.Clear()
            d.dim_value = int(v)
    return fixed


def _shapes(model: onnx.ModelProto) -> dict[str, tuple[int, ...] | None]:
    """value name -> static shape (None where any dimension is symbolic or unknown)."""
    out: dict[str, tuple[int, ...] | None] = {}
    g = model.graph
    for vi in (*g.input, *g.value_info, *g.output):
        t = vi.type.tensor_type
        if not t.HasField("shape"):
            out[vi.name] = None
            continue
        dims = [d.dim_value if d.HasField("dim_value") else None for d in t.shape.dim]
        out[vi.name] = None if any(d is None for d in dims) else tuple(dims)
    for init in g.initializer:
        out[init.name] = tuple(init.dims)
    return out


def _attr(node: onnx.NodeProto, name: str, default: int) -> int:
    for a in node.attribute:
        if a.name == name:
            return int(a.i)
    return default


def _node_macs(node: onnx.NodeProto, shape: Mapping[str, tuple[int, ...] | None]) -> int | None:
    get = lambda i: shape.get(node.input[i]) if len(node.input) > i else None  # noqa: E731
    if node.op_type == "Conv":
        w, y = get(1), shape.get(node.output[0])
        return None if w is None or y is None else math.prod(y) * math.prod(w[1:])
    if node.op_type == "ConvTranspose":
        x, w = get(0), get(1)
        return None if x is None or w is None else math.prod(x) * math.prod(w[1:])
    if node.op_type == "MatMul":
        a, y = get(0), shape.get(node.output[0])
        return None if a is None or y is None else math.prod(y) * a[-1]
    if node.op_type == "Gemm":
        a, y = get(0), shape.get(node.output[0])
        if a is None or y is None:
            return None
        k = a[0] if _attr(node, "transA", 0) else a[1]
        return math.prod(y) * k
    raise ValueError(f"no MAC rule for op type {node.op_type!r}")


def count_graph_macs(model: onnx.ModelProto, input_shapes: Mapping[str, Sequence[int]] | None = None) -> GraphMacs:
    """MACs of one run of ``model`` with inputs of ``input_shapes`` (name -> shape; default: the graph's own).

    Nodes inside subgraphs (If / Loop bodies) are not counted; the streamdet graphs have none.
    """
    if input_shapes:
        model = with_input_shapes(model, input_shapes)
    inferred = onnx.shape_inference.infer_shapes(model, data_prop=True)
    shape = _shapes(inferred)
    by_op: dict[str, int] = {}
    unresolved: list[str] = []
    for node in inferred.graph.node:
        if node.op_type not in MAC_OPS:
            continue
        macs = _node_macs(node, shape)
        if macs is None:
            unresolved.append(node.name or node.op_type)
        else:
            by_op[node.op_type] = by_op.get(node.op_type, 0) + macs
    return GraphMacs(total=sum(by_op.values()), by_op=by_op, unresolved=tuple(unresolved))
