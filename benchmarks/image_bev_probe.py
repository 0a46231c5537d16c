"""How strongly does the image BEV reach the fusion point, and does it name the class? (issue 19, items 1 and 2)

    python -m streamdet.benchmarks.image_bev_probe --checkpoint F --data DIR [--split val] [--max-samples N]

For a camera + LiDAR checkpoint, over the samples of a split, on the BEV cells that hold LiDAR pillars:

- RMS of the image BEV at the fusion point (after ``ImageBevNorm`` where the preset has it) in eval mode, and of
  the raw image BEV with the image lane (encoder and lifter) in train mode (BatchNorm on this sample's six
  cameras) vs eval mode;
- RMS of the point BEV (the pillar net's scattered features) on the same cells, and the image / point ratio;
- a linear probe: multinomial logistic regression (class-balanced) of the class from the image BEV, and from the
  point BEV, at the cells under the ground-truth centres; fitted on the first 70 % of the samples, balanced
  accuracy on the rest.

The issue's targets: train / eval RMS within 10 %, image / point RMS within [0.5, 2], probe balanced accuracy
>= 0.6. Figures go to docs, not here.
"""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np
import torch

from streamdet.core.table_version import DEFAULT_TABLE_VERSION
from streamdet.core.sectors import quadrants_of_sector
from streamdet.core.slicing import split_sweep
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.splits import split_sample_tokens
from streamdet.models.pillars import scatter_pillars
from streamdet.progress import progressbar
from streamdet.runtime_ort.pillarize import pillarize
from streamdet.training.checkpoint import load_weights


def _rms(x: torch.Tensor) -> float:
    return float(x.square().mean().sqrt()) if x.numel() else float("nan")


