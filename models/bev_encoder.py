"""BEV encoder: CenterPoint's RPN (strided stages of k3 convs, each brought to the head stride, concatenated)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from streamdet.models.presets import BevEncoderConfig


def conv_bn_relu(in_ch: int, out_ch: int, kernel: int, stride: int = 1, padding: int = 0) -> list[nn.Module]:
    return [
        nn.Conv2d(in_ch, out_ch, kernel, stride=stride, padding=padding, bias=False),
        nn.BatchNorm2d(out_ch, eps=1e-3, momentum=0.01),
        nn.ReLU(inplace=True),
    ]


class BevEncoder(nn.Module):
    """``forward(x (Q, in_channels, Yq, Xq)) -> (Q, sum(num_upsample_filters), Yq / s, Xq / s)``, s = head stride.

    Stage i: a k3 conv with stride ``layer_strides[i]`` then ``layer_nums[i]`` k3 convs. Deblock i: a transposed
    conv (kernel = stride = upsample factor) when the stage is coarser than the head, a strided conv when it is
    finer, a 1x1 conv when equal. The concatenation of the deblocks is the multi-scale fusion ("FPN") of the paper.
    """

    def __init__(self, cfg: BevEncoderConfig, in_channels: int) -> None:
        super().__init__()
        self.blocks = nn.ModuleList()
        self.deblocks = nn.ModuleList()
        ch = in_channels
        for n, stride, filters, up, up_filters in zip(
            cfg.layer_nums, cfg.layer_strides, cfg.num_filters, cfg.upsample_strides, cfg.num_upsample_filters
        ):
            layers = conv_bn_relu(ch, filters, 3, stride=stride, padding=1)
            for _ in range(n):
                layers += conv_bn_relu(filters, filters, 3, padding=1)
            self.blocks.append(nn.Sequential(*layers))
            if up >= 1:
                factor = round(up)
                deblock = [
                    nn.ConvTranspose2d(filters, up_filters, factor, stride=factor, bias=False),
                    nn.BatchNorm2d(up_filters, eps=1e-3, momentum=0.01),
                    nn.ReLU(inplace=True),
                ]
            else:
                factor = round(1.0 / up)
                deblock = conv_bn_relu(filters, up_filters, factor, stride=factor)
            self.deblocks.append(nn.Sequential(*deblock))
            ch = filters
        self.out_channels = cfg.out_channels

    def forward(self, x: Tensor) -> Tensor:
        return self.from_first_stage(self.blocks[0](x))

    def from_first_stage(self, x: Tensor) -> Tensor:
        """The rest of the encoder after stage 0, whose output ``x`` is; the export's split first conv enters here."""
        ups = [deblock(s) for deblock, s in zip(self.deblocks, self.stage_outputs(x))]
        return torch.cat(ups, dim=1)  # (Q, sum(num_upsample_filters), Hh, Wh)

    def stage_outputs(self, x: Tensor) -> list[Tensor]:
        """Every stage's output, the deblocks' inputs, given stage 0's output ``x``."""
        outs = [x]
        for block in self.blocks[1:]:
            outs.append(block(outs[-1]))
        return outs
