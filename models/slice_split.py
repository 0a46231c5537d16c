"""The slice net rewritten for export: its concatenations split into sums of convolutions, BatchNorms folded.

SliceNet concatenates twice, and a convolution of a concatenation is the sum of one convolution per part:

- the point BEV (scattered pillars, built channels-last) with the image BEV (the lifter's output) before stage 0's
  first k3 convolution: the export computes ``relu(conv_p(point_bev) + conv_i(image_bev))``;
- the deblocks' outputs (the multi-scale fusion) before the head's shared k3 convolution: the export computes
  ``relu(sum_i conv_i(up_i))``.

onnxruntime then never materialises a concatenated map: each sum folds into a convolution of its blocked (NCHWc)
layout as that convolution's ``Sum`` input, the point BEV's channels-last -> NCHW transpose into the reorder of its
convolution. The point BEV itself is built by a gather (``pillars.gather_pillars``, the same map). A deblock that
is a 1x1 stride-1 transposed convolution (the stage already at the head's stride) is exported as the 1x1
convolution it equals (weight transposed), which onnxruntime runs in the blocked layout too instead of leaving it
for its NCHW ConvTranspose. A multi-head's branches are grouped across its tasks
(``GroupedTaskHead``); with ``peak_regression`` a single head returns its heatmap logits and regression features,
whose outputs the decode computes at its peaks (``PeakHead``, peak_head.py). Measured in the benchmark's slice rows (small preset, Zen 4, 2 threads): see
benchmarks/RESULTS.md.

Same function as SliceNet (tests/test_models_slice_split.py; the export's parity check compares the graph with
the PyTorch SliceNet). Training never sees this module. The LiDAR-only net has no image concatenation; the rest
is rewritten alike.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn

from streamdet.models.bn_fold import fold_bn, stacked_conv_bn
from streamdet.models.detector import SliceNet, slice_map_shape
from streamdet.models.heads import HEAD_OUTPUTS, CenterHead, HeadMaps
from streamdet.models.image_half import IMAGE_BEV, IMAGE_HALF, check_image_layout
from streamdet.models.peak_head import PeakHead
from streamdet.models.pillars import MapShape, gather_pillars


def _conv_bn_relu(stage: nn.Module) -> tuple[nn.Conv2d, nn.BatchNorm2d]:
    """The (conv, bn) of a Sequential that starts Conv2d, BatchNorm2d, ReLU, or a clear error."""
    parts = list(stage)[:3]
    if not (
        len(parts) == 3
        and isinstance(parts[0], nn.Conv2d)
        and isinstance(parts[1], nn.BatchNorm2d)
        and isinstance(parts[2], nn.ReLU)
    ):
        raise ValueError(f"expected Conv2d, BatchNorm2d, ReLU, got {parts}")
    return parts[0], parts[1]


def split_conv_bn(conv: nn.Conv2d, bn: nn.BatchNorm2d, in_splits: list[int], bias_part: int = 0) -> nn.ModuleList:
    """One convolution per input part, ``sum_i part_i(x_i) == bn(conv(cat(x, dim=1)))`` (eval statistics).

    The BatchNorm's shift becomes the bias of part ``bias_part`` (the conv itself must have none).
    """
    if conv.groups != 1 or conv.bias is not None:
        raise ValueError(
            f"can only split a dense convolution without bias, got groups={conv.groups}, bias={conv.bias is not None}"
        )
    if sum(in_splits) != conv.in_channels:
        raise ValueError(f"input parts {in_splits} do not add up to the conv's {conv.in_channels} input channels")
    kw = dict(kernel_size=conv.kernel_size, stride=conv.stride, padding=conv.padding, dilation=conv.dilation,
              dtype=conv.weight.dtype)  # the derived weights keep the source's precision
    parts = nn.ModuleList(nn.Conv2d(c, conv.out_channels, bias=i == bias_part, **kw) for i, c in enumerate(in_splits))
    with torch.no_grad():
        weight, bias = fold_bn(conv.weight, None, bn)  # (Co, Ci, k, k), (Co,)
        for part, w in zip(parts, weight.split(in_splits, dim=1)):
            part.weight.copy_(w)
        parts[bias_part].bias.copy_(bias)
    return parts


def export_deblock(deblock: nn.Sequential) -> nn.Module:
    """``deblock`` as it is, or, for ConvTranspose2d(k=1, s=1) + BN + ReLU, the equal Conv2d(k=1) + ReLU."""
    first = deblock[0]
    if not (
        isinstance(first, nn.ConvTranspose2d)
        and first.kernel_size == (1, 1)
        and first.stride == (1, 1)
        and first.padding == (0, 0)
        and first.output_padding == (0, 0)
        and first.groups == 1
        and isinstance(deblock[1], nn.BatchNorm2d)
    ):
        return deblock
    conv = nn.Conv2d(first.in_channels, first.out_channels, 1, bias=True, dtype=first.weight.dtype)
    with torch.no_grad():
        # ConvTranspose2d keeps (Ci, Co, 1, 1); Conv2d wants (Co, Ci, 1, 1)
        weight, bias = fold_bn(first.weight.transpose(0, 1), first.bias, deblock[1])
        conv.weight.copy_(weight)
        conv.bias.copy_(bias)
    return nn.Sequential(conv, *deblock[2:])


OUTPUT_BLOCK = 16  # output channels onnxruntime computes per block with AVX-512 (its NCHWc block)


class GroupedTaskHead(nn.Module):
    """``CenterHead.from_shared`` of a multi-head with each output's branches grouped across the T tasks.

    CenterPoint's multi-head runs T x 6 thin branches (conv k3 Ch -> Ch, BN, ReLU, conv -> a few channels), all
    reading the shared conv's output. Per output (heatmap, reg, ...) this computes the branches of consecutive
    tasks as two convs: the hidden convs stacked (Ch -> n * Ch, BNs folded) and the output convs as one
    block-diagonal conv (n * Ch -> sum of the n outputs), with as many tasks per group as fit one output block of
    ``OUTPUT_BLOCK`` channels (onnxruntime pads the outputs of a convolution to whole blocks: the small preset's six
    3-channel dim branches take two groups, not one 18-channel conv costing two blocks over 6 * Ch inputs).
    onnxruntime runs 14 convs for T = 6 instead of 12 T = 72, no per-branch reorder, and the stacked outputs are
    already the (Q, T, ch, Hh, Wh) layout the merge reads. The zero blocks cost MACs (``grouped_head_mac_ratio``):
    fewer, wider convolutions still run faster (benchmarks/RESULTS.md).
    """

    def __init__(self, head: CenterHead) -> None:
        super().__init__()
        self.head = head  # the merge's buffers; its branches are only read here
        self.hidden = nn.ModuleDict()
        self.output = nn.ModuleDict()
        self.relu = nn.ReLU(inplace=True)
        self.group_sizes: dict[str, list[int]] = {}
        for name in HEAD_OUTPUTS:
            branches = [list(task.branches[name]) for task in head.tasks]
            groups = task_groups([b[3].out_channels for b in branches])
            self.group_sizes[name] = [len(g) for g in groups]
            hidden = [stacked_conv_bn([branches[t][0] for t in g], [branches[t][1] for t in g]) for g in groups]
            self.hidden[name] = nn.ModuleList(hidden)
            self.output[name] = nn.ModuleList(_block_diagonal_conv([branches[t][3] for t in g]) for g in groups)

    def forward(self, x: Tensor) -> HeadMaps:
        per_output = []
        for name in HEAD_OUTPUTS:
            parts = [out(self.relu(hidden(x))) for hidden, out in zip(self.hidden[name], self.output[name])]
            per_output.append(parts)  # each (Q, n * ch, Hh, Wh), n tasks of the group
        heat = _cat(per_output[0])  # (Q, sum of task classes, Hh, Wh)
        q, _, hh, wh = heat.shape
        regression = []
        for name, parts in zip(HEAD_OUTPUTS[1:], per_output[1:]):
            # reshape, not unflatten: unflatten exports shape arithmetic that onnxruntime's symbolic shape
            # inference (run by the int8 quantizer) cannot follow
            stacks = [p.reshape(q, n, -1, hh, wh) for p, n in zip(parts, self.group_sizes[name])]  # (Q, n, ch, Hh, Wh)
            regression.append(_cat(stacks))  # (Q, T, ch, Hh, Wh)
        return self.head.merge(heat, regression)


def task_groups(out_channels: list[int], block: int = OUTPUT_BLOCK) -> list[range]:
    """Consecutive tasks grouped so that each group's output channels fit ``block`` (a wider task alone)."""
    if not out_channels or min(out_channels) < 1:
        raise ValueError(f"task_groups needs one positive channel count per task, got {out_channels!r}")
    groups: list[range] = []
    start, total = 0, 0
    for t, c in enumerate(out_channels):
        if t > start and total + c > block:
            groups.append(range(start, t))
            start, total = t, 0
        total += c
    groups.append(range(start, len(out_channels)))
    return groups


