"""Hostile checkpoints (fuzz audit part 2, findings 5, 6, 7 and 11): every loader ends in a one-line ValueError (or
CheckpointError) naming the file and what does not fit, never a RuntimeError / AttributeError / TypeError, a huge
allocation or an inflated zip bomb."""

from __future__ import annotations

import copy
import dataclasses
import zipfile
from pathlib import Path

import pytest
import torch

from streamdet.export.weights import CheckpointError, checkpoint_preset, load_detector
from streamdet.models.detector import build_detector
from streamdet.models.presets import MAX_CHANNELS, Preset, get_preset, preset_names
from streamdet.models.resnet import ResNet, load_backbone_weights
from streamdet.training.checkpoint import (
    check_torch_zip,
    load_checkpoint,
    load_encoder_weights,
    load_weights,
    read_torch_file,
    save_atomic,
    save_weights,
)
from streamdet.training.trainer import TrainConfig, _load_init_weights, train
from streamdet.training.dataset import build_store

TINY = get_preset("tiny")
REPO = Path(__file__).resolve().parents[1]
FIRST = "image_encoder.backbone.conv1.weight"




def _edit_model(obj: dict, how: str) -> dict:
    m = dict(obj["model"])
    if how == "nontensor":
        m[FIRST] = 5
    elif how == "intkey":
        m[7] = torch.zeros(1)
    elif how == "shape":
        m[FIRST] = torch.zeros(5, 5)
    elif how == "missing":
        del m[FIRST]
    elif how == "extra":
        m["bogus.weight"] = torch.zeros(2)
    elif how == "int":
        m = {k: v.long() for k, v in m.items()}
    elif how in ("nan", "inf"):
        m[FIRST] = torch.full_like(m[FIRST], float(how))
    return {**obj, "model": m}


BAD_MODELS = {
    "nontensor": rf"model\['{FIRST}'\] is a int, not a tensor",
    "intkey": "has a key 7 of type int, not a str",
    "shape": rf"1 shape mismatches \(e.g. {FIRST}: \(5, 5\)",
    "missing": rf"1 missing keys \(e.g. {FIRST}\)",
    "extra": r"1 unexpected keys \(e.g. bogus.weight\)",
    "int": rf"{FIRST} holds torch.int64 values where .* has torch.float32 weights",
    "nan": rf"{FIRST} holds non-finite values",
    "inf": rf"{FIRST} holds non-finite values",
}


@pytest.mark.parametrize("how", list(BAD_MODELS))
def test_load_weights_and_init_refuse_a_malformed_model(tiny_weights, tmp_path, how):
    path = tmp_path / f"{how}.pt"
    torch.save(_edit_model(torch.load(tiny_weights, weights_only=True), how), path)
    with pytest.raises(ValueError, match=rf"checkpoint {path}.*{BAD_MODELS[how]}") as e:
        load_weights(path)
    assert "\n" not in str(e.value)
    detector = build_detector(TINY)
    with pytest.raises(ValueError, match=rf"init checkpoint {path}.*{BAD_MODELS[how]}"):
        _load_init_weights(detector, TINY, path, lambda m: None)


@pytest.mark.parametrize("how", ["shape", "missing", "extra", "int", "nan"])
def test_export_refuses_a_malformed_model(tiny_weights, tmp_path, how):
    path = tmp_path / f"{how}.pt"
    torch.save(_edit_model(torch.load(tiny_weights, weights_only=True), how), path)
    with pytest.raises(CheckpointError, match=rf"checkpoint {path}"):
        load_detector(TINY, path)


def test_init_with_another_preset_refuses_an_edited_part(tiny_weights, tmp_path):
    """A transferable part (same config) whose tensor was edited: a ValueError, not a RuntimeError."""
    obj = torch.load(tiny_weights, weights_only=True)
    student = dataclasses.replace(TINY, head=dataclasses.replace(TINY.head, head_channels=16))
    for how, match in (("shape", "shape mismatches"), ("nan", "non-finite"), ("int", "torch.int64")):
        path = tmp_path / f"{how}.pt"
        torch.save(_edit_model(obj, how), path)
        with pytest.raises(ValueError, match=rf"init checkpoint {path}.*{match}"):
            _load_init_weights(build_detector(student), student, path, lambda m: None)


def test_valid_weights_still_load(tiny_weights, tmp_path):
    model, preset = load_weights(tiny_weights)
    assert preset == TINY
    half = tmp_path / "half.pt"
    save_weights(half, TINY, model, half=True)
    _load_init_weights(build_detector(TINY), TINY, half, lambda m: None)
    load_detector(TINY, half)


