"""The single head's regression outputs computed at the decode's peaks only: an export-time rewrite.

The head (heads.py) ends each of its six branches in a k x k output convolution over the whole head map, but the
decode (decode.py) reads the five regression maps (centre offset, z, log size, yaw, velocity) at its top-K peaks
alone. In the export form the regression branches stop at their hidden features, and the decode computes the ten
regression values at each peak from the k x k patch of those features around it: one gather of K * k * k feature
rows and one matrix product, the same arithmetic as the convolutions at those cells (zero padding included).

Why: onnxruntime pads a convolution's outputs to whole channel blocks, so each 1-3 channel output convolution
costs what a block of 8 or 16 channels does, over every cell; these convolutions stay float in the int8 export
(export/int8_quantize.py: the decode turns them into box values directly). The six branches' hidden
convolutions, which all read the shared features, run as one stacked convolution. Measured in
benchmarks/RESULTS.md ("The head's regression at the peaks").

Only the single head (the paper's, ``HeadConfig.multi_head`` False) is rewritten: a multi-head picks each cell's
regression from the task of its best class (``CenterHead.merge``), which ``GroupedTaskHead`` (slice_split.py)
exports instead.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from streamdet.models.bn_fold import stacked_conv_bn
from streamdet.models.heads import HEAD_OUTPUTS, CenterHead


class PeakHead(nn.Module):
    """``forward(x (Q, Ch, Hh, Wh)) -> (heatmap logits (Q, C_cls, Hh, Wh), regression features (Q, 5 Ch, Hh, Wh))``.

    The regression features are the five regression branches' hidden features (after their ReLU), in
    ``REGRESSION_OUTPUTS`` order; ``regression_at_peaks`` turns them into the regression values at given cells
    with ``regression_weight`` / ``regression_bias``.
    """

    def __init__(self, head: CenterHead) -> None:
        super().__init__()
        if len(head.tasks) != 1:
            raise ValueError(f"PeakHead rewrites the single head only, got {len(head.tasks)} task heads")
        branches = [list(head.tasks[0].branches[name]) for name in HEAD_OUTPUTS]  # conv, bn, relu, output conv
        self.hidden_channels = branches[0][0].out_channels
        # all six hidden convs read the shared features: one convolution, BNs folded
        self.hidden = stacked_conv_bn([b[0] for b in branches], [b[1] for b in branches])
        self.relu = nn.ReLU(inplace=True)
        self.heatmap = branches[0][3]  # the trained output conv, shared
        outputs = [b[3] for b in branches[1:]]
        self.kernel = outputs[0].kernel_size[0]
        ch, k = self.hidden_channels, self.kernel
        # block-diagonal: output o of branch b reads branch b's hidden channels only
        weight = torch.zeros(sum(o.out_channels for o in outputs), len(outputs) * ch, k, k, dtype=outputs[0].weight.dtype)
        bias = torch.zeros(weight.shape[0], dtype=weight.dtype)
        row = 0
        with torch.no_grad():
            for b, conv in enumerate(outputs):
                weight[row : row + conv.out_channels, b * ch : (b + 1) * ch] = conv.weight
                if conv.bias is not None:
                    bias[row : row + conv.out_channels] = conv.bias
                row += conv.out_channels
        # (k * k * 5 Ch, 10): rows in the (dy, dx, channel) order of the gathered patches
        self.register_buffer("regression_weight", weight.permute(2, 3, 1, 0).reshape(-1, weight.shape[0]).contiguous())
        self.register_buffer("regression_bias", bias)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        hidden = self.relu(self.hidden(x))  # (Q, 6 Ch, Hh, Wh)
        heat = self.heatmap(hidden[:, : self.hidden_channels])  # (Q, C_cls, Hh, Wh)
        return heat, hidden[:, self.hidden_channels :]  # (Q, 5 Ch, Hh, Wh)


def regression_at_peaks(features: Tensor, weight: Tensor, bias: Tensor, row: Tensor, col: Tensor, kernel: int) -> Tensor:
    """The regression values at cells (row, col), each (Q, K) int64: (Q, 10, K), the layout of the stacked
    regression maps read at those cells.

    features (Q, Cf, Hh, Wh); weight (kernel * kernel * Cf, 10) and bias (10,) as in ``PeakHead``. Equal to a
    zero-padded ``kernel`` x ``kernel`` convolution read at the cells.
    """
    k = int(row.shape[1])
    cf, hh, wh = int(features.shape[1]), int(features.shape[2]), int(features.shape[3])
    r = kernel // 2
    hp, wp = hh + 2 * r, wh + 2 * r
    # channels-last rows of the zero-padded map: a patch is kernel * kernel rows of Cf contiguous values, one
    # Gather (measured faster than a GatherElements over NCHW, and than clamped indices masked without the pad)
    rows = F.pad(features, (r, r, r, r)).permute(0, 2, 3, 1).reshape(-1, cf)  # (Q * Hp * Wp, Cf)
    # quadrant ids (Q, 1) as a cumulative sum, not an arange of a shape read: ONNX shape inference follows it
    quadrant = torch.ones_like(row[:, :1]).cumsum(0) - 1
    centre = (row + r) * wp + (col + r) + quadrant * (hp * wp)  # (Q, K)
    offsets = torch.tensor([dy * wp + dx for dy in range(-r, r + 1) for dx in range(-r, r + 1)], device=row.device)
    index = (centre.unsqueeze(2) + offsets).flatten()  # (Q * K * k * k,), (dy, dx) order within a peak
    # -1 (not Q) and a static K: ONNX shape inference then sizes the product (benchmarks/graph_macs.py counts it)
    patches = rows.index_select(0, index).reshape(-1, k, kernel * kernel * cf)  # (Q, K, k * k * Cf)
    values = patches @ weight + bias  # (Q, K, 10)
    return values.transpose(1, 2)  # (Q, 10, K)


def peak_head_mac_ratio(head: CenterHead, cells: int, peaks: int) -> float:
    """MACs the export computes for the head's six branches (``PeakHead`` over the map, its regression product at
    ``peaks`` peaks, block-diagonal zeros included) per MAC of the trained branches, on a map of ``cells`` head
    cells (per quadrant)."""
    branches = [head.tasks[0].branches[name] for name in HEAD_OUTPUTS]
    hidden = sum(b[0].weight.numel() for b in branches) * cells  # each weight element: one MAC per cell
    heat = branches[0][3].weight.numel() * cells
    outputs = [b[3] for b in branches[1:]]
    own = sum(o.weight.numel() for o in outputs) * cells
    # the product reads every output's patch of all five branches' hidden channels (PeakHead.regression_weight)
    at_peaks = sum(o.out_channels for o in outputs) * len(outputs) * outputs[0].weight[0].numel() * peaks
    return (hidden + heat + at_peaks) / (hidden + heat + own)
