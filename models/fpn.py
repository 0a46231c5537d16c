"""Feature pyramid network collapsed to one stride-4 output map (the only level the lifter reads)."""

from __future__ import annotations

from collections.abc import Sequence

import torch.nn.functional as F
from torch import Tensor, nn


class FPN(nn.Module):
    """Lateral 1x1 convs on C2..C5, top-down nearest upsampling, 3x3 output conv on the stride-4 level.

    The upsampling goes to the lateral's exact size instead of a factor of 2: ResNet rounds odd sizes up
    (450 -> 113 -> 57 -> 29 rows), so a factor-2 upsample would be off by one row.
    """

    def __init__(self, in_channels: Sequence[int], out_channels: int) -> None:
        super().__init__()
        self.lateral = nn.ModuleList(nn.Conv2d(c, out_channels, kernel_size=1) for c in in_channels)
        self.output = nn.Conv2d(out_channels, out_channels, kernel_size=3, padding=1)

    def forward(self, feats: Sequence[Tensor]) -> Tensor:
        top = self.lateral[-1](feats[-1])
        for i in range(len(feats) - 2, -1, -1):
            lateral = self.lateral[i](feats[i])
            top = lateral + F.interpolate(top, size=lateral.shape[-2:], mode="nearest")
        return self.output(top)  # (B, out_channels, H/4, W/4)
