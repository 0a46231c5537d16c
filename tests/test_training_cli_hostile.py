"""streamdet-train / streamdet-train-image given hostile command lines: an --out over an input, an export or another
tool's folder, a bad --device, options that contradict each other. Every refusal happens before any data is read, so
most tests run on a stand-in dataset (a folder with its table folder) and never train."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from streamdet.training import image_pretrain, trainer
from streamdet.training.cli import _check_cache_dir
from streamdet.training.cli import main as train_main
from streamdet.training.dataset import build_store
from streamdet.training.image_pretrain import PretrainConfig, pretrain
from streamdet.training.image_pretrain_cli import main as pretrain_main
from streamdet.training.trainer import RUN_FILES, TrainConfig, check_device, check_out_dir, discard_unstarted_run, train

VERSION = "v1.0-synth"


@pytest.fixture
def data(tmp_path) -> Path:
    """What the CLIs check before training: DATA/<version>/ exists. Nothing here is ever read."""
    root = tmp_path / "data"
    (root / VERSION).mkdir(parents=True)
    (root / "samples" / "CAM_FRONT").mkdir(parents=True)
    (root / "splits.json").write_text('{"train": [], "val": []}')
    return root


def _listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else b"" for p in sorted(folder.rglob("*"))}


def _one_line(res) -> str:
    """The command's one error line (a refusal, never a traceback)."""
    assert res.exit_code != 0 and isinstance(res.exception, SystemExit), (res.output, res.exception)  # not a crash
    errors = [line for line in res.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, res.output
    return errors[0]


def _train(data: Path, out: Path, *args: str):
    return CliRunner().invoke(train_main, ["--data", str(data), "--out", str(out), "--preset", "tiny", "--steps", "1", *args])


def _pretrain(data: Path, out: Path, *args: str):
    return CliRunner().invoke(pretrain_main, ["--data", str(data), "--out", str(out), "--preset", "tiny", "--steps", "1", *args])


# ---- A10: --out over an input, an export, a saved eval run, another tool's folder ----------------------------------


@pytest.mark.parametrize("cli", [_train, _pretrain])
@pytest.mark.parametrize("where, said", [("", "is the input --data"), (VERSION, "lies inside the input --data"),
                                         ("samples/CAM_FRONT", "lies inside the input --data")])  # fmt: skip
def test_out_in_the_dataset_is_refused(cli, data, where, said):
    before = _listing(data)
    line = _one_line(cli(data, data / where if where else data))
    assert "--out" in line and said in line
    assert _listing(data) == before


def test_out_inside_an_explicit_cache_is_refused(data, tmp_path):
    line = _one_line(_train(data, tmp_path / "cache" / "run", "--cache-dir", str(tmp_path / "cache")))
    assert "--out" in line and "lies inside the input --cache-dir" in line


def _export(folder: Path) -> None:
    (folder / "manifest.json").write_text('{"version": 1}')
    (folder / "lut.npz").write_bytes(b"lut")


def _eval_run(folder: Path) -> None:
    for name in ("results.json", "gt.json", "samples.json"):
        (folder / name).write_text("{}")


def _hub_model(folder: Path) -> None:
    (folder / "config.json").write_text('{"model_type": "bert"}')  # a model hub folder: not a run's config.json


def _user_files(folder: Path) -> None:
    (folder / "notes.txt").write_text("precious")
    (folder / "src").mkdir()


@pytest.mark.parametrize("cli", [_train, _pretrain])
@pytest.mark.parametrize("fill, said", [(_export, "is a streamdet export (manifest.json)"),
                                        (_eval_run, "is a saved streamdet-eval run"),
                                        (_hub_model, "holds a config.json that is not a"),
                                        (_user_files, "is not empty and holds no")])  # fmt: skip
@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_out_holding_what_is_not_a_run_is_refused_even_with_overwrite(cli, data, tmp_path, fill, said, overwrite):
    out = tmp_path / "victim"
    out.mkdir()
    fill(out)
    before = _listing(out)
    line = _one_line(cli(data, out, *overwrite))
    assert f"--out {out}" in line and said in line
    assert _listing(out) == before


def test_export_holding_a_run_is_still_refused(data, tmp_path):
    out = tmp_path / "exp"
    out.mkdir()
    _export(out)
    (out / "config.json").write_text('{"train": {}}')  # a run someone already mixed into the export
    (out / "metrics.jsonl").write_text("{}\n")
    assert "is a streamdet export" in _one_line(_train(data, out, "--overwrite"))


def test_one_tools_run_is_refused_by_the_other(data, tmp_path):
    image_run = tmp_path / "image_run"
    image_run.mkdir()
    (image_run / "config.json").write_text('{"pretrain": {}}')
    (image_run / "last.pt").write_bytes(b"x")
    assert "not a streamdet-train run's" in _one_line(_train(data, image_run, "--overwrite"))
    det_run = tmp_path / "det_run"
    det_run.mkdir()
    (det_run / "config.json").write_text('{"train": {}}')
    assert "not a streamdet-train-image run's" in _one_line(_pretrain(data, det_run, "--overwrite"))


def test_overwrite_replaces_only_the_runs_own_files(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text('{"train": {}}')
    for name in RUN_FILES:
        (out / name).write_text("old")
    (out / "notes.txt").write_text("mine")  # the user's, beside the run: kept, never deleted
    with pytest.raises(ValueError, match="already holds a run"):
        check_out_dir(out, RUN_FILES, None, False)
    assert sorted(p.name for p in check_out_dir(out, RUN_FILES, None, True)) == sorted(RUN_FILES)
    assert check_out_dir(out, RUN_FILES, out / "last.pt", False) == []  # --resume continues it, extras and all
    assert (out / "notes.txt").read_text() == "mine"


def test_a_run_holding_its_own_evaluation_resumes(tmp_path):
    """streamdet-eval --save-results RUN leaves results.json and gt.json in the run's folder: still the run's."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text('{"train": {}}')
    for name in (*RUN_FILES, "results.json", "gt.json", "samples.json"):
        (out / name).write_text("{}")
    assert check_out_dir(out, RUN_FILES, out / "last.pt", False) == []
    (out / "manifest.json").write_text("{}")  # an export mixed into it is not
    with pytest.raises(ValueError, match="is a streamdet export"):
        check_out_dir(out, RUN_FILES, out / "last.pt", False)


@pytest.mark.parametrize("option", ["--init", "--teacher"])
def test_overwrite_would_delete_an_input_it_reads(data, tmp_path, option):
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text('{"train": {}}')
    (out / "model.pt").write_bytes(b"weights")
    line = _one_line(_train(data, tmp_path / "run", option, str(out / "model.pt"), "--overwrite"))
    assert option in line and "model.pt" in line and "--overwrite deletes" in line
    assert (out / "model.pt").read_bytes() == b"weights"


@pytest.mark.parametrize("where, said", [(VERSION, "is the input --data"), (f"{VERSION}/cache", "lies inside the input --data"),
                                         ("samples/CAM_FRONT", "lies inside the input --data"), ("", "is the --data root")])  # fmt: skip
def test_cache_dir_in_the_dataset_is_refused(data, tmp_path, where, said):
    cache = data / where if where else data
    line = _one_line(_train(data, tmp_path / "run", "--cache-dir", str(cache)))
    assert "--cache-dir" in line and said in line
    assert not (tmp_path / "run").exists()


def test_cache_dir_beside_the_tables_stays_allowed(data):
    for cache in (data / ".streamdet_cache", data / "my_cache", data.parent / "elsewhere"):
        _check_cache_dir(cache, data, VERSION)  # no error


# ---- B1: --device ----------------------------------------------------------------------------------------------


BAD_DEVICES = ["foo", "", "meta", "cuda:99", "cpu:x", "x" * 500]
if not torch.cuda.is_available():
    BAD_DEVICES.append("cuda")
if not torch.backends.mps.is_available():
    BAD_DEVICES.append("mps")


@pytest.mark.parametrize("cli", [_train, _pretrain])
@pytest.mark.parametrize("device", BAD_DEVICES)
def test_bad_device_is_one_line_and_makes_nothing(cli, data, tmp_path, device):
    out = tmp_path / "new" / "run"
    line = _one_line(cli(data, out, "--device", device))
    assert "--device" in line and repr(device)[:20] in line and len(line) < 300
    assert not (tmp_path / "new").exists()


def test_check_device_accepts_what_this_machine_has():
    assert check_device("cpu") == torch.device("cpu")
    if torch.cuda.is_available():
        assert check_device("cuda:0").type == "cuda"
    with pytest.raises(ValueError, match="not on meta"):
        check_device("meta")


def test_library_refuses_a_bad_device_before_making_out(tmp_path):
    config = TrainConfig(preset="tiny", steps=1)
    with pytest.raises(ValueError, match="'meta': training runs on"):
        train(config, "unused", tmp_path / "a" / "run", device="meta", echo=lambda m: None)
    with pytest.raises(ValueError, match="'foo' is not a torch device"):
        pretrain(PretrainConfig(preset="tiny", steps=1), "unused", tmp_path / "b" / "run", device="foo", echo=lambda m: None)
    assert list(tmp_path.iterdir()) == []


def test_discard_unstarted_run_keeps_what_is_worth_keeping(tmp_path):
    def fresh(name: str, **files: str) -> Path:
        out = tmp_path / name
        out.mkdir()
        for file, text in files.items():
            (out / file.replace("_", ".")).write_text(text)
        return out

    empty = fresh("empty", config_json='{"train": {}}', metrics_jsonl="")
    discard_unstarted_run(empty, RUN_FILES, [empty])
    assert not empty.exists()  # nothing to resume or read: gone, so the next attempt is not refused
    logged = fresh("logged", config_json="{}", metrics_jsonl='{"step": 10}\n')
    discard_unstarted_run(logged, RUN_FILES, [logged])
    assert sorted(p.name for p in logged.iterdir()) == ["config.json", "metrics.jsonl"]
    checkpointed = fresh("ckpt", config_json="{}", metrics_jsonl="", last_pt="x")
    discard_unstarted_run(checkpointed, RUN_FILES, [checkpointed])
    assert (checkpointed / "metrics.jsonl").exists()
    shared = fresh("shared", config_json="{}", metrics_jsonl="", cache_txt="a cache the user put here")
    discard_unstarted_run(shared, RUN_FILES, [shared])
    assert sorted(p.name for p in shared.iterdir()) == ["cache.txt"]  # the run's files go, the folder stays


@pytest.fixture(scope="module")
def lidar_store(tiny_train_data, tmp_path_factory):
    return build_store(tiny_train_data, "train", None, cache_dir=tmp_path_factory.mktemp("cache"))


def _lidar_config() -> TrainConfig:
    return TrainConfig(preset="tiny", use_image=False, steps=1, log_every=5)


def test_a_run_failing_in_set_up_or_before_its_first_record_leaves_nothing(lidar_store, tmp_path, monkeypatch):
    out = tmp_path / "new" / "run"

    def loop_boom(*args, **kwargs):
        raise RuntimeError("the first step failed on the device")

    def set_up_boom(*args, **kwargs):
        raise RuntimeError("set-up failed: no device")

    monkeypatch.setattr(trainer, "_loop", loop_boom)  # after set-up: config.json and metrics.jsonl are written
    with pytest.raises(RuntimeError, match="first step"):
        train(_lidar_config(), "unused", out, store=lidar_store, echo=lambda m: None)
    assert not (tmp_path / "new").exists()
    monkeypatch.undo()  # the real loop again: only set-up fails below
    monkeypatch.setattr(trainer, "_set_up", set_up_boom)
    with pytest.raises(RuntimeError, match="set-up failed"):
        train(_lidar_config(), "unused", out, store=lidar_store, echo=lambda m: None)
    assert not (tmp_path / "new").exists()
    monkeypatch.undo()
    result = train(_lidar_config(), "unused", out, store=lidar_store, echo=lambda m: None)  # not "already holds a run"
    assert result.steps_done == 1 and (out / "model.pt").is_file()


def test_a_failed_overwrite_keeps_the_old_run_until_set_up_succeeds(lidar_store, tmp_path, monkeypatch):
    out = tmp_path / "run"
    train(_lidar_config(), "unused", out, store=lidar_store, echo=lambda m: None)
    before = _listing(out)

    def boom(*args, **kwargs):
        raise RuntimeError("set-up failed")

    monkeypatch.setattr(trainer, "_set_up", boom)
    with pytest.raises(RuntimeError, match="set-up failed"):
        train(_lidar_config(), "unused", out, store=lidar_store, echo=lambda m: None, overwrite=True)
    assert _listing(out) == before


def test_pretrain_failing_in_set_up_leaves_nothing(tmp_path, monkeypatch):
    def boom(*args, **kwargs):
        raise ValueError("a mask is missing")

    monkeypatch.setattr(image_pretrain, "load_masked_images", boom)
    with pytest.raises(ValueError, match="mask"):
        pretrain(PretrainConfig(preset="tiny", steps=1), "unused", tmp_path / "new" / "run", echo=lambda m: None)
    assert list(tmp_path.iterdir()) == []


# ---- C3: options that contradict each other --------------------------------------------------------------------


@pytest.mark.parametrize("weight", ["100", "1.0"])
def test_distill_weight_without_teacher_is_refused(data, tmp_path, weight):
    line = _one_line(_train(data, tmp_path / "run", "--distill-weight", weight))
    assert "--distill-weight" in line and f"{float(weight):g} weighs" in line and "--teacher" in line


def test_max_slices_per_sample_is_a_cap_up_to_the_largest_count(data, tmp_path):
    line = _one_line(_train(data, tmp_path / "run", "--max-slices-per-sample", "1000"))
    assert "--max-slices-per-sample" in line and "1000" in line and "8 slices" in line
    # a cap for the 8-slice draws, a subset of the 32: accepted (the run then stops at the --out over --data)
    line = _one_line(_train(data, data, "--num-slices", "8,32", "--max-slices-per-sample", "16"))
    assert "--out" in line
    assert "A cap" in CliRunner().invoke(train_main, ["--help"]).output


@pytest.mark.parametrize("steps", [str(10**12), str(10**8 + 1)])
def test_pretrain_steps_are_bounded_like_train(data, tmp_path, steps):
    res = CliRunner().invoke(pretrain_main, ["--data", str(data), "--out", str(tmp_path / "run"), "--steps", steps])
    assert res.exit_code == 2 and "--steps" in _one_line(res) and "100000000" in res.output


def test_stop_at_step_past_steps_is_refused(data, tmp_path):
    line = _one_line(_pretrain(data, tmp_path / "run", "--stop-at-step", "5"))
    assert "--stop-at-step" in line and "5" in line and "--steps 1" in line
    assert "--out" in _one_line(_pretrain(data, data, "--stop-at-step", "1"))  # equal to --steps: accepted
    with pytest.raises(ValueError, match="stop_at_step 5 is past the end"):
        PretrainConfig(preset="tiny", steps=1, stop_at_step=5)


def test_config_json_of_a_run_is_recognised(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text(json.dumps({"train": {"preset": "tiny"}}))
    assert check_out_dir(out, RUN_FILES, None, False) == []  # a run's config alone: nothing to replace
