"""Slice graph outputs -> detections in the LiDAR frame, and the aggregation of a sweep's slices (numpy only).

`slice_head.onnx` returns, per touched quadrant, its top-K boxes with x, y relative to the quadrant's
minimum corner (docs/architecture.md, "The three graphs"); a LiDAR-only graph without the crop returns one map of
the whole grid, relative to the grid's minimum corner (`calibration/slice_maps.py`). Post-processing uncrops them
(adds `GridSpec.quadrant_origin_m(q)`, or the grid's corner), drops low scores and boxes no net output of this grid
can mean (`plausible_boxes`), optionally keeps only boxes centred in the slice's sector, and runs per-class NMS. The paper then aggregates the slices of a sweep with one more per-class NMS,
which removes objects detected twice across a slice border.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from streamdet.calibration.grid import GridSpec
from streamdet.calibration.slice_maps import slice_maps
from streamdet.core.boxes import BOX_DIM, H, W, X, Y
from streamdet.core.classes import CLASS_NAMES
from streamdet.core.sectors import azimuth_deg, check_quadrants, slice_index_of
from streamdet.runtime_ort.nms import NmsConfig, nms


@dataclass(frozen=True)
class Detections:
    """Boxes (N, 9) float32 in the LiDAR frame (layout of `core/boxes.py`), scores (N,), labels (N,)."""

    boxes: np.ndarray  # (N, 9) float32
    scores: np.ndarray  # (N,) float32
    labels: np.ndarray  # (N,) int64, indexes CLASS_NAMES

    def __post_init__(self) -> None:
        boxes = np.asarray(self.boxes, dtype=np.float32)
        scores = np.asarray(self.scores, dtype=np.float32)
        labels = np.asarray(self.labels)
        if boxes.ndim != 2 or boxes.shape[1] != BOX_DIM:
            raise ValueError(f"Detections.boxes must be (N, {BOX_DIM}), got shape {boxes.shape}")
        n = boxes.shape[0]
        if scores.shape != (n,):
            raise ValueError(f"Detections.scores must be ({n},) to match boxes, got shape {scores.shape}")
        if labels.shape != (n,):
            raise ValueError(f"Detections.labels must be ({n},) to match boxes, got shape {labels.shape}")
        if n and not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(f"Detections.labels must be integers, got dtype {labels.dtype}")
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "scores", scores)
        object.__setattr__(self, "labels", labels.astype(np.int64))

    @classmethod
    def empty(cls) -> "Detections":
        return cls(np.zeros((0, BOX_DIM), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))

    @classmethod
    def concatenate(cls, parts: Sequence["Detections"]) -> "Detections":
        if not parts:
            return cls.empty()
        return cls(
            np.concatenate([p.boxes for p in parts]),
            np.concatenate([p.scores for p in parts]),
            np.concatenate([p.labels for p in parts]),
        )

    def select(self, which: np.ndarray) -> "Detections":
        """The detections picked by a boolean mask (N,) or an integer index array."""
        which = np.asarray(which)
        if which.dtype == bool and which.shape != (len(self),):
            raise ValueError(f"a boolean selection must be ({len(self)},), got shape {which.shape}")
        return Detections(self.boxes[which], self.scores[which], self.labels[which])

    def __len__(self) -> int:
        return self.boxes.shape[0]


@dataclass(frozen=True)
class PostprocessConfig:
    score_threshold: float = 0.1  # keep boxes scoring >= this (CenterPoint's nuScenes test setting)
    restrict_to_sector: bool = False  # keep only boxes whose BEV centre lies in the slice's own sector
    nms: NmsConfig = field(default_factory=NmsConfig)  # per-class NMS inside the slice

    def __post_init__(self) -> None:
        if not math.isfinite(self.score_threshold):
            raise ValueError(f"PostprocessConfig.score_threshold must be finite, got {self.score_threshold}")


def uncrop_boxes(det_boxes: np.ndarray, quadrants: Sequence[int], grid: GridSpec, crop: bool = True) -> np.ndarray:
    """(Q, K, 9) boxes relative to their map's minimum corner -> (Q, K, 9) float32 in the LiDAR frame.

    With the crop the maps are the slice's quadrants; without it (``crop`` False) one map of the whole grid (Q = 1)."""
    qs = check_quadrants(quadrants)
    maps = slice_maps(grid, qs, crop)
    det_boxes = np.asarray(det_boxes)
    if det_boxes.ndim != 3 or det_boxes.shape[0] != maps.count or det_boxes.shape[2] != BOX_DIM:
        what = f"quadrants {qs}" if crop else "the whole-grid map (no crop)"
        raise ValueError(f"det_boxes must be (Q={maps.count}, K, {BOX_DIM}) for {what}, got shape {det_boxes.shape}")
    origin = np.array(maps.origins_m, dtype=np.float64)  # (Q, 2)
    boxes = det_boxes.astype(np.float64)  # float64 add, then one rounding to float32
    boxes[..., X] += origin[:, None, 0]  # basic indexing: a fancy [X, Y] update costs several times more
    boxes[..., Y] += origin[:, None, 1]
    return boxes.astype(np.float32)


