"""Training-side inputs and outputs (audit of training / image pretraining / trajectories): each malformed case next
to the valid one.

- the training cache is rebuilt when the dataset changes (tables, point files), reused while it does not;
- --max-minutes is a finite number of minutes in (0, 7 days] (streamdet-train, streamdet-train-image, both configs);
- a mask .npz is checked from its zip directory and .npy headers before it is inflated, then its contents;
- trajectories.npz and the training cache's arrays are checked (ValueError naming the file);
- an --out holding a run is refused without --resume / --overwrite; train-image never appends to an old log;
- a NaN / inf loss stops training with the step and the loss, writing no weights;
- streamdet-train-image --resume of a streamdet-train checkpoint names what the file is.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from streamdet.core.classes import NUM_CLASSES
from streamdet.models.presets import get_preset
from streamdet.training.cli import main as train_main
from streamdet.training.dataset import build_store
from streamdet.training.image_pretrain import MASK_NONE, PretrainConfig, load_masked_images, pretrain, read_mask
from streamdet.training.image_pretrain_cli import main as pretrain_main
from streamdet.training.trainer import MAX_MINUTES, TrainConfig, check_weights_finite, train
from streamdet.data.synth_trajectories import TRAJECTORIES_FILE, load_trajectories

TINY = get_preset("tiny")
SIZE = (TINY.image.width_px, TINY.image.height_px)
H, W = 90, 160  # the masks' image size in tiny_synth_data


def _config(**kw) -> TrainConfig:
    return TrainConfig(**{**dict(preset="tiny", steps=2, batch_size=1, lr=1e-3, log_every=1, checkpoint_every=100, seed=0), **kw})


def _one_line(res) -> str:
    assert res.exit_code != 0 and "Traceback" not in res.output, res.output
    errors = [line for line in res.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, res.output
    return errors[0]


@pytest.fixture(scope="module")
def store(tiny_train_data, tmp_path_factory):
    return build_store(tiny_train_data, "train", SIZE, cache_dir=tmp_path_factory.mktemp("cache"))


@pytest.fixture(scope="module")
def train_last_pt(store, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("det_run")
    train(_config(steps=1), "unused", out, store=store, echo=lambda m: None)
    return out / "last.pt"


# ---- 1. stale training cache --------------------------------------------------------------------------------------


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(".streamdet_cache"))
    return dst


def test_cache_is_reused_while_the_data_is_unchanged(tiny_train_data, tmp_path):
    data = _copy(tiny_train_data, tmp_path / "d")
    first = build_store(data, "train", SIZE, cache_dir=tmp_path / "c")
    again = build_store(data, "train", SIZE, cache_dir=tmp_path / "c")
    assert isinstance(again.points, np.memmap) and len(list((tmp_path / "c").iterdir())) == 1
    assert np.array_equal(np.asarray(again.boxes), first.boxes)


def test_cache_is_rebuilt_when_the_annotations_change(tiny_train_data, tmp_path):
    data = _copy(tiny_train_data, tmp_path / "d")
    old = build_store(data, "train", SIZE, cache_dir=tmp_path / "c")
    table = data / "v1.0-synth" / "sample_annotation.json"
    rows = json.loads(table.read_text())
    for r in rows:
        r["translation"][0] += 20.0
    table.write_text(json.dumps(rows))
    new = build_store(data, "train", SIZE, cache_dir=tmp_path / "c")
    fresh = build_store(data, "train", SIZE)  # no cache: what the dataset holds now
    assert not isinstance(new.boxes, np.memmap)  # read from the dataset, not the old cache
    assert np.array_equal(new.boxes, fresh.boxes) and not np.array_equal(new.boxes, old.boxes)
    assert len(list((tmp_path / "c").iterdir())) == 1  # the rebuilt cache replaced the stale one (prune_stale_caches)


def test_cache_is_rebuilt_when_a_point_file_changes(tiny_train_data, tmp_path):
    data = _copy(tiny_train_data, tmp_path / "d")
    old = build_store(data, "train", SIZE, cache_dir=tmp_path / "c")
    for sweep in (data / "samples" / "LIDAR_TOP").glob("*.bin"):
        pts = np.fromfile(sweep, np.float32).reshape(-1, 5)
        pts[:, 2] += 1.0  # same size, other content
        pts.tofile(sweep)
        st = sweep.stat()
        os.utime(sweep, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # a later mtime even on a coarse-clock filesystem
    new = build_store(data, "train", SIZE, cache_dir=tmp_path / "c")
    assert np.array_equal(new.points, build_store(data, "train", SIZE).points)
    assert not np.array_equal(new.points, old.points)


# ---- 2. --max-minutes -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [math.inf, math.nan, 0.0, -1.0, MAX_MINUTES + 1.0])
def test_max_minutes_must_be_finite_and_bounded(bad):
    with pytest.raises(ValueError, match="max_minutes must be a finite number of minutes"):
        _config(max_minutes=bad)
    with pytest.raises(ValueError, match="max_minutes must be a finite number of minutes"):
        PretrainConfig(preset="tiny", max_minutes=bad)


def test_max_minutes_valid_values():
    assert _config(steps=None, max_minutes=60.0).max_minutes == 60.0
    assert _config(max_minutes=MAX_MINUTES).max_minutes == MAX_MINUTES
    assert PretrainConfig(preset="tiny", max_minutes=1e-9).max_minutes == 1e-9


@pytest.mark.parametrize("cli", [train_main, pretrain_main])
@pytest.mark.parametrize("value, message", [("inf", "not in the range"), ("20000", "not in the range"), ("nan", "is not a number")])
def test_cli_max_minutes(cli, tiny_train_data, tmp_path, value, message):
    res = CliRunner().invoke(cli, ["--data", str(tiny_train_data), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                   "--max-minutes", value])  # fmt: skip
    assert message in _one_line(res) and not (tmp_path / "o").exists()


# ---- 3. masks -----------------------------------------------------------------------------------------------------


def _mask_arrays() -> dict[str, np.ndarray]:
    class_id = np.full((H, W), MASK_NONE, np.uint8)
    class_id[10:20, 30:50] = 0
    class_id[40:60, 70:90] = NUM_CLASSES - 1
    instance = np.zeros((H, W), np.uint16)
    instance[10:20, 30:50] = 1
    instance[40:60, 70:90] = 2
    return {"class_id": class_id, "instance": instance, "ids": np.array([1, 2], np.uint16),
            "tokens": np.array(["a" * 32, "b" * 32], np.str_)}  # fmt: skip


def _write_mask(path: Path, **changes) -> Path:
    arrays = _mask_arrays()
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    np.savez_compressed(path, **arrays)
    return path


def test_valid_mask_reads(tmp_path):
    class_id, instance, ids, tokens = read_mask(_write_mask(tmp_path / "m.npz"), H, W)
    want = _mask_arrays()
    assert np.array_equal(class_id, want["class_id"]) and np.array_equal(instance, want["instance"])
    assert ids.tolist() == [1, 2] and tokens.tolist() == ["a" * 32, "b" * 32]


def _bomb(path: Path) -> Path:
    """A small file whose class_id inflates to 20 MB (a real bomb declares gigabytes; the check is the same)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in {**_mask_arrays(), "class_id": np.zeros((4000, 5000), np.uint8)}.items():
            with zf.open(f"{k}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, v)
    return path


def _padded(path: Path) -> Path:
    """class_id of the right header, but the member declares more bytes than the header implies."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in _mask_arrays().items():
            with zf.open(f"{k}.npy", "w") as f:
                np.lib.format.write_array(f, v)
                if k == "class_id":
                    f.write(bytes(1 << 20))
    return path


class _Evil:
    def __reduce__(self):
        return (print, ("ran",))


BAD_MASKS = {
    "bomb": (_bomb, "class_id must be an integer map of the image's shape \\(90, 160\\), got uint8 \\(4000, 5000\\)"),
    "padded": (_padded, "class_id.npy declares .* truncated or padded"),
    "class_200": (lambda p: _write_mask(p, class_id=np.where(_mask_arrays()["class_id"] == 0, 200, 255).astype(np.uint8)),
                  "class_id 200 at 200 pixel"),
    "class_wraps": (lambda p: _write_mask(p, class_id=np.where(_mask_arrays()["class_id"] == 0, 256, 255).astype(np.uint16)),
                    "class_id 256"),
    "class_negative": (lambda p: _write_mask(p, class_id=np.full((H, W), -1, np.int16)), "class_id -1"),
    "class_nan": (lambda p: _write_mask(p, class_id=np.full((H, W), np.nan, np.float32)), "integer map .* got float32"),
    "transposed": (lambda p: _write_mask(p, class_id=np.ascontiguousarray(_mask_arrays()["class_id"].T)), "got uint8 \\(160, 90\\)"),
    "tiny": (lambda p: _write_mask(p, class_id=np.zeros((2, 2), np.uint8)), "got uint8 \\(2, 2\\)"),
    "scalar": (lambda p: _write_mask(p, class_id=np.uint8(0)), "got uint8 \\(\\)"),
    "instance_shape": (lambda p: _write_mask(p, instance=np.zeros((W, H), np.uint16)), "instance must be an integer map"),
    "instance_negative": (lambda p: _write_mask(p, instance=np.full((H, W), -3, np.int32)), "instance holds a negative id"),
    "ids_tokens_len": (lambda p: _write_mask(p, tokens=np.array(["a"], np.str_)), "tokens must be 2 strings"),
    "missing_member": (lambda p: _write_mask(p, tokens=None), "missing member\\(s\\) \\['tokens'\\]"),
    "pickle": (lambda p: np.savez(p, **{**_mask_arrays(), "class_id": np.array([_Evil()], dtype=object)}), "Python objects"),
    "empty": (lambda p: p.write_bytes(b""), "not a readable .npz"),
    "npy": (lambda p: np.save(open(p, "wb"), _mask_arrays()["class_id"]), "not a readable .npz"),
    "truncated": (lambda p: p.write_bytes(_write_mask(p).read_bytes()[:200]), "not a readable .npz"),
}


@pytest.mark.parametrize("name", list(BAD_MASKS))
def test_bad_mask_is_a_one_line_error_naming_the_file(tmp_path, name):
    make, match = BAD_MASKS[name]
    path = tmp_path / "x.jpg.mask.npz"
    make(path)
    with pytest.raises(ValueError, match=f"mask {path}: .*{match}") as e:
        read_mask(path, H, W)
    assert "\n" not in str(e.value)


def _corrupt_first_mask(data: Path, make) -> Path:
    mask = sorted((data / "samples" / "CAM_FRONT").glob("*.mask.npz"))[0]
    make(mask)
    return mask


def test_load_masked_images_checks_every_mask(tiny_synth_data, tmp_path):
    ok = load_masked_images(tiny_synth_data, None, SIZE, 30.0, max_samples=1)
    assert ok.labels.max() <= NUM_CLASSES and len(ok) == 6
    data = _copy(tiny_synth_data, tmp_path / "d")
    mask = _corrupt_first_mask(data, BAD_MASKS["class_200"][0])
    with pytest.raises(ValueError, match=f"mask {mask}: class_id 200"):
        load_masked_images(data, None, SIZE, 30.0, max_samples=1)


def test_train_image_cli_bad_mask_one_line(tiny_synth_data, tmp_path):
    data = _copy(tiny_synth_data, tmp_path / "d")
    mask = _corrupt_first_mask(data, _bomb)
    res = CliRunner().invoke(pretrain_main, ["--data", str(data), "--out", str(tmp_path / "o"), "--preset", "tiny", "--steps", "1",
                                             "--max-samples", "1"])  # fmt: skip
    assert str(mask) in _one_line(res)


# ---- 4. trajectories and cache arrays -----------------------------------------------------------------------------


def _traj_root(tiny_synth_data: Path, tmp_path: Path) -> tuple[Path, str]:
    root = tmp_path / "t"
    root.mkdir()
    shutil.copy(tiny_synth_data / TRAJECTORIES_FILE, root / TRAJECTORIES_FILE)
    with np.load(root / TRAJECTORIES_FILE) as f:
        scene = f.files[0].split("/")[0]
    return root, scene


def _edit_traj(path: Path, scene: str, **kw) -> None:
    with np.load(path) as f:
        a = {k: f[k] for k in f.files}
    for k, v in kw.items():
        if v is None:
            a.pop(f"{scene}/{k}")
        else:
            a[f"{scene}/{k}"] = v(a[f"{scene}/{k}"])
    np.savez_compressed(path, **a)


BAD_TRAJECTORIES = {
    "truncated": (lambda p, s: p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]), "not an .npz archive"),
    "not_zip": (lambda p, s: p.write_bytes(b"hello"), "not an .npz archive"),
    "npy": (lambda p, s: np.save(open(p, "wb"), np.zeros(3)), "one .npy array"),
    "pickle": (lambda p, s: _edit_traj(p, s, names=lambda n: np.array([_Evil()] * len(n), dtype=object)), "allow_pickle=False"),
    "missing_member": (lambda p, s: _edit_traj(p, s, boxes=None), "lacks"),
    "nan_boxes": (lambda p, s: _edit_traj(p, s, boxes=lambda b: np.full_like(b, np.nan)), "boxes holds non-finite"),
    "huge_boxes": (lambda p, s: _edit_traj(p, s, boxes=lambda b: b + np.array([1e9, 0, 0, 0, 0, 0, 0, 0, 0])), "beyond"),
    "zero_size": (lambda p, s: _edit_traj(p, s, boxes=lambda b: b * np.array([1, 1, 1, 0, 1, 1, 1, 1, 1])), "sizes"),
    "nan_ego": (lambda p, s: _edit_traj(p, s, ego2global=lambda e: np.full_like(e, np.inf)), "ego2global holds non-finite"),
    "dup_times": (lambda p, s: _edit_traj(p, s, times_us=lambda t: np.repeat(t[::2], 2)[: len(t)]), "increase strictly"),
    "reversed_times": (lambda p, s: _edit_traj(p, s, times_us=lambda t: t[::-1].copy()), "increase strictly"),
    "times_float": (lambda p, s: _edit_traj(p, s, times_us=lambda t: t.astype(np.float64) + 0.5), "integer timestamps"),
    "names_short": (lambda p, s: _edit_traj(p, s, names=lambda n: n[:1]), "names must be"),
    "wrong_class": (lambda p, s: _edit_traj(p, s, names=lambda n: np.array(["zebra"] * len(n))), "'zebra'"),
    "boxes_rank2": (lambda p, s: _edit_traj(p, s, boxes=lambda b: b[:, :, 0]), "boxes must be floats of shape"),
    "boxes_str": (lambda p, s: _edit_traj(p, s, boxes=lambda b: b.astype(str)), "boxes must be floats of shape"),
    "ego_shape": (lambda p, s: _edit_traj(p, s, ego2global=lambda e: e[:, :3]), "ego2global must be floats of shape"),
}


def test_valid_trajectories_load(tiny_synth_data, tmp_path):
    root, scene = _traj_root(tiny_synth_data, tmp_path)
    t = load_trajectories(root, scene)
    assert t is not None and t.boxes.shape[0] == len(t.times_us) and t.boxes_at(float(t.times_us[1])).shape == t.boxes.shape[1:]
    assert load_trajectories(root, "no-such-scene") is None
    (root / TRAJECTORIES_FILE).unlink()
    (root / TRAJECTORIES_FILE).mkdir()  # a directory: no trajectories (key frames are interpolated instead)
    assert load_trajectories(root, scene) is None


@pytest.mark.parametrize("name", list(BAD_TRAJECTORIES))
def test_bad_trajectories_name_the_file(tiny_synth_data, tmp_path, name):
    root, scene = _traj_root(tiny_synth_data, tmp_path)
    make, match = BAD_TRAJECTORIES[name]
    make(root / TRAJECTORIES_FILE, scene)
    with pytest.raises(ValueError, match=f"trajectories file {root / TRAJECTORIES_FILE}: .*{match}") as e:
        load_trajectories(root, scene)
    assert "\n" not in str(e.value)


def _cache_folder(tiny_train_data: Path, tmp_path: Path) -> Path:
    build_store(tiny_train_data, "train", SIZE, cache_dir=tmp_path / "c")
    (folder,) = (tmp_path / "c").iterdir()
    return folder


def _resave(folder: Path, name: str, fn) -> None:
    np.save(folder / f"{name}.npy", fn(np.load(folder / f"{name}.npy")))


def _edit_meta(folder: Path, fn) -> None:
    path = folder / "meta.json"
    path.write_text(json.dumps(fn(json.loads(path.read_text()))))


BAD_CACHES = {
    "pickle": (lambda c: np.save(c / "labels.npy", np.array([_Evil()] * 3, dtype=object), allow_pickle=True), "labels.npy: not a readable"),
    "truncated": (lambda c: (c / "points.npy").write_bytes((c / "points.npy").read_bytes()[:1000]), "points.npy: not a readable"),
    "labels_out_of_range": (lambda c: _resave(c, "labels", lambda a: np.full_like(a, 50)), "labels.npy: labels must be -1"),
    "labels_int32": (lambda c: _resave(c, "labels", lambda a: a.astype(np.int32)), "labels.npy: expected a int64"),
    "offsets_past_end": (lambda c: _resave(c, "point_offsets", lambda a: a * 10**6), "point_offsets.npy: expected 5 non-decreasing"),
    "offsets_negative": (lambda c: _resave(c, "box_offsets", lambda a: -a), "box_offsets.npy: expected 5 non-decreasing"),
    "boxes_nan": (lambda c: _resave(c, "boxes", lambda a: np.full_like(a, np.nan)), "boxes.npy: holds non-finite"),
    "points_cols": (lambda c: _resave(c, "points", lambda a: a[:, :3].copy()), "points.npy: expected a float32 array of shape \\(N, 5\\)"),
    "lidar_negative": (lambda c: _resave(c, "num_lidar_pts", lambda a: a - 10**6), "num_lidar_pts.npy: negative"),
    "images_4ch": (lambda c: _resave(c, "images", lambda a: np.concatenate([a, a[..., :1]], axis=-1)), "images.npy: expected uint8 RGB"),
    "images_float": (lambda c: _resave(c, "images", lambda a: a.astype(np.float64)), "images.npy: expected uint8 RGB"),
    "images_missing": (lambda c: (c / "images.npy").unlink(), "images.npy is missing"),
    "meta_garbage": (lambda c: (c / "meta.json").write_text("{not json"), "meta.json is not valid JSON"),
    "meta_list": (lambda c: (c / "meta.json").write_text("[]"), "meta.json: expected a JSON object"),
    "meta_no_tokens": (lambda c: _edit_meta(c, lambda m: {k: v for k, v in m.items() if k != "tokens"}), "'tokens' are not"),
    "meta_tokens_short": (lambda c: _edit_meta(c, lambda m: {**m, "tokens": m["tokens"][:1]}), "'tokens' are not"),
    "meta_rigs_ints": (lambda c: _edit_meta(c, lambda m: {**m, "rigs": [1, 2, 3, 4]}), "rigs\\[0\\] must be a calibration object"),
    "meta_rigs_short": (lambda c: _edit_meta(c, lambda m: {**m, "rigs": m["rigs"][:1]}), "'rigs' must be a list of 4"),
    "meta_rig_broken": (lambda c: _edit_meta(c, lambda m: {**m, "rigs": [{"cameras": 5}] * 4}), "rigs\\[0\\] is not a camera rig"),
    "meta_format": (lambda c: _edit_meta(c, lambda m: {**m, "format": "other"}), "not a streamdet-train-cache-v2 cache"),
    "meta_fingerprint": (lambda c: _edit_meta(c, lambda m: {**m, "data_fingerprint": "0" * 64}), "built from other data"),
}


@pytest.mark.parametrize("name", list(BAD_CACHES))
def test_bad_cache_names_the_file(tiny_train_data, tmp_path, name):
    folder = _cache_folder(tiny_train_data, tmp_path)
    assert isinstance(build_store(tiny_train_data, "train", SIZE, cache_dir=tmp_path / "c").points, np.memmap)  # the valid cache
    make, match = BAD_CACHES[name]
    make(folder)
    with pytest.raises(ValueError, match=match) as e:
        build_store(tiny_train_data, "train", SIZE, cache_dir=tmp_path / "c")
    assert str(folder) in str(e.value) and "\n" not in str(e.value)


# ---- 5. existing runs ---------------------------------------------------------------------------------------------


def test_train_refuses_an_out_holding_a_run(store, tmp_path):
    out = tmp_path / "run"
    train(_config(steps=1), "unused", out, store=store, echo=lambda m: None)
    before = (out / "model.pt").read_bytes()
    with pytest.raises(ValueError, match=f"--out {out} already holds a run \\(last.pt, model.pt, metrics.jsonl\\): pass --resume"):
        train(_config(steps=1, seed=7), "unused", out, store=store, echo=lambda m: None)
    assert (out / "model.pt").read_bytes() == before
    again = train(_config(steps=1, seed=7), "unused", out, store=store, echo=lambda m: None, overwrite=True)
    assert again.steps_done == 1 and (out / "model.pt").read_bytes() != before
    assert len((out / "metrics.jsonl").read_text().splitlines()) == 1
    part = tmp_path / "part"
    train(_config(max_minutes=1e-9), "unused", part, store=store, echo=lambda m: None)  # stops after one step
    resumed = train(_config(), "unused", part, resume=part / "last.pt", store=store, echo=lambda m: None)  # resume: allowed
    assert resumed.steps_done == 2


def test_train_cli_refuses_an_out_holding_a_run(tiny_train_data, train_last_pt, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(train_last_pt.parent, out)
    before = (out / "model.pt").read_bytes()
    args = ["--data", str(tiny_train_data), "--out", str(out), "--preset", "tiny", "--steps", "1", "--cache-dir", str(tmp_path / "c")]
    line = _one_line(CliRunner().invoke(train_main, args))
    assert "already holds a run" in line and "--resume" in line and "--overwrite" in line
    assert (out / "model.pt").read_bytes() == before
    assert "give only one" in _one_line(CliRunner().invoke(train_main, [*args, "--overwrite", "--resume", str(out / "last.pt")]))
    res = CliRunner().invoke(train_main, [*args, "--overwrite", "--seed", "3"])
    assert res.exit_code == 0, res.output
    assert (out / "model.pt").read_bytes() != before


def _pretrain_config(**kw) -> PretrainConfig:
    return PretrainConfig(**{**dict(preset="tiny", steps=1, batch_size=2, eval_every=1), **kw})


def test_pretrain_refuses_an_out_holding_a_run_and_never_appends(tiny_synth_data, tmp_path):
    out = tmp_path / "ti"
    pretrain(_pretrain_config(), tiny_synth_data, out, splits=(None, None), echo=lambda s: None, max_samples=1)
    lines = (out / "metrics.jsonl").read_text().splitlines()
    with pytest.raises(ValueError, match="already holds a run \\(last.pt, encoder.pt, detector_init.pt, metrics.jsonl, result.json\\)"):
        pretrain(_pretrain_config(seed=1), tiny_synth_data, out, splits=(None, None), echo=lambda s: None, max_samples=1)
    assert (out / "metrics.jsonl").read_text().splitlines() == lines
    pretrain(_pretrain_config(seed=1), tiny_synth_data, out, splits=(None, None), echo=lambda s: None, max_samples=1, overwrite=True)
    assert len((out / "metrics.jsonl").read_text().splitlines()) == len(lines)  # the new run alone, not appended
    line = _one_line(CliRunner().invoke(pretrain_main, ["--data", str(tiny_synth_data), "--out", str(out), "--preset", "tiny",
                                                        "--steps", "1", "--max-samples", "1"]))  # fmt: skip
    assert "already holds a run" in line and "--overwrite" in line


# ---- 6. non-finite training ---------------------------------------------------------------------------------------


@pytest.fixture
def huge_lr_allowed(monkeypatch):
    """Lets the configs take lr 1e30, past MAX_LR (--lr's bound): the quickest way to a loss that turns NaN, to test
    the divergence stop (a lr within the bound needs many steps to get there)."""
    from streamdet.training import train_config

    monkeypatch.setattr(train_config, "MAX_LR", 1e31)


def test_nan_loss_stops_training_without_weights(store, tmp_path, huge_lr_allowed):
    out = tmp_path / "huge_lr"
    with pytest.raises(ValueError, match="training diverged: the loss is nan at step 2 \\(lr ") as e:
        train(_config(lr=1e30), "unused", out, store=store, echo=lambda m: None)
    assert "\n" not in str(e.value)
    assert not (out / "model.pt").exists() and not (out / "last.pt").exists()
    with pytest.raises(ValueError, match="training diverged: the loss is inf at step 1"):
        train(_config(image_class_weight=1e300), "unused", tmp_path / "huge_w", store=store, echo=lambda m: None)
    assert not (tmp_path / "huge_w" / "model.pt").exists()
    ok = train(_config(lr=1e-3), "unused", tmp_path / "ok", store=store, echo=lambda m: None)  # the valid path
    assert math.isfinite(ok.final_loss) and (tmp_path / "ok" / "model.pt").is_file()


def test_nan_weights_are_never_checkpointed():
    lin = torch.nn.Linear(2, 2)
    check_weights_finite(lin, 3)
    with torch.no_grad():
        lin.weight[0, 0] = math.nan
    with pytest.raises(ValueError, match="after step 3 the weight weight holds NaN"):
        check_weights_finite(lin, 3)


def test_train_cli_nan_loss_is_one_line(tiny_train_data, tmp_path):
    # --lr is bounded (MAX_LR) below what diverges in two steps: a huge loss weight makes the loss inf at once instead
    res = CliRunner().invoke(train_main, ["--data", str(tiny_train_data), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                          "--steps", "2", "--image-class-weight", "1e300", "--cache-dir", str(tmp_path / "c")])  # fmt: skip
    assert "training diverged: the loss is inf at step 1" in _one_line(res) and "done after" not in res.output  # the end line


def test_pretrain_nan_loss_stops(tiny_synth_data, tmp_path, huge_lr_allowed):
    with pytest.raises(ValueError, match="training diverged: the loss is nan at step 2"):
        pretrain(_pretrain_config(steps=2, lr=1e30, warmup_steps=1), tiny_synth_data, tmp_path / "o", splits=(None, None),
                 echo=lambda s: None, max_samples=1)  # fmt: skip
    assert not (tmp_path / "o" / "encoder.pt").exists()


@pytest.mark.parametrize("field, value", [("lr", math.inf), ("lr", math.nan), ("lr", 0.0), ("image_class_weight", math.inf),
                                          ("image_class_weight", -1.0), ("image_class_weight", math.nan)])  # fmt: skip
def test_lr_and_image_class_weight_are_bounded(field, value):
    with pytest.raises(ValueError, match=field):
        _config(**{field: value})
    assert getattr(_config(**{field: 0.5}), field) == 0.5


@pytest.mark.parametrize("value", [math.inf, math.nan, 0.0, -1.0])
def test_pretrain_lr_is_finite_positive(value):
    with pytest.raises(ValueError, match="PretrainConfig.lr must be a finite number > 0"):
        PretrainConfig(preset="tiny", lr=value)
    assert PretrainConfig(preset="tiny", lr=1e-3).lr == 1e-3


@pytest.mark.parametrize("args, message", [(["--lr", "inf"], "'--lr': inf is not in the range 0<x<=10"),
                                           (["--lr", "nan"], "is not a number")])  # fmt: skip
def test_pretrain_cli_numeric(tiny_synth_data, tmp_path, args, message):
    res = CliRunner().invoke(pretrain_main, ["--data", str(tiny_synth_data), "--out", str(tmp_path / "o"), "--preset", "tiny", *args])
    assert message in _one_line(res)


@pytest.mark.parametrize("args, message", [(["--lr", "inf"], "'--lr': inf is not in the range 0<x<=10"),
                                           (["--image-class-weight", "inf"], "image_class_weight")])  # fmt: skip
def test_train_cli_numeric(tiny_train_data, tmp_path, args, message):
    res = CliRunner().invoke(train_main, ["--data", str(tiny_train_data), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                          "--steps", "1", *args])  # fmt: skip
    assert message in _one_line(res)


# ---- 7. train-image --resume of a streamdet-train checkpoint ------------------------------------------------------


def test_pretrain_resume_of_a_detector_checkpoint(tiny_synth_data, tiny_train_data, train_last_pt, tmp_path):
    with pytest.raises(ValueError, match=f"--resume {train_last_pt} is a streamdet-train checkpoint") as e:
        pretrain(_pretrain_config(steps=2), tiny_synth_data, tmp_path / "o", resume=train_last_pt, splits=(None, None),
                 echo=lambda s: None, max_samples=1)  # fmt: skip
    assert "\n" not in str(e.value)
    line = _one_line(CliRunner().invoke(pretrain_main, ["--data", str(tiny_train_data), "--out", str(tmp_path / "o2"), "--preset",
                                                        "tiny", "--steps", "2", "--max-samples", "1", "--resume", str(train_last_pt)]))
    assert "is a streamdet-train checkpoint" in line


def test_pretrain_resume_of_its_own_checkpoint_and_edited_ones(tiny_synth_data, tmp_path):
    out = tmp_path / "ti"
    # cut at step 1 of 2: the resume continues the same --steps (another is refused, as is resuming a finished run)
    pretrain(_pretrain_config(steps=2, stop_at_step=1), tiny_synth_data, out, splits=(None, None), echo=lambda s: None,
             max_samples=1)  # fmt: skip
    state = torch.load(out / "last.pt", weights_only=True)
    first = next(iter(state["model"]))
    for name, edit, match in [
        ("shape", {**state, "model": {**state["model"], first: torch.zeros(3, 3)}}, "does not fit the image segmenter"),
        ("nan", {**state, "model": {**state["model"], first: torch.full_like(state["model"][first], math.nan)}}, "non-finite"),
        ("step", {**state, "step": -1}, "'step' must be an integer >= 0"),
        ("optimizer", {**state, "optimizer": {}}, "optimizer state does not fit"),
    ]:
        path = tmp_path / f"{name}.pt"
        torch.save(edit, path)
        with pytest.raises(ValueError, match=match):
            pretrain(_pretrain_config(steps=2), tiny_synth_data, tmp_path / f"o_{name}", resume=path, splits=(None, None),
                     echo=lambda s: None, max_samples=1)  # fmt: skip
    resumed = pretrain(_pretrain_config(steps=2), tiny_synth_data, out, resume=out / "last.pt", splits=(None, None),
                       echo=lambda s: None, max_samples=1)  # fmt: skip
    assert resumed["step"] == 2 and resumed["finished"]


@pytest.mark.parametrize("args, said", [
    (["--num-slices", "8,,8"], "an empty entry"),
    (["--num-slices", "8192"], "up to 4096"),
    (["--workers", "300"], "300 is not in the range 0<=x<=256"),
    (["--steps", str(10**21)], "is not in the range 1<=x<=100000000"),
    (["--epochs", str(10**9)], "is not in the range 1<=x<=100000000"),
])  # fmt: skip
def test_train_cli_counts_are_bounded_and_lists_clean(tmp_path, args, said):
    from click.testing import CliRunner

    from streamdet.training.cli import main as train_main

    result = CliRunner().invoke(train_main, ["--data", str(tmp_path / "d"), "--out", str(tmp_path / "o"), *args])
    assert result.exit_code == 2 and re.search(said, result.output), result.output


def test_a_repeated_slice_count_is_a_weight():
    """8,8,32 is the shipped models' recipe (docs/training/): each sample draws one entry, so 8 comes twice as often.
    An audit once refused repeats as slips, and every documented reproduction stopped at its first line."""
    from streamdet.training.cli import _parse_slices
    from streamdet.training.dataset import DataConfig

    assert _parse_slices(None, None, "8,8,32") == (8, 8, 32)
    counts = DataConfig(num_slices=(8, 8, 32)).num_slices
    rng = np.random.default_rng(0)
    drawn = np.array([counts[rng.integers(len(counts))] for _ in range(6000)])  # SliceDataset's draw
    assert abs((drawn == 8).mean() - 2 / 3) < 0.03


def test_an_out_that_cannot_be_written_is_refused_before_any_data_is_read(tmp_path):
    from streamdet.training.trainer import check_out_dir

    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(ValueError, match=r"--out .*a_file/run cannot be written"):
        check_out_dir(blocker / "run", ("last.pt",), None, False)
    assert check_out_dir(tmp_path / "new" / "run", ("last.pt",), None, False) == [] and (tmp_path / "new" / "run").is_dir()


def test_a_run_without_last_pt_is_not_offered_for_resume(tmp_path):
    from streamdet.training.trainer import check_out_dir

    (tmp_path / "metrics.jsonl").write_text("{}\n")  # what a diverged run leaves
    with pytest.raises(ValueError, match=r"already holds a run \(metrics.jsonl\): pass --overwrite") as e:
        check_out_dir(tmp_path, ("last.pt", "model.pt", "metrics.jsonl"), None, False)
    assert "--resume" not in str(e.value)
