"""The image BEV's scale at fusion (``Preset.image_bev_norm``): both halves of the fused BEV meet at one scale.

Without it the lifter's output reaches the BEV encoder far weaker than the point BEV (issue 19 measured the
ratio), so the encoder's first convolution learns to ignore it. ``ImageBevNorm`` divides each channel by its
root mean square (batch statistics in training, a running average in eval) and multiplies by a gain:

- ``target="learnt"``: a learnt gain per channel. Training is free to shrink it (after training, issue 19 found the
  image half well below the point half's RMS while the model depended on it; measured:
  docs/training/issue19_plan.md, section "Results of the fifth session: three seeds a side, the verdict");
- ``target="point"``: no learnt gain; every channel is brought to the point BEV's RMS on the cells that hold points,
  a running average of it kept as a buffer, and the image's own mean square is taken on those same cells (the cells
  where the two halves meet). Both statistics are updated in training only; the point BEV's is detached (the image
  lane's scale must not pull on the pillar features).

It has no shift on purpose: an all-zero image BEV (no image lifted yet, a cell no camera sees) stays zero, and in
eval the layer is one per-channel scale (``scale()``), which the export folds exactly into the input channels of the
first convolution that reads it (``models/slice_split.py``); a shift would not fold exactly through that
convolution's zero padding.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from streamdet.models.presets import IMAGE_BEV_TARGETS


class ImageBevNorm(nn.Module):
    """``forward(image_bev (Q, C, Yq, Xq), point_bev (Q, C, Yq, Xq) | None) -> (Q, C, Yq, Xq)``: each channel scaled
    to RMS ``weight`` (learnt) or to the point BEV's RMS on occupied cells (point)."""

    def __init__(self, channels: int, target: str = "learnt", momentum: float = 0.01, eps: float = 1e-6) -> None:
        super().__init__()
        if target not in IMAGE_BEV_TARGETS:
            raise ValueError(f"image BEV scale target must be one of {IMAGE_BEV_TARGETS}, got {target!r}")
        self.target = target
        if target == "learnt":
            self.weight = nn.Parameter(torch.ones(channels))  # the gain: the RMS each channel leaves with
        else:
            self.register_buffer("point_ms", torch.ones(()))  # running mean of the point BEV's x^2 on occupied cells
        self.register_buffer("running_ms", torch.ones(channels))  # running mean of x^2 per channel
        self.momentum = momentum
        self.eps = eps

    def gain(self) -> Tensor:
        """(C,) or () the RMS each channel is brought to."""
        return self.weight if self.target == "learnt" else torch.sqrt(self.point_ms)

    def scale(self) -> Tensor:
        """(C,) the eval-mode per-channel factor, ``gain / sqrt(running_ms + eps)``: what the export folds."""
        return self.gain() / torch.sqrt(self.running_ms + self.eps)  # a () gain broadcasts to (C,)

    def forward(self, x: Tensor, point_bev: Tensor | None = None) -> Tensor:
        if not self.training:
            return x * self.scale().view(1, -1, 1, 1)
        if self.target == "learnt":
            ms = x.square().mean(dim=(0, 2, 3))  # (C,) this batch's mean square
        else:
            if point_bev is None:
                raise ValueError("ImageBevNorm(target='point') needs the point BEV in training")
            mask = (point_bev.detach().abs().sum(dim=1, keepdim=True) > 0).to(x.dtype)  # (Q, 1, Yq, Xq) occupied
            cells = mask.sum()
            # a slice without points has nothing to match: its running statistics stand (no host sync to branch)
            some = cells > 0
            ms = torch.where(some, (x.square() * mask).sum(dim=(0, 2, 3)) / cells.clamp(min=1), self.running_ms)  # (C,)
            point_ms = (point_bev.detach().square() * mask).sum() / (cells.clamp(min=1) * point_bev.shape[1])  # ()
            with torch.no_grad():
                point_ms = point_ms.to(self.point_ms.dtype)
                self.point_ms.copy_(torch.where(some, self.point_ms.lerp(point_ms, self.momentum), self.point_ms))
        with torch.no_grad():  # the buffers stay float32 under autocast, where x (so ms) is bfloat16 / float16
            self.running_ms.lerp_(ms.detach().to(self.running_ms.dtype), self.momentum)  # unchanged where ms is the running value
        return x * (self.gain() / torch.sqrt(ms + self.eps)).view(1, -1, 1, 1)
