"""The graphs streamdet builds at run time carry the IR version of their opsets, not the installed onnx's newest.

An onnxruntime older than the installed onnx refuses a newer IR ("Unsupported model IR version"); the package's
floor (pyproject: onnxruntime>=1.18) reads up to IR 10.
"""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from streamdet.benchmarks.lut_gather import slots_graph
from streamdet.benchmarks.probe import matmul_model
from streamdet.runtime_ort.lifter_split import term_graph
from streamdet.runtime_ort.onnx_build import make_model

IR_OF_THE_ONNXRUNTIME_FLOOR = 10  # onnxruntime 1.18 reads IR <= 10


def _identity_graph() -> onnx.GraphProto:
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [2])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [2])
    return helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g", [x], [y])


@pytest.mark.parametrize("opset,ir", [(13, 7), (15, 8), (17, 8), (19, 9), (21, 10)])
def test_the_ir_version_is_the_oldest_the_opset_needs(opset, ir):
    model = make_model(_identity_graph(), [helper.make_opsetid("", opset)])
    assert model.ir_version == ir
    onnx.checker.check_model(model)


def test_an_onnxruntime_domain_adds_no_requirement():
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid("com.microsoft", 1)]
    assert make_model(_identity_graph(), opsets).ir_version == 8


def test_a_model_without_opsets_is_refused():
    with pytest.raises(ValueError, match="at least one opset"):
        make_model(_identity_graph(), [])


@pytest.mark.parametrize("sparse", [True, False])
def test_the_runtimes_own_graphs_load_in_the_oldest_supported_onnxruntime(sparse):
    rng = np.random.default_rng(0)
    models = {
        "probe": matmul_model(8),
        "term": term_graph(rng.standard_normal((3, 10)).astype(np.float32), 5, (4, 6), 2, sparse=sparse),
        "lut_gather": slots_graph(rng.integers(0, 4, (6, 2)), rng.random((6, 2)).astype(np.float32), 3),
    }
    for name, model in models.items():
        assert model.ir_version <= IR_OF_THE_ONNXRUNTIME_FLOOR, (name, model.ir_version)
