"""The single head's regression at the peaks (models/peak_head.py): a naive per-cell convolution as the reference,
the decode through it equal to the decode of the full maps, and the exported slice graph without the regression
output convolutions."""

from __future__ import annotations

import dataclasses

import numpy as np
import onnxruntime as ort
import pytest
import torch

from streamdet.export.onnx_export import SLICE_HEAD_IO, export_slice_head
from streamdet.models.decode import SliceDecoder, decode_head_maps, decode_peak_head
from streamdet.models.detector import SliceNet, StreamDetector
from streamdet.models.heads import CenterHead, REGRESSION_OUTPUTS
from streamdet.models.peak_head import PeakHead, regression_at_peaks
from streamdet.models.presets import get_preset
from streamdet.models.slice_split import ExportSliceNet

from bn_helpers import random_bn

TINY = get_preset("tiny")


def naive_conv_at(features: np.ndarray, weight: np.ndarray, bias: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """A zero-padded k x k convolution (weight (Co, Ci, k, k)) evaluated at cells (row, col) (Q, K), one by one."""
    q, ci, h, w = features.shape
    co, _, k, _ = weight.shape
    r = k // 2
    out = np.zeros((q, co, row.shape[1]))
    for qi in range(q):
        for j in range(row.shape[1]):
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    y, x = row[qi, j] + dy, col[qi, j] + dx
                    if 0 <= y < h and 0 <= x < w:
                        out[qi, :, j] += weight[:, :, dy + r, dx + r] @ features[qi, :, y, x]
            out[qi, :, j] += bias
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("q,kernel", [(1, 3), (3, 3), (2, 1), (2, 5)])
def test_regression_at_peaks_equals_naive_convolution(seed, dtype, q, kernel):
    rng = np.random.default_rng(seed)
    cf, h, w, k = 12, 7, 9, 20
    features = rng.normal(size=(q, cf, h, w))
    weight = rng.normal(size=(10, cf, kernel, kernel))
    bias = rng.normal(size=10)
    # every border and corner cell among the peaks, the rest random (repeats allowed: top-K may not repeat, but the
    # gather must not care)
    border = [(0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1), (0, 4), (h - 1, 3), (2, 0), (5, w - 1)]
    cells = [border + [tuple(rng.integers(0, (h, w))) for _ in range(k - len(border))] for _ in range(q)]
    row = np.array([[c[0] for c in cs] for cs in cells])
    col = np.array([[c[1] for c in cs] for cs in cells])
    flat_w = torch.from_numpy(weight).permute(2, 3, 1, 0).reshape(-1, 10).to(dtype)  # PeakHead's (dy, dx, c) rows
    got = regression_at_peaks(
        torch.from_numpy(features).to(dtype), flat_w, torch.from_numpy(bias).to(dtype),
        torch.from_numpy(row), torch.from_numpy(col), kernel,
    )  # fmt: skip
    assert got.shape == (q, 10, k) and got.dtype == dtype
    ref = naive_conv_at(features, weight, bias, row, col)
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    np.testing.assert_allclose(got.numpy(), ref, rtol=tol, atol=tol)


def test_regression_at_peaks_of_no_quadrant_is_empty():
    features = torch.zeros(0, 4, 5, 5)
    none = torch.zeros(0, 3, dtype=torch.int64)
    got = regression_at_peaks(features, torch.zeros(36, 10), torch.zeros(10), none, none, 3)
    assert got.shape == (0, 10, 3)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_peak_head_decode_equals_decode_of_the_full_maps(seed, dtype):
    torch.manual_seed(seed)
    head = CenterHead(TINY.head, 16).eval()
    random_bn(head, seed)
    head = head.to(dtype)
    peak = PeakHead(head).eval()
    x = torch.randn(2, 16, 12, 10, dtype=dtype)
    with torch.no_grad():
        maps = head(x)
        heat, features = peak(head.shared(x))  # the peak head starts after the shared conv, as from_shared does
        torch.testing.assert_close(heat, maps[0])  # the heatmap branch itself, its hidden conv stacked
        assert features.shape == (2, len(REGRESSION_OUTPUTS) * TINY.head.head_channels, 12, 10)
        ref = decode_head_maps(maps, 0.8, 30)
        got = decode_peak_head(heat, features, peak, 0.8, 30)
    for g, r in zip(got, ref):
        torch.testing.assert_close(g, r)


def test_peak_head_refuses_a_multi_head():
    head = CenterHead(dataclasses.replace(TINY.head, multi_head=True), 16)
    with pytest.raises(ValueError, match="single head"):
        PeakHead(head)


@pytest.mark.parametrize("multi_head", [False, True])
def test_export_slice_net_takes_the_peak_head_for_a_single_head_only(multi_head):
    preset = dataclasses.replace(TINY, head=dataclasses.replace(TINY.head, multi_head=multi_head))
    net = SliceNet(preset).eval()
    assert ExportSliceNet(net).peak_head is None  # off unless asked: the rewrite's parity tests compare head maps
    rewritten = ExportSliceNet(net, peak_regression=True)
    assert (rewritten.peak_head is None) == multi_head
    if not multi_head:
        assert rewritten.peak_head.heatmap is net.head.tasks[0].branches["heatmap"][3]  # the trained module


@pytest.mark.parametrize("seed", [0, 3])
def test_exported_slice_graph_computes_regression_at_the_peaks(seed):
    torch.manual_seed(seed)
    det = StreamDetector(TINY).eval()
    random_bn(det.slice_net, seed)
    g, pc = TINY.grid, TINY.pillars
    gen = torch.Generator().manual_seed(seed)
    num_pillars, q = 50, 2
    mask = (torch.arange(pc.max_points_per_pillar)[None] < torch.randint(1, 9, (num_pillars, 1), generator=gen)).float()
    feats = torch.randn(num_pillars, pc.max_points_per_pillar, 11, generator=gen) * mask[..., None]
    index = torch.randperm(q * g.quadrant_ny * g.quadrant_nx, generator=gen)[:num_pillars].sort().values
    bev = torch.randn(q, TINY.channels, g.quadrant_ny, g.quadrant_nx, generator=gen)
    args = (feats, mask, index, bev)
    model = export_slice_head(det, args)
    head_convs = sorted(n.name for n in model.graph.node if n.op_type == "Conv" and "/peak_head/" in n.name)
    # the stacked hidden conv and the heatmap's output conv: no regression output conv is left
    assert len(head_convs) == 2 and "heatmap" in head_convs[0] and "hidden" in head_convs[1], head_convs
    assert not [n for n in model.graph.node if "/tasks.0/" in n.name]
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    got = sess.run(None, {name: t.numpy() for name, t in zip(SLICE_HEAD_IO.inputs, args)})
    with torch.no_grad():
        ref = SliceDecoder(det.slice_net, TINY).eval()(*args)  # the trained net, full maps
    np.testing.assert_allclose(got[1], ref[1].numpy(), rtol=1e-4, atol=1e-5)  # scores
    np.testing.assert_array_equal(got[2], ref[2].numpy())  # labels
    np.testing.assert_allclose(got[0], ref[0].numpy(), rtol=1e-4, atol=1e-4)  # boxes


def test_int8_slice_graph_quantizes_the_hidden_conv_and_reads_no_dequantized_shape(tiny_int8_export):
    import onnx

    model = onnx.load(str(tiny_int8_export.path / "slice_head.int8.onnx"))
    producer = {o: n for n in model.graph.node for o in n.output}

    def read_dequantized(node) -> bool:
        source = producer.get(node.input[0])
        return source is not None and source.op_type == "DequantizeLinear"

    convs = {n.name: n for n in model.graph.node if n.op_type == "Conv" and "/peak_head/" in n.name}
    hidden = next(n for name, n in convs.items() if "hidden" in name)
    heatmap = next(n for name, n in convs.items() if "heatmap" in name)
    assert read_dequantized(hidden)  # a QDQ unit: onnxruntime runs it as a QLinearConv
    assert not read_dequantized(heatmap) or heatmap.input[1] in {i.name for i in model.graph.initializer}  # float weights
    assert not [n.name for n in model.graph.node if n.op_type == "Shape" and read_dequantized(n)]


def test_peak_head_mac_ratio_counts_what_the_export_computes():
    from streamdet.models.flops import count_gmac
    from streamdet.models.peak_head import peak_head_mac_ratio

    head = CenterHead(TINY.head, 16).eval()
    hh, wh, k = 12, 10, 30
    x = torch.randn(1, TINY.head.head_channels, hh, wh)
    peak = PeakHead(head).eval()
    row, col = torch.randint(0, hh, (1, k)), torch.randint(0, wh, (1, k))

    def exported(x):
        heat, features = peak(x)
        return heat, regression_at_peaks(features, peak.regression_weight, peak.regression_bias, row, col, peak.kernel)

    with torch.no_grad():
        graph = count_gmac(exported, x)
        trained = count_gmac(lambda x: [task(x) for task in head.tasks], x)
    assert peak_head_mac_ratio(head, hh * wh, k) == pytest.approx(graph / trained, rel=1e-9)
