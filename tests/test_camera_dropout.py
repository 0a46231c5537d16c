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
from streamdet.training.camera_dropout import check_camera_dropout, draw_camera_keep, drops_cameras, step_generator, stored_statistics
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
@given(b=st.integers(0, 40), j=st.integers(1, 8), seed=st.integers(0, 2**70))
def test_every_sample_of_a_dropping_step_loses_one_to_all_cameras(b, j, seed):
    keep = draw_camera_keep(b, j, step_generator(seed, 3))
    assert keep.shape == (b, j) and keep.dtype == torch.bool
    lost = (~keep).sum(dim=1)
    assert ((lost >= 1) & (lost <= j)).all()


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("j", [1, 6])
def test_draw_matches_its_distribution(seed, j):
    n = 20000
    keep = draw_camera_keep(n, j, torch.Generator().manual_seed(seed)).numpy()
    lost = (~keep).sum(axis=1)
    # k uniform in 1..J, and every camera as likely as any other
    counts = np.bincount(lost, minlength=j + 1)[1:]
    expected = n / j
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected))
    per_camera = (~keep).mean(axis=0)
    assert np.allclose(per_camera, per_camera.mean(), atol=0.03)
    assert abs(per_camera.mean() - (j + 1) / (2 * j)) < 0.02  # E[k] / J


@pytest.mark.parametrize("p", [0.0, 0.3, 0.7])
def test_a_share_p_of_the_steps_drop(p):
    steps = 4000
    share = np.mean([drops_cameras(p, step_generator(5, s)) for s in range(steps)])
    assert abs(share - p) < 4 * np.sqrt(max(p * (1 - p), 1e-9) / steps) + 1e-9


def test_the_generators_are_reproducible_for_any_seed():
    a = draw_camera_keep(50, 6, step_generator(7, 11, 0))
    assert torch.equal(a, draw_camera_keep(50, 6, step_generator(7, 11, 0)))
    assert not torch.equal(a, draw_camera_keep(50, 6, step_generator(7, 11, 1)))  # processes draw apart
    draw_camera_keep(3, 6, step_generator(2**80, 10**12, 3))  # no overflow for a huge seed or step
    assert draw_camera_keep(0, 6).shape == (0, 6)


@pytest.mark.parametrize("bad", [-0.1, 1.0, 1.5, float("nan"), float("inf"), True, "0.3", None])
def test_bad_probability_is_refused_quoting_it(bad):
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        check_camera_dropout(bad)
    with pytest.raises(ValueError, match="camera_dropout"):
        TrainConfig(preset="tiny", steps=1, camera_dropout=bad)


def test_draw_refuses_no_cameras():
    with pytest.raises(ValueError, match="num_cameras"):
        draw_camera_keep(3, 0)


# ---- the lift -----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(3))
def test_dropped_cameras_lift_as_zero_features(batch, seed):
    torch.manual_seed(seed)
    model = TrainingModel(build_detector(TINY)).eval()
    det = model.detector
    b = batch.num_samples
    j = batch.images.shape[0] // b
    keep = draw_camera_keep(b, j, torch.Generator().manual_seed(seed))
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


@pytest.mark.parametrize("preset", ["tiny", "small_v3_swift"])
def test_a_dropping_step_normalises_with_the_stored_statistics_and_keeps_them(store, tiny_train_data, tmp_path_factory, preset):
    """In training mode a dropping step's forward equals the eval-mode forward (what the exported graphs compute), its
    BatchNorm statistics stay as they were, and every module gets its mode back."""
    torch.manual_seed(0)
    p = get_preset(preset)
    size = (p.image.width_px, p.image.height_px)
    here = store if size == SIZE else build_store(tiny_train_data, "train", size, cache_dir=tmp_path_factory.mktemp("c"))
    ds = SliceDataset(here, p, DataConfig(num_slices=(8,), max_slices_per_sample=2), seed=2)
    b = Collator(p)([ds[0]])
    model = TrainingModel(build_detector(p)).train()
    keep = torch.ones(1, b.images.shape[0], dtype=torch.bool)
    keep[0, 1] = False
    before = {k: v.clone() for k, v in model.state_dict().items()}
    norm = model.detector.slice_net.image_bev_norm
    seen = []
    if norm is not None:
        norm.register_forward_pre_hook(lambda m, args: seen.append(m.training))
    with torch.no_grad():
        got = model.image_bev(b, camera_keep=keep)
        model(b, camera_keep=keep)
        model.eval()
        want = model.image_bev(b, camera_keep=keep)
        model.train()
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)  # the exported graphs' normalisation
    assert seen == ([False] if norm is not None else [])  # the forward of the dropping step
    after = model.state_dict()
    cam = [k for k in before if k.startswith(("detector.image_encoder", "detector.lifter", "detector.slice_net.image_bev_norm"))
           and ("running" in k or "num_batches" in k or k.endswith("_ms"))]  # fmt: skip
    assert cam and all(torch.equal(before[k], after[k]) for k in cam)
    assert all(m.training for m in model.modules())
    with torch.no_grad():
        model(b)  # a step without dropout updates them as before
    assert any(not torch.equal(before[k], model.state_dict()[k]) for k in cam)


