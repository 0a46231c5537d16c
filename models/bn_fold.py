"""Eval-mode BatchNorm folded into the linear map next to it: the one fold every export-time rewrite uses.

The folds of the export form (models/export_form.py) all go through ``fold_bn``: the pillar net's Linear + BN,
the lifter's input BN into its 1x1x1 projection and its Conv3d + BN pairs over folded z (models/lifter_fold.py),
the slice net's split, stacked and 1x1 deblock convolutions (models/slice_split.py).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

BatchNorm = nn.BatchNorm1d | nn.BatchNorm2d | nn.BatchNorm3d


def bn_scale_shift(bn: BatchNorm) -> tuple[Tensor, Tensor]:
    """(scale, shift), each (C,), with bn(x) = scale * x + shift per channel under the running statistics."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    return scale, bn.bias - bn.running_mean * scale


def fold_bn(
    weight: Tensor, bias: Tensor | None, bn: BatchNorm, *, planes: int = 1, bn_first: bool = False
) -> tuple[Tensor, Tensor]:
    """(weight, bias) of the linear map (Linear or convolution, output channels on dim 0, inputs on dim 1) with
    the BatchNorm folded in.

    ``bn_first`` False: the map computes ``bn(conv(x))``; BN channel c scales output channels
    ``c * planes .. c * planes + planes - 1`` (``planes`` > 1: the lifter's z planes folded into channels).
    ``bn_first`` True: the map computes ``conv(bn(x))`` (the BN's C channels are the map's inputs); only for a
    1x1 kernel, where a padded border cannot tell the two apart.
    """
    scale, shift = bn_scale_shift(bn)  # (C,)
    if bn_first:
        if planes != 1 or any(k != 1 for k in weight.shape[2:]):
            raise ValueError(f"a BatchNorm before the map folds only into a 1x1 map, got weight {tuple(weight.shape)}")
        taps = weight.reshape(weight.shape[0], weight.shape[1])  # (Co, C)
        folded = weight * scale.view(1, -1, *([1] * (weight.dim() - 2)))  # (Co, C, ...)
        shifted = taps @ shift  # (Co,)
        return folded, shifted if bias is None else bias + shifted
    if weight.shape[0] != scale.shape[0] * planes:
        raise ValueError(f"weight {tuple(weight.shape)} has not {scale.shape[0]} x {planes} output channels")
    if planes != 1:  # (Co,): channel c * planes + z
        scale, shift = scale.repeat_interleave(planes), shift.repeat_interleave(planes)
    folded = weight * scale.view(-1, *([1] * (weight.dim() - 1)))  # (Co, ...)
    return folded, shift if bias is None else shift + scale * bias


def stacked_conv_bn(convs: list[nn.Conv2d], bns: list[nn.BatchNorm2d]) -> nn.Conv2d:
    """One conv whose output channels are ``bn_t(conv_t(x))`` for t in order (same input, same geometry)."""
    first = convs[0]
    out = nn.Conv2d(first.in_channels, sum(c.out_channels for c in convs), first.kernel_size, stride=first.stride,
                    padding=first.padding, bias=True, dtype=first.weight.dtype)  # fmt: skip
    with torch.no_grad():
        weights, biases = [], []
        for conv, bn in zip(convs, bns):
            weight, bias = fold_bn(conv.weight, conv.bias, bn)
            weights.append(weight)
            biases.append(bias)
        out.weight.copy_(torch.cat(weights))
        out.bias.copy_(torch.cat(biases))
    return out
