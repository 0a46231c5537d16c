"""Camera dropout (training/camera_dropout.py): the draw against its stated distribution, a dropped camera lifted
exactly as zero features (the runtime's missing camera), every camera dropped = the lift of zero features (the
runtime's camera-less BEV), the image-side class loss reading only samples that kept every camera, and the trainer:
config, CLI, resume drawing what the uninterrupted run drew."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset
from streamdet.training.batching import Collator
from streamdet.training.camera_dropout import check_camera_dropout, draw_camera_keep
from streamdet.training.checkpoint import load_checkpoint
from streamdet.training.cli import main as train_main
from streamdet.training.dataset import DataConfig, SliceDataset, build_store
from streamdet.training.model import TrainingModel
from streamdet.training.trainer import TrainConfig, train

TINY = get_preset("tiny")
SIZE = (TINY.image.width_px, TINY.image.height_px)


@pytest.fixture(scope="module")
def store(tiny_train_data, tmp_path_factory):
    return build_store(tiny_train_data, "train", SIZE, cache_dir=tmp_path_factory.mktemp("cache"))


@pytest.fixture(scope="module")
def batch(store):
    ds = SliceDataset(store, TINY, DataConfig(num_slices=(8,), max_slices_per_sample=3), seed=2)
    return Collator(TINY)([ds[0], ds[1], ds[2]])


# ---- the draw ---------------------------------------------------------------------------------------------------------
@settings(max_examples=60, deadline=None)
@given(b=st.integers(0, 40), j=st.integers(1, 8), p=st.floats(0.0, 0.99), seed=st.integers(0, 2**31))
def test_draw_shape_and_at_least_one_drop_when_dropping(b, j, p, seed):
    keep = draw_camera_keep(b, j, p, torch.Generator().manual_seed(seed))
    assert keep.shape == (b, j) and keep.dtype == torch.bool
    # a sample either keeps every camera or loses 1..J of them: never "dropping" nothing
    lost = (~keep).sum(dim=1)
    assert ((lost >= 0) & (lost <= j)).all()


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("j", [1, 6])
def test_draw_matches_its_distribution(seed, j):
    p, n = 0.3, 20000
    keep = draw_camera_keep(n, j, p, torch.Generator().manual_seed(seed)).numpy()
    lost = (~keep).sum(axis=1)
    share = (lost > 0).mean()
    assert abs(share - p) < 4 * np.sqrt(p * (1 - p) / n)
    # k uniform in 1..J among the samples that lose cameras, and every camera as likely as any other
    counts = np.bincount(lost[lost > 0], minlength=j + 1)[1:]
    expected = (lost > 0).sum() / j
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected))
    per_camera = (~keep[lost > 0]).mean(axis=0)
    assert np.allclose(per_camera, per_camera.mean(), atol=0.03)
    assert abs(per_camera.mean() - (j + 1) / (2 * j)) < 0.02  # E[k] / J


def test_draw_is_reproducible_and_p0_keeps_everything():
    a = draw_camera_keep(50, 6, 0.5, torch.Generator().manual_seed(7))
    b = draw_camera_keep(50, 6, 0.5, torch.Generator().manual_seed(7))
    assert torch.equal(a, b)
    assert draw_camera_keep(50, 6, 0.0, torch.Generator().manual_seed(7)).all()
    assert draw_camera_keep(0, 6, 0.5).shape == (0, 6)


@pytest.mark.parametrize("bad", [-0.1, 1.0, 1.5, float("nan"), float("inf"), True, "0.3", None])
def test_bad_probability_is_refused_quoting_it(bad):
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        check_camera_dropout(bad)
    with pytest.raises(ValueError, match="camera_dropout"):
        TrainConfig(preset="tiny", steps=1, camera_dropout=bad)


def test_draw_refuses_no_cameras():
    with pytest.raises(ValueError, match="num_cameras"):
        draw_camera_keep(3, 0, 0.5)


# ---- the lift -----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(3))
def test_dropped_cameras_lift_as_zero_features(batch, seed):
    torch.manual_seed(seed)
    model = TrainingModel(build_detector(TINY)).eval()
    det = model.detector
    b = batch.num_samples
    j = batch.images.shape[0] // b
    keep = draw_camera_keep(b, j, 0.9, torch.Generator().manual_seed(seed))
    with torch.no_grad():
        got = model.image_bev(batch, camera_keep=keep)
        feats = det.image_encoder(batch.images)  # the naive reference: zero the dropped rows by hand
        for row, kept in enumerate(keep.reshape(-1).tolist()):
            if not kept:
                feats[row] = 0
        ref = det.lifter(feats, batch.lut_index, batch.lut_weight).index_select(0, batch.map_source)
        assert torch.equal(model.image_bev(batch, camera_keep=torch.ones(b, j, dtype=torch.bool)), model.image_bev(batch))
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-6)


def test_every_camera_dropped_is_the_lift_of_zero_features(batch):
    torch.manual_seed(0)
    model = TrainingModel(build_detector(TINY)).eval()
    det = model.detector
    keep = torch.zeros(batch.num_samples, batch.images.shape[0] // batch.num_samples, dtype=torch.bool)
    with torch.no_grad():
        got = model.image_bev(batch, camera_keep=keep)
        zeros = torch.zeros_like(det.image_encoder(batch.images))
        ref = det.lifter(zeros, batch.lut_index, batch.lut_weight).index_select(0, batch.map_source)
    torch.testing.assert_close(got, ref, rtol=0, atol=0)


def test_camera_keep_of_the_wrong_size_is_refused(batch):
    model = TrainingModel(build_detector(TINY)).eval()
    with pytest.raises(ValueError, match="camera_keep"):
        model.image_bev(batch, camera_keep=torch.ones(1, 2, dtype=torch.bool))


def test_image_class_loss_reads_only_samples_that_kept_every_camera(batch):
    torch.manual_seed(0)
    model = TrainingModel(build_detector(TINY), image_classifier=True).train()
    j = batch.images.shape[0] // batch.num_samples
    keep = torch.ones(batch.num_samples, j, dtype=torch.bool)
    keep[1, 2] = False  # sample 1 lost one camera
    _, (logits, labels) = model(batch, camera_keep=keep)
    whole = (batch.map_sample != 1)[:, None] & batch.mask
    assert logits.shape[0] == labels.shape[0] == int(whole.sum())
    assert torch.equal(labels, batch.label[whole])
    _, (logits_all, _) = model(batch)
    assert logits_all.shape[0] == int(batch.mask.sum())


def test_map_sample_names_each_maps_sample(store):
    ds = SliceDataset(store, TINY, DataConfig(num_slices=(8,), max_slices_per_sample=2), seed=0)
    items = [ds[0], ds[1]]
    batch = Collator(TINY)(items)
    per_sample = [sum(len(sl.quadrants) for sl in it.slices) for it in items]
    assert batch.map_sample.tolist() == [b for b, n in enumerate(per_sample) for _ in range(n)]


# ---- the trainer ----------------------------------------------------------------------------------------------------------
def _config(**kw) -> TrainConfig:
    base = dict(preset="tiny", steps=3, batch_size=2, lr=1e-3, log_every=1, checkpoint_every=100, seed=0, camera_dropout=0.6)
    return TrainConfig(**{**base, **kw})


def test_trainer_records_dropout_and_resumes_exactly(store, tmp_path):
    full = train(_config(image_class_weight=0.5), "unused", tmp_path / "full", store=store, echo=lambda m: None)
    assert full.steps_done == 3
    a = load_checkpoint(tmp_path / "full" / "last.pt")
    assert a["config"]["camera_dropout"] == 0.6
    part = train(_config(image_class_weight=0.5, max_minutes=1e-9), "unused", tmp_path / "part", store=store, echo=lambda m: None)
    assert part.stopped_early
    train(_config(image_class_weight=0.5), "unused", tmp_path / "resumed", resume=tmp_path / "part" / "last.pt",
          store=store, echo=lambda m: None)  # fmt: skip
    b = load_checkpoint(tmp_path / "resumed" / "last.pt")
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    plain = train(_config(camera_dropout=0.0), "unused", tmp_path / "plain", store=store, echo=lambda m: None)
    assert plain.steps_done == 3
    assert "camera_dropout" not in load_checkpoint(tmp_path / "plain" / "last.pt")["config"]  # older runs' configs unchanged


def test_dropout_without_the_image_lane_is_refused():
    with pytest.raises(ValueError, match="needs the image lane"):
        TrainConfig(preset="tiny", steps=1, use_image=False, camera_dropout=0.3)


@pytest.mark.parametrize("value", ["1", "-0.2", "nan"])
def test_cli_refuses_a_bad_dropout(tiny_train_data, tmp_path, value):
    r = CliRunner().invoke(train_main, ["--data", str(tiny_train_data), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                        "--steps", "1", "--camera-dropout", value])  # fmt: skip
    assert r.exit_code == 2 and "--camera-dropout" in r.output
