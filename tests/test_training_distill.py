"""Distillation (training/distill.py) and the frozen camera lane: the loss against a cell-by-cell reference, the
teacher's compatibility check, a frozen lane that does not move, one lift shared with the teacher, resume rules
and the CLI's refusals. The tiny preset on the shared tiny dataset (conftest)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from streamdet.models.detector import build_detector
from streamdet.models.presets import get_preset
from streamdet.training.checkpoint import load_checkpoint, save_weights
from streamdet.training.cli import main as train_main
from streamdet.training.dataset import build_store
from streamdet.training.distill import DistillConfig, Teacher, check_teacher, distill_loss, distill_sums
from streamdet.training.losses import DEFAULT_CODE_WEIGHTS
from streamdet.training.model import CAMERA_LANE, TrainingModel
from streamdet.training.trainer import TrainConfig, train

TINY = get_preset("tiny")
SIZE = (TINY.image.width_px, TINY.image.height_px)
CODES = torch.tensor(DEFAULT_CODE_WEIGHTS)


@pytest.fixture(scope="module")
def data_dir(tiny_train_data) -> Path:
    return tiny_train_data


@pytest.fixture(scope="module")
def store(data_dir, tmp_path_factory):
    return build_store(data_dir, "train", SIZE, cache_dir=tmp_path_factory.mktemp("cache"))


def _maps(gen: torch.Generator, q: int, classes: tuple[int, ...], h: int = 5, w: int = 6):
    """One task's HeadMaps: heatmap logits (Q, C_t, H, W) and the regression maps (2, 1, 3, 2, 2 channels)."""
    return (torch.randn(q, len(classes), h, w, generator=gen) * 3,) + tuple(torch.randn(q, c, h, w, generator=gen) for c in (2, 1, 3, 2, 2))


def _naive(student, teacher, min_score: float):
    """The two sums per task, cell by cell."""
    heat, box = [], []
    for s, t in zip(student, teacher):
        q, c, h, w = s[0].shape
        s_box, t_box = torch.cat(s[1:], 1), torch.cat(t[1:], 1)
        hs = bs = 0.0
        for i in range(q):
            for y in range(h):
                for x in range(w):
                    probs = [1 / (1 + math.exp(-float(t[0][i, k, y, x]))) for k in range(c)]
                    for k in range(c):
                        hs += (1 / (1 + math.exp(-float(s[0][i, k, y, x]))) - probs[k]) ** 2
                    top = max(probs)
                    if top >= min_score:
                        bs += top * sum(float(CODES[d]) * abs(float(s_box[i, d, y, x] - t_box[i, d, y, x])) for d in range(10))
        heat.append(hs)
        box.append(bs)
    return heat, box


