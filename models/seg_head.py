"""A per-pixel segmentation head on the image encoder's stride-4 FPN map: image pretraining on the world's masks.

Training only (``training/image_pretrain.py``): it never enters the detector or an exported graph. Its job is to
make the encoder's features name the object classes before detection starts, as the paper's backbone was
pretrained on driving images. GroupNorm, so that it behaves the same at any batch size.
"""

from __future__ import annotations

import math

import torch.nn.functional as F
from torch import Tensor, nn

from streamdet.models.image_encoder import ImageEncoder

MAX_GROUPS = 8


class SegHead(nn.Module):
    """``forward(features (B, C, Hf, Wf)) -> logits (B, num_labels, Hf, Wf)``: conv3x3-GN-ReLU, then a 1x1 classifier."""

    def __init__(self, in_channels: int, num_labels: int, hidden: int | None = None) -> None:
        super().__init__()
        hidden = hidden or in_channels
        self.conv = nn.Conv2d(in_channels, hidden, kernel_size=3, padding=1, bias=False)
        self.norm = nn.GroupNorm(math.gcd(MAX_GROUPS, hidden), hidden)
        self.relu = nn.ReLU(inplace=True)
        self.classifier = nn.Conv2d(hidden, num_labels, kernel_size=1)

    def forward(self, features: Tensor) -> Tensor:
        x = self.relu(self.norm(self.conv(features)))
        return self.classifier(x)  # (B, num_labels, Hf, Wf)


class ImageSegmenter(nn.Module):
    """``forward(images uint8 (B, H, W, 3)) -> logits (B, num_labels, H, W)``: the detector's image encoder + SegHead."""

    def __init__(self, encoder: ImageEncoder, num_labels: int, channels: int) -> None:
        super().__init__()
        self.encoder = encoder
        self.head = SegHead(channels, num_labels)

    def forward(self, images: Tensor) -> Tensor:
        logits = self.head(self.encoder(images))  # (B, L, Hf, Wf)
        return F.interpolate(logits, size=images.shape[1:3], mode="bilinear", align_corners=False)  # (B, L, H, W)
