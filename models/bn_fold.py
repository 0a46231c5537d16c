"""Eval-mode BatchNorm as a per-channel affine map, for the export-time rewrites that fold it into a convolution."""

from __future__ import annotations

import torch
from torch import Tensor, nn


def bn_scale_shift(bn: nn.BatchNorm2d | nn.BatchNorm3d) -> tuple[Tensor, Tensor]:
    """(scale, shift), each (C,), with bn(x) = scale * x + shift per channel under the running statistics."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    return scale, bn.bias - bn.running_mean * scale


def fold_bn(weight: Tensor, bias: Tensor | None, bn: nn.BatchNorm2d) -> tuple[Tensor, Tensor]:
    """(weight, bias) of the convolution ``bn(conv(x))`` for a conv with output channels on dim 0 of ``weight``."""
    scale, shift = bn_scale_shift(bn)  # (Co,)
    folded = weight * scale.view(-1, *([1] * (weight.dim() - 1)))  # (Co, ...)
    return folded, shift if bias is None else shift + scale * bias
