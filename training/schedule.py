"""One-cycle learning-rate and momentum schedule (Smith 2018, CenterPoint's), over steps or over wall time.

``progress`` in [0, 1] is either ``step / total_steps`` (reproducible: resume and data-parallel runs retrace the
same curve) or ``elapsed / budget`` (a fixed time budget on a machine shared with others: the run anneals on
time whatever the step rate turns out to be, at the price of step-exact reproducibility).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


def _cos_anneal(start: float, end: float, t: float) -> float:
    return end + (start - end) / 2.0 * (1.0 + math.cos(math.pi * min(max(t, 0.0), 1.0)))


@dataclass
class OneCycle:
    """lr rises from max_lr / div_factor to max_lr over pct_start, then falls to that / final_div_factor;
    beta1 moves the opposite way between max_momentum and base_momentum."""

    max_lr: float
    pct_start: float = 0.4
    div_factor: float = 10.0
    final_div_factor: float = 1e4
    base_momentum: float = 0.85
    max_momentum: float = 0.95
    total_steps: int | None = None  # step mode
    budget_s: float | None = None  # time mode
    step: int = 0
    elapsed_s: float = 0.0

    def __post_init__(self) -> None:
        if (self.total_steps is None) == (self.budget_s is None):
            raise ValueError("OneCycle needs exactly one of total_steps (step mode) and budget_s (time mode)")
        if self.total_steps is not None and self.total_steps < 1:
            raise ValueError(f"OneCycle.total_steps must be >= 1, got {self.total_steps}")
        if self.budget_s is not None and not self.budget_s > 0:
            raise ValueError(f"OneCycle.budget_s must be > 0, got {self.budget_s}")

    @property
    def by_time(self) -> bool:
        return self.budget_s is not None

    @property
    def progress(self) -> float:
        if self.by_time:
            return self.elapsed_s / self.budget_s
        return self.step / self.total_steps

    @property
    def done(self) -> bool:
        return self.progress >= 1.0

    def values(self, progress: float | None = None) -> tuple[float, float]:
        """(lr, beta1) at ``progress`` (default: the current one)."""
        p = self.progress if progress is None else progress
        low = self.max_lr / self.div_factor
        if p < self.pct_start:
            t = p / self.pct_start
            return _cos_anneal(low, self.max_lr, t), _cos_anneal(self.max_momentum, self.base_momentum, t)
        t = (p - self.pct_start) / (1.0 - self.pct_start)
        return _cos_anneal(self.max_lr, low / self.final_div_factor, t), _cos_anneal(self.base_momentum, self.max_momentum, t)

    def apply(self, optimizer) -> float:
        """Write the current lr and beta1 into every param group; returns the lr."""
        lr, beta1 = self.values()
        for group in optimizer.param_groups:
            group["lr"] = lr
            group["betas"] = (beta1, group["betas"][1])
        return lr

    def advance(self, elapsed_s: float) -> None:
        """One optimizer step done; ``elapsed_s`` is the training time so far (all of it, across resumes)."""
        self.step += 1
        self.elapsed_s = float(elapsed_s)

    def state_dict(self) -> dict:
        return {"step": self.step, "elapsed_s": self.elapsed_s, "total_steps": self.total_steps, "budget_s": self.budget_s,
                "max_lr": self.max_lr}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        if state.get("total_steps") != self.total_steps or state.get("budget_s") != self.budget_s:
            raise ValueError(
                f"the checkpoint's schedule (total_steps={state.get('total_steps')}, budget_s={state.get('budget_s')}) "
                f"is not this run's (total_steps={self.total_steps}, budget_s={self.budget_s})"
            )
        self.step = int(state["step"])
        self.elapsed_s = float(state["elapsed_s"])
