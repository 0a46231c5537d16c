"""Knowledge distillation: a trained detector (the teacher) gives its head's responses as dense soft targets beside
the labels (``streamdet-train --teacher``).

Response distillation of the CenterPoint head, per head task, on the same slice maps the student sees (the way
CenterPoint students are distilled in Yang et al., "Towards Efficient 3D Object Detection with Knowledge
Distillation", NeurIPS 2022):

- **heatmap**: the squared difference of the student's and the teacher's class probabilities (sigmoids) summed
  over every cell: where the teacher sees objects, and how sure it is, labelled or not;
- **box**: the L1 difference of the ten regression channels (weighted by the CenterPoint code weights) at every
  cell, each cell weighted by the teacher's top class probability where that is at least
  ``DistillConfig.min_teacher_score`` (0 elsewhere): a box wherever the teacher finds something object-like, not
  only at the labelled centres.

Both are sums divided by the object count of the global batch, like the CenterPoint terms they sit beside
(training/losses.py), so data-parallel runs get the gradient of one process holding the whole batch.

The teacher must make the same maps as the student (``check_teacher``): grid, head stride, the grouping of the
classes into head tasks, the camera lane on or off, the quadrant crop. Its slice net and camera lane may be any
size; it runs in eval mode without gradients. When the student's camera lane is frozen (``freeze_camera_lane``)
and holds the teacher's very weights, the image BEV is lifted once per step for both (``shares_camera_lane``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from streamdet.core.classes import CLASS_NAMES
from streamdet.models.detector import StreamDetector
from streamdet.models.heads import HeadMaps
from streamdet.models.presets import Preset
from streamdet.training.checkpoint import load_weights
from streamdet.training.model import CAMERA_LANE, TrainingModel

# The preset fields that decide the maps a head writes and what they mean (``check_teacher``).
SAME_MAPS_FIELDS = ("grid", "use_image", "slice_crop")


@dataclass(frozen=True)
class DistillConfig:
    heatmap_weight: float = 1.0  # of the heatmap term (the CenterPoint focal term's weight is 1)
    box_weight: float = 0.25  # of the box term (CenterPoint's regression weight)
    min_teacher_score: float = 0.1  # cells whose teacher top class probability is below this get no box term

    def __post_init__(self) -> None:
        for name in ("heatmap_weight", "box_weight"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"DistillConfig.{name} must be a number >= 0, got {v!r}")
        if not (isinstance(self.min_teacher_score, (int, float)) and 0.0 <= self.min_teacher_score < 1.0):
            raise ValueError(f"DistillConfig.min_teacher_score must be in [0, 1), got {self.min_teacher_score!r}")


def check_teacher(teacher: Preset, student: Preset) -> None:
    """Raise a ValueError naming both presets unless the teacher's head writes the maps the student's does."""
    t, s = teacher.to_dict(), student.to_dict()
    differ = [f for f in SAME_MAPS_FIELDS if t.get(f) != s.get(f)]
    if teacher.head.out_stride != student.head.out_stride:
        differ.append("head.out_stride")
    if head_task_classes(teacher) != head_task_classes(student):
        differ.append("head tasks (multi_head, tasks)")
    if differ:
        raise ValueError(f"the teacher (preset {teacher.name!r}) does not make the maps the student (preset {student.name!r}) "
                         f"makes: {', '.join(differ)} differ")  # fmt: skip


def head_task_classes(preset: Preset) -> tuple[tuple[int, ...], ...]:
    """The classes (CLASS_NAMES indices) of each head task, in the order ``CenterHead.task_classes`` has them."""
    tasks = preset.head.tasks if preset.head.multi_head else (CLASS_NAMES,)
    return tuple(tuple(CLASS_NAMES.index(c) for c in task) for task in tasks)


class Teacher:
    """A trained detector that runs beside the student, in eval mode and without gradients."""

    def __init__(self, path: str | Path, student: Preset, device: torch.device) -> None:
        detector, preset = load_weights(path)
        check_teacher(preset, student)
        self.path = Path(path)
        self.preset = preset
        self.model = TrainingModel(detector).to(device).eval()
        for p in self.model.parameters():
            p.requires_grad_(False)

    def shares_camera_lane(self, student: StreamDetector) -> bool:
        """True when the student's image encoder and lifter hold exactly the teacher's weights and buffers."""
        mine = self.model.detector.state_dict()
        theirs = student.state_dict()
        keys = [k for k in mine if k.startswith(tuple(p + "." for p in CAMERA_LANE))]
        return bool(keys) and all(k in theirs and theirs[k].shape == mine[k].shape and torch.equal(theirs[k].to(mine[k].device), mine[k]) for k in keys)

    @torch.no_grad()
    def maps(self, batch, use_image: bool, lifted: Tensor | None = None) -> list[HeadMaps]:
        return self.model(batch, use_image=use_image, lifted=lifted)[0]


def distill_sums(student: list[HeadMaps], teacher: list[HeadMaps], code_weights: Tensor, min_teacher_score: float) -> tuple[Tensor, Tensor]:
    """Per-task un-normalised sums of the two terms (see the module doc): heatmap (T,) and box (T,).

    ``student[t]`` and ``teacher[t]`` are task t's HeadMaps over the same slice maps: heatmap logits (Q, C_t, H, W)
    then the regression maps whose channels concatenate to the ten box codes (Q, 10, H, W); ``code_weights`` (10,).
    """
    if len(student) != len(teacher):
        raise ValueError(f"student and teacher have {len(student)} and {len(teacher)} head tasks")
    heat, box = [], []
    for s, t in zip(student, teacher):
        s_prob = s[0].float().sigmoid()  # (Q, C_t, H, W)
        t_prob = t[0].float().sigmoid()
        if s_prob.shape != t_prob.shape:
            raise ValueError(f"student and teacher heatmaps differ in shape: {tuple(s_prob.shape)} and {tuple(t_prob.shape)}")
        heat.append((s_prob - t_prob).pow(2).sum())
        score = t_prob.max(dim=1, keepdim=True).values  # (Q, 1, H, W)
        weight = torch.where(score >= min_teacher_score, score, torch.zeros_like(score))
        s_box = torch.cat([m.float() for m in s[1:]], dim=1)  # (Q, 10, H, W)
        t_box = torch.cat([m.float() for m in t[1:]], dim=1)
        diff = (s_box - t_box).abs() * code_weights.view(1, -1, 1, 1)  # (Q, 10, H, W)
        box.append((diff * weight).sum())
    return torch.stack(heat), torch.stack(box)


def distill_loss(
    student: list[HeadMaps], teacher: list[HeadMaps], num_objects: Tensor, code_weights: Tensor, config: DistillConfig
) -> tuple[Tensor, dict[str, Tensor]]:
    """The distillation loss of one batch: the two sums per task divided by that task's (global) object count
    ``num_objects`` (T,) (at least 1), weighted and summed over tasks; and its parts for the log."""
    heat, box = distill_sums(student, teacher, code_weights, config.min_teacher_score)
    n = num_objects.clamp(min=1.0)  # (T,)
    heat_term = (heat / n).sum()
    box_term = (box / n).sum()
    total = config.heatmap_weight * heat_term + config.box_weight * box_term
    return total, {"distill_heatmap": heat_term.detach(), "distill_box": box_term.detach()}