# ---- finding 6: a saved preset that asks for a huge model --------------------------------------------------------

HUGE_PRESETS = {
    "channels": (lambda p: p.__setitem__("channels", 10**6), r"Preset.channels must be <= 4096"),
    "head": (lambda p: p["head"].__setitem__("head_channels", 10**6), "HeadConfig.head_channels must be <= 4096"),
    "filters": (lambda p: p["bev"].__setitem__("num_filters", [8, 10**6]), "BevEncoderConfig.num_filters must be <= 4096"),
    "upsample": (lambda p: p["bev"].__setitem__("num_upsample_filters", [8, 10**5]), "num_upsample_filters must be <= 4096"),
    "layers": (lambda p: p["bev"].__setitem__("layer_nums", [1, 10**6]), "BevEncoderConfig.layer_nums must be <= 64"),
    "width": (lambda p: p["image"].__setitem__("width_px", 10**6), "ImageConfig.width_px must be <= 65536"),
    "height": (lambda p: p["image"].__setitem__("height_px", 10**7), "ImageConfig.height_px must be <= 65536"),
    "pillars": (lambda p: p["pillars"].__setitem__("max_pillars", 10**12), "PillarConfig.max_pillars must be <="),
    "points": (lambda p: p["pillars"].__setitem__("max_points_per_pillar", 10**9), "max_points_per_pillar must be <="),
    "kernel": (lambda p: p["head"].__setitem__("final_kernel", 10**6 + 1), "HeadConfig.final_kernel must be <= 15"),
    "lut": (lambda p: p["lifter"].__setitem__("lut_heights_per_voxel", 10**6), "lut_heights_per_voxel must be <= 64"),
    "zpool": (lambda p: p["lifter"].__setitem__("z_pool", 10**6), "LifterConfig.z_pool must be <= 64"),
    "detections": (lambda p: p["post"].__setitem__("max_detections", 10**12), "PostConfig.max_detections must be <="),
}


@pytest.mark.parametrize("name", list(HUGE_PRESETS))
def test_preset_upper_bounds(tiny_weights, tmp_path, name):
    edit, match = HUGE_PRESETS[name]
    d = copy.deepcopy(TINY.to_dict())
    edit(d)
    with pytest.raises(ValueError, match=match):
        Preset.from_dict(d)
    path = tmp_path / f"{name}.pt"
    torch.save({**torch.load(tiny_weights, weights_only=True), "preset": d}, path)
    with pytest.raises(ValueError, match=rf"checkpoint {path}: .*{match}"):
        load_weights(path)


def test_preset_within_bounds_but_not_its_tensors_is_refused_before_building(tiny_weights, tmp_path):
    """channels = MAX_CHANNELS is a valid preset; the model is checked on the meta device, so a checkpoint whose
    tensors do not fill it is refused without allocating it."""
    d = copy.deepcopy(TINY.to_dict())
    d["channels"] = MAX_CHANNELS
    d["head"]["head_channels"] = MAX_CHANNELS
    path = tmp_path / "big.pt"
    torch.save({**torch.load(tiny_weights, weights_only=True), "preset": d}, path)
    with pytest.raises(ValueError, match=rf"checkpoint {path} does not fit its own preset 'tiny': .*shape mismatches"):
        load_weights(path)


@pytest.mark.parametrize("name", preset_names())
def test_every_shipped_preset_validates(name):
    p = get_preset(name)
    assert Preset.from_dict(p.to_dict()) == p


# ---- finding 7: compressed members (a zip bomb) ---------------------------------------------------------------


def _deflated_copy(src: Path, dst: Path) -> None:
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            zi = zipfile.ZipInfo(info.filename, date_time=(1980, 1, 1, 0, 0, 0))
            zi.compress_type = zipfile.ZIP_DEFLATED if "/data/" in info.filename else zipfile.ZIP_STORED
            zout.writestr(zi, zin.read(info))


