"""The runtime's numpy stages timed alone: pillarizing 30,000 points, and post-processing 500 candidates.

These are the vehicle runtime's own budgets (pillarize under 5 ms for 30,000 points, decode + uncrop + per-class
NMS under 3 ms for 500 candidates). Each stage runs on fixed inputs, so the figures do not depend on a model:

- pillarize, real sweep: the first 30,000 points of the bundled nuScenes sweep (tiled when it holds fewer), every
  quadrant, as a one-slice sweep would (many points per pillar near the car);
- pillarize, uniform: 30,000 points spread uniformly over one quadrant (about one pillar per point, the most
  pillars to sort and fill: the worst case);
- post, circle / rotated NMS: 500 candidates (the decode's top-K) in one quadrant, every one above the score
  threshold, with nuScenes-like classes and sizes, through ``postprocess_slice`` with each NMS kind. The centres
  are spread over the quadrant, as a real slice's are, so each NMS sees a realistic number of overlaps; ``crowded``
  packs them into a 10 m square, the worst case for the rotated IoU.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from streamdet.benchmarks.timing import MIN_P95_SAMPLES, TimingConfig, TimingStats, time_callable
from streamdet.calibration.grid import GridSpec
from streamdet.core.boxes import BOX_DIM
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.slicing import split_sweep
from streamdet.data.sample import load_bundled_sample
from streamdet.runtime_ort.nms import NmsKind
from streamdet.runtime_ort.pillarize import pillarize
from streamdet.runtime_ort.postprocess import PostprocessConfig, postprocess_slice

NUM_POINTS = 30_000
NUM_CANDIDATES = 500
PILLARIZE_BUDGET_MS = 5.0
POST_BUDGET_MS = 3.0
# Typical (w, l, h) in metres per class, CLASS_NAMES order (nuScenes means, rounded).
_CLASS_SIZE_M = np.array(
    [[1.9, 4.6, 1.7], [2.5, 6.9, 2.8], [2.9, 12.3, 3.9], [2.9, 11.0, 3.5], [2.7, 6.4, 3.2],
     [0.6, 1.7, 1.3], [0.8, 2.1, 1.5], [0.7, 0.7, 1.8], [0.4, 0.4, 1.1], [2.5, 0.5, 1.0]],
    dtype=np.float32,
)  # fmt: skip


@dataclass(frozen=True)
class PrePostCase:
    name: str
    stage: str  # pre | post
    stats: TimingStats
    budget_ms: float
    detail: str  # what the input held (pillars made, boxes kept)

    @property
    def met(self) -> bool:
        return self.stats.median_ms <= self.budget_ms


def real_sweep_points(num_points: int = NUM_POINTS) -> np.ndarray:
    """(num_points, 6) float32 from the bundled sweep, tiled when the sweep is shorter."""
    points = split_sweep(load_bundled_sample().points, 1)[0]  # (N, 6) with relative time and slice index
    reps = -(-num_points // len(points))
    return np.ascontiguousarray(np.tile(points, (reps, 1))[:num_points])


def uniform_quadrant_points(grid: GridSpec, quadrant: int, num_points: int = NUM_POINTS, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ox, oy = grid.quadrant_origin_m(quadrant)
    ex, ey = grid.quadrant_nx * grid.voxel_xy_m, grid.quadrant_ny * grid.voxel_xy_m
    pts = np.empty((num_points, 6), np.float32)
    pts[:, 0] = ox + rng.uniform(0, ex, num_points)
    pts[:, 1] = oy + rng.uniform(0, ey, num_points)
    pts[:, 2] = rng.uniform(grid.z_range_m[0], grid.z_range_m[1], num_points)
    pts[:, 3] = rng.uniform(0, 255, num_points)
    pts[:, 4] = rng.uniform(0, 0.05, num_points)
    pts[:, 5] = 0
    return pts


def candidates(grid: GridSpec, num: int = NUM_CANDIDATES, extent_m: float | None = None, seed: int = 0):
    """Decoded slice-graph outputs for one quadrant: boxes (1, K, 9) relative to its corner, scores, labels (1, K)."""
    rng = np.random.default_rng(seed)
    ex = grid.quadrant_nx * grid.voxel_xy_m if extent_m is None else extent_m
    ey = grid.quadrant_ny * grid.voxel_xy_m if extent_m is None else extent_m
    labels = rng.integers(0, len(CLASS_NAMES), num)
    boxes = np.zeros((num, BOX_DIM), np.float32)
    boxes[:, 0] = rng.uniform(0, ex, num)
    boxes[:, 1] = rng.uniform(0, ey, num)
    boxes[:, 2] = rng.uniform(-1.0, 1.0, num)
    boxes[:, 3:6] = _CLASS_SIZE_M[labels] * rng.uniform(0.8, 1.2, (num, 1)).astype(np.float32)
    boxes[:, 6] = rng.uniform(-np.pi, np.pi, num)
    boxes[:, 7:9] = rng.normal(0, 2, (num, 2))
    scores = rng.uniform(0.11, 1.0, num).astype(np.float32)
    return boxes[None], scores[None], labels[None].astype(np.int64)


def measure_prepost(
    grid: GridSpec,
    max_points_per_pillar: int,
    max_pillars: int,
    post: PostprocessConfig = PostprocessConfig(),
    timing: TimingConfig = TimingConfig(repeat=50, budget_s=5.0),
) -> tuple[PrePostCase, ...]:
    cases = []
    all_quadrants = (0, 1, 2, 3)
    for name, pts, quadrants in (
        (f"pillarize {NUM_POINTS:,} points, real sweep, 4 quadrants", real_sweep_points(), all_quadrants),
        (f"pillarize {NUM_POINTS:,} points, uniform in 1 quadrant", uniform_quadrant_points(grid, 0), (0,)),
    ):
        made = pillarize(pts, grid, quadrants, max_points_per_pillar, max_pillars)
        stats = time_callable(lambda: pillarize(pts, grid, quadrants, max_points_per_pillar, max_pillars), timing)
        cases.append(PrePostCase(name, "pre", stats, PILLARIZE_BUDGET_MS, f"{made.num_pillars:,} pillars"))
    for spread, extent in (("spread over the quadrant", None), ("crowded in 10 m", 10.0)):
        boxes, scores, labels = candidates(grid, extent_m=extent)
        for kind in (NmsKind.CIRCLE, NmsKind.ROTATED):
            cfg = replace(post, score_threshold=0.1, restrict_to_sector=False, nms=replace(post.nms, kind=kind))
            kept = postprocess_slice(boxes, scores, labels, (0,), grid, cfg)
            stats = time_callable(lambda: postprocess_slice(boxes, scores, labels, (0,), grid, cfg), timing)
            cases.append(
                PrePostCase(f"post {NUM_CANDIDATES} candidates, {kind.value} NMS, {spread}", "post", stats,
                            POST_BUDGET_MS, f"{len(kept.scores)} kept")  # fmt: skip
            )
    return tuple(cases)


def _p95(stats: TimingStats) -> str:
    """The p95 column: "n/a" under MIN_P95_SAMPLES samples, as the report's other p95s (the JSON keeps it)."""
    return f"{stats.p95_ms:6.2f} ms" if stats.count >= MIN_P95_SAMPLES else f"{'n/a':>9}"


def format_prepost(cases: tuple[PrePostCase, ...]) -> str:
    lines = ["runtime numpy stages alone (1 thread; budgets of the runtime: pillarize <= 5 ms, post <= 3 ms)"]
    for c in cases:
        s = c.stats
        lines.append(
            f"  {c.name:<58} p50 {s.median_ms:6.2f} ms  p95 {_p95(s)}  n={s.count}  "
            f"[{'within' if c.met else 'OVER'} {c.budget_ms:g} ms]  ({c.detail})"
        )
    return "\n".join(lines)


def prepost_to_dict(cases: tuple[PrePostCase, ...]) -> list[dict]:
    return [{"name": c.name, "stage": c.stage, "budget_ms": c.budget_ms, "met": c.met, "detail": c.detail,
             **c.stats.to_dict()} for c in cases]  # fmt: skip
