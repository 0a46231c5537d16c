"""The image lane's second graph: image features -> image BEV through a volume (``volumetric_lifter.onnx``).

Paper Sec. III-B. Every voxel of the quadrant volumes takes the feature of the pixel its centre projects to,
averaged over the cameras that see it; voxels no camera sees stay zero. The projection itself is precomputed
into a LUT (``calibration/lut.py``), so the graph is a gather plus a weighted sum, and a calibration change
needs a new LUT, not a new graph. Then: BN3d, 1x1x1 conv + ReLU (image feature space -> point feature space),
a residual k3 Conv3d block, a k3 Conv3d with z-stride 2, AvgPool over z, max over z.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from streamdet.models.presets import LifterConfig


def gather_volume(features: Tensor, lut_index: Tensor, lut_weight: Tensor) -> Tensor:
    """Fill the quadrant volumes from the feature maps.

    features (J, C, Hf, Wf); lut_index, lut_weight (Q, K, Z, Yq, Xq): row ``j * Hf * Wf + v * Wf + u`` of the
    flattened feature table, or the sentinel ``J * Hf * Wf`` (an appended all-zero row) for an empty slot.
    Returns V (Q, C, Z, Yq, Xq) = sum_k weight * feature[index] (the weights hold 1 / number of cameras).
    """
    volume = gather_rows(feature_table(features), lut_index, lut_weight)  # (Q, Z, Yq, Xq, C)
    return volume.permute(0, 4, 1, 2, 3)  # (Q, C, Z, Yq, Xq)


def gather_z_major(features: Tensor, lut_index: Tensor, lut_weight: Tensor) -> Tensor:
    """``gather_volume`` with z folded into channels, z outermost: (Q, Z * C, Yq, Xq), channel ``z * C + c``.

    The LUT (an int32 map, 1 / C of the volume's size) is permuted to (Q, K, Yq, Xq, Z) instead of the gathered
    volume, so the rows come out channels-last in the folded order and nothing of the volume's size is transposed
    before the convolutions (the export's folded lifter, lifter_fold.py, and the flat lifter, flat_lifter.py).
    """
    index = lut_index.permute(0, 1, 3, 4, 2)  # (Q, K, Yq, Xq, Z)
    weight = lut_weight.permute(0, 1, 3, 4, 2)
    volume = gather_rows(feature_table(features), index, weight)  # (Q, Yq, Xq, Z, C)
    return volume.flatten(3).permute(0, 3, 1, 2)  # (Q, Z*C, Yq, Xq): channel z * C + c


def z_major(volume: Tensor) -> Tensor:
    """A volume (Q, C, Z, Y, X) as the folded map (Q, Z * C, Y, X), channel ``z * C + c``: what ``gather_z_major``
    yields, for code handed the volume itself."""
    q, c, z, y, x = volume.shape
    return volume.permute(0, 2, 1, 3, 4).reshape(q, z * c, y, x)  # (Q, Z, C, Y, X) -> (Q, Z*C, Y, X)


def feature_table(features: Tensor) -> Tensor:
    """(J, C, Hf, Wf) -> (J * Hf * Wf + 1, C): one row per pixel, then the all-zero sentinel row."""
    c = features.shape[1]
    table = features.permute(0, 2, 3, 1).reshape(-1, c)  # (J*Hf*Wf, C)
    return torch.cat([table, table.new_zeros(1, c)], dim=0)


def gather_rows(table: Tensor, index: Tensor, weight: Tensor) -> Tensor:
    """sum_k weight * table[index] over dim 1 (the K slots): index, weight (Q, K, ...) -> (Q, ..., C)."""
    rows = table.index_select(0, index.reshape(-1))  # (Q*K*..., C)
    rows = rows.reshape(*index.shape, table.shape[1]) * weight.unsqueeze(-1)  # (Q, K, ..., C)
    return rows.sum(dim=1)  # (Q, ..., C)


class VolumetricLifter(nn.Module):
    """``forward(features (J, C, Hf, Wf), lut_index (Q, K, Z, Yq, Xq) int32, lut_weight (Q, K, Z, Yq, Xq) f32)
    -> image_bev (Q, C, Yq, Xq)``."""

    def __init__(self, cfg: LifterConfig, channels: int) -> None:
        super().__init__()
        c = channels
        # BN first: the stacked quadrants of a batch share the FPN feature statistics (paper Sec. III-C).
        self.input_norm = nn.BatchNorm3d(c)
        self.project = nn.Conv3d(c, c, kernel_size=1)
        self.residual = nn.Sequential(
            nn.Conv3d(c, c, kernel_size=3, padding=1, bias=False), nn.BatchNorm3d(c), nn.ReLU(inplace=True)
        )
        stride = (cfg.z_conv_stride, 1, 1)
        self.z_down = nn.Sequential(
            nn.Conv3d(c, c, kernel_size=3, stride=stride, padding=1, bias=False), nn.BatchNorm3d(c), nn.ReLU(inplace=True)
        )
        self.z_pool = nn.AvgPool3d(kernel_size=(cfg.z_pool, 1, 1), stride=(cfg.z_pool, 1, 1))
        self.relu = nn.ReLU(inplace=True)

    def forward(self, features: Tensor, lut_index: Tensor, lut_weight: Tensor) -> Tensor:
        v = gather_volume(features, lut_index, lut_weight)  # (Q, C, Z, Yq, Xq)
        return self.convs(v)

    def convs(self, volume: Tensor) -> Tensor:
        """Everything after the gather: (Q, C, Z, Yq, Xq) -> (Q, C, Yq, Xq); the benchmark's 3D-conv rows time it alone."""
        v = self.relu(self.project(self.input_norm(volume)))
        v = v + self.residual(v)
        v = self.z_pool(self.z_down(v))  # (Q, C, Z / (z_conv_stride * z_pool), Yq, Xq)
        return v.amax(dim=2)  # (Q, C, Yq, Xq)


def batch_lut_index(lut_indices: Sequence[Tensor], images_per_sample: Sequence[int], rows_per_image: int) -> Tensor:
    """Concatenate the LUT indices of several samples whose images are stacked into one features tensor.

    Sample b's rows shift by the rows of the images before it, and every sentinel (its ``J_b * rows_per_image``)
    moves to the one sentinel of the batch, ``sum(J) * rows_per_image``. ``rows_per_image = Hf * Wf``.
    Returns (sum Q_b, K, Z, Yq, Xq) with the input dtype.
    """
    if len(lut_indices) != len(images_per_sample):
        raise ValueError(f"got {len(lut_indices)} LUT indices but {len(images_per_sample)} image counts")
    if not lut_indices:
        raise ValueError("batch_lut_index needs at least one sample")
    total = sum(images_per_sample) * rows_per_image
    out, offset = [], 0
    for idx, j in zip(lut_indices, images_per_sample):
        sentinel = j * rows_per_image
        out.append(torch.where(idx == sentinel, torch.full_like(idx, total), idx + offset))
        offset += sentinel
    return torch.cat(out, dim=0)
