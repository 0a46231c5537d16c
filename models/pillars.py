"""Point-cloud lane: PointPillars feature net and the scatter to the stacked quadrant BEV maps."""

from __future__ import annotations

from torch import Tensor, nn


class PillarFeatureNet(nn.Module):
    """One PointNet layer per pillar: ``(P, M, 11) -> (P, C)``; Linear + BN + ReLU per point, max over points.

    Padding points are zeroed after the ReLU, so they never win the max over a pillar's points (all real
    outputs are >= 0). BN statistics include the padding rows, as in PointPillars.
    """

    def __init__(self, num_point_features: int, channels: int) -> None:
        super().__init__()
        self.linear = nn.Linear(num_point_features, channels, bias=False)
        self.norm = nn.BatchNorm1d(channels)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, pillar_features: Tensor, pillar_mask: Tensor) -> Tensor:
        x = self.linear(pillar_features)  # (P, M, C)
        x = self.norm(x.transpose(1, 2)).transpose(1, 2)  # BN1d wants (P, C, M)
        x = self.relu(x) * pillar_mask.unsqueeze(-1)  # (P, M, C)
        return x.amax(dim=1)  # (P, C)


def scatter_pillars(pillar_feats: Tensor, pillar_index: Tensor, like: Tensor) -> Tensor:
    """Place pillar features (P, C) into zero maps (Q, C, Yq, Xq) whose Q, Yq, Xq come from ``like``.

    pillar_index (P,) int64 is flat ``qi * Yq * Xq + row * Xq + col``. Indices must be unique (pillarize makes
    them so); with duplicates which pillar wins is unspecified.
    """
    q, _, yq, xq = like.shape
    c = pillar_feats.shape[1]
    canvas = pillar_feats.new_zeros(q * yq * xq, c)  # (Q*Yq*Xq, C)
    canvas = canvas.index_put((pillar_index,), pillar_feats)
    return canvas.reshape(q, yq, xq, c).permute(0, 3, 1, 2)  # (Q, C, Yq, Xq)
