"""The slice net's first BEV convolution split over point and image BEV: the same function as SliceNet."""

from __future__ import annotations

import dataclasses

import numpy as np
import onnxruntime as ort
import pytest
import torch

from streamdet.export.onnx_export import SLICE_HEAD_IO, export_slice_head, slice_decoder
from streamdet.models.decode import SliceDecoder
from streamdet.models.detector import SliceNet, StreamDetector
from streamdet.models.presets import get_preset
from streamdet.models.slice_split import SplitInputSliceNet, export_slice_net

TINY = get_preset("tiny")


def _random_bn(net: torch.nn.Module, seed: int) -> None:
    """Eval statistics far from the identity, so a wrong fold shows."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.copy_(torch.randn(m.num_features, generator=gen))
                m.running_var.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
                m.weight.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
                m.bias.copy_(torch.randn(m.num_features, generator=gen) * 0.3)


def _inputs(preset, q: int, num_pillars: int, seed: int, dtype=torch.float32):
    g, pc = preset.grid, preset.pillars
    gen = torch.Generator().manual_seed(seed)
    cells = q * g.quadrant_ny * g.quadrant_nx
    counts = torch.randint(1, pc.max_points_per_pillar + 1, (num_pillars,), generator=gen)
    mask = (torch.arange(pc.max_points_per_pillar)[None] < counts[:, None]).to(dtype)  # (P, M)
    feats = torch.randn(num_pillars, pc.max_points_per_pillar, 11, generator=gen, dtype=dtype) * mask[..., None]
    index = torch.randperm(cells, generator=gen)[:num_pillars].sort().values  # (P,)
    bev = torch.randn(q, preset.channels, g.quadrant_ny, g.quadrant_nx, generator=gen, dtype=dtype)
    return feats, mask, index, bev


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("multi_head", [False, True])
@pytest.mark.parametrize("q,num_pillars,seed", [(1, 40, 0), (2, 100, 1), (4, 7, 2), (3, 0, 3)])
def test_split_net_equals_slice_net(q, num_pillars, seed, multi_head, dtype):
    preset = dataclasses.replace(TINY, head=dataclasses.replace(TINY.head, multi_head=multi_head))
    torch.manual_seed(seed)
    net = SliceNet(preset).eval()
    _random_bn(net, seed)
    net = net.to(dtype)
    split = SplitInputSliceNet(net).to(dtype)
    args = _inputs(preset, q, num_pillars, seed, dtype)
    with torch.no_grad():
        for got, ref in zip(split(*args), net(*args)):
            torch.testing.assert_close(got, ref)


def test_split_shares_the_trained_modules():
    net = SliceNet(TINY).eval()
    split = SplitInputSliceNet(net)
    assert split.pillar_net is net.pillar_net and split.head is net.head and split.bev_encoder is net.bev_encoder
    assert split.stage0_rest[0] is net.bev_encoder.blocks[0][3]
    assert split.point_conv.in_channels == TINY.channels and split.image_conv.in_channels == TINY.channels


def test_lidar_only_net_is_exported_as_it_is():
    net = SliceNet(dataclasses.replace(TINY, use_image=False)).eval()
    assert export_slice_net(net) is net
    with pytest.raises(ValueError, match="LiDAR-only"):
        SplitInputSliceNet(net)


def test_unexpected_stage_layout_is_refused():
    net = SliceNet(TINY).eval()
    net.bev_encoder.blocks[0][1] = torch.nn.Identity()
    with pytest.raises(ValueError, match="Conv2d, BatchNorm2d, ReLU"):
        SplitInputSliceNet(net)


def test_exported_slice_graph_has_no_bev_concat_and_matches_torch():
    torch.manual_seed(0)
    det = StreamDetector(TINY).eval()
    _random_bn(det.slice_net, 5)
    args = _inputs(TINY, 2, 60, 4)
    model = export_slice_head(det, args)
    assert isinstance(slice_decoder(det).slice_net, SplitInputSliceNet)
    assert not [n for n in model.graph.node if n.op_type == "Concat" and "image_bev" in n.input]
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    got = sess.run(None, {name: t.numpy() for name, t in zip(SLICE_HEAD_IO.inputs, args)})
    with torch.no_grad():
        ref = SliceDecoder(det.slice_net, TINY).eval()(*args)
    np.testing.assert_allclose(got[1], ref[1].numpy(), rtol=1e-4, atol=1e-5)  # scores
    np.testing.assert_allclose(got[0], ref[0].numpy(), rtol=1e-4, atol=1e-4)  # boxes
