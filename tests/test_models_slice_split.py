"""The slice net's export form (concatenations split into sums of convolutions, 1x1 deblocks as convolutions): the
same function as SliceNet."""

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
from streamdet.models.heads import CenterHead
from streamdet.models.slice_split import (
    ExportSliceNet,
    GroupedTaskHead,
    task_groups,
    export_deblock,
    export_slice_net,
    grouped_head_mac_ratio,
    split_conv_bn,
)

from bn_helpers import random_bn

TINY = get_preset("tiny")


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
    random_bn(net, seed)
    net = net.to(dtype)
    split = ExportSliceNet(net).to(dtype)
    args = _inputs(preset, q, num_pillars, seed, dtype)
    with torch.no_grad():
        for got, ref in zip(split(*args), net(*args)):
            torch.testing.assert_close(got, ref)


def test_split_shares_the_trained_modules():
    net = SliceNet(TINY).eval()
    split = ExportSliceNet(net)
    assert split.pillar_net is net.pillar_net and split.head is net.head and split.bev_encoder is net.bev_encoder
    assert split.stage0_rest[0] is net.bev_encoder.blocks[0][3]
    assert split.point_conv.in_channels == TINY.channels and split.image_conv.in_channels == TINY.channels
    assert split.point_conv.bias is None and split.image_conv.bias is not None
    assert [p.in_channels for p in split.shared_parts] == list(TINY.bev.num_upsample_filters)
    assert split.head.tasks is net.head.tasks


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("q,num_pillars,seed", [(1, 40, 0), (4, 7, 2), (3, 0, 3)])
def test_lidar_only_export_form_equals_the_net(q, num_pillars, seed, dtype):
    preset = dataclasses.replace(TINY, use_image=False)
    torch.manual_seed(seed)
    net = SliceNet(preset).eval()
    random_bn(net, seed)
    net = net.to(dtype)
    rewritten = export_slice_net(net)
    assert not hasattr(rewritten, "point_conv")  # nothing to split off at stage 0
    feats, mask, index, _ = _inputs(preset, q, num_pillars, seed, dtype)
    shape_only = feats.new_zeros(q, 0, preset.grid.quadrant_ny, preset.grid.quadrant_nx)
    with torch.no_grad():
        for got, ref in zip(rewritten(feats, mask, index, shape_only), net(feats, mask, index, shape_only)):
            torch.testing.assert_close(got, ref)
        # the LiDAR-only signature: Q without any image BEV tensor
        for got, ref in zip(rewritten(feats, mask, index, num_quadrants=q), net(feats, mask, index, shape_only)):
            torch.testing.assert_close(got, ref)


def test_unexpected_stage_layout_is_refused():
    net = SliceNet(TINY).eval()
    net.bev_encoder.blocks[0][1] = torch.nn.Identity()
    with pytest.raises(ValueError, match="Conv2d, BatchNorm2d, ReLU"):
        ExportSliceNet(net)


def test_exported_slice_graph_has_no_bev_concat_and_matches_torch():
    torch.manual_seed(0)
    det = StreamDetector(TINY).eval()
    random_bn(det.slice_net, 5)
    args = _inputs(TINY, 2, 60, 4)
    model = export_slice_head(det, args)
    assert isinstance(slice_decoder(det).slice_net, ExportSliceNet)
    assert not [n for n in model.graph.node if n.op_type == "Concat" and "image_bev" in n.input]
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    got = sess.run(None, {name: t.numpy() for name, t in zip(SLICE_HEAD_IO.inputs, args)})
    with torch.no_grad():
        ref = SliceDecoder(det.slice_net, TINY).eval()(*args)
    np.testing.assert_allclose(got[1], ref[1].numpy(), rtol=1e-4, atol=1e-5)  # scores
    np.testing.assert_allclose(got[0], ref[0].numpy(), rtol=1e-4, atol=1e-4)  # boxes