# How far past the grid's edge a box centre may lie: a centre is regressed from its head cell (0.4-0.8 m in the presets,
# models/presets.py head_cell_m) and can leave an edge cell by part of one; a few cells of slack keep every such box.
EDGE_MARGIN_M = 2.0


def plausible_boxes(boxes: np.ndarray, grid: GridSpec) -> np.ndarray:
    """Boolean (N,): the box's BEV centre lies inside the grid (up to ``EDGE_MARGIN_M`` past its edge) and its sizes
    are positive and at most the grid's extent. A trained net's boxes are; out-of-range inputs (a corrupted point,
    an image of garbage) can drive the regression anywhere, and such a box would reach the caller with whatever
    score came with it."""
    span_m = max(grid.x_range_m[1] - grid.x_range_m[0], grid.y_range_m[1] - grid.y_range_m[0])
    (x_lo, x_hi), (y_lo, y_hi) = grid.x_range_m, grid.y_range_m
    x, y = boxes[:, X], boxes[:, Y]
    sizes = boxes[:, W : H + 1]  # (N, 3) w, l, h
    inside = (x >= x_lo - EDGE_MARGIN_M) & (x <= x_hi + EDGE_MARGIN_M) & (y >= y_lo - EDGE_MARGIN_M) & (y <= y_hi + EDGE_MARGIN_M)
    return inside & (sizes > 0).all(axis=1) & (sizes <= span_m).all(axis=1)


class SliceRun(NamedTuple):
    """The slices one graph run detects: ``slice_indices`` of ``num_slices`` (consecutive, in scan order) in the scan
    layout ``start_deg`` / ``clockwise`` (``core/sectors.py``)."""

    slice_indices: Sequence[int]
    num_slices: int
    start_deg: float = 0.0
    clockwise: bool = False


def in_slices(boxes: np.ndarray, run: SliceRun) -> np.ndarray:
    """Boolean (N,): the BEV centre lies in one of the run's slices by ``slice_index_of``, the rule that slices the
    points (``split_sweep``) and hands a coalesced run's boxes to its slices (``split_by_slice``). Being integer, it
    partitions centres exactly between adjacent slices; comparing azimuths with bounds in float (``in_sector``) does
    not: ``hi - lo`` and the azimuth both round, so a centre on a shared bound was kept by both slices or by neither."""
    k = slice_index_of(boxes[:, X], boxes[:, Y], run.num_slices, run.start_deg, run.clockwise)  # (N,)
    return (k[:, None] == np.asarray(run.slice_indices, np.int64)[None, :]).any(axis=1)  # a few boxes, a few slices


def in_sector(boxes: np.ndarray, sector_deg: tuple[float, float]) -> np.ndarray:
    """Boolean (N,): the BEV centre's azimuth lies in [lo, hi) of the sector (wrapping past 360 deg). For a sector
    given by its bounds only: two adjacent sectors' bounds round apart, so for a sweep's slices use ``in_slices``."""
    lo, hi = float(sector_deg[0]), float(sector_deg[1])
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < hi - lo <= 360.0):
        raise ValueError(f"sector_deg must be (lo, hi) with 0 < hi - lo <= 360, got {sector_deg!r}")
    rel = np.mod(azimuth_deg(boxes[:, X], boxes[:, Y]) - lo, 360.0)
    return rel < hi - lo


