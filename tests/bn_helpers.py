"""Test helper (not a test module): BatchNorm eval statistics far from the identity, so a wrong BN fold shows."""

from __future__ import annotations

import torch


def random_bn(net: torch.nn.Module, seed: int) -> None:
    """Eval statistics far from the identity for every BatchNorm2d of ``net``, seeded."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.copy_(torch.randn(m.num_features, generator=gen))
                m.running_var.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
                m.weight.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
                m.bias.copy_(torch.randn(m.num_features, generator=gen) * 0.3)