def _bn(channels: int, seed: int, dtype) -> torch.nn.BatchNorm2d:
    bn = torch.nn.BatchNorm2d(channels).eval()
    random_bn(bn, seed)
    return bn.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("splits,bias_part", [([8, 8], 0), ([8, 8], 1), ([4, 16, 12], 2), ([32], 0)])
def test_split_conv_bn_equals_bn_of_conv_of_concat(splits, bias_part, seed, dtype):
    torch.manual_seed(seed)
    conv = torch.nn.Conv2d(sum(splits), 6, 3, stride=1 + seed % 2, padding=1, bias=False).to(dtype)
    bn = _bn(6, seed, dtype)
    parts = split_conv_bn(conv, bn, splits, bias_part)
    xs = [torch.randn(2, c, 9, 11, dtype=dtype) for c in splits]
    got = sum(part(x) for part, x in zip(parts, xs))
    with torch.no_grad():
        ref = bn(conv(torch.cat(xs, dim=1)))
        torch.testing.assert_close(got.detach(), ref)
    assert [p.bias is not None for p in parts] == [i == bias_part for i in range(len(splits))]
    assert all(p.weight.dtype == dtype for p in parts)


def test_split_conv_bn_refuses_what_it_cannot_split():
    bn = torch.nn.BatchNorm2d(4).eval()
    with pytest.raises(ValueError, match=r"\[3, 3\] do not add up to the conv's 8"):
        split_conv_bn(torch.nn.Conv2d(8, 4, 3, bias=False), bn, [3, 3])
    with pytest.raises(ValueError, match="groups=2"):
        split_conv_bn(torch.nn.Conv2d(8, 4, 3, groups=2, bias=False), bn, [4, 4])
    with pytest.raises(ValueError, match="bias=True"):
        split_conv_bn(torch.nn.Conv2d(8, 4, 3, bias=True), bn, [4, 4])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("bias", [False, True])
def test_export_deblock_turns_a_1x1_transposed_conv_into_a_conv(bias, seed, dtype):
    torch.manual_seed(seed)
    transposed = torch.nn.ConvTranspose2d(12, 8, 1, stride=1, bias=bias)
    deblock = torch.nn.Sequential(transposed, _bn(8, seed, torch.float32), torch.nn.ReLU())
    deblock = deblock.eval().to(dtype)
    rewritten = export_deblock(deblock)
    assert isinstance(rewritten[0], torch.nn.Conv2d) and rewritten[0].kernel_size == (1, 1)
    x = torch.randn(2, 12, 7, 5, dtype=dtype)
    with torch.no_grad():
        torch.testing.assert_close(rewritten(x), deblock(x))


@pytest.mark.parametrize(
    "first",
    [torch.nn.ConvTranspose2d(8, 4, 2, stride=2, bias=False), torch.nn.Conv2d(8, 4, 2, stride=2, bias=False)],
)
def test_export_deblock_leaves_other_deblocks(first):
    deblock = torch.nn.Sequential(first, torch.nn.BatchNorm2d(4), torch.nn.ReLU()).eval()
    assert export_deblock(deblock) is deblock


def test_exported_slice_graph_stores_the_point_bev_shape():
    """onnxruntime fuses the split convolutions' sums only where it can prove equal shapes (export/onnx_export.py:
    with_inferred_shapes): the scattered point BEV must carry the image BEV's symbolic (Q, C, Yq, Xq)."""
    torch.manual_seed(0)
    det = StreamDetector(TINY).eval()
    model = export_slice_head(det, _inputs(TINY, 2, 60, 4))
    image_bev = next(i for i in model.graph.input if i.name == "image_bev")
    want = [d.dim_param or d.dim_value for d in image_bev.type.tensor_type.shape.dim]
    assert want[0] == "Q"
    nodes = model.graph.node
    point_conv = next(n for n in nodes if n.op_type == "Conv" and n.name.startswith("/slice_net/point_conv/"))
    shapes = {vi.name: [d.dim_param or d.dim_value for d in vi.type.tensor_type.shape.dim] for vi in model.graph.value_info}
    assert shapes[point_conv.input[0]] == want
    maps_concat = [
        n for n in nodes
        if n.op_type == "Concat" and n.name.startswith("/slice_net/") and all(len(shapes.get(i, ())) == 4 for i in n.input)
    ]
    assert not maps_concat  # neither the point | image BEV nor the deblocks are concatenated
    assert not [n for n in model.graph.node if n.op_type == "ConvTranspose" and "deblocks.0" in n.name]


