"""Dataset, collate and trainer on a tiny synthetic dataset with the tiny preset: batching vs per-sample
references, the loss going down, resume == uninterrupted run, the LiDAR-only switch, the CLI's bad input."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset
from streamdet.training.batching import Collator
from streamdet.training.checkpoint import load_checkpoint, load_weights, save_weights
from streamdet.training.cli import main as train_main
from streamdet.training.dataset import DataConfig, SliceDataset, build_store, class_balanced_indices
from streamdet.training.losses import CenterPointLoss, loss_terms
from streamdet.training.model import TrainingModel
from streamdet.training.trainer import TrainConfig, init_head_outputs, train

TINY = get_preset("tiny")
SIZE = (TINY.image.width_px, TINY.image.height_px)


@pytest.fixture(scope="module")
def data_dir(tiny_train_data) -> Path:
    assert SIZE == (128, 72)  # the shared dataset's image size (conftest)
    return tiny_train_data  # scenes 0, 1 train (4 samples), scene 2 val


@pytest.fixture(scope="module")
def store(data_dir, tmp_path_factory):
    return build_store(data_dir, "train", SIZE, cache_dir=tmp_path_factory.mktemp("cache"))


def test_store_cache_round_trip(data_dir, store, tmp_path):
    again = build_store(data_dir, "train", SIZE, cache_dir=tmp_path)  # writes a cache
    cached = build_store(data_dir, "train", SIZE, cache_dir=tmp_path)  # reads it back (memory-mapped)
    assert isinstance(cached.points, np.memmap) and not isinstance(again.points, np.memmap)
    assert len(store) == 4 and cached.tokens == store.tokens
    for name in ("points", "boxes", "labels", "num_lidar_pts", "images", "point_offsets"):
        assert np.array_equal(np.asarray(getattr(cached, name)), getattr(store, name)), name
    assert [r.sha256() for r in cached.rigs] == [r.sha256() for r in store.rigs]
    assert build_store(data_dir, "train", None).images is None
    with pytest.raises(ValueError, match="split 'test'"):
        build_store(data_dir, "test", None)


@pytest.mark.parametrize("seed", range(2))
def test_item_slices_pillars_and_targets(store, seed):
    ds = SliceDataset(store, TINY, DataConfig(num_slices=(8, 4), max_slices_per_sample=3), seed=seed)
    for i in range(len(ds)):
        item = ds[i]
        assert len(item.slices) == 3 and item.images.shape == (6, SIZE[1], SIZE[0], 3)
        n = item.slices[0].num_slices
        assert n in (8, 4) and [s.index for s in item.slices] == sorted(s.index for s in item.slices)
        for sl in item.slices:
            assert len(sl.quadrants) == 1 and len(sl.targets) == 1 and sl.camera_names
            pts = sl.pillars
            if pts.num_pillars:  # slice index feature is the slice's own k
                assert np.all(pts.features[..., 5][pts.mask > 0] == sl.index)
        again = ds[i]  # same (seed, epoch, index): same item
        assert [s.index for s in again.slices] == [s.index for s in item.slices]
    ds.set_epoch(1)
    picks = {tuple(s.index for s in ds[i].slices) for i in range(len(ds))}
    assert picks  # another epoch draws again (no assertion on which: it is random)


@pytest.fixture
def one_torch_thread():
    """torch on one intra-op thread for the test: tiny tensors gain nothing from a second, and on a busy machine the
    threads wait for each other (measured on 2 cores with one busy loop: 0.9 s with two threads, 0.6 s with one)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_collate_matches_per_sample_forward(store, one_torch_thread):
    """The batched image lane (stacked images, shifted LUT rows, one sentinel, one lift per sample and quadrant shared
    by that quadrant's two slices) and pillar offsets give each slice map exactly what a per-slice StreamDetector
    call gives (eval mode: no batch statistics).

    The per-slice call is image_bev (encoder, then lifter) then slice_net: the reference encodes each sample's images
    once and lifts each of its quadrants once (the same inputs give the same outputs), and is checked against the
    whole call itself, bit for bit, on each sample's first slice."""
    torch.manual_seed(0)
    det = build_detector(TINY).eval()
    model = TrainingModel(det).eval()
    ds = SliceDataset(store, TINY, DataConfig(num_slices=(8,)))
    items = [ds[0], ds[2]]
    collate = Collator(TINY, "all")
    batch = collate(items)
    assert batch.num_maps == 16 and batch.lut_index.shape[0] == 8  # 4 quadrant lifts per sample
    with torch.no_grad():
        maps = model(batch)[0][0]
    row = whole = lifts = 0
    for item in items:
        lut = collate.lut(item.rig)
        images = torch.from_numpy(item.images)
        with torch.no_grad():
            feats = det.image_encoder(images)
        bevs: dict[tuple[int, ...], torch.Tensor] = {}
        for sl in item.slices:
            idx, w = lut.for_quadrants(sl.quadrants)
            idx, w = torch.from_numpy(idx.astype(np.int64)), torch.from_numpy(w)
            pil = sl.pillars
            pillars = (torch.from_numpy(pil.features), torch.from_numpy(pil.mask), torch.from_numpy(pil.index))
            with torch.no_grad():
                if sl.quadrants not in bevs:
                    bevs[sl.quadrants] = det.lifter(feats, idx, w)
                    lifts += 1
                ref = det.slice_net(*pillars, bevs[sl.quadrants])
                if sl is item.slices[0]:  # the reference is the per-slice call
                    for a, b in zip(ref, det(images, idx, w, *pillars), strict=True):
                        torch.testing.assert_close(a, b, rtol=0, atol=0)
                    whole += 1
            for got, want in zip(maps, ref, strict=True):
                torch.testing.assert_close(got[row : row + 1], want, rtol=1e-4, atol=1e-4)
            row += 1
    assert row == 16 and whole == 2 and lifts == 8  # every slice map; every quadrant of both samples


