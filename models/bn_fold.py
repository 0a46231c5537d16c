"""Eval-mode BatchNorm as a per-channel affine map, for the export-time rewrites that fold it into a convolution."""

from __future__ import annotations

import torch
from torch import Tensor, nn


def bn_scale_shift(bn: nn.BatchNorm2d | nn.BatchNorm3d) -> tuple[Tensor, Tensor]:
    """(scale, shift), each (C,), with bn(x) = scale * x + shift per channel under the running statistics."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    return scale, bn.bias - bn.running_mean * scale