def test_compressed_checkpoint_is_refused_before_loading(tiny_weights, tmp_path):
    bomb = tmp_path / "bomb.pt"
    _deflated_copy(tiny_weights, bomb)
    assert torch.load(bomb, weights_only=True)["preset"]["name"] == "tiny"  # torch itself would inflate it
    match = rf"{bomb}: member '.*/data/.*' is compressed .*torch.save never compresses"
    with pytest.raises(ValueError, match=match):
        check_torch_zip(bomb)
    with pytest.raises(ValueError, match=match):
        read_torch_file(bomb)
    with pytest.raises(ValueError, match=match):
        load_weights(bomb)
    with pytest.raises(ValueError, match=match):
        load_checkpoint(bomb)
    with pytest.raises(CheckpointError, match=match):
        load_detector(TINY, bomb)
    with pytest.raises(ValueError, match=match):
        _load_init_weights(build_detector(TINY), TINY, bomb, lambda m: None)
    with pytest.raises(ValueError, match=match):
        load_backbone_weights(ResNet(18, width_divisor=16), bomb)
    assert checkpoint_preset(bomb) is None


def test_declared_sizes_past_the_file_are_refused(tiny_weights, tmp_path):
    """A central directory whose declared (uncompressed) size lies past the file: refused from the directory."""
    raw = bytearray(tiny_weights.read_bytes())
    with zipfile.ZipFile(tiny_weights) as z:
        info = max(z.infolist(), key=lambda i: i.file_size)
    # patch the central-directory record of the largest member: uncompressed size at offset 24 (4 bytes)
    name = info.filename.encode()
    pos = raw.find(b"PK\x01\x02")
    while pos >= 0:
        n = int.from_bytes(raw[pos + 28 : pos + 30], "little")
        if bytes(raw[pos + 46 : pos + 46 + n]) == name:
            break
        pos = raw.find(b"PK\x01\x02", pos + 4)
    assert pos >= 0
    if int.from_bytes(raw[pos + 24 : pos + 28], "little") == 0xFFFFFFFF:
        pytest.skip("zip64 sizes")
    raw[pos + 24 : pos + 28] = (0xFFFFFFF0).to_bytes(4, "little")
    bad = tmp_path / "lying.pt"
    bad.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=rf"{bad}: its members declare \d+ bytes, more than the file's"):
        read_torch_file(bad)


def test_every_bundled_and_documented_checkpoint_passes_the_zip_check():
    files = sorted((REPO / "models" / "weights").rglob("*.pt")) + sorted((REPO / "docs").rglob("*.pt"))
    assert files
    for path in files:
        check_torch_zip(path)  # raises on failure
    for path in sorted((REPO / "models" / "weights").glob("*.pt")):
        model, preset = load_weights(path)
        assert preset.name