def _cat(parts: list[Tensor]) -> Tensor:
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)


def _block_diagonal_conv(convs: list[nn.Conv2d]) -> nn.Conv2d:
    """One conv on the concatenation of the convs' inputs whose outputs are the convs' outputs, concatenated."""
    first = convs[0]
    cin = sum(c.in_channels for c in convs)
    out = nn.Conv2d(cin, sum(c.out_channels for c in convs), first.kernel_size, stride=first.stride,
                    padding=first.padding, bias=True, dtype=first.weight.dtype)  # fmt: skip
    with torch.no_grad():
        out.weight.zero_()
        out.bias.zero_()
        o = i = 0
        for conv in convs:
            out.weight[o : o + conv.out_channels, i : i + conv.in_channels] = conv.weight
            if conv.bias is not None:
                out.bias[o : o + conv.out_channels] = conv.bias
            o, i = o + conv.out_channels, i + conv.in_channels
    return out


def grouped_head_mac_ratio(head: CenterHead) -> float:
    """MACs of ``GroupedTaskHead``'s convs per MAC of the head's branch convs (per head-map cell)."""
    own = grouped = 0
    for name in HEAD_OUTPUTS:
        outs = [task.branches[name][3] for task in head.tasks]
        for g in task_groups([o.out_channels for o in outs]):
            for t in g:
                hidden, out = head.tasks[t].branches[name][0], outs[t]
                h = hidden.weight.numel()  # per output cell: Co * Ci * k * k
                own += h + out.weight.numel()
                grouped += h + out.weight.numel() * len(g)  # each output conv reads its group's hidden channels
    return grouped / own


