"""The slice net's first BEV convolution split over its two inputs, for export.

SliceNet concatenates the point BEV (scattered pillars, built channels-last) and the image BEV (the lifter's
output) and runs a k3 convolution on the 2C channels. A convolution of a concatenation is the sum of one
convolution per part, so the export computes ``relu(conv_p(point_bev) + conv_i(image_bev))`` with stage 0's
BatchNorm folded into both. onnxruntime then never materialises the concatenated (Q, 2C, Yq, Xq) map: the point
BEV's channels-last -> NCHW transpose folds into the reorder of its convolution, and the sum into that
convolution. Measured in the benchmark's slice rows (small preset, Zen 4, 2 threads): see benchmarks/RESULTS.md.

Same function as SliceNet (tests/test_models_slice_split.py; the export's parity check compares the graph with
the PyTorch SliceNet). Training never sees this module. The LiDAR-only net has no concatenation and is exported
as it is.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from streamdet.models.bn_fold import bn_scale_shift
from streamdet.models.detector import SliceNet
from streamdet.models.heads import HeadMaps
from streamdet.models.pillars import scatter_pillars


class SplitInputSliceNet(nn.Module):
    """``SliceNet.forward`` with the first convolution split into a point part and an image part.

    Shares the trained net's pillar net, encoder and head (so the exported node scopes stay ``/slice_net/...``);
    only the first convolution's weights are derived (BN folded, eval statistics).
    """

    def __init__(self, net: SliceNet) -> None:
        super().__init__()
        if not net.use_image:
            raise ValueError("a LiDAR-only SliceNet has no image BEV to split off; export it as it is")
        self.pillar_net = net.pillar_net
        self.bev_encoder = net.bev_encoder
        self.head = net.head
        stage0 = list(net.bev_encoder.blocks[0])
        conv, bn, relu = stage0[0], stage0[1], stage0[2]
        if not (isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d) and isinstance(relu, nn.ReLU)):
            raise ValueError(f"stage 0 must start with Conv2d, BatchNorm2d, ReLU, got {stage0[:3]}")
        c = conv.in_channels // 2  # point BEV channels first, then image BEV (SliceNet.fused_bev)
        self.point_channels = c
        kw = dict(kernel_size=conv.kernel_size, stride=conv.stride, padding=conv.padding)
        self.point_conv = nn.Conv2d(c, conv.out_channels, bias=False, **kw)
        self.image_conv = nn.Conv2d(conv.in_channels - c, conv.out_channels, bias=True, **kw)
        self.relu = nn.ReLU(inplace=True)
        self.stage0_rest = nn.Sequential(*stage0[3:])  # the same modules: stage 0 after its first conv
        with torch.no_grad():
            scale, shift = bn_scale_shift(bn)  # (Co,)
            weight = conv.weight * scale[:, None, None, None]  # (Co, 2C, k, k)
            self.point_conv.weight.copy_(weight[:, :c])
            self.image_conv.weight.copy_(weight[:, c:])
            self.image_conv.bias.copy_(shift)

    def forward(self, pillar_features: Tensor, pillar_mask: Tensor, pillar_index: Tensor, image_bev: Tensor) -> HeadMaps:
        p_bev = scatter_pillars(self.pillar_net(pillar_features, pillar_mask), pillar_index, image_bev)  # (Q, C, Yq, Xq)
        x = self.relu(self.point_conv(p_bev) + self.image_conv(image_bev))  # (Q, C0, Yq / s, Xq / s)
        x = self.stage0_rest(x)
        return self.head(self.bev_encoder.from_first_stage(x))


def export_slice_net(net: SliceNet) -> nn.Module:
    """What the exporter traces for the slice net: the split form when there is an image BEV, else the net."""
    return SplitInputSliceNet(net).eval() if net.use_image else net