@pytest.mark.parametrize("min_score", [0.0, 0.1, 0.6])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_distill_sums_match_a_cell_by_cell_reference(seed, min_score):
    gen = torch.Generator().manual_seed(seed)
    tasks = ((0,), (1, 2), (8, 9))
    student = [_maps(gen, 2, c) for c in tasks]
    teacher = [_maps(gen, 2, c) for c in tasks]
    heat, box = distill_sums(student, teacher, CODES, min_score)
    want_heat, want_box = _naive(student, teacher, min_score)
    torch.testing.assert_close(heat, torch.tensor(want_heat), rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(box, torch.tensor(want_box), rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("seed", [0, 1])
def test_distill_loss_is_zero_for_the_teacher_itself_and_normalised_by_objects(seed):
    gen = torch.Generator().manual_seed(seed)
    teacher = [_maps(gen, 3, (0, 1))]
    loss, parts = distill_loss(teacher, teacher, torch.tensor([4.0]), CODES, DistillConfig())
    assert float(loss) == 0.0 and set(parts) == {"distill_heatmap", "distill_box"}
    student = [_maps(gen, 3, (0, 1))]
    cfg = DistillConfig(heatmap_weight=2.0, box_weight=0.5)
    heat, box = distill_sums(student, teacher, CODES, cfg.min_teacher_score)
    for n in (0.0, 1.0, 5.0):  # no objects: divided by 1
        loss, _ = distill_loss(student, teacher, torch.tensor([n]), CODES, cfg)
        torch.testing.assert_close(loss, (2.0 * heat[0] + 0.5 * box[0]) / max(n, 1.0))


def test_distill_sums_of_empty_maps_and_mismatches():
    gen = torch.Generator().manual_seed(0)
    empty = [_maps(gen, 0, (0,))]
    heat, box = distill_sums(empty, empty, CODES, 0.1)
    assert heat.tolist() == [0.0] and box.tolist() == [0.0]
    with pytest.raises(ValueError, match="1 and 2 head tasks"):
        distill_sums(empty, empty * 2, CODES, 0.1)
    with pytest.raises(ValueError, match="differ in shape"):
        distill_sums([_maps(gen, 1, (0,))], [_maps(gen, 1, (0, 1))], CODES, 0.1)


@pytest.mark.parametrize("kw,message", [(dict(heatmap_weight=-1.0), "heatmap_weight"), (dict(box_weight=float("nan")), "box_weight"),
                                        (dict(min_teacher_score=1.0), "min_teacher_score")])  # fmt: skip
def test_distill_config_validation(kw, message):
    with pytest.raises(ValueError, match=message):
        DistillConfig(**kw)


def test_check_teacher_names_what_differs():
    check_teacher(get_preset("small_v3_lite"), get_preset("small_v3_thin"))  # other widths, same maps
    multi = dataclasses.replace(TINY, head=dataclasses.replace(TINY.head, multi_head=not TINY.head.multi_head))
    with pytest.raises(ValueError, match=r"teacher \(preset 'tiny'\).*student \(preset 'tiny'\).*head tasks"):
        check_teacher(multi, TINY)
    with pytest.raises(ValueError, match="grid"):
        check_teacher(get_preset("small"), TINY)
    with pytest.raises(ValueError, match="use_image"):
        check_teacher(dataclasses.replace(TINY, use_image=False), TINY)


def _config(**kw) -> TrainConfig:
    base = dict(preset="tiny", steps=2, batch_size=1, lr=1e-3, log_every=1, checkpoint_every=100, seed=0)
    return TrainConfig(**{**base, **kw})


def _weights(tmp_path: Path, seed: int, name: str) -> Path:
    torch.manual_seed(seed)
    path = tmp_path / name
    save_weights(path, TINY, build_detector(TINY))
    return path


def test_frozen_camera_lane_keeps_weights_and_statistics(store, tmp_path):
    init = _weights(tmp_path, 5, "init.pt")
    run = train(_config(freeze_camera_lane=True, lr=1e-2), "unused", tmp_path / "run", init=init, store=store, echo=lambda m: None)
    got, src = load_checkpoint(run.weights)["model"], load_checkpoint(init)["model"]
    lane = [k for k in src if k.startswith(tuple(p + "." for p in CAMERA_LANE))]
    assert lane and any("running_mean" in k for k in lane)
    for k in lane:  # weights and BatchNorm buffers
        assert torch.equal(got[k], src[k]), k
    assert not all(torch.equal(got[k], src[k]) for k in src if k.startswith("slice_net.bev_encoder.") and src[k].is_floating_point())
    model = TrainingModel(build_detector(TINY), freeze_camera_lane=True).train()
    assert not any(m.training for part in CAMERA_LANE for m in getattr(model.detector, part).modules())
    assert model.detector.slice_net.training
    with pytest.raises(ValueError, match="give init"):
        train(_config(freeze_camera_lane=True), "unused", tmp_path / "bad", store=store, echo=lambda m: None)
    with pytest.raises(ValueError, match="image lane"):
        TrainConfig(preset="tiny", steps=1, use_image=False, freeze_camera_lane=True)


def test_teacher_sharing_the_frozen_lane_gives_the_same_loss_as_lifting_twice(store, tmp_path, monkeypatch):
    """The one-lift path is an optimisation only: the first step's loss equals that of the same run in which the
    teacher lifts for itself (the same camera lane weights, both in eval mode)."""
    teacher = _weights(tmp_path, 5, "teacher.pt")
    said: list[str] = []
    cfg = _config(steps=1, teacher=str(teacher), freeze_camera_lane=True)
    shared = train(cfg, "unused", tmp_path / "shared", init=teacher, store=store, echo=said.append)
    assert any("one lift per step" in m for m in said)
    line = (tmp_path / "shared" / "metrics.jsonl").read_text().splitlines()[0]
    assert '"distill_heatmap"' in line and '"distill_box"' in line
    monkeypatch.setattr(Teacher, "shares_camera_lane", lambda self, student: False)
    said.clear()
    twice = train(cfg, "unused", tmp_path / "twice", init=teacher, store=store, echo=said.append)
    assert any("distilling from" in m for m in said) and not any("one lift per step" in m for m in said)
    assert math.isclose(shared.final_loss, twice.final_loss, rel_tol=1e-5), (shared.final_loss, twice.final_loss)
    monkeypatch.undo()
    other_lane = _weights(tmp_path, 6, "other.pt")  # another camera lane: nothing to share
    said.clear()
    train(cfg, "unused", tmp_path / "separate", init=other_lane, store=store, echo=said.append)
    assert not any("one lift per step" in m for m in said)


def test_distill_weight_zero_leaves_the_loss_as_without_a_teacher(store, tmp_path):
    teacher = _weights(tmp_path, 5, "teacher.pt")
    cfg = _config(steps=1)
    plain = train(cfg, "unused", tmp_path / "plain", init=teacher, store=store, echo=lambda m: None)
    zero = train(dataclasses.replace(cfg, teacher=str(teacher), distill_weight=0.0), "unused", tmp_path / "zero", init=teacher,
                 store=store, echo=lambda m: None)  # fmt: skip
    assert math.isclose(zero.final_loss, plain.final_loss, rel_tol=1e-6)
    one = train(dataclasses.replace(cfg, teacher=str(teacher)), "unused", tmp_path / "one", init=teacher, store=store, echo=lambda m: None)
    assert one.final_loss > plain.final_loss  # the student normalises with its batch statistics, the teacher with its running ones


def test_resume_needs_the_same_teacher_and_lane(store, tmp_path):
    teacher = _weights(tmp_path, 5, "teacher.pt")
    cfg = _config(steps=3, teacher=str(teacher), max_minutes=1e-9)
    part = train(cfg, "unused", tmp_path / "part", init=teacher, store=store, echo=lambda m: None)
    assert part.stopped_early
    last = tmp_path / "part" / "last.pt"
    with pytest.raises(ValueError, match="teacher="):
        train(_config(steps=3), "unused", tmp_path / "r1", resume=last, store=store, echo=lambda m: None)
    with pytest.raises(ValueError, match="freeze_camera_lane"):
        train(dataclasses.replace(cfg, max_minutes=None, freeze_camera_lane=True), "unused", tmp_path / "r2", resume=last, store=store,
              echo=lambda m: None)  # fmt: skip
    done = train(dataclasses.replace(cfg, max_minutes=None), "unused", tmp_path / "r3", resume=last, store=store, echo=lambda m: None)
    assert done.steps_done == 3


def test_teacher_of_other_maps_is_refused(store, tmp_path):
    multi = dataclasses.replace(TINY, head=dataclasses.replace(TINY.head, multi_head=not TINY.head.multi_head))
    torch.manual_seed(0)
    path = tmp_path / "multi.pt"
    save_weights(path, multi, build_detector(multi))
    with pytest.raises(ValueError, match="head tasks"):
        Teacher(path, TINY, torch.device("cpu"))
    with pytest.raises(ValueError, match="head tasks"):
        train(_config(steps=1, teacher=str(path)), "unused", tmp_path / "run", store=store, echo=lambda m: None)


@pytest.mark.parametrize(
    "extra,message",
    [
        (["--teacher", "missing.pt"], "--teacher missing.pt does not exist"),
        (["--freeze-camera-lane"], "add --init"),
        (["--distill-weight", "-1"], "-1"),
    ],
)
def test_cli_refusals(data_dir, tmp_path, extra, message):
    result = CliRunner().invoke(train_main, ["--data", str(data_dir), "--out", str(tmp_path / "o"), "--preset", "tiny", "--steps", "1", *extra])
    assert result.exit_code != 0 and message in result.output, result.output


def test_config_round_trip_keeps_old_form():
    assert "teacher" not in TrainConfig(preset="tiny", steps=1).to_dict()
    d = TrainConfig(preset="tiny", steps=1, teacher="t.pt", freeze_camera_lane=True).to_dict()
    assert d["teacher"] == "t.pt" and d["freeze_camera_lane"] is True and d["distill"]["min_teacher_score"] == 0.1
    with pytest.raises(ValueError, match="distill_weight"):
        TrainConfig(preset="tiny", steps=1, distill_weight=float("inf"))
