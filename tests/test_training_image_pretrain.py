"""Image pretraining on the synthetic masks (training/image_pretrain.py): data, mIoU against a naive count, resume."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from streamdet.core.classes import NUM_CLASSES
from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset
from streamdet.models.seg_head import ImageSegmenter, SegHead
from streamdet.training.checkpoint import load_weights
from streamdet.training.image_pretrain import (
    IGNORE,
    NUM_LABELS,
    PretrainConfig,
    build_segmenter,
    class_weights,
    confusion,
    load_encoder_weights,
    load_masked_images,
    miou_from_confusion,
    pretrain,
    pretrain_preset,
)
from streamdet.training.image_pretrain_cli import main


def _naive_miou(pred: np.ndarray, labels: np.ndarray) -> float:
    ious = []
    for c in range(1, NUM_LABELS):
        tp = fp = fn = 0
        present = False
        for p, t in zip(pred.ravel().tolist(), labels.ravel().tolist()):
            if t == IGNORE:
                continue
            present |= t == c
            tp += p == c and t == c
            fp += p == c and t != c
            fn += p != c and t == c
        if present:
            ious.append(tp / (tp + fp + fn))
    return float(np.mean(ious)) if ious else math.nan


@pytest.mark.parametrize("seed", range(4))
def test_miou_matches_a_naive_pixel_count(seed):
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 4, (2, 5, 7)).astype(np.uint8)
    labels[rng.random(labels.shape) < 0.2] = IGNORE
    pred = rng.integers(0, 5, labels.shape)
    got = miou_from_confusion(confusion(pred, labels))["mIoU"]
    assert got == pytest.approx(_naive_miou(pred, labels))


def test_miou_of_nothing_is_nan_and_perfect_is_one():
    labels = np.full((3, 3), IGNORE, np.uint8)
    assert math.isnan(miou_from_confusion(confusion(np.zeros((3, 3)), labels))["mIoU"])
    labels = np.array([[0, 1], [2, 0]], np.uint8)
    assert miou_from_confusion(confusion(labels, labels))["mIoU"] == 1.0


def test_masked_images_and_class_weights(tiny_synth_data):
    size = (64, 36)
    data = load_masked_images(tiny_synth_data, None, size, range_m=30.0)
    assert data.images.shape[1:] == (36, 64, 3) and data.labels.shape == data.images.shape[:3]
    assert data.labels.max() <= NUM_CLASSES
    ignored = data.eval_labels == IGNORE
    assert np.all(data.labels[ignored] > 0)  # only object pixels are ever ignored (the far ones)
    assert np.array_equal(data.labels[~ignored], data.eval_labels[~ignored])
    near = load_masked_images(tiny_synth_data, None, size, range_m=1e-3)
    assert np.all(near.eval_labels[near.labels > 0] == IGNORE)
    w = class_weights(data.labels, PretrainConfig(preset="tiny"))
    assert w.shape == (NUM_LABELS,) and w[0] == 1.0 and torch.all(w[1:] >= 1.0)


def test_images_of_another_aspect_than_the_cameras_are_refused(tiny_synth_data):
    """The rule of streamdet-train and the runtime (check_rig_fits): a resize to another aspect would distort them."""
    with pytest.raises(ValueError, match=r"dataset .*, sample \S+: its cameras do not fit the 64x48 images"):
        load_masked_images(tiny_synth_data, None, (64, 48), 30.0)


def test_missing_mask_is_named(tiny_synth_data, tmp_path):
    import shutil

    copy = tmp_path / "d"
    shutil.copytree(tiny_synth_data, copy)
    next(copy.glob("samples/CAM_FRONT/*.mask.npz")).unlink()
    with pytest.raises(FileNotFoundError, match="mask.npz is missing"):
        load_masked_images(copy, None, (64, 36), 30.0)


def test_pretrain_resumes_and_its_weights_load_into_the_detector(tiny_synth_data, tmp_path):
    # a 4-step schedule cut at step 2, then resumed to its end (with other evaluation and checkpoint intervals,
    # which a resume may change; another --steps it may not: training/image_pretrain.py PRETRAIN_RESUME_OPTIONS)
    cfg = PretrainConfig(preset="tiny", steps=4, batch_size=2, eval_every=1, checkpoint_every=1, warmup_steps=1, stop_at_step=2)
    first = pretrain(cfg, tiny_synth_data, tmp_path, splits=(None, None), echo=lambda s: None)
    assert first["step"] == 2 and 0.0 <= first["mIoU"] <= 1.0 and not first["finished"]
    cfg4 = PretrainConfig(preset="tiny", steps=4, batch_size=2, eval_every=10, checkpoint_every=10, warmup_steps=1)
    again = pretrain(cfg4, tiny_synth_data, tmp_path, resume=tmp_path / "last.pt", splits=(None, None), echo=lambda s: None)
    assert again["step"] == 4 and again["finished"]
    lines = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert any("val_mIoU" in x for x in lines)
    det = build_detector(get_preset("tiny"))
    load_encoder_weights(det, tmp_path / "encoder.pt")
    init, preset = load_weights(tmp_path / "detector_init.pt")
    assert preset == get_preset("tiny")
    enc = torch.load(tmp_path / "encoder.pt", weights_only=True)
    for k, v in init.image_encoder.state_dict().items():
        torch.testing.assert_close(v, enc[k])
    with pytest.raises(ValueError, match="does not fit"):
        load_encoder_weights(build_detector(get_preset("small")), tmp_path / "encoder.pt")


def test_max_minutes_stops_with_a_checkpoint(tiny_synth_data, tmp_path):
    cfg = PretrainConfig(preset="tiny", steps=50, batch_size=2, max_minutes=1e-9)
    out = pretrain(cfg, tiny_synth_data, tmp_path, splits=(None, None), echo=lambda s: None)
    assert out["step"] == 0 and not out["finished"] and (tmp_path / "last.pt").is_file()


def test_stop_at_step_cuts_the_schedule_where_resume_continues_it(tiny_synth_data, tmp_path):
    cut = PretrainConfig(preset="tiny", steps=4, batch_size=2, eval_every=10, checkpoint_every=10, warmup_steps=1, stop_at_step=2)
    out = pretrain(cut, tiny_synth_data, tmp_path / "cut", splits=(None, None), echo=lambda s: None)
    assert out["step"] == 2 and not out["finished"]
    whole = dataclasses.replace(cut, stop_at_step=None)
    resumed = pretrain(whole, tiny_synth_data, tmp_path / "cut", resume=tmp_path / "cut" / "last.pt", splits=(None, None),
                       echo=lambda s: None)  # fmt: skip
    straight = pretrain(whole, tiny_synth_data, tmp_path / "straight", splits=(None, None), echo=lambda s: None)
    assert resumed["step"] == straight["step"] == 4 and resumed["finished"]
    a = torch.load(tmp_path / "cut" / "encoder.pt", weights_only=True)
    b = torch.load(tmp_path / "straight" / "encoder.pt", weights_only=True)
    for k in b:
        torch.testing.assert_close(a[k], b[k])


@pytest.mark.parametrize("bad", [0, -1, True, 1.5])
def test_stop_at_step_refuses_non_positive_integers(bad):
    with pytest.raises(ValueError, match="stop_at_step"):
        PretrainConfig(preset="tiny", stop_at_step=bad)


def test_frozen_batch_preset_pretrains_with_batch_statistics_and_the_head_stays_out():
    v2 = get_preset("small_v2")
    assert pretrain_preset(v2).image.norm == "batch" and pretrain_preset(get_preset("small")) == get_preset("small")
    seg = build_segmenter(get_preset("tiny"))
    assert isinstance(seg, ImageSegmenter)
    assert not any(isinstance(m, SegHead) for m in build_detector(get_preset("tiny")).modules())
    with pytest.raises(ValueError, match="use_image=False"):
        build_segmenter(dataclasses.replace(get_preset("tiny"), use_image=False))


def test_seg_head_output_is_image_sized():
    seg = build_segmenter(get_preset("tiny")).eval()
    with torch.no_grad():
        out = seg(torch.randint(0, 255, (2, 36, 64, 3), dtype=torch.uint8))
    assert out.shape == (2, NUM_LABELS, 36, 64)


def test_cli_errors_are_one_line(tmp_path):
    res = CliRunner().invoke(main, ["--data", str(tmp_path), "--out", str(tmp_path / "o")])
    assert res.exit_code != 0 and "no table folder" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(main, ["--data", str(tmp_path), "--out", str(tmp_path / "o"), "--resume", str(tmp_path / "x.pt")])
    assert res.exit_code != 0


class _Payload:
    """What a hostile checkpoint would hold: unpickling it runs code (here: writes a marker file)."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_resume_never_unpickles_code(tiny_synth_data, tmp_path):
    marker = tmp_path / "ran"
    evil = tmp_path / "evil.pt"
    torch.save({"config": {"preset": "tiny"}, "step": 0, "payload": _Payload(str(marker))}, evil)
    cfg = PretrainConfig(preset="tiny", steps=1, batch_size=2, eval_every=1)
    with pytest.raises(ValueError, match="--resume checkpoint .*evil.pt cannot be read with weights_only=True"):
        pretrain(cfg, tiny_synth_data, tmp_path / "o", resume=evil, splits=(None, None), echo=lambda s: None)
    assert not marker.exists()
    torch.save([1, 2], evil)
    with pytest.raises(ValueError, match="not a streamdet-train-image last.pt"):
        pretrain(cfg, tiny_synth_data, tmp_path / "o", resume=evil, splits=(None, None), echo=lambda s: None)
