"""Normalisation layers of the image backbone that work at batch 1 (``ImageConfig.norm``).

The image lane sees one sample's six correlated cameras per step: BatchNorm's batch statistics are then those of
one street scene, and train-mode and eval-mode features differ (the measurement is in issue 19). Two layers that do
not depend on the batch:

- ``FrozenBatchNorm2d``: a ``BatchNorm2d`` that always normalises with its running statistics and never updates
  them (mmdetection's ``norm_eval`` / torchvision's frozen BN, with the affine kept trainable). It is meant for a
  backbone whose statistics were learnt first, e.g. by the segmentation pretraining (``training/image_pretrain``):
  from scratch its statistics are the identity. Being a ``BatchNorm2d`` it keeps torchvision's parameter names
  and every export-time fold.
- ``nn.GroupNorm``: statistics per image and channel group; trainable from scratch. Its parameter names are
  ``weight`` / ``bias`` as BatchNorm's, so a torchvision checkpoint loads its affine (its running statistics are
  then unexpected keys).
"""

from __future__ import annotations

import math

import torch.nn.functional as F
from torch import Tensor, nn

NORM_KINDS = ("batch", "frozen_batch", "group")
MAX_GROUPS = 32  # GroupNorm's usual group count; fewer where the channels do not divide by it


class FrozenBatchNorm2d(nn.BatchNorm2d):
    """``BatchNorm2d`` in eval mode whatever the module's mode: running statistics only, never updated."""

    def forward(self, x: Tensor) -> Tensor:
        return F.batch_norm(x, self.running_mean, self.running_var, self.weight, self.bias, False, 0.0, self.eps)


def norm2d(kind: str, channels: int) -> nn.Module:
    """The backbone's normalisation over ``channels`` feature maps: ``kind`` one of ``NORM_KINDS``."""
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "frozen_batch":
        return FrozenBatchNorm2d(channels)
    if kind == "group":
        return nn.GroupNorm(math.gcd(MAX_GROUPS, channels), channels)
    raise ValueError(f"image norm must be one of {NORM_KINDS}, got {kind!r}")