@torch.no_grad()
def sample_features(model, preset, sample, lut_for) -> dict:
    """Per sample: image BEV (eval, at fusion; raw eval; raw train-mode encoder) and point BEV, each (4, C, Yq, Xq),
    the occupied-cell mask (4, Yq, Xq), and the GT centre cells with their labels."""
    p, g = preset, preset.grid
    lut = lut_for(sample)
    images = torch.from_numpy(sample.load_images((p.image.width_px, p.image.height_px)))
    index = torch.from_numpy(np.asarray(lut.index, np.int64))
    weight = torch.from_numpy(np.array(lut.weight))
    raw_eval = model.image_bev(images, index, weight)  # (4, C, Yq, Xq)
    # the image lane in train mode (its BatchNorms on this sample's cameras); their running statistics restored after
    saved = {k: v.clone() for k, v in model.state_dict().items()}
    model.image_encoder.train()
    model.lifter.train()
    raw_train = model.image_bev(images, index, weight)
    model.load_state_dict(saved)
    model.eval()
    norm = model.slice_net.image_bev_norm
    fused = raw_eval if norm is None else norm(raw_eval)
    point = torch.zeros_like(raw_eval)
    for k, points in enumerate(split_sweep(np.asarray(sample.points, np.float32), 4)):
        quads = quadrants_of_sector(k, 4)
        pil = pillarize(points, g, quads, p.pillars.max_points_per_pillar, 4 * p.pillars.max_pillars)
        feats = model.slice_net.pillar_net(torch.from_numpy(pil.features), torch.from_numpy(pil.mask))
        point[list(quads)] += scatter_pillars(feats, torch.from_numpy(pil.index), (len(quads), g.quadrant_ny, g.quadrant_nx))
    occupied = point.abs().sum(dim=1) > 0  # (4, Yq, Xq)
    keep = sample.gt_labels >= 0
    xy = sample.gt_boxes[keep, :2]
    q = g.quadrant_of_xy(xy[:, 0], xy[:, 1])
    cells = []
    for (x, y), qq in zip(xy.tolist(), q.tolist()):
        x0, y0 = g.quadrant_origin_m(qq)
        cells.append((qq, int((y - y0) // g.voxel_xy_m), int((x - x0) // g.voxel_xy_m)))
    ok = np.array([0 <= r < g.quadrant_ny and 0 <= c < g.quadrant_nx for _, r, c in cells], dtype=bool)
    return {"fused": fused, "raw_eval": raw_eval, "raw_train": raw_train, "point": point, "occupied": occupied,
            "cells": [c for c, o in zip(cells, ok) if o], "labels": sample.gt_labels[keep][ok]}  # fmt: skip


def balanced_probe(x_train: np.ndarray, y_train: np.ndarray, x_test: np.ndarray, y_test: np.ndarray,
                   steps: int = 500, lr: float = 0.5, l2: float = 1e-3) -> float:  # fmt: skip
    """Class-balanced multinomial logistic regression (full-batch gradient descent on standardised features, numpy);
    balanced accuracy on the test rows of the classes seen in training. NaN with fewer than 2 classes or no test row."""
    classes = np.unique(y_train)
    if len(classes) < 2 or len(x_test) == 0:
        return float("nan")
    remap = {c: i for i, c in enumerate(classes.tolist())}
    mu, sd = x_train.mean(0), x_train.std(0) + 1e-6
    xt = (x_train - mu) / sd  # (N, D)
    yt = np.array([remap[c] for c in y_train.tolist()])
    onehot = np.eye(len(classes))[yt]  # (N, K)
    counts = onehot.sum(0)
    row_w = (len(yt) / (len(classes) * counts))[yt][:, None] / len(yt)  # (N, 1) class-balanced, mean-normalised
    w = np.zeros((xt.shape[1], len(classes)))
    b = np.zeros(len(classes))
    for _ in range(steps):
        z = xt @ w + b
        z -= z.max(axis=1, keepdims=True)
        prob = np.exp(z)
        prob /= prob.sum(axis=1, keepdims=True)
        grad = row_w * (prob - onehot)  # (N, K)
        w -= lr * (xt.T @ grad + l2 * w)
        b -= lr * grad.sum(0)
    seen = np.isin(y_test, classes)
    pred = (((x_test[seen] - mu) / sd) @ w + b).argmax(1)
    truth = np.array([remap[c] for c in y_test[seen].tolist()])
    recalls = [float(np.mean(pred[truth == c] == c)) for c in np.unique(truth)]
    return float(np.mean(recalls)) if recalls else float("nan")


def measure(checkpoint: Path, data: Path, split: str | None, max_samples: int | None, version: str = DEFAULT_TABLE_VERSION) -> dict:
    from streamdet.calibration.lut_build import build_lut

    model, preset = load_weights(checkpoint)
    if not preset.use_image:
        raise ValueError(f"{checkpoint} is a LiDAR-only checkpoint: it has no image BEV")
    reader = NuScenesReader(data, version)
    tokens = split_sample_tokens(reader, data, split)[:max_samples]
    luts: dict = {}

    def lut_for(sample):
        key = sample.rig.sha256()
        if key not in luts:
            img = preset.image
            luts[key] = build_lut(sample.rig, preset.grid, img.feature_stride, (img.width_px, img.height_px),
                                  heights_per_voxel=preset.lifter.lut_heights_per_voxel)  # fmt: skip
        return luts[key]

    sums = {k: [] for k in ("fused", "raw_eval", "raw_train", "point")}
    probe = {"image": [], "point": [], "labels": []}
    with progressbar(tokens, label="samples") as bar:
        for token in bar:
            f = sample_features(model, preset, reader.get(token), lut_for)
            occ = f["occupied"]
            for k in sums:
                sums[k].append(f[k].permute(0, 2, 3, 1)[occ])  # (cells, C)
            rows = [(q, r, c) for q, r, c in f["cells"]]
            probe["image"].append(np.stack([f["fused"][q, :, r, c].numpy() for q, r, c in rows]) if rows else np.zeros((0, preset.channels)))
            probe["point"].append(np.stack([f["point"][q, :, r, c].numpy() for q, r, c in rows]) if rows else np.zeros((0, preset.channels)))
            probe["labels"].append(np.asarray(f["labels"]))
    rms = {k: _rms(torch.cat(v)) for k, v in sums.items()}
    split_at = int(0.7 * len(tokens))
    out = {"checkpoint": str(checkpoint), "preset": preset.name, "samples": len(tokens), "rms_occupied": rms,
           "train_over_eval_rms": rms["raw_train"] / rms["raw_eval"], "image_over_point_rms": rms["fused"] / rms["point"]}  # fmt: skip
    for key in ("image", "point"):
        xtr, xte = np.concatenate(probe[key][:split_at]), np.concatenate(probe[key][split_at:])
        ytr, yte = np.concatenate(probe["labels"][:split_at]), np.concatenate(probe["labels"][split_at:])
        out[f"probe_balanced_accuracy_{key}"] = balanced_probe(xtr, ytr, xte, yte)
    return out


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--checkpoint", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path), help="Camera + LiDAR checkpoint.")
@click.option("--data", required=True, type=click.Path(exists=True, file_okay=False, path_type=Path), help="Dataset root.")
@click.option("--split", default="val", show_default=True, help="Split of DATA/splits.json, or 'all'.")
@click.option("--max-samples", type=click.IntRange(min=2), default=24, show_default=True, help="Samples to measure.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also write JSON here.")
def main(checkpoint: Path, data: Path, split: str, max_samples: int, json_path: Path | None) -> None:
    """Image BEV scale at fusion, train/eval RMS, and a linear class probe at ground-truth centres."""
    torch.set_num_threads(1)  # a shared 2-core machine: one thread is faster than two fighting (benchmarks/RESULTS.md)
    try:
        out = measure(checkpoint, data, None if split == "all" else split, max_samples)
    except (ValueError, FileNotFoundError, KeyError) as e:
        raise click.ClickException(str(e).splitlines()[0]) from None
    click.echo(json.dumps(out, indent=1))
    if json_path is not None:
        json_path.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
