"""The flat lifter: the volume's z planes stacked into channels, then 2D convolutions (``LifterConfig.form="flat"``).

Same contract as ``VolumetricLifter`` (lifter.py): ``forward(features (J, C, Hf, Wf), lut_index, lut_weight
(Q, K, Z, Yq, Xq)) -> image_bev (Q, C, Yq, Xq)``, the same LUT and gather. What follows the gather differs: the
Z planes of each cell are one feature vector of Z * C channels (Fast-BEV's "space to channel", Li et al. 2023),
and the lifter is

    BN2d(Z*C) -> 1x1 conv Z*C -> C, BN, ReLU -> residual k3 conv C -> C, BN, ReLU

(the residual's k3 conv factorised into a depthwise k3 and a 1x1 conv with ``LifterConfig.residual="separable"``)
instead of the paper's three Conv3d layers. Why: the lift of one quadrant has to fit between two slices of the
LiDAR for the phase-locked image lane (issue 22, docs/replay.md "What the geometry allows"); the paper's lifter
spends most of the image lane's MACs on Conv3d layers over a volume that, on the small presets, is four planes
deep. The MACs of both forms are printed by ``python -m streamdet.benchmarks.flops_report``.

The gather is z-major: the LUT is permuted, not the volume; training gathers with ``F.embedding_bag``
(``gather_z_major_bag``), the export form with index_select (``gather_z_major``), and folds every BatchNorm
(``FlatLifterExport``); training never sees it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from streamdet.models.bn_fold import fold_bn
from streamdet.models.lifter import feature_table, gather_z_major, z_major


def gather_z_major_bag(features: Tensor, lut_index: Tensor, lut_weight: Tensor) -> Tensor:
    """``gather_z_major`` (lifter.py) as one ``F.embedding_bag``: the same sums, (Q, Z * C, Yq, Xq).

    Training's form: embedding_bag's backward accumulates the feature gradient several times faster than
    index_select's on CPU (measured: docs/training/issue19_plan.md, "Fourth session"). ONNX has no EmbeddingBag,
    so the export form keeps ``gather_z_major``; ``tests/test_models_flat_lifter.py`` holds the two equal.
    """
    table = feature_table(features)  # (R + 1, C), the all-zero sentinel row last
    q, k, z, yq, xq = lut_index.shape
    c = table.shape[1]
    index = lut_index.permute(0, 3, 4, 2, 1).reshape(-1, k).long()  # (Q*Yq*Xq*Z, K): one bag per voxel, z-major
    # in the table's dtype: under autocast the features (and so the table) are bfloat16 / float16 while the LUT's
    # weights stay float32, and embedding_bag takes per_sample_weights only in the table's own dtype
    weight = lut_weight.permute(0, 3, 4, 2, 1).reshape(-1, k).to(table.dtype)
    rows = F.embedding_bag(index, table, per_sample_weights=weight, mode="sum", padding_idx=table.shape[0] - 1)
    return rows.reshape(q, yq, xq, z * c).permute(0, 3, 1, 2)  # (Q, Z*C, Yq, Xq): channel z * C + c


def residual_block(c: int, form: str) -> nn.Sequential:
    """The residual branch, conv(s) -> BN -> ReLU: one k3 conv C -> C ("conv"), or a depthwise k3 conv then a 1x1
    conv ("separable", LifterConfig.residual): the same receptive field for about a seventh of the MACs at C = 32."""
    if form == "conv":
        convs = [nn.Conv2d(c, c, kernel_size=3, padding=1, bias=False)]
    elif form == "separable":
        convs = [nn.Conv2d(c, c, kernel_size=3, padding=1, groups=c, bias=False), nn.Conv2d(c, c, kernel_size=1, bias=False)]
    else:
        raise ValueError(f"residual must be 'conv' or 'separable', got {form!r}")
    return nn.Sequential(*convs, nn.BatchNorm2d(c), nn.ReLU(inplace=True))


class FlatLifter(nn.Module):
    """``forward(features (J, C, Hf, Wf), lut_index (Q, K, Z, Yq, Xq) int32, lut_weight (Q, K, Z, Yq, Xq) f32)
    -> image_bev (Q, C, Yq, Xq)``."""

    def __init__(self, channels: int, nz: int, residual: str = "conv") -> None:
        super().__init__()
        c = channels
        self.channels, self.nz = c, nz
        # BN first, as in the volumetric lifter: one statistic per (height, channel), channel z * C + c
        self.input_norm = nn.BatchNorm2d(nz * c)
        self.project = nn.Sequential(nn.Conv2d(nz * c, c, kernel_size=1, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True))
        self.residual = residual_block(c, residual)

    def forward(self, features: Tensor, lut_index: Tensor, lut_weight: Tensor) -> Tensor:
        return self.folded(gather_z_major_bag(features, lut_index, lut_weight))  # (Q, C, Yq, Xq)

    def convs(self, volume: Tensor) -> Tensor:
        """Everything after the gather, from the volume (Q, C, Z, Yq, Xq), as ``VolumetricLifter.convs``."""
        return self.folded(z_major(volume))

    def folded(self, v: Tensor) -> Tensor:
        """(Q, Z*C, Yq, Xq), channel z * C + c -> image_bev (Q, C, Yq, Xq)."""
        if v.shape[1] != self.nz * self.channels:
            raise ValueError(f"expected {self.nz} x {self.channels} folded channels, got shape {tuple(v.shape)}")
        v = self.project(self.input_norm(v))  # (Q, C, Yq, Xq)
        return v + self.residual(v)


class FlatLifterConvs(nn.Module):
    """``FlatLifter.folded`` with every BatchNorm folded into the convolution next to it (eval statistics), in the
    lifter's dtype and on its device (the folded weights keep the source's precision, as slice_split.py's)."""

    def __init__(self, lifter: FlatLifter) -> None:
        super().__init__()
        c, nz = lifter.channels, lifter.nz
        self.channels, self.nz = c, nz
        source = lifter.project[0].weight
        self.project = nn.Conv2d(nz * c, c, kernel_size=1, dtype=source.dtype, device=source.device)
        # every conv of the residual branch but the last as it is (no bias), the last with the branch's BN folded in
        convs = _convs(lifter.residual)
        self.residual = nn.Sequential(*(_like(m, bias=i == len(convs) - 1) for i, m in enumerate(convs)))
        self.relu = nn.ReLU(inplace=True)
        self.load_from(lifter)

    @torch.no_grad()
    def load_from(self, lifter: FlatLifter) -> None:
        conv, bn = lifter.project[0], lifter.project[1]
        weight, bias = fold_bn(conv.weight, None, lifter.input_norm, bn_first=True)  # conv(BN(v))
        weight, bias = fold_bn(weight, bias, bn)  # BN(conv(BN(v)))
        self.project.weight.copy_(weight)
        self.project.bias.copy_(bias)
        convs = _convs(lifter.residual)
        bn = lifter.residual[len(convs)]
        for mine, theirs in zip(self.residual[:-1], convs[:-1]):
            mine.weight.copy_(theirs.weight)
        weight, bias = fold_bn(convs[-1].weight, None, bn)
        self.residual[-1].weight.copy_(weight)
        self.residual[-1].bias.copy_(bias)

    def forward(self, volume: Tensor) -> Tensor:
        """From the volume (Q, C, Z, Yq, Xq), like ``FlatLifter.convs`` (the benchmark's lifter rows)."""
        return self.folded(z_major(volume))

    def folded(self, v: Tensor) -> Tensor:
        """(Q, Z*C, Yq, Xq), channel z * C + c -> image_bev (Q, C, Yq, Xq)."""
        v = self.relu(self.project(v))
        return v + self.relu(self.residual(v))


def _convs(branch: nn.Sequential) -> list[nn.Conv2d]:
    """The convs of a ``residual_block`` branch, in order (the BN and ReLU follow them)."""
    return [m for m in branch if isinstance(m, nn.Conv2d)]


def _like(conv: nn.Conv2d, bias: bool) -> nn.Conv2d:
    """A Conv2d of ``conv``'s geometry, dtype and device, with or without a bias."""
    return nn.Conv2d(conv.in_channels, conv.out_channels, conv.kernel_size, padding=conv.padding, groups=conv.groups, bias=bias,
                     dtype=conv.weight.dtype, device=conv.weight.device)  # fmt: skip


class FlatLifterExport(nn.Module):
    """What the exporter traces for a ``FlatLifter``: the z-major gather, then ``FlatLifterConvs``."""

    def __init__(self, lifter: FlatLifter) -> None:
        super().__init__()
        self.convs = FlatLifterConvs(lifter).eval()

    def forward(self, features: Tensor, lut_index: Tensor, lut_weight: Tensor) -> Tensor:
        return self.convs.folded(gather_z_major(features, lut_index, lut_weight))  # (Q, C, Yq, Xq)