def _multi(preset):
    return dataclasses.replace(preset, head=dataclasses.replace(preset.head, multi_head=True))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("preset_name", ["tiny", "small"])
def test_grouped_task_head_equals_the_multi_head(preset_name, seed, dtype):
    preset = _multi(get_preset(preset_name))
    torch.manual_seed(seed)
    head = CenterHead(preset.head, 24).eval()
    random_bn(head, seed)
    for m in head.modules():  # non-zero output biases, so a misplaced bias shows
        if isinstance(m, torch.nn.Conv2d) and m.bias is not None:
            torch.nn.init.normal_(m.bias)
    head = head.to(dtype)
    grouped = GroupedTaskHead(head).eval()
    x = torch.randn(2, preset.head.head_channels, 12, 10, dtype=dtype)
    with torch.no_grad():
        for got, ref in zip(grouped(x), head.from_shared(x)):
            torch.testing.assert_close(got, ref)
    convs = [c for group in grouped.output.values() for c in group]
    assert len(convs) == sum(len(v) for v in grouped.hidden.values()) < 6 * len(head.tasks)
    assert all(c.out_channels <= 16 for c in convs)  # every output conv fits one AVX-512 block


def test_export_form_groups_only_a_multi_head():
    assert ExportSliceNet(SliceNet(TINY).eval()).grouped_head is None
    assert isinstance(ExportSliceNet(SliceNet(_multi(TINY)).eval()).grouped_head, GroupedTaskHead)


@pytest.mark.parametrize("preset_name", ["tiny", "small", "paper"])
def test_grouped_head_mac_ratio_counts_the_zero_blocks(preset_name):
    """Against the MACs of the grouped convs themselves (per output cell), over those of the head's branches."""
    head = CenterHead(_multi(get_preset(preset_name)).head, 16).eval()
    macs = lambda conv: conv.weight.numel()  # noqa: E731 - per output cell, groups 1
    own = sum(macs(task.branches[name][i]) for task in head.tasks for name in task.branches for i in (0, 3))
    grouped = GroupedTaskHead(head)
    got = sum(macs(c) for group in list(grouped.hidden.values()) + list(grouped.output.values()) for c in group)
    assert grouped_head_mac_ratio(head) == pytest.approx(got / own)
    assert grouped_head_mac_ratio(head) > 1


@pytest.mark.parametrize(
    "channels,block,want",
    [
        ([3, 3, 3, 3, 3, 3], 16, [[0, 1, 2, 3, 4], [5]]),
        ([2, 2, 2, 2, 2, 2], 16, [[0, 1, 2, 3, 4, 5]]),
        ([1, 2, 2, 1, 2, 2], 16, [[0, 1, 2, 3, 4, 5]]),
        ([20, 1, 30], 16, [[0], [1], [2]]),  # a task wider than a block stands alone
        ([8, 8, 8], 16, [[0, 1], [2]]),
        ([5], 4, [[0]]),
    ],
)
def test_task_groups_fill_blocks_in_task_order(channels, block, want):
    assert [list(g) for g in task_groups(channels, block)] == want


@pytest.mark.parametrize("bad", [[], [3, 0, 2]])
def test_task_groups_refuses_no_tasks_or_empty_ones(bad):
    with pytest.raises(ValueError, match="one positive channel count per task"):
        task_groups(bad)

