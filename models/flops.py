"""Multiply-accumulate counting with ``torch.utils.flop_counter.FlopCounterMode``.

FlopCounterMode reports FLOPs = 2 x MACs for convolutions and matmuls and ignores element-wise work (BN, ReLU,
pooling, gathers); we report MACs, labelled GMAC, as the paper's "GFLOPS" column does. Modules and inputs may
live on ``torch.device("meta")``: only shapes matter, so the paper-size graphs are counted in milliseconds.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode


def count_macs(fn: Callable[..., Any] | nn.Module, *inputs: Any, **kwargs: Any) -> int:
    """MACs of one call ``fn(*inputs, **kwargs)`` (no grad)."""
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        fn(*inputs, **kwargs)
    return counter.get_total_flops() // 2


def count_gmac(fn: Callable[..., Any] | nn.Module, *inputs: Any, **kwargs: Any) -> float:
    """Like ``count_macs`` in units of 1e9 MAC."""
    return count_macs(fn, *inputs, **kwargs) / 1e9
