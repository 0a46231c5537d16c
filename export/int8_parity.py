"""int8 graphs against fp32 graphs: relative L2 of every output, boxes paired by label and centre."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from streamdet.core.boxes import YAW, pair_boxes
from streamdet.runtime_ort.manifest_records import BoxAgreement, Int8OutputParity
from streamdet.runtime_ort.recording import GraphRecording

BOX_SCORE_THRESHOLD = 0.1  # boxes compared by box_agreement (the pipeline parity's threshold)


def relative_l2(got: np.ndarray, ref: np.ndarray) -> float:
    """||got - ref|| / ||ref|| in float64; 0 when both are zero, inf when only ref is."""
    got = np.asarray(got, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if got.shape != ref.shape:
        raise ValueError(f"shapes differ: {got.shape} vs the reference's {ref.shape}")
    diff = float(np.linalg.norm(got - ref))
    norm = float(np.linalg.norm(ref))
    if norm == 0.0:
        return 0.0 if diff == 0.0 else math.inf
    return diff / norm


def dense_parity(graph: str, output: str, inputs: str, got: Sequence[np.ndarray], ref: Sequence[np.ndarray], note: str = "") -> Int8OutputParity:
    """Relative L2 error over all parity inputs together (outputs flattened and concatenated)."""
    g = np.concatenate([np.ravel(a) for a in got]) if got else np.zeros(0)
    r = np.concatenate([np.ravel(a) for a in ref]) if ref else np.zeros(0)
    max_abs = float(np.abs(g.astype(np.float64) - r).max()) if r.size else 0.0
    return Int8OutputParity(graph, output, inputs, relative_l2(g, r), max_abs, len(ref), note)


def box_agreement(
    dets32: Sequence[Sequence[np.ndarray]],
    dets8: Sequence[Sequence[np.ndarray]],
    cell_m: float,
    score_threshold: float = BOX_SCORE_THRESHOLD,
) -> BoxAgreement:
    """Boxes with score >= threshold of the fp32 and int8 pipelines, slice by slice and quadrant by quadrant.

    ``dets32`` / ``dets8``: per slice (det_boxes (Q, K, 9), det_scores (Q, K), det_labels (Q, K)).
    Pairs: same label, centres within two head cells (``pair_boxes``).
    """
    if len(dets32) != len(dets8):
        raise ValueError(f"{len(dets32)} fp32 slices but {len(dets8)} int8 slices")
    radius = 2.0 * cell_m
    n32 = n8 = 0
    dists, score_diffs, box_pairs = [], [], []
    for (b32, s32, l32), (b8, s8, l8) in zip(dets32, dets8):
        for q in range(s32.shape[0]):
            k32 = s32[q] >= score_threshold
            k8 = s8[q] >= score_threshold
            n32 += int(k32.sum())
            n8 += int(k8.sum())
            ia, ib, d = pair_boxes(b32[q][k32], l32[q][k32], b8[q][k8], l8[q][k8], radius)
            dists.append(d)
            score_diffs.append(np.abs(s32[q][k32][ia].astype(np.float64) - s8[q][k8][ib]))
            box_pairs.append((b32[q][k32][ia], b8[q][k8][ib]))
    dist = np.concatenate(dists) if dists else np.zeros(0)
    sd = np.concatenate(score_diffs) if score_diffs else np.zeros(0)
    matched = int(dist.size)
    return BoxAgreement(
        num_slices=len(dets32),
        score_threshold=score_threshold,
        pair_radius_m=radius,
        count_fp32=n32,
        count_int8=n8,
        matched=matched,
        max_centre_diff_m=float(dist.max()) if matched else math.nan,
        mean_centre_diff_m=float(dist.mean()) if matched else math.nan,
        max_score_diff=float(sd.max()) if matched else math.nan,
        note=f"{n32 - matched} fp32 and {n8 - matched} int8 boxes without a partner",
    )


def _slice_parity(
    inputs: str, dets8: Sequence[Sequence[np.ndarray]], dets32: Sequence[Sequence[np.ndarray]], cell_m: float
) -> list[Int8OutputParity]:
    """det_scores: the top-K scores sorted per quadrant (rank swaps between near-equal peaks do not count);
    det_boxes: the boxes above the threshold paired as in ``box_agreement``."""
    s8 = [np.sort(d[1], axis=1)[:, ::-1] for d in dets8]
    s32 = [np.sort(d[1], axis=1)[:, ::-1] for d in dets32]
    scores = dense_parity("slice_head", "det_scores", inputs, s8, s32, "top-K scores sorted per quadrant")
    got, ref = [], []
    for (b32, sc32, l32), (b8, sc8, l8) in zip(dets32, dets8):
        for q in range(sc32.shape[0]):
            k32, k8 = sc32[q] >= BOX_SCORE_THRESHOLD, sc8[q] >= BOX_SCORE_THRESHOLD
            ia, ib, _ = pair_boxes(b32[q][k32], l32[q][k32], b8[q][k8], l8[q][k8], 2.0 * cell_m)
            r, g = b32[q][k32][ia].astype(np.float64), b8[q][k8][ib].astype(np.float64)
            g[:, YAW] = r[:, YAW] + _wrap(g[:, YAW] - r[:, YAW])  # yaw pi and -pi are one heading
            ref.append(r)
            got.append(g)
    boxes = dense_parity("slice_head", "det_boxes", inputs, got, ref,
                         f"boxes with score >= {BOX_SCORE_THRESHOLD} paired by label and centre (all 9 columns, yaw "
                         "difference wrapped to [-pi, pi))")  # fmt: skip
    return [scores, boxes]


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2 * np.pi) - np.pi


@dataclass(frozen=True)
class Int8Parity:
    outputs: tuple[Int8OutputParity, ...]
    boxes: BoxAgreement


def int8_parity(run32: GraphRecording, run8: GraphRecording, sessions8: Mapping[str, Any], cell_m: float,
                lifter_output: str = "image_bev") -> Int8Parity:  # fmt: skip
    """int8 graphs against fp32 graphs, from the graph runs the fp32 and the int8 detector recorded over the same
    samples (``StreamingDetector.recording``): each int8 graph alone on the fp32 graph's recorded feeds
    (``sessions8``: the int8 detector's sessions by graph name), then the int8 pipeline (the int8 detector's own
    runs: int8 encoder -> int8 lifter -> int8 slice graph) against the fp32 pipeline.

    A LiDAR-only export (no encoder runs) has the slice graph as its whole pipeline: the int8 detector ran it on the
    fp32 detector's feeds, compared once."""
    out: list[Int8OutputParity] = []
    dets32 = run32.outputs("slice_head")
    if not run32.of("image_encoder"):
        dets8 = run8.outputs("slice_head")
        out.extend(_slice_parity("same", dets8, dets32, cell_m))
        return Int8Parity(tuple(out), box_agreement(dets32, dets8, cell_m))

    def alone(name: str) -> list[list[np.ndarray]]:
        return [sessions8[name].run(feeds) for feeds in run32.feeds(name)]

    def first(outputs: Sequence[Sequence[np.ndarray]]) -> list[np.ndarray]:
        return [o[0] for o in outputs]

    out.append(dense_parity("image_encoder", "features", "same", first(alone("image_encoder")), first(run32.outputs("image_encoder"))))
    bev32 = first(run32.outputs("volumetric_lifter"))
    # lifter_output: image_bev, or image_half in that layout (models/image_half.py)
    out.append(dense_parity("volumetric_lifter", lifter_output, "same", first(alone("volumetric_lifter")), bev32))
    out.extend(_slice_parity("same", alone("slice_head"), dets32, cell_m))
    # the int8 pipeline: each int8 graph fed by the int8 graph before it, as the int8 detector runs them
    out.append(dense_parity("volumetric_lifter", lifter_output, "pipeline", first(run8.outputs("volumetric_lifter")), bev32))
    dets8 = run8.outputs("slice_head")
    out.extend(_slice_parity("pipeline", dets8, dets32, cell_m))
    return Int8Parity(tuple(out), box_agreement(dets32, dets8, cell_m))
