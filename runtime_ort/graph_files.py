"""An export's graph files checked as ONNX models before onnxruntime sees them.

The runtime reads each file of an export once (``manifest.read_export_file``: confined, a regular file within its
size limit, hashed from the bytes read) and hands those bytes on: to onnxruntime (``GraphSession(model=...)``) and
the LUT reader (``Lut.load(data=...)``), so a file swapped after its check is never the one loaded.

A graph must also keep every tensor inside its own file. ONNX allows "external data" (weights in a side file the
graph names); such a file is covered by no sha256 of the manifest, and onnxruntime versions before 1.21 follow
absolute, ``..`` and symlinked locations out of the export. ``streamdet-export`` never writes external data, so a
graph with any is refused (``checked_model``).
"""

from __future__ import annotations

from pathlib import Path

import onnx
from google.protobuf.message import DecodeError

from streamdet.runtime_ort.manifest import GraphEntry, ManifestError
from streamdet.runtime_ort.signature import TensorSignature


def checked_model(path: Path, raw: bytes, entry: GraphEntry | None = None) -> onnx.ModelProto:
    """The ONNX model in ``raw`` (read from ``path``), refused (ManifestError) when it does not parse, keeps any
    tensor's data in another file, or (given its manifest ``entry``) has another opset or precision than recorded:
    an fp16 graph copied over the fp32 one, its sha256 updated, would otherwise run as "fp32"."""
    try:
        model = onnx.load_model_from_string(raw)
    except (DecodeError, ValueError, RuntimeError) as e:
        raise ManifestError(f"{path}: not an ONNX model (its protobuf does not parse: {' '.join(str(e).split()) or type(e).__name__})") from None
    if not model.graph.node or not model.opset_import:  # e.g. an empty file: a valid, empty protobuf
        raise ManifestError(f"{path}: not an ONNX model (no graph nodes or no opset: an empty or foreign file)")
    outside = external_tensors(model)
    if outside:
        name, location = outside[0]
        raise ManifestError(
            f"{path}: {len(outside)} tensor(s) keep their data in another file ({name!r} in {location!r}); an export "
            "keeps every weight inside its graph file, where the manifest's sha256 covers it"
        )
    if entry is not None:
        _check_recorded(path, model, entry)
    return model


def graph_precision(model: onnx.ModelProto) -> str:
    """What a graph's contents say its precision is: "int8" with quantize / QLinear nodes, "fp16" with float16
    weights, else "fp32" (what streamdet-export writes for each, export/fp16.py and export/int8.py)."""
    ops = {n.op_type for n in model.graph.node}
    if any(op == "QuantizeLinear" or op.startswith("QLinear") for op in ops):
        return "int8"
    if any(t.data_type == onnx.TensorProto.FLOAT16 for t in model.graph.initializer):
        return "fp16"
    return "fp32"


def _check_recorded(path: Path, model: onnx.ModelProto, entry: GraphEntry) -> None:
    opset = next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), None)
    if opset != entry.opset:
        raise ManifestError(f"{path}: the graph is opset {opset}, the manifest records opset {entry.opset} (another export's graph?)")
    precision = graph_precision(model)
    if precision != entry.precision:
        raise ManifestError(f"{path}: the graph holds a {precision} model, the manifest records {entry.precision} "
                            "(a graph of another precision copied over it?)")  # fmt: skip


def model_signature(model: onnx.ModelProto) -> tuple[tuple[TensorSignature, ...], tuple[TensorSignature, ...]]:
    """(inputs, outputs) a parsed graph declares, as ``GraphSession`` reads them from a session (named or unknown
    dimensions None; initializers listed as inputs by old exporters left out): a graph checked without a session."""
    inits = {t.name for t in model.graph.initializer}

    def sig(v: onnx.ValueInfoProto) -> TensorSignature:
        t = v.type.tensor_type
        dtype = onnx.helper.tensor_dtype_to_np_dtype(t.elem_type).name if t.elem_type else "undefined"
        return TensorSignature(v.name, dtype, tuple(d.dim_value if d.HasField("dim_value") else None for d in t.shape.dim))

    return (tuple(sig(v) for v in model.graph.input if v.name not in inits), tuple(sig(v) for v in model.graph.output))


def external_tensors(model: onnx.ModelProto) -> list[tuple[str, str]]:
    """(tensor name, location) of every tensor stored as external data: initializers, sparse initializers and
    tensor attributes, in every subgraph."""
    found: list[tuple[str, str]] = []
    graphs = [model.graph]
    while graphs:
        g = graphs.pop()
        tensors = list(g.initializer)
        tensors += [t for s in g.sparse_initializer for t in (s.values, s.indices)]
        for node in g.node:
            for a in node.attribute:
                tensors += [a.t] if a.HasField("t") else []
                tensors += list(a.tensors)
                sparse = ([a.sparse_tensor] if a.HasField("sparse_tensor") else []) + list(a.sparse_tensors)
                tensors += [t for s in sparse for t in (s.values, s.indices)]
                graphs += [a.g] if a.HasField("g") else []
                graphs += list(a.graphs)
        for t in tensors:
            if t.data_location == onnx.TensorProto.EXTERNAL or len(t.external_data):
                location = next((kv.value for kv in t.external_data if kv.key == "location"), "?")
                found.append((t.name, location))
    return found
