"""The image lane's first graph: uint8 camera images -> stride-4 feature maps (``image_encoder.onnx``)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from streamdet.models.fpn import FPN
from streamdet.models.presets import ImageConfig
from streamdet.models.resnet import ResNet

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class ImageEncoder(nn.Module):
    """``forward(images uint8 (J, H, W, 3) RGB) -> features float32 (J, C, ceil(H/4), ceil(W/4))``.

    Normalisation lives inside so the exported graph takes raw camera bytes: the vehicle process never has to
    agree with the training code on mean and std.
    """

    def __init__(self, cfg: ImageConfig, out_channels: int) -> None:
        super().__init__()
        self.backbone = ResNet(cfg.backbone_depth, cfg.width_divisor, cfg.norm)
        self.neck = FPN(self.backbone.out_channels, out_channels)
        # (1, 3, 1, 1) folded scale and shift: (x / 255 - mean) / std = x * scale + shift
        std = torch.tensor(IMAGENET_STD)
        self.register_buffer("scale", (1.0 / (255.0 * std)).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("shift", (-torch.tensor(IMAGENET_MEAN) / std).view(1, 3, 1, 1), persistent=False)

    def forward(self, images: Tensor) -> Tensor:
        # NCHW-contiguous before the cast: .float() of the permuted view keeps its channels-last strides, so the
        # whole ResNet ran torch's channels-last CPU kernels, whose backward corrupted the heap under torch 2.13 CPU
        # (tiny preset, an odd batch of images: the process died in loss.backward()). The exported graph is the same
        # Transpose either way.
        x = images.permute(0, 3, 1, 2).contiguous().float()  # (J, 3, H, W)
        x = x * self.scale + self.shift
        return self.neck(self.backbone(x))  # (J, C, Hf, Wf)