def test_stored_statistics_restores_mixed_modes():
    net = torch.nn.Sequential(torch.nn.BatchNorm1d(2), torch.nn.Sequential(torch.nn.BatchNorm1d(2)))
    net.train()
    net[1].eval()
    with stored_statistics([net, None]):
        assert not any(m.training for m in net.modules())
    assert net.training and net[0].training and not net[1].training and not net[1][0].training


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
    base = dict(preset="tiny", steps=4, batch_size=2, lr=1e-3, log_every=1, checkpoint_every=100, seed=2, camera_dropout=0.6)
    return TrainConfig(**{**base, **kw})


def test_trainer_records_dropout_and_resumes_exactly(store, tmp_path):
    full = train(_config(image_class_weight=0.5), "unused", tmp_path / "full", store=store, echo=lambda m: None)
    assert full.steps_done == 4
    drops = [drops_cameras(0.6, step_generator(2, step)) for step in range(5)]
    assert any(drops[:4]) and any(drops[1:]) and not all(drops)  # the run drops in some steps, not in all
    a = load_checkpoint(tmp_path / "full" / "last.pt")
    assert a["config"]["camera_dropout"] == 0.6
    part = train(_config(image_class_weight=0.5, max_minutes=1e-9), "unused", tmp_path / "part", store=store, echo=lambda m: None)
    assert part.stopped_early
    train(_config(image_class_weight=0.5), "unused", tmp_path / "resumed", resume=tmp_path / "part" / "last.pt",
          store=store, echo=lambda m: None)  # fmt: skip
    b = load_checkpoint(tmp_path / "resumed" / "last.pt")
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    plain = train(_config(image_class_weight=0.5, camera_dropout=0.0), "unused", tmp_path / "plain", store=store,
                  echo=lambda m: None)  # fmt: skip
    assert plain.steps_done == 4
    c = load_checkpoint(tmp_path / "plain" / "last.pt")
    assert "camera_dropout" not in c["config"]  # older runs' configs unchanged
    assert any(not torch.equal(a["model"][k], c["model"][k]) for k in a["model"])  # the drops changed the run


def test_dropout_without_the_image_lane_is_refused():
    with pytest.raises(ValueError, match="needs the image lane"):
        TrainConfig(preset="tiny", steps=1, use_image=False, camera_dropout=0.3)


@pytest.mark.parametrize("value", ["1", "-0.2", "nan"])
def test_cli_refuses_a_bad_dropout(tiny_train_data, tmp_path, value):
    r = CliRunner().invoke(train_main, ["--data", str(tiny_train_data), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                        "--steps", "1", "--camera-dropout", value])  # fmt: skip
    assert r.exit_code == 2 and "--camera-dropout" in r.output


def test_a_resume_with_another_dropout_says_so(store, tmp_path):
    train(_config(max_minutes=1e-9), "unused", tmp_path / "part", store=store, echo=lambda m: None)
    said = []
    train(_config(camera_dropout=0.2), "unused", tmp_path / "resumed", resume=tmp_path / "part" / "last.pt", store=store,
          echo=said.append)  # fmt: skip
    assert any("camera_dropout 0.2; it was trained with 0.6" in line for line in said)
