"""The image-side class loss beside detection (training/image_class.py): the centre cells against the probe's own
cell arithmetic, the classifier against a per-object loop, empty input, and the trainer's use of it (loss part,
checkpoint, resume, never in the exported weights)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from streamdet.core.boxes import BOX_DIM, X, Y
from streamdet.models.presets import get_preset
from streamdet.training.batching import Collator
from streamdet.training.checkpoint import load_checkpoint, load_weights
from streamdet.training.dataset import SliceDataset, build_store
from streamdet.training.image_class import ImageBevClassifier, centre_cells, image_class_loss_sum
from streamdet.training.model import TrainingModel
from streamdet.training.targets import TargetConfig, build_targets
from streamdet.training.trainer import TrainConfig, train

TINY = get_preset("tiny")
SMALL = get_preset("small_v2")


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("preset", [TINY, SMALL], ids=["tiny", "small_v2"])
@pytest.mark.parametrize("stride", [1, 2, 4])
def test_centre_cells_are_the_cells_holding_the_centres(seed, preset, stride):
    g = preset.grid
    rng = np.random.default_rng(seed)
    quadrant = int(rng.integers(4))
    x0, y0 = g.quadrant_origin_m(quadrant)
    n = 40
    # centres away from cell borders (float32 sub-cell offsets must not round across one)
    col = rng.integers(0, g.quadrant_nx, n)
    row = rng.integers(0, g.quadrant_ny, n)
    boxes = np.zeros((n, BOX_DIM))
    boxes[:, X] = x0 + (col + rng.uniform(0.05, 0.95, n)) * g.voxel_xy_m
    boxes[:, Y] = y0 + (row + rng.uniform(0.05, 0.95, n)) * g.voxel_xy_m
    boxes[:, 3:6] = 1.0
    t = build_targets(boxes, np.zeros(n, np.int64), quadrant, g, stride, TargetConfig(max_objects=64))
    got = centre_cells(torch.from_numpy(t.index)[None], torch.from_numpy(t.box)[None], g.quadrant_nx // stride, stride)[0]
    # the probe's arithmetic (benchmarks/image_bev_probe.py): the BEV cell of the metric centre
    want = [int((y - y0) // g.voxel_xy_m) * g.quadrant_nx + int((x - x0) // g.voxel_xy_m) for x, y in boxes[:, :2]]
    assert got[: t.num_objects].tolist() == want


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_classifier_matches_a_per_object_loop(seed, dtype):
    torch.manual_seed(seed)
    q, c, h, w, k, classes = 3, 5, 6, 7, 4, 10
    bev = torch.randn(q, c, h, w, dtype=dtype) * torch.rand(1, c, 1, 1, dtype=dtype)
    cells = torch.randint(0, h * w, (q, k))
    mask = torch.rand(q, k) > 0.4
    head = ImageBevClassifier(c, classes).to(dtype)
    got = head(bev, cells, mask)
    rms = bev.square().mean(dim=(0, 2, 3)).add(1e-6).sqrt()
    rows = [head.linear(bev[i, :, cells[i, j] // w, cells[i, j] % w] / rms) for i in range(q) for j in range(k) if mask[i, j]]
    want = torch.stack(rows) if rows else torch.zeros(0, classes, dtype=dtype)
    torch.testing.assert_close(got, want)
    # a per-channel scale of the image BEV (what ImageBevNorm applies) does not change the read-out (up to the eps)
    scaled = head(bev * torch.rand(1, c, 1, 1, dtype=dtype).add(0.5), cells, mask)
    torch.testing.assert_close(scaled, got, rtol=1e-3, atol=1e-4)


def test_no_objects_give_a_zero_loss_that_still_back_propagates():
    head = ImageBevClassifier(4, 10)
    bev = torch.randn(2, 4, 3, 3, requires_grad=True)
    logits = head(bev, torch.zeros(2, 5, dtype=torch.int64), torch.zeros(2, 5, dtype=torch.bool))
    assert logits.shape == (0, 10)
    loss = image_class_loss_sum(logits, torch.zeros(0, dtype=torch.int64))
    assert float(loss.detach()) == 0.0
    loss.backward()  # no error: the classifier stays in the graph (DDP's unused-parameter check)


def test_loss_is_the_summed_cross_entropy():
    logits = torch.tensor([[2.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    labels = torch.tensor([0, 2])
    want = sum(-torch.log_softmax(logits[i], 0)[labels[i]] for i in range(2))
    torch.testing.assert_close(image_class_loss_sum(logits, labels), want)


def test_training_model_needs_the_image_lane():
    from streamdet.models.detector import build_detector

    lidar = build_detector(TINY.__class__(**{**TINY.__dict__, "use_image": False}))
    with pytest.raises(ValueError, match="image lane"):
        TrainingModel(lidar, image_classifier=True)


@pytest.fixture(scope="module")
def store(tiny_train_data, tmp_path_factory):
    return build_store(tiny_train_data, "train", (TINY.image.width_px, TINY.image.height_px),
                       cache_dir=tmp_path_factory.mktemp("cache"))  # fmt: skip


def test_forward_returns_one_logit_row_per_object(store):
    torch.manual_seed(0)
    from streamdet.models.detector import build_detector

    model = TrainingModel(build_detector(TINY), image_classifier=True).train()
    batch = Collator(TINY)([SliceDataset(store, TINY)[0]])
    maps, (logits, labels) = model(batch)
    assert logits.shape == (int(batch.mask.sum()), 10) and torch.isfinite(logits).all()
    assert torch.equal(labels, batch.label[batch.mask])
    assert model(batch, use_image=False)[1] is None  # the image lane off (warm-up): nothing to read


def _config(**kw) -> TrainConfig:
    base = dict(preset="tiny", steps=3, batch_size=1, lr=1e-3, log_every=1, checkpoint_every=100, seed=0, image_class_weight=0.5)
    return TrainConfig(**{**base, **kw})


def test_trainer_logs_saves_and_resumes_the_class_loss(store, tmp_path: Path):
    full = train(_config(), "unused", tmp_path / "full", store=store, echo=lambda m: None)
    assert full.steps_done == 3
    lines = (tmp_path / "full" / "metrics.jsonl").read_text().splitlines()
    assert all('"image_class"' in line for line in lines)
    ckpt = load_checkpoint(tmp_path / "full" / "last.pt")
    assert set(ckpt["image_classifier"]) == {"linear.weight", "linear.bias"}
    assert ckpt["config"]["image_class_weight"] == 0.5
    det, _ = load_weights(tmp_path / "full" / "model.pt")  # the exported model has no classifier
    assert not any("classifier" in k for k in det.state_dict())
    part = train(_config(max_minutes=1e-9), "unused", tmp_path / "part", store=store, echo=lambda m: None)
    assert part.stopped_early
    resumed = train(_config(), "unused", tmp_path / "resumed", resume=tmp_path / "part" / "last.pt", store=store, echo=lambda m: None)
    assert resumed.steps_done == 3
    b = load_checkpoint(tmp_path / "resumed" / "last.pt")
    for k in ckpt["image_classifier"]:
        assert torch.equal(ckpt["image_classifier"][k], b["image_classifier"][k]), k
    for k in ckpt["model"]:
        assert torch.equal(ckpt["model"][k], b["model"][k]), k
    with pytest.raises(ValueError, match="image class loss"):
        train(_config(image_class_weight=0.0), "unused", tmp_path / "mismatch", resume=tmp_path / "part" / "last.pt",
              store=store, echo=lambda m: None)  # fmt: skip


@pytest.mark.parametrize("weight", [-1.0, float("nan"), float("inf")])
def test_config_rejects_bad_weights(weight):
    with pytest.raises(ValueError, match="image_class_weight"):
        _config(image_class_weight=weight)


def test_config_rejects_the_loss_without_images():
    with pytest.raises(ValueError, match="needs the image lane"):
        _config(use_image=False)
    assert "image_class_weight" not in _config(image_class_weight=0.0).to_dict()  # old runs' configs unchanged
