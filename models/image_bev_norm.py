"""The image BEV's scale at fusion (``Preset.image_bev_norm``): both halves of the fused BEV meet at one scale.

Without it the lifter's output reaches the BEV encoder far weaker than the point BEV (issue 19 measured the
ratio), so the encoder's first convolution learns to ignore it. ``ImageBevNorm`` divides each channel by its
root mean square (batch statistics in training, a running average in eval) and multiplies by a learnt gain.

It has no shift on purpose: an all-zero image BEV (no image lifted yet, a cell no camera sees) stays zero, and in
eval the layer is one per-channel scale, which the export folds exactly into the input channels of the first
convolution that reads it (``models/slice_split.py``); a shift would not fold exactly through that convolution's
zero padding.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class ImageBevNorm(nn.Module):
    """``forward(image_bev (Q, C, Yq, Xq)) -> (Q, C, Yq, Xq)``: each channel scaled to RMS ``weight``."""

    def __init__(self, channels: int, momentum: float = 0.01, eps: float = 1e-6) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))  # the gain: the RMS each channel leaves with
        self.register_buffer("running_ms", torch.ones(channels))  # running mean of x^2 per channel
        self.momentum = momentum
        self.eps = eps

    def scale(self) -> Tensor:
        """(C,) the eval-mode per-channel factor, ``weight / sqrt(running_ms + eps)``: what the export folds."""
        return self.weight / torch.sqrt(self.running_ms + self.eps)

    def forward(self, x: Tensor) -> Tensor:
        if self.training:
            ms = x.detach().square().mean(dim=(0, 2, 3))  # (C,) this batch's mean square
            with torch.no_grad():
                self.running_ms.lerp_(ms, self.momentum)
            scale = self.weight / torch.sqrt(x.square().mean(dim=(0, 2, 3)) + self.eps)  # (C,)
        else:
            scale = self.scale()
        return x * scale.view(1, -1, 1, 1)