# ---- load_backbone_weights ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "content,match",
    [
        (b"", "backbone checkpoint .* cannot be read with weights_only=True"),
        (b"PK\x03\x04garbage", "backbone checkpoint .* cannot be read with weights_only=True"),
        ({"conv1.weight": 5}, r"state_dict\['conv1.weight'\] is a int, not a tensor"),
        ({1: torch.zeros(1)}, "has a key 1 of type int, not a str"),
        ("int", "conv1.weight holds torch.int64 values"),
        ("nan", "conv1.weight holds non-finite values"),
    ],
)
def test_load_backbone_weights_refuses_bad_files(tmp_path, content, match):
    path = tmp_path / "bb.pth"
    model = ResNet(18, width_divisor=16)
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content == "int":
        torch.save({k: v.long() for k, v in model.state_dict().items()}, path)
    elif content == "nan":
        torch.save({k: (torch.full_like(v, float("nan")) if v.is_floating_point() else v)
                    for k, v in model.state_dict().items()}, path)  # fmt: skip
    else:
        torch.save(content, path)
    with pytest.raises(ValueError, match=match) as e:
        load_backbone_weights(model, path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_load_encoder_weights_refuses_nontensors_and_nan(tmp_path):
    det = build_detector(TINY)
    path = tmp_path / "encoder.pt"
    state = dict(det.image_encoder.state_dict())
    torch.save({**state, "backbone.conv1.weight": 5}, path)
    with pytest.raises(ValueError, match=rf"{path}: .*is a int, not a tensor"):
        load_encoder_weights(det, path)
    torch.save({**state, "backbone.conv1.weight": torch.full_like(state["backbone.conv1.weight"], float("nan"))}, path)
    with pytest.raises(ValueError, match=rf"{path}: backbone.conv1.weight holds non-finite values"):
        load_encoder_weights(det, path)


# ---- --resume -------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def store(tiny_train_data, tmp_path_factory):
    return build_store(tiny_train_data, "train", (TINY.image.width_px, TINY.image.height_px),
                       cache_dir=tmp_path_factory.mktemp("cache"))  # fmt: skip


def _config(**kw) -> TrainConfig:
    return TrainConfig(**{**dict(preset="tiny", steps=3, batch_size=1, lr=1e-3, log_every=1, checkpoint_every=100, seed=0), **kw})


@pytest.fixture(scope="module")
def last_pt(store, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("part")
    part = train(_config(max_minutes=1e-9), "unused", out, store=store, echo=lambda m: None)
    assert part.stopped_early and part.steps_done == 1
    return out / "last.pt"


def _bad_optimizer_shape(o: dict) -> dict:
    opt = copy.deepcopy(o["optimizer"])
    first = next(iter(opt["state"]))
    opt["state"][first]["exp_avg"] = torch.zeros(3, 3)
    return opt


def _bad_optimizer_nan(o: dict) -> dict:
    opt = copy.deepcopy(o["optimizer"])
    first = next(iter(opt["state"]))
    opt["state"][first]["exp_avg"] = torch.full_like(opt["state"][first]["exp_avg"], float("nan"))
    return opt


BAD_RESUMES = {
    "model_shape": (lambda o: {**o, "model": {**o["model"], FIRST: torch.zeros(5, 5)}}, "does not fit preset 'tiny': 1 shape mismatches"),
    "model_nontensor": (lambda o: {**o, "model": {**o["model"], FIRST: 5}}, "is a int, not a tensor"),
    "model_nan": (lambda o: {**o, "model": {**o["model"], FIRST: torch.full_like(o["model"][FIRST], float("nan"))}}, "non-finite"),
    "scheduler_int": (lambda o: {**o, "scheduler": 7}, "'scheduler' is a int, not a state dict"),
    "scheduler_empty": (lambda o: {**o, "scheduler": {}}, "its scheduler state does not fit this run"),
    "scheduler_step": (lambda o: {**o, "scheduler": {**o["scheduler"], "step": None}}, "its scheduler state does not fit"),
    "scheduler_neg": (lambda o: {**o, "scheduler": {**o["scheduler"], "step": -5}}, "must be >= 0 and finite"),
    "config_list": (lambda o: {**o, "config": [1]}, "'config' is a list, not the TrainConfig dict"),
    "epoch_none": (lambda o: {**o, "epoch": None}, "'epoch' must be an integer >= 0, got None"),
    "epoch_step_neg": (lambda o: {**o, "epoch_step": -1}, "'epoch_step' must be an integer >= 0, got -1"),
    "optimizer_int": (lambda o: {**o, "optimizer": 7}, "'optimizer' is a int, not a state dict"),
    "optimizer_groups": (lambda o: {**o, "optimizer": {**o["optimizer"], "param_groups": []}}, "its optimizer state does not fit"),
    "optimizer_empty": (lambda o: {**o, "optimizer": {}}, "its optimizer state does not fit"),
    "optimizer_shape": (lambda o: {**o, "optimizer": _bad_optimizer_shape(o)}, r"optimizer state 'exp_avg' has shape \(3, 3\)"),
    "optimizer_nan": (lambda o: {**o, "optimizer": _bad_optimizer_nan(o)}, "optimizer state 'exp_avg' holds non-finite"),
}


@pytest.mark.parametrize("name", list(BAD_RESUMES))
def test_resume_refuses_a_malformed_checkpoint(store, last_pt, tmp_path, name):
    edit, match = BAD_RESUMES[name]
    path = tmp_path / f"{name}.pt"
    torch.save(edit(torch.load(last_pt, weights_only=True)), path)
    with pytest.raises(ValueError, match=rf"checkpoint {path}.*{match}") as e:
        train(_config(), "unused", tmp_path / "run", resume=path, store=store, echo=lambda m: None)
    assert "\n" not in str(e.value)


def test_resume_of_a_valid_checkpoint_still_works(store, last_pt, tmp_path):
    resumed = train(_config(), "unused", tmp_path / "run", resume=last_pt, store=store, echo=lambda m: None)
    assert resumed.steps_done == 3


def test_checkpoints_are_saved_atomically(tiny_weights, tmp_path):
    """A checkpoint replaces a symlink at its path rather than writing through it, and a save that fails part-way
    leaves the previous file whole and no temp file beside it."""
    victim = tmp_path / "victim.pt"
    victim.write_bytes(b"not yours")
    link = tmp_path / "last.pt"
    link.symlink_to(victim)
    save_weights(link, TINY, build_detector(TINY))
    assert victim.read_bytes() == b"not yours"
    assert not link.is_symlink()
    load_weights(link)
    before = link.read_bytes()

    class Unsaveable:
        def __reduce__(self):
            raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        save_atomic({"model": Unsaveable()}, link)
    assert link.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt", "victim.pt"]
