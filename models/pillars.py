"""Point-cloud lane: PointPillars feature net and the scatter to the stacked quadrant BEV maps."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from streamdet.models.bn_fold import fold_bn

# The (Q, Yq, Xq) of the stacked quadrant maps: a (Q, C, Yq, Xq) map to take them from, or the three sizes.
MapShape = Tensor | tuple[int, int, int]


class PillarFeatureNet(nn.Module):
    """One PointNet layer per pillar: ``(P, M, 11) -> (P, C)``; Linear + BN + ReLU per point, max over points.

    Padding rows of ``pillar_features`` must be zero, as the pillar_features contract says: the eval graph
    relies on it (see ``forward``) rather than re-masking the input, which costs as much in onnxruntime as the
    matmul itself. Padding points then never count: a zero row maps to exactly 0, which cannot win a max over
    ReLU outputs. BN statistics in training include the padding rows, as in PointPillars.
    """

    def __init__(self, num_point_features: int, channels: int) -> None:
        super().__init__()
        self.linear = nn.Linear(num_point_features, channels, bias=False)
        self.norm = nn.BatchNorm1d(channels)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, pillar_features: Tensor, pillar_mask: Tensor) -> Tensor:
        mask = pillar_mask.unsqueeze(-1)  # (P, M, 1)
        if self.training:  # batch statistics need the unfused BN
            p, m, _ = pillar_features.shape
            if p == 0:  # no pillars: all-zero maps, as in eval; BN has no rows to take statistics of (they stand)
                return pillar_features.new_zeros(0, self.linear.out_features)  # (0, C)
            y = self.norm(self.linear(pillar_features).reshape(p * m, -1)).reshape(p, m, -1)  # (P, M, C)
            return (self.relu(y) * mask).amax(dim=1)  # (P, C)
        # Eval: BN folded into the linear layer, its bias carried by the mask as a 12th input, so a (zero)
        # padding row maps to exactly 0. ReLU is monotone and >= 0, so max-then-ReLU equals ReLU-then-max over
        # the real points. The (P, M, C) tensor then sees only the matmul and the max; unfused, this small net
        # took half of the small preset's slice graph time in onnxruntime.
        weight, bias = fold_bn(self.linear.weight, None, self.norm)  # (C, F), (C,)
        x = torch.cat([pillar_features, mask], dim=-1)  # (P, M, F + 1)
        y = x @ torch.cat([weight, bias[:, None]], dim=1).t()  # (P, M, C)
        return self.relu(y.amax(dim=1))  # (P, C)


def map_shape(like: MapShape) -> tuple[int, int, int]:
    """(Q, Yq, Xq) of a (Q, C, Yq, Xq) map (C may be 0: only the shape is read), or the triple itself."""
    if isinstance(like, Tensor):
        q, _, yq, xq = like.shape
        return q, yq, xq
    q, yq, xq = like
    return q, yq, xq


def scatter_pillars(pillar_feats: Tensor, pillar_index: Tensor, like: MapShape) -> Tensor:
    """Place pillar features (P, C) into zero maps (Q, C, Yq, Xq); ``like`` gives Q, Yq, Xq (``map_shape``).

    pillar_index (P,) int64 is flat ``qi * Yq * Xq + row * Xq + col``. Indices must be unique (pillarize makes
    them so); with duplicates which pillar wins is unspecified.
    """
    q, yq, xq = map_shape(like)
    c = pillar_feats.shape[1]
    canvas = pillar_feats.new_zeros(q * yq * xq, c)  # (Q*Yq*Xq, C)
    canvas = canvas.index_put((pillar_index,), pillar_feats)
    return canvas.reshape(q, yq, xq, c).permute(0, 3, 1, 2)  # (Q, C, Yq, Xq)


def gather_pillars(pillar_feats: Tensor, pillar_index: Tensor, like: MapShape) -> Tensor:
    """``scatter_pillars`` computed as a gather, for export: the same (Q, C, Yq, Xq) map.

    Each cell looks up its pillar (1 + its position in pillar_index, 0 for an empty cell) in a (Q*Yq*Xq,) int64
    slot map, then gathers its row from the pillar features with a zero row in front. onnxruntime then writes the
    float map once, where ScatterND fills a zero map and copies it before scattering: three passes over
    Q * Yq * Xq * C floats instead of one, which costs most when another process shares the last-level cache
    (benchmarks/RESULTS.md). Indices must be unique, as for scatter_pillars.
    """
    q, yq, xq = map_shape(like)
    p, c = pillar_feats.shape
    slot = torch.zeros(q * yq * xq, dtype=torch.int64, device=pillar_index.device)  # (Q*Yq*Xq,): 0 = empty
    slot = slot.index_put((pillar_index,), torch.arange(1, p + 1, device=pillar_index.device))
    table = torch.cat([pillar_feats.new_zeros(1, c), pillar_feats], dim=0)  # (1 + P, C): row 0 for empty cells
    canvas = table.index_select(0, slot)  # (Q*Yq*Xq, C)
    return canvas.reshape(q, yq, xq, c).permute(0, 3, 1, 2)  # (Q, C, Yq, Xq)

