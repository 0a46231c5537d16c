"""The ONNX-graph MAC counter against the torch counter (models/flops.py) on small modules and the tiny rows."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch
from torch import nn

from streamdet.benchmarks.graph_macs import count_graph_macs, with_input_shapes
from streamdet.benchmarks.modules import build_rows
from streamdet.export.onnx_export import GraphIO, export_module
from streamdet.models.flops import count_gmac, count_macs
from streamdet.models.lifter_fold import folded_mac_ratio
from streamdet.models.presets import get_preset


class BatchedMatmul(nn.Module):
    def __init__(self, k: int, n: int) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.randn(k, n))

    def forward(self, x):
        return torch.relu(x @ self.w) @ self.w.t()  # (B, M, N) then back to (B, M, K)


def random_module(kind: str, rng: np.random.Generator) -> tuple[nn.Module, torch.Tensor]:
    r = lambda lo, hi: int(rng.integers(lo, hi + 1))  # noqa: E731
    groups = r(1, 3)
    cin, cout = groups * r(1, 4), groups * r(1, 4)
    if kind == "conv2d":
        conv = nn.Conv2d(cin, cout, r(1, 3) * 2 - 1, stride=r(1, 2), padding=r(0, 2), groups=groups)
        return conv, torch.randn(r(1, 2), cin, r(5, 12), r(5, 12))
    if kind == "conv_transpose2d":
        k = r(1, 4)
        return nn.ConvTranspose2d(cin, cout, k, stride=k, groups=groups), torch.randn(r(1, 2), cin, r(3, 8), r(3, 8))
    if kind == "conv3d":
        return nn.Conv3d(cin, cout, 3, stride=(2, 1, 1), padding=1, bias=False), torch.randn(1, cin, r(2, 6), r(3, 7), r(3, 7))
    if kind == "linear_gemm":
        return nn.Linear(r(2, 9), r(2, 9)), None  # input built below: 2-D -> Gemm
    if kind == "linear_matmul":
        return nn.Linear(r(2, 9), r(2, 9), bias=False), None  # 3-D input -> MatMul
    if kind == "batched_matmul":
        return BatchedMatmul(r(2, 9), r(2, 9)), None
    if kind == "mixed":
        net = nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU(), nn.ConvTranspose2d(cout, cin, 2, stride=2))
        return net, torch.randn(1, cin, r(4, 9), r(4, 9))
    raise AssertionError(kind)


def export(module: nn.Module, x: torch.Tensor) -> onnx.ModelProto:
    io = GraphIO("m", ("x",), ("y",), {"x": {0: "B"}, "y": {0: "B"}})
    return export_module(module.eval(), (x,), io)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("kind", ["conv2d", "conv_transpose2d", "conv3d", "linear_gemm", "linear_matmul", "batched_matmul", "mixed"])
def test_graph_macs_match_torch_counter(kind, seed):
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    module, x = random_module(kind, rng)
    if x is None:
        k = module.in_features if isinstance(module, nn.Linear) else module.w.shape[0]
        x = torch.randn(3, k) if kind == "linear_gemm" else torch.randn(2, int(rng.integers(2, 6)), k)
    model = export(module, x)
    ops = {n.op_type for n in model.graph.node}
    if kind == "linear_gemm":
        assert "Gemm" in ops
    expected = count_macs(module, x)
    assert expected > 0
    got = count_graph_macs(model, {"x": tuple(x.shape)})
    assert got.complete, got.unresolved
    assert got.total == expected, (kind, got.by_op)
    # the exported batch axis is dynamic: binding another batch size scales the count
    bigger = (3 * x.shape[0], *x.shape[1:])
    assert count_graph_macs(model, {"x": bigger}).total == count_macs(module, torch.randn(bigger))


def test_conv_transpose_formula():
    """C_in * C_out / groups * k * k * H_in * W_in, as the issue states it."""
    m = nn.ConvTranspose2d(6, 4, 3, stride=2, groups=2)
    x = torch.randn(1, 6, 5, 7)
    assert count_graph_macs(export(m, x), {"x": (1, 6, 5, 7)}).total == 6 * 4 // 2 * 3 * 3 * 5 * 7


def test_tiny_rows_graph_macs_match(tmp_path):
    p = get_preset("tiny")
    for row in build_rows(p, [(128, 72)]):
        model = export_module(row.graph_net, row.inputs, row.io)
        got = count_graph_macs(model, row.input_shapes())
        assert got.complete
        if row.kind == "conv3d":  # exported over folded z: the graph counts what the folded module computes
            assert got.gmac == pytest.approx(count_gmac(row.graph_net, *row.inputs), rel=1e-9), row.module
            assert got.gmac == pytest.approx(row.gmac * folded_mac_ratio(p.lifter, p.grid.nz), rel=1e-9), row.module
        elif row.key == "slice_multi_head":  # branches grouped across tasks: the graph counts their zero blocks
            assert got.gmac == pytest.approx(count_gmac(row.graph_net, *row.inputs), rel=1e-9), row.module
            assert got.gmac > row.gmac
        elif row.key.startswith("slice_single_head"):  # regression at the peaks only (models/peak_head.py)
            assert got.gmac == pytest.approx(count_gmac(row.graph_net, *row.inputs), rel=1e-9), row.module
            assert got.gmac < row.gmac
        else:
            assert got.gmac == pytest.approx(row.gmac, rel=1e-9), row.module


def test_symbolic_dimension_leaves_node_unresolved():
    m = nn.Conv2d(2, 3, 3)
    model = export(m, torch.randn(1, 2, 6, 6))
    got = count_graph_macs(model)  # the batch axis stays symbolic
    assert not got.complete and got.total == 0 and len(got.unresolved) == 1


def test_input_shape_errors():
    model = export(nn.Conv2d(2, 3, 3), torch.randn(1, 2, 6, 6))
    with pytest.raises(ValueError, match=r"names \['images'\], which are not inputs"):
        with_input_shapes(model, {"images": (1, 2, 6, 6)})
    with pytest.raises(ValueError, match="input 'x' has rank 4 in the graph, got shape \\(1, 2, 6\\)"):
        with_input_shapes(model, {"x": (1, 2, 6)})
    with pytest.raises(ValueError, match="must be >= 0"):
        with_input_shapes(model, {"x": (1, -2, 6, 6)})


def test_empty_graph_counts_zero():
    x = onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [2])
    y = onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [2])
    g = onnx.helper.make_graph([onnx.helper.make_node("Relu", ["x"], ["y"])], "g", [x], [y])
    got = count_graph_macs(onnx.helper.make_model(g))
    assert got.total == 0 and got.complete and got.by_op == {}
