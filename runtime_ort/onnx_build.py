"""ModelProtos that streamdet builds itself at run time (lifter pieces, benchmark probes).

``onnx.helper.make_model`` stamps a graph with the newest IR version the *installed* onnx knows, which an older
onnxruntime refuses to load ("Unsupported model IR version: 14, max supported IR version: 13") although the graph
uses nothing newer than its opsets. The exported graphs carry the IR of their opset; the graphs built here get the
same: the oldest IR version that every opset they import needs, so that each onnxruntime the package supports loads
them whatever onnx is installed beside it.
"""

from __future__ import annotations

from collections.abc import Sequence

import onnx
from onnx import helper


def make_model(graph: onnx.GraphProto, opset_imports: Sequence[onnx.OperatorSetIdProto]) -> onnx.ModelProto:
    """``helper.make_model`` with the IR version the opsets need instead of the installed onnx's newest.

    Domains onnx does not know (``com.microsoft``) add no requirement: their operators are onnxruntime's own.
    """
    if not opset_imports:
        raise ValueError("a model needs at least one opset import, got none")
    ir_version = helper.find_min_ir_version_for(list(opset_imports), ignore_unknown=True)
    return helper.make_model(graph, opset_imports=list(opset_imports), ir_version=ir_version)
