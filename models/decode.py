"""In-graph decode of the head maps into top-K boxes per quadrant (the tail of ``slice_head.onnx``).

Box centre convention (training targets must use the inverse, ``encode_center``)
------------------------------------------------------------------------------
A head-map cell (row, col) of one quadrant covers ``[col * s, (col + 1) * s)`` metres in x from the quadrant's
minimum corner, and likewise for y with row, where ``s = grid.voxel_xy_m * head.out_stride`` is the cell edge.
The ``reg`` map holds the centre's offset from the cell *centre*, in cells::

    x_rel = (col + 0.5 + reg_x) * s        y_rel = (row + 0.5 + reg_y) * s

so a centre anywhere in its cell has ``reg`` in [-0.5, 0.5). x_rel, y_rel are metres relative to
``GridSpec.quadrant_origin_m(q)``; the runtime adds the origin ("uncrop"). The other columns:
``z = height``, ``(w, l, h) = exp(dim)``, ``yaw = atan2(rot_sin, rot_cos)``, ``(vx, vy) = vel``.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from streamdet.models.detector import SliceNet
from streamdet.models.heads import REGRESSION_OUTPUTS, HeadMaps
from streamdet.models.peak_head import PeakHead, regression_at_peaks
from streamdet.models.presets import Preset


def encode_center(x_rel: np.ndarray, y_rel: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of the decode formula: (row, col) int64 of the cell holding each centre and (reg_x, reg_y).

    x_rel, y_rel in metres from the quadrant's minimum corner; cells outside the map are the caller's to drop.
    """
    u = np.asarray(x_rel, dtype=np.float64) / cell_m
    v = np.asarray(y_rel, dtype=np.float64) / cell_m
    col = np.floor(u).astype(np.int64)
    row = np.floor(v).astype(np.int64)
    return row, col, (u - col - 0.5).astype(np.float32), (v - row - 0.5).astype(np.float32)


def decode_head_maps(maps: HeadMaps, cell_m: float, top_k: int) -> tuple[Tensor, Tensor, Tensor]:
    """Head maps (each (Q, ch, Hh, Wh)) -> det_boxes (Q, K, 9), det_scores (Q, K), det_labels (Q, K) int64.

    3x3 max-pool peak picking on the logits (a cell survives if it equals its neighbourhood max), sigmoid, top-K over
    classes x cells per quadrant. ``top_k`` must not exceed classes x cells (``Preset.top_k`` clamps it).
    """
    heatmap, *regression = maps
    scores, labels, cell, row, col = pick_peaks(heatmap, top_k)
    # one gather for every regression map at the peaks
    stacked = torch.cat(regression, dim=1)  # (Q, 10, Hh, Wh)
    at_peaks = stacked.flatten(2).gather(2, cell.unsqueeze(1).expand(-1, stacked.shape[1], -1))  # (Q, 10, K)
    return boxes_at_peaks(at_peaks, row, col, cell_m), scores, labels


def decode_peak_head(heatmap: Tensor, features: Tensor, head: PeakHead, cell_m: float, top_k: int) -> tuple[Tensor, Tensor, Tensor]:
    """``decode_head_maps`` of a ``PeakHead``'s output: the regression values computed at the peaks only."""
    scores, labels, cell, row, col = pick_peaks(heatmap, top_k)
    at_peaks = regression_at_peaks(features, head.regression_weight, head.regression_bias, row, col, head.kernel)
    return boxes_at_peaks(at_peaks, row, col, cell_m), scores, labels