def top_k_reached(det_scores: np.ndarray, score_threshold: float) -> bool:
    """Whether some quadrant's last decoded score, (Q, K) in descending order as the graph's top-K gives them, passes
    the threshold: every one of its K boxes was kept, so the cap may have cut more."""
    scores = np.asarray(det_scores)
    if scores.ndim != 2:
        raise ValueError(f"det_scores must be (Q, K), got shape {scores.shape}")
    return scores.shape[1] > 0 and bool((scores[:, -1] >= score_threshold).any())


def postprocess_slice(
    det_boxes: np.ndarray,
    det_scores: np.ndarray,
    det_labels: np.ndarray,
    quadrants: Sequence[int],
    grid: GridSpec,
    config: PostprocessConfig = PostprocessConfig(),
    sector_deg: tuple[float, float] | None = None,
    crop: bool = True,
    slices: SliceRun | None = None,
) -> Detections:
    """Decoded slice graph outputs (Q, K, 9), (Q, K), (Q, K) -> the slice's detections in the LiDAR frame.

    Steps: uncrop, drop rows with a non-finite value, score threshold, implausible boxes (`plausible_boxes`), sector restriction (when
    `config.restrict_to_sector`), per-class NMS. The restriction needs the run's `slices` (`in_slices`: the slices of a
    sweep split the centres exactly), or else a `sector_deg` (lo, hi), e.g. `grid.sector_bounds_deg(k, n)`
    (`in_sector`: a centre on a bound shared with the next slice may be kept by both or by neither).
    `crop` False: the outputs are one map of the whole grid (a LiDAR-only net without the quadrant crop).
    """
    det_scores = np.asarray(det_scores)
    det_labels = np.asarray(det_labels)
    boxes = uncrop_boxes(det_boxes, quadrants, grid, crop)
    if det_scores.shape != boxes.shape[:2]:
        raise ValueError(f"det_scores must be {boxes.shape[:2]} to match det_boxes, got shape {det_scores.shape}")
    if det_labels.shape != boxes.shape[:2]:
        raise ValueError(f"det_labels must be {boxes.shape[:2]} to match det_boxes, got shape {det_labels.shape}")
    if not np.issubdtype(det_labels.dtype, np.integer):
        raise ValueError(f"det_labels must be integers, got dtype {det_labels.dtype}")
    if config.restrict_to_sector and sector_deg is None and slices is None:
        raise ValueError("PostprocessConfig.restrict_to_sector is set but no slices or sector_deg was given")
    if sector_deg is not None and slices is not None:
        raise ValueError(f"give the slices or a sector_deg to restrict to, not both: got {slices!r} and {sector_deg!r}")

    boxes = boxes.reshape(-1, BOX_DIM)  # (Q * K, 9)
    scores = det_scores.reshape(-1).astype(np.float32)  # (Q * K,)
    labels = det_labels.reshape(-1).astype(np.int64)
    bad_label = (labels < 0) | (labels >= len(CLASS_NAMES))
    if bad_label.any():
        raise ValueError(f"det_labels must index CLASS_NAMES (0..{len(CLASS_NAMES) - 1}), got {labels[bad_label][0]}")

    keep = np.isfinite(boxes).all(axis=1) & np.isfinite(scores) & (scores >= config.score_threshold)
    passed = np.flatnonzero(keep)  # the few above the threshold: the plausibility test on those only
    keep[passed[~plausible_boxes(boxes[passed], grid)]] = False
    if config.restrict_to_sector:  # on the few boxes still kept
        passed = np.flatnonzero(keep)
        inside = in_slices(boxes[passed], slices) if slices is not None else in_sector(boxes[passed], sector_deg)
        keep[passed[~inside]] = False
    dets = Detections(boxes[keep], scores[keep], labels[keep])
    return dets.select(nms(dets.boxes, dets.scores, dets.labels, config.nms))


def aggregate_sweep(slice_detections: Sequence[Detections], nms_config: NmsConfig = NmsConfig()) -> Detections:
    """The detections of a sweep's slices, concatenated and de-duplicated by one per-class NMS."""
    merged = Detections.concatenate(list(slice_detections))
    return merged.select(nms(merged.boxes, merged.scores, merged.labels, nms_config))