def test_overlapping_cameras_equal_zero_features(store):
    torch.manual_seed(0)
    det = build_detector(TINY).eval()
    ds = SliceDataset(store, TINY, DataConfig(num_slices=(8,), max_slices_per_sample=2), seed=1)
    item = ds[1]
    collate = Collator(TINY, "overlapping")
    batch = collate([item])
    assert batch.lut_index.shape[0] == 2  # one lift per slice map
    lut = collate.lut(item.rig)
    with torch.no_grad():
        bev = TrainingModel(det).image_bev(batch)
        feats = det.image_encoder(torch.from_numpy(item.images))
        for i, sl in enumerate(item.slices):
            zeroed = feats.clone()
            off = [j for j, name in enumerate(item.rig.names) if name not in sl.camera_names]
            zeroed[off] = 0
            idx, w = lut.for_quadrants(sl.quadrants)
            ref = det.lifter(zeroed, torch.from_numpy(idx.astype(np.int64)), torch.from_numpy(w))
            torch.testing.assert_close(bev[i : i + 1], ref, rtol=1e-5, atol=1e-5)


def test_pillar_index_offsets(store):
    ds = SliceDataset(store, dataclasses.replace(TINY, use_image=False), DataConfig(num_slices=(4,)))
    items = [ds[0], ds[1]]
    batch = Collator(dataclasses.replace(TINY, use_image=False))(items)
    cells = TINY.grid.quadrant_nx * TINY.grid.quadrant_ny
    expect = np.concatenate([sl.pillars.index + m * cells for m, sl in enumerate(s for it in items for s in it.slices)])
    assert np.array_equal(batch.pillar_index.numpy(), expect)
    assert batch.images is None and batch.map_source is None and batch.num_maps == 8


def test_class_balanced_indices():
    sets = [np.array([0]), np.array([0]), np.array([0]), np.array([0, 7]), np.array([], np.int64)]
    idx = class_balanced_indices(sets, seed=0)
    counts = np.bincount(idx, minlength=5)
    assert counts[4] == 0 and counts[3] > counts[:3].max()  # the only pedestrian sample is drawn most
    with pytest.raises(ValueError, match="at least one sample"):
        class_balanced_indices([np.array([], np.int64)], 0)