def pick_peaks(heatmap: Tensor, top_k: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """heatmap logits (Q, C_cls, Hh, Wh) -> scores, labels, cell (= row * Wh + col), row, col, each (Q, K)."""
    # Python ints: the head map size is static in the slice graph, so the index arithmetic below exports with
    # constants instead of shape computations
    classes, hh, wh = int(heatmap.shape[-3]), int(heatmap.shape[-2]), int(heatmap.shape[-1])
    if top_k > classes * hh * wh:  # torch.topk's own error ("selected index k out of range") names neither
        raise ValueError(f"top_k must be at most classes x cells of the head map ({classes * hh * wh}), got {top_k!r}")
    # the peak test on the logits, the sigmoid after it: the sigmoid is monotone, so the peaks are the same, but in
    # float32 it rounds every logit above about 16.6 to exactly 1.0, and a confident object's neighbour cell would
    # then tie with its centre and pass as a second peak
    hmax = F.max_pool2d(heatmap, kernel_size=3, stride=1, padding=1)
    heat = heatmap.sigmoid() * (hmax == heatmap).to(heatmap.dtype)  # (Q, C_cls, Hh, Wh), non-peaks zeroed
    scores, flat = heat.flatten(1).topk(top_k, dim=1)  # (Q, K)
    cells_per_class = hh * wh
    # top-k indices are non-negative, so truncating division is floor division (and one ONNX Div, where floor
    # division exports as a dozen nodes that fix up negative operands)
    labels = torch.div(flat, cells_per_class, rounding_mode="trunc")  # (Q, K)
    cell = flat - labels * cells_per_class  # (Q, K) = row * Wh + col
    row = torch.div(cell, wh, rounding_mode="trunc")
    col = cell - row * wh
    return scores, labels, cell, row, col


def boxes_at_peaks(at_peaks: Tensor, row: Tensor, col: Tensor, cell_m: float) -> Tensor:
    """The regression values at the peaks (Q, 10, K; ``REGRESSION_OUTPUTS`` stacked) -> det_boxes (Q, K, 9)."""
    r, z, log_size, sc, v = at_peaks.split([c for _, c in REGRESSION_OUTPUTS], dim=1)
    x = (col.to(r.dtype) + 0.5 + r[:, 0]) * cell_m  # (Q, K)
    y = (row.to(r.dtype) + 0.5 + r[:, 1]) * cell_m
    size = log_size.exp()  # (Q, 3, K): w, l, h
    sin = sc[:, 0]  # (Q, K)
    cos = sc[:, 1]
    # ONNX has no Atan2: the exporter writes Atan(sin / cos) with quadrant fixes, NaN at sin = cos = 0 where torch
    # gives 0 (exact zeros come from an int8 head or untrained weights); atan2(0, 1) is that 0 in both. Not patched:
    # at sin = +0, cos < 0 the graph gives -pi where torch gives +pi: the same heading, so the export's parity
    # checks compare yaw modulo 2 pi (export/parity.py)
    cos = torch.where((sin == 0) & (cos == 0), torch.ones_like(cos), cos)
    yaw = torch.atan2(sin, cos)
    boxes = torch.cat([x[:, None], y[:, None], z, size, yaw[:, None], v], dim=1)  # (Q, 9, K)
    return boxes.transpose(1, 2)  # (Q, K, 9)


class SliceDecoder(nn.Module):
    """SliceNet plus decode: the module exported as ``slice_head.onnx``.

    ``forward(pillar_features, pillar_mask, pillar_index, image_bev) -> det_boxes (Q, K, 9), det_scores (Q, K),
    det_labels (Q, K) int64`` with K = ``preset.top_k`` (post.top_k clamped to classes x head cells).
    """

    def __init__(self, slice_net: SliceNet | nn.Module, preset: Preset) -> None:  # nn.Module: SliceNet's export form
        super().__init__()
        self.slice_net = slice_net
        self.cell_m = preset.head_cell_m
        self.top_k = preset.top_k  # static: the head map size is fixed by the preset, only Q and P are dynamic

    def forward(
        self, pillar_features: Tensor, pillar_mask: Tensor, pillar_index: Tensor, image_bev: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        return self.decode(self.slice_net(pillar_features, pillar_mask, pillar_index, image_bev))

    def decode(self, out: HeadMaps | tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """The slice net's output decoded: head maps, or a ``PeakHead``'s (heatmap, regression features)."""
        head = getattr(self.slice_net, "peak_head", None)
        if head is None:
            return decode_head_maps(out, self.cell_m, self.top_k)
        heatmap, features = out
        return decode_peak_head(heatmap, features, head, self.cell_m, self.top_k)
