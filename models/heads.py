"""CenterPoint detection head, single (the paper, after PolarStream) or one per task (CenterPoint's original).

Both variants return the same six maps, each (Q, ch, Hh, Wh), in ``HEAD_OUTPUTS`` order:

    heatmap  num_classes  class logits, channel k = CLASS_NAMES[k]
    reg      2            centre offset (x, y) inside the cell, in cells (see decode.py for the exact formula)
    height   1            centre z in metres, LiDAR frame
    dim      3            log(w), log(l), log(h) in metres
    rot      2            sin(yaw), cos(yaw)
    vel      2            vx, vy in m/s

In the multi-head variant each task predicts its own regression maps; ``forward`` merges them per cell from the
task of the cell's highest-logit class (what a per-task decode would read at that peak), so decode and export
see one layout. Training with per-task losses reads ``forward_tasks`` instead.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from streamdet.core.classes import CLASS_NAMES
from streamdet.models.presets import HeadConfig

# (name, channels) of the regression branches; the heatmap branch comes first with one channel per class.
REGRESSION_OUTPUTS: tuple[tuple[str, int], ...] = (("reg", 2), ("height", 1), ("dim", 3), ("rot", 2), ("vel", 2))
HEAD_OUTPUTS: tuple[str, ...] = ("heatmap",) + tuple(name for name, _ in REGRESSION_OUTPUTS)

HeadMaps = tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]


class SeparateHead(nn.Module):
    """One CenterPoint task: six branches, each conv3x3 + BN + ReLU then an output conv."""

    def __init__(self, channels: int, num_classes: int, final_kernel: int, heatmap_bias_init: float) -> None:
        super().__init__()
        outs = (("heatmap", num_classes),) + REGRESSION_OUTPUTS
        self.branches = nn.ModuleDict()
        for name, out_ch in outs:
            self.branches[name] = nn.Sequential(
                nn.Conv2d(channels, channels, 3, padding=1, bias=False),
                nn.BatchNorm2d(channels),
                nn.ReLU(inplace=True),
                nn.Conv2d(channels, out_ch, final_kernel, padding=final_kernel // 2, bias=True),
            )
        for name, branch in self.branches.items():
            for m in branch.modules():
                if isinstance(m, nn.Conv2d):
                    nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                    if m.bias is not None:
                        nn.init.zeros_(m.bias)
            if name == "heatmap":
                nn.init.constant_(branch[-1].bias, heatmap_bias_init)  # a low prior keeps the focal loss stable early

    def forward(self, x: Tensor) -> HeadMaps:
        return tuple(self.branches[name](x) for name in HEAD_OUTPUTS)  # type: ignore[return-value]


class CenterHead(nn.Module):
    """``forward(x (Q, in_channels, Hh, Wh)) -> HeadMaps`` in the single-head layout, for either variant."""

    def __init__(self, cfg: HeadConfig, in_channels: int) -> None:
        super().__init__()
        self.shared = nn.Sequential(
            nn.Conv2d(in_channels, cfg.head_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(cfg.head_channels),
            nn.ReLU(inplace=True),
        )
        tasks = cfg.tasks if cfg.multi_head else (CLASS_NAMES,)
        # task t predicts classes task_classes[t] (indices into CLASS_NAMES) in this order
        self.task_classes: tuple[tuple[int, ...], ...] = tuple(tuple(CLASS_NAMES.index(c) for c in t) for t in tasks)
        self.tasks = nn.ModuleList(
            SeparateHead(cfg.head_channels, len(t), cfg.final_kernel, cfg.heatmap_bias_init) for t in tasks
        )
        order = [k for t in self.task_classes for k in t]  # class of each concatenated task channel
        # channel k of the merged heatmap = concatenated channel order.index(k)
        self.register_buffer("merge_index", torch.tensor([order.index(k) for k in range(len(CLASS_NAMES))]), persistent=False)
        class_task = [next(i for i, t in enumerate(self.task_classes) if k in t) for k in range(len(CLASS_NAMES))]
        self.register_buffer("class_task", torch.tensor(class_task), persistent=False)

    def forward_tasks(self, x: Tensor) -> list[HeadMaps]:
        """Per-task maps; task t's heatmap channels are the classes ``task_classes[t]`` in that order."""
        x = self.shared(x)
        return [task(x) for task in self.tasks]

    def forward(self, x: Tensor) -> HeadMaps:
        return self.from_shared(self.shared(x))

    def from_shared(self, x: Tensor) -> HeadMaps:
        """The head after its shared conv, whose output ``x`` is; the export's split shared conv enters here."""
        per_task = [task(x) for task in self.tasks]
        if len(per_task) == 1:  # static: the single head already has the merged layout
            return per_task[0]
        heat = torch.cat([t[0] for t in per_task], dim=1)  # (Q, sum of task classes, Hh, Wh)
        regression = [torch.stack([t[i] for t in per_task], dim=1) for i in range(1, len(HEAD_OUTPUTS))]
        return self.merge(heat, regression)

    def merge(self, heat_by_task: Tensor, regression_by_task: list[Tensor]) -> HeadMaps:
        """The multi-head's maps in the single-head layout.

        heat_by_task (Q, sum of task classes, Hh, Wh): the tasks' heatmaps concatenated in task order;
        regression_by_task[i] (Q, T, ch, Hh, Wh): regression output i + 1 of ``HEAD_OUTPUTS`` of every task.
        """
        heat = heat_by_task.index_select(1, self.merge_index)  # (Q, C_cls, Hh, Wh)
        task = self.class_task[heat.argmax(dim=1)]  # (Q, Hh, Wh): task of each cell's best class
        merged = [heat]
        for stack in regression_by_task:
            pick = task[:, None, None].expand(-1, 1, stack.shape[2], -1, -1)  # (Q, 1, ch, Hh, Wh)
            merged.append(stack.gather(1, pick).squeeze(1))  # (Q, ch, Hh, Wh)
        return tuple(merged)  # type: ignore[return-value]
