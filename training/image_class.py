"""An image-side loss beside detection (issue 19, item 1): each object's class read linearly from the image BEV at
its centre cell.

Through detection alone the image lane learns only what the BEV encoder's first convolution asks of it, and the
class of an object at its own BEV cell stayed hard to read from the image BEV (the linear probe of
``benchmarks/image_bev_probe.py``). This loss asks for exactly that read-out: a linear classifier on the image BEV at
the ground-truth centres, with cross-entropy, added to the CenterPoint loss with ``TrainConfig.image_class_weight``.
The classifier lives in ``TrainingModel``, not in ``StreamDetector``: it is never exported and costs nothing at run
time.

The centre cell is the head cell refined by the target's sub-cell offset (``training/targets.py``): the BEV cell the
box centre falls in, the cell the probe reads.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from streamdet.training.losses import gather_cells

_EPS = 1e-6


def centre_cells(index: Tensor, box: Tensor, head_width: int, stride: int) -> Tensor:
    """Flat image-BEV cells (Q, K) of the objects' centres.

    ``index`` (Q, K) flat head cells ``row * head_width + col``; ``box`` (Q, K, 10) regression targets whose first two
    entries are the sub-cell offsets ``reg_x, reg_y`` in [-0.5, 0.5) head cells; ``stride`` BEV cells per head cell.
    """
    row = torch.div(index, head_width, rounding_mode="floor")  # (Q, K)
    col = index - row * head_width  # (Q, K)
    sub_x = ((box[..., 0] + 0.5) * stride).floor().long().clamp(0, stride - 1)  # (Q, K)
    sub_y = ((box[..., 1] + 0.5) * stride).floor().long().clamp(0, stride - 1)  # (Q, K)
    return (row * stride + sub_y) * (head_width * stride) + col * stride + sub_x  # (Q, K)


class ImageBevClassifier(nn.Module):
    """``forward(image_bev (Q, C, Yq, Xq), cells (Q, K), mask (Q, K)) -> logits (N, num_classes)`` for the N objects
    where ``mask`` holds, in ``mask`` order (row-major over (Q, K)).

    Each channel is divided by its RMS over the batch's cells (detached) before the linear layer, as the probe
    standardises its features: the loss asks for separable classes, not for a scale (``ImageBevNorm`` sets that).
    """

    def __init__(self, channels: int, num_classes: int) -> None:
        super().__init__()
        self.linear = nn.Linear(channels, num_classes)

    def forward(self, image_bev: Tensor, cells: Tensor, mask: Tensor) -> Tensor:
        rms = image_bev.detach().square().mean(dim=(0, 2, 3)).add(_EPS).sqrt()  # (C,)
        feats = gather_cells(image_bev, cells)  # (Q, K, C)
        return self.linear(feats[mask] / rms)  # (N, num_classes)


def image_class_loss_sum(logits: Tensor, labels: Tensor) -> Tensor:
    """Cross-entropy summed over the objects (the trainer divides by the global object count, as the other terms)."""
    if logits.shape[0] == 0:
        return logits.sum() * 0.0  # keeps the graph (and DDP's view of the classifier) without objects
    return nn.functional.cross_entropy(logits.float(), labels, reduction="sum")