def test_training_steps_reduce_loss_on_a_fixed_batch(store):
    torch.manual_seed(0)
    model = TrainingModel(build_detector(TINY)).train()
    batch = Collator(TINY)([SliceDataset(store, TINY)[0]])
    init_head_outputs(model.detector)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    crit = CenterPointLoss()
    losses = []
    for _ in range(8):
        terms = loss_terms(model(batch)[0], model.task_classes, batch.heatmap, batch.index, batch.mask, batch.label, batch.box)
        loss, _ = crit(terms)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.7 * losses[0], losses


def _config(**kw) -> TrainConfig:
    base = dict(preset="tiny", steps=3, batch_size=1, lr=1e-3, log_every=1, checkpoint_every=100, seed=0)
    return TrainConfig(**{**base, **kw})


def test_resume_continues_exactly(store, tmp_path):
    full = train(_config(), "unused", tmp_path / "full", store=store, echo=lambda m: None)
    assert full.steps_done == 3 and not full.stopped_early
    # The same plan cut short: the time limit stops it after its first step (schedule unchanged), then resume.
    part = train(_config(max_minutes=1e-9), "unused", tmp_path / "part", store=store, echo=lambda m: None)
    assert part.stopped_early and part.steps_done == 1
    resumed = train(_config(), "unused", tmp_path / "resumed", resume=tmp_path / "part" / "last.pt", store=store,
                    echo=lambda m: None)  # fmt: skip
    assert resumed.steps_done == 3
    a = load_checkpoint(tmp_path / "full" / "last.pt")
    b = load_checkpoint(tmp_path / "resumed" / "last.pt")
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert a["scheduler"]["step"] == b["scheduler"]["step"] == 3 and a["step"] == 3
    lines = (tmp_path / "full" / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == 3 and '"samples_per_s"' in lines[0]


def test_max_minutes_counts_this_invocation_not_the_whole_run(store, tmp_path):
    # A run split over sessions: the first part already trained for "a day"; resumed with a limit of an hour, the
    # limit is this invocation's, so the plan finishes instead of stopping after one step.
    part = train(_config(max_minutes=1e-9), "unused", tmp_path / "part", store=store, echo=lambda m: None)
    assert part.stopped_early and part.steps_done == 1
    ckpt = load_checkpoint(tmp_path / "part" / "last.pt")
    ckpt["scheduler"]["elapsed_s"] = 86_400.0
    torch.save(ckpt, tmp_path / "part" / "last.pt")
    resumed = train(_config(max_minutes=60.0), "unused", tmp_path / "resumed", resume=tmp_path / "part" / "last.pt",
                    store=store, echo=lambda m: None)  # fmt: skip
    assert resumed.steps_done == 3 and not resumed.stopped_early


def test_weights_file_loads_in_export_and_half_precision(store, tmp_path):
    from streamdet.export.weights import load_detector

    train(_config(steps=1), "unused", tmp_path / "run", store=store, echo=lambda m: None)
    det, source = load_detector(TINY, tmp_path / "run" / "model.pt")  # the export engineer's loader
    own, preset = load_weights(tmp_path / "run" / "model.pt")
    assert preset == TINY and source.checkpoint is not None
    for k, v in own.state_dict().items():
        assert torch.equal(v, det.state_dict()[k])
    save_weights(tmp_path / "half.pt", TINY, own, half=True)
    back, _ = load_weights(tmp_path / "half.pt")
    assert (tmp_path / "half.pt").stat().st_size < 0.6 * (tmp_path / "run" / "model.pt").stat().st_size
    w = back.state_dict()["slice_net.pillar_net.linear.weight"]
    assert w.dtype == torch.float32
    torch.testing.assert_close(w, own.state_dict()["slice_net.pillar_net.linear.weight"], rtol=1e-3, atol=1e-3)


def test_cli_lidar_only_switch(data_dir, tmp_path):
    out = tmp_path / "lidar"
    res = CliRunner().invoke(train_main, ["--data", str(data_dir), "--out", str(out), "--preset", "tiny", "--steps", "2",
                                          "--no-image", "--num-slices", "8,4", "--cache-dir", str(tmp_path / "c")])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "LiDAR only" in res.output and "samples/s" in res.output
    ckpt = load_checkpoint(out / "last.pt")
    assert ckpt["preset"]["use_image"] is False and ckpt["step"] == 2
    assert not any(k.startswith(("image_encoder", "lifter")) for k in ckpt["model"])
    det, preset = load_weights(out / "model.pt")
    assert det.image_encoder is None and not preset.use_image


@pytest.mark.parametrize(
    "args, message",
    [
        (["--num-slices", "6"], "multiple of 4"),
        (["--num-slices", "x"], "slice counts"),
        (["--steps", "0"], "--steps"),
        (["--resume", "/nonexistent/last.pt"], "does not exist"),
        (["--preset", "huge"], "huge"),
        (["--version", "v9"], "no table folder"),
    ],
)
def test_cli_bad_input(data_dir, tmp_path, args, message):
    res = CliRunner().invoke(train_main, ["--data", str(data_dir), "--out", str(tmp_path / "o"), "--preset", "tiny", *args])
    assert res.exit_code != 0
    assert message in res.output and "Traceback" not in res.output


def test_training_gives_the_process_its_subnormal_floats_back(store, tmp_path):
    train(_config(steps=1), "unused", tmp_path / "run", store=store, echo=lambda m: None)
    tiny = float("1e-310")  # subnormal: flushed to 0 while denormals are flushed
    assert tiny * 1.0 > 0.0 and torch.tensor([1e-40]).mul(1.0).item() > 0.0


def test_cli_resume_of_weights_only_file(data_dir, tmp_path, store):
    train(_config(steps=1), "unused", tmp_path / "run", store=store, echo=lambda m: None)
    res = CliRunner().invoke(train_main, ["--data", str(data_dir), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                          "--steps", "2", "--resume", str(tmp_path / "run" / "model.pt"),
                                          "--cache-dir", str(tmp_path / "c")])  # fmt: skip
    assert res.exit_code != 0 and "weights only" in res.output


def test_train_config_validation():
    for kwargs, field in [({"steps": 0}, "steps"), ({"lr": -1.0}, "lr"), ({"amp": "int8"}, "amp"), ({"pct_start": 1.0}, "pct_start"),
                          ({"workers": -1}, "workers"), ({"max_minutes": 0.0}, "max_minutes")]:  # fmt: skip
        with pytest.raises(ValueError, match=field):
            _config(**kwargs)
    with pytest.raises(ValueError, match="camera_mode"):
        DataConfig(camera_mode="some")
    with pytest.raises(ValueError, match="multiple of 4"):
        DataConfig(num_slices=(6,))


def test_init_starts_from_weights_with_a_fresh_schedule(store, tmp_path):
    first = train(_config(steps=1), "unused", tmp_path / "first", store=store, echo=lambda m: None)
    start = load_checkpoint(first.weights)["model"]
    # another seed draws other initial weights: with init, the run must start from first's instead
    other = dataclasses.replace(_config(steps=1), seed=1)
    second = train(other, "unused", tmp_path / "second", init=first.weights, store=store, echo=lambda m: None)
    fresh = train(other, "unused", tmp_path / "fresh", store=store, echo=lambda m: None)
    after = load_checkpoint(second.weights)
    assert after["meta"]["init"] == str(first.weights)
    assert load_checkpoint(tmp_path / "second" / "last.pt")["scheduler"]["step"] == 1  # a fresh schedule
    key = "slice_net.pillar_net.linear.weight"
    near = (after["model"][key] - start[key]).abs().max()
    far = (load_checkpoint(fresh.weights)["model"][key] - start[key]).abs().max()
    assert near < 0.1 * far


def test_init_refuses_other_preset_and_resume_together(store, tmp_path):
    first = train(_config(steps=1), "unused", tmp_path / "first", store=store, echo=lambda m: None)
    with pytest.raises(ValueError, match="not both"):
        train(_config(steps=1), "unused", tmp_path / "x", init=first.weights, resume=tmp_path / "first" / "last.pt",
              store=store, echo=lambda m: None)  # fmt: skip
    obj = load_checkpoint(first.weights)
    obj["preset"] = dict(obj["preset"], name="other", channels=obj["preset"]["channels"] * 2)  # no part alike
    torch.save(obj, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="another preset.*shares none"):
        train(_config(steps=1), "unused", tmp_path / "y", init=tmp_path / "other.pt", store=store, echo=lambda m: None)


def test_init_from_another_preset_takes_the_parts_configured_alike(store, tmp_path):
    """A checkpoint whose slice net differs (another BEV encoder): the camera lane and the pillar net come from it,
    the BEV encoder and head from the seed; tensors of a part alike in config but not in shape are refused."""
    torch.manual_seed(11)
    source = build_detector(get_preset("tiny"))
    obj = {"preset": dict(get_preset("tiny").to_dict(), name="wider"), "model": source.state_dict()}
    obj["preset"]["bev"] = dict(obj["preset"]["bev"], num_filters=[16, 32])  # its slice net is another one
    torch.save(obj, tmp_path / "wider.pt")
    cfg = dataclasses.replace(_config(steps=1, lr=1e-9), seed=3)  # lr ~ 0: the weights stay where they started
    said = []
    run = train(cfg, "unused", tmp_path / "run", init=tmp_path / "wider.pt", store=store, echo=said.append)
    fresh = train(cfg, "unused", tmp_path / "fresh", store=store, echo=lambda m: None)
    got, ref = load_checkpoint(run.weights)["model"], load_checkpoint(fresh.weights)["model"]
    src = source.state_dict()
    params = dict(source.named_parameters())  # BatchNorm's running statistics move in the one step; weights do not
    for part in ("image_encoder.", "lifter.", "slice_net.pillar_net."):
        keys = [k for k in params if k.startswith(part)]
        assert keys, part
        for k in keys:
            torch.testing.assert_close(got[k], src[k], atol=1e-6, rtol=0)
    bev = [k for k in params if k.startswith("slice_net.bev_encoder.")]
    assert bev
    for k in bev:  # the seed's own, not the checkpoint's
        torch.testing.assert_close(got[k], ref[k], atol=1e-6, rtol=0)
    assert not all(torch.allclose(got[k], src[k]) for k in bev)
    assert any("image_encoder, lifter, slice_net.pillar_net" in m and "'wider'" in m for m in said)
    obj["model"]["lifter." + next(k[len("lifter."):] for k in src if k.startswith("lifter.") and src[k].ndim > 1)] = torch.zeros(1, 2)
    torch.save(obj, tmp_path / "edited.pt")
    with pytest.raises(ValueError, match="edited.pt"):
        train(cfg, "unused", tmp_path / "edited", init=tmp_path / "edited.pt", store=store, echo=lambda m: None)


def test_init_from_an_image_encoder_keeps_the_seeded_rest(store, tmp_path):
    """streamdet-train-image's encoder.pt as --init: the encoder's weights, every other weight the seed's own."""
    torch.manual_seed(7)
    encoder = build_detector(get_preset("tiny")).image_encoder
    torch.save(encoder.state_dict(), tmp_path / "encoder.pt")
    cfg = dataclasses.replace(_config(steps=1, lr=1e-9), seed=3)  # lr ~ 0: the weights stay where they started
    run = train(cfg, "unused", tmp_path / "run", init=tmp_path / "encoder.pt", store=store, echo=lambda m: None)
    fresh = train(cfg, "unused", tmp_path / "fresh", store=store, echo=lambda m: None)
    got, ref = load_checkpoint(run.weights)["model"], load_checkpoint(fresh.weights)["model"]
    key = "image_encoder.backbone.conv1.weight"
    torch.testing.assert_close(got[key], encoder.state_dict()["backbone.conv1.weight"], atol=1e-6, rtol=0)
    assert not torch.allclose(got[key], ref[key])
    torch.testing.assert_close(got["slice_net.pillar_net.linear.weight"], ref["slice_net.pillar_net.linear.weight"])
    torch.save({"backbone.conv1.weight": torch.zeros(1)}, tmp_path / "wrong.pt")
    with pytest.raises(ValueError, match="does not fit the detector's image encoder"):
        train(cfg, "unused", tmp_path / "wrong", init=tmp_path / "wrong.pt", store=store, echo=lambda m: None)
