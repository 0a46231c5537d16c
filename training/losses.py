"""CenterPoint losses: FastFocalLoss on the heatmap, masked L1 on the regression at the object cells.

Both return *sums* and the number of objects separately, so the trainer can normalise by the object count of
the whole global batch (summed over data-parallel processes): then N processes compute exactly the gradient of
one process holding all N shards, instead of an average of per-shard normalised losses.

The total is CenterPoint's: ``hm_weight * focal + reg_weight * sum_c(code_weight_c * l1_c)``, each term divided
by the object count (at least 1), summed over tasks for the multi-head variant (each task by its own count).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from streamdet.models.heads import HeadMaps
from streamdet.training.targets import BOX_CODE_SIZE

# CenterPoint nuScenes: x, y, z, w, l, h, sin, cos at 1, velocity at 0.2.
DEFAULT_CODE_WEIGHTS = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.2, 0.2)
_PROB_EPS = 1e-4  # CenterPoint clamps the sigmoid to [1e-4, 1 - 1e-4] before the logs


@dataclass(frozen=True)
class LossConfig:
    heatmap_weight: float = 1.0
    reg_weight: float = 0.25  # CenterPoint's loc_weight
    code_weights: tuple[float, ...] = DEFAULT_CODE_WEIGHTS

    def __post_init__(self) -> None:
        if len(self.code_weights) != BOX_CODE_SIZE:
            raise ValueError(f"LossConfig.code_weights must have {BOX_CODE_SIZE} entries, got {self.code_weights!r}")
        for name in ("heatmap_weight", "reg_weight"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"LossConfig.{name} must be >= 0, got {getattr(self, name)!r}")


def gather_cells(maps: Tensor, index: Tensor) -> Tensor:
    """maps (Q, C, H, W), index (Q, K) flat cells -> (Q, K, C)."""
    q, c = maps.shape[:2]
    flat = maps.reshape(q, c, -1)  # (Q, C, H*W)
    return flat.gather(2, index.unsqueeze(1).expand(-1, c, -1)).transpose(1, 2)  # (Q, K, C)


def focal_loss_sum(logits: Tensor, target: Tensor, index: Tensor, mask: Tensor, label: Tensor) -> Tensor:
    """CenterPoint's FastFocalLoss numerator (alpha 2, beta 4): negatives over every cell, positives at objects.

    logits, target (Q, C, H, W); index, mask, label (Q, K). Returns the un-normalised loss (a scalar).
    """
    p = logits.float().sigmoid().clamp(_PROB_EPS, 1 - _PROB_EPS)
    neg = torch.log(1 - p) * p.pow(2) * (1 - target).pow(4)
    pos_p = gather_cells(p, index).gather(2, label.unsqueeze(2)).squeeze(2)  # (Q, K)
    pos = torch.log(pos_p) * (1 - pos_p).pow(2) * mask.to(p.dtype)
    return -(neg.sum() + pos.sum())


def l1_loss_sum(pred: Tensor, target: Tensor, index: Tensor, mask: Tensor) -> Tensor:
    """Masked L1 per code channel: pred (Q, D, H, W) read at index (Q, K), target (Q, K, D) -> (D,) sums."""
    m = mask.to(pred.dtype).unsqueeze(2)  # (Q, K, 1)
    diff = (gather_cells(pred.float(), index) - target) * m  # (Q, K, D)
    return diff.abs().sum(dim=(0, 1))  # (D,)


@dataclass(frozen=True)
class LossTerms:
    """Un-normalised sums of one (local) batch, per task."""

    heatmap: Tensor  # (T,) focal-loss sums
    box: Tensor  # (T, BOX_CODE_SIZE) L1 sums per code channel
    num_objects: Tensor  # (T,) float object counts


def loss_terms(
    task_maps: list[HeadMaps],
    task_classes: tuple[tuple[int, ...], ...],
    heatmap: Tensor,
    index: Tensor,
    mask: Tensor,
    label: Tensor,
    box: Tensor,
) -> LossTerms:
    """Sums of every task's losses. ``task_maps[t]`` is ``CenterHead.forward_tasks`` output t, whose heatmap
    channels are the classes ``task_classes[t]``; targets are in CLASS_NAMES channels: heatmap (Q, C, H, W),
    index / mask / label (Q, K), box (Q, K, 10)."""
    if len(task_maps) != len(task_classes):
        raise ValueError(f"got {len(task_maps)} task outputs for {len(task_classes)} tasks")
    hm_sums, box_sums, counts = [], [], []
    for maps, classes in zip(task_maps, task_classes):
        cls = torch.as_tensor(classes, device=label.device)
        # Position of each object's class inside this task (-1: another task's object, masked out).
        lookup = torch.full((heatmap.shape[1],), -1, dtype=torch.int64, device=label.device)
        lookup[cls] = torch.arange(len(classes), device=label.device)
        task_label = lookup[label]  # (Q, K)
        task_mask = mask & (task_label >= 0)
        hm_sums.append(focal_loss_sum(maps[0], heatmap.index_select(1, cls), index, task_mask, task_label.clamp(min=0)))
        pred = torch.cat(list(maps[1:]), dim=1)  # (Q, 10, H, W): reg, height, dim, rot, vel
        box_sums.append(l1_loss_sum(pred, box, index, task_mask))
        counts.append(task_mask.sum().to(torch.float32))
    return LossTerms(torch.stack(hm_sums), torch.stack(box_sums), torch.stack(counts))


class CenterPointLoss(nn.Module):
    """Combines ``LossTerms`` into the scalar CenterPoint loss; ``num_objects`` may be a global count."""

    def __init__(self, config: LossConfig = LossConfig()) -> None:
        super().__init__()
        self.config = config
        self.register_buffer("code_weights", torch.tensor(config.code_weights, dtype=torch.float32), persistent=False)

    def forward(self, terms: LossTerms, num_objects: Tensor | None = None, scale: float = 1.0) -> tuple[Tensor, dict[str, Tensor]]:
        """``num_objects`` (T,) normalises (default: the terms' own counts); ``scale`` multiplies the result
        (the data-parallel world size, since DDP averages gradients)."""
        n = (terms.num_objects if num_objects is None else num_objects).clamp(min=1.0)  # (T,)
        hm = (terms.heatmap / n).sum()
        per_code = (terms.box / n[:, None]).sum(dim=0)  # (10,)
        reg = (per_code * self.code_weights).sum()
        total = self.config.heatmap_weight * hm + self.config.reg_weight * reg
        parts = {"heatmap": hm.detach(), "reg": reg.detach(), "loc_xy": per_code[:2].sum().detach(),
                 "z": per_code[2].detach(), "dim": per_code[3:6].sum().detach(), "rot": per_code[6:8].sum().detach(),
                 "vel": per_code[8:].sum().detach()}  # fmt: skip
        return total * scale, parts