class ExportSliceNet(nn.Module):
    """``SliceNet.forward`` with its concatenations split into sums of convolutions (module docstring).

    Shares the trained net's pillar net, encoder stages and head branches (so the exported node scopes stay
    ``/slice_net/...``); only the split convolutions and the 1x1 deblocks are derived (BN folded, eval statistics).
    A LiDAR-only net has no image BEV: its stage 0 is kept whole, the rest is rewritten alike.
    """

    def __init__(self, net: SliceNet, image_layout: str = IMAGE_BEV, peak_regression: bool = False) -> None:
        super().__init__()
        self.use_image = net.use_image
        # image_half: the image half runs in the lifter graph and arrives precomputed (image_half.py)
        self.image_layout = check_image_layout(image_layout)
        self.map_cells = net.map_cells  # (Yq, Xq), or (ny, nx) without the crop
        self.pillar_net = net.pillar_net
        self.bev_encoder = net.bev_encoder
        self.head = net.head
        stage0 = list(net.bev_encoder.blocks[0])
        conv, bn = _conv_bn_relu(stage0)
        if self.use_image:
            c = conv.in_channels // 2  # point BEV channels first, then image BEV (SliceNet.fused_bev)
            # the image part carries the BN shift (the point BEV is the mostly-empty one), unless the image half is
            # precomputed: then the point part does, so a zeroed image BEV's image half is exactly zero
            bias_part = 1 if image_layout == IMAGE_BEV else 0
            self.point_conv, self.image_conv = split_conv_bn(conv, bn, [c, conv.in_channels - c], bias_part=bias_part)
            if net.image_bev_norm is not None:  # a per-channel scale without shift folds exactly into the inputs
                with torch.no_grad():
                    self.image_conv.weight.mul_(net.image_bev_norm.scale().view(1, -1, 1, 1))
            self.relu = nn.ReLU(inplace=True)
            self.stage0_rest = nn.Sequential(*stage0[3:])  # the same modules: stage 0 after its first conv
        self.deblocks = nn.ModuleList(export_deblock(d) for d in net.bev_encoder.deblocks)
        shared_conv, shared_bn = _conv_bn_relu(net.head.shared)
        splits = [_out_channels(d) for d in net.bev_encoder.deblocks]
        self.shared_parts = split_conv_bn(shared_conv, shared_bn, splits)
        self.shared_rest = nn.Sequential(*list(net.head.shared)[2:])  # its ReLU
        self.grouped_head = GroupedTaskHead(net.head) if len(net.head.tasks) > 1 else None
        # peak_regression (a single head only): forward returns (heatmap logits, regression features) and the
        # decode computes the regression values at its peaks (peak_head.py; SliceDecoder.decode)
        self.peak_head = PeakHead(net.head) if peak_regression and self.grouped_head is None else None

    def forward(self, pillar_features: Tensor, pillar_mask: Tensor, pillar_index: Tensor,
                image_bev: Tensor | None = None, *, num_quadrants: int | None = None) -> HeadMaps | tuple[Tensor, Tensor]:  # fmt: skip
        """SliceNet's signature: the image BEV, or None with ``num_quadrants`` (LiDAR-only; zeros for a fused net).

        In the ``image_half`` layout ``image_bev`` is the precomputed image half (Q, C0, Yh, Xh) instead. Returns
        the head maps, or with ``peak_head`` its (heatmap logits, regression features).
        """
        half = self.image_layout == IMAGE_HALF
        if half and image_bev is not None:
            shape: MapShape = (image_bev.shape[0], *self.map_cells)
        else:
            shape = slice_map_shape(image_bev, num_quadrants, self.map_cells)
        # the same map as scatter_pillars, built by a gather (pillars.py: one pass over the map instead of three)
        p_bev = gather_pillars(self.pillar_net(pillar_features, pillar_mask), pillar_index, shape)  # (Q, C, Yq, Xq)
        if self.use_image:
            x = self.point_conv(p_bev)  # (Q, C0, Yq / s, Xq / s)
            if half and image_bev is not None:
                x = x + image_bev  # the image half, computed once per lift
            elif not half:
                if image_bev is None:  # no image lifted yet (SliceNet.fused_bev)
                    image_bev = torch.zeros_like(p_bev)
                x = x + self.image_conv(image_bev)
            # else no image yet: its image half is exactly zero (the shift is on the point half)
            x = self.relu(x)
            x = self.stage0_rest(x)
        else:
            x = self.bev_encoder.blocks[0](p_bev)  # (Q, C0, Yq / s, Xq / s)
        stages = self.bev_encoder.stage_outputs(x)
        ups = [deblock(s) for deblock, s in zip(self.deblocks, stages)]  # each (Q, Cu_i, Hh, Wh)
        shared = self.shared_parts[0](ups[0])
        for part, up in zip(self.shared_parts[1:], ups[1:]):
            shared = shared + part(up)
        x = self.shared_rest(shared)  # (Q, Ch, Hh, Wh) into the branches
        if self.peak_head is not None:
            return self.peak_head(x)
        return self.head.from_shared(x) if self.grouped_head is None else self.grouped_head(x)


def _out_channels(deblock: nn.Sequential) -> int:
    first = deblock[0]
    if not isinstance(first, (nn.Conv2d, nn.ConvTranspose2d)):
        raise ValueError(f"a deblock must start with a convolution, got {type(first).__name__}")
    return first.out_channels


def export_slice_net(net: SliceNet, image_layout: str = IMAGE_BEV) -> ExportSliceNet:
    """``ExportSliceNet`` of a copy of ``net``, in eval mode; ``net`` itself is left as it was (its mode included).

    The exporter goes through ``export_form.to_export_form``, which copies the whole detector the same way;
    ``ExportSliceNet`` shares its modules with the net it is given, so without the copy ``.eval()`` would switch a
    training net's pillar net, encoder and head to eval (their BatchNorm statistics would stop updating).
    """
    return ExportSliceNet(copy.deepcopy(net), image_layout).eval()
