"""The training side of the hostile-input review of streamdet-train / streamdet-train-image (findings H2, H3, M1, M2,
M5, M6, M7, L1, L2, L3, L8): each hostile case beside the valid one it must not break.

- H2: --resume A/last.pt --out B, B holding another run, is refused naming both (a new or empty --out is a copy);
- H3: a sample whose sweep has no usable point (empty, all NaN, outside the grid) is left out of its batch, counted
  and named, never a traceback; a split of only such samples stops with one line instead of spinning;
- M1: a FIFO or a symlink at a run file (metrics.jsonl ...) is refused before any work, by both trainers;
- M2: --resume keeps the run's own config (batch size, seed, lr, slices, steps, data ...), refused naming the option
  and both values before the dataset is read and before config.json is rewritten; what may change is allowed;
- M5: streamdet-train-image --resume checks the optimizer state's shapes as streamdet-train does;
- M6: an --out inside a dataset's symlinked table folder is refused;
- M7: --no-image refuses --image-warmup and --camera-mode;
- L1 / L2: --lr and --seed are bounded (usage errors naming them, before the data is read);
- L3: the cache folder is checked before the split is read (loops, broken links, files, exports, runs);
- L8: a failed --resume into a new --out leaves no folder behind.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from streamdet.models.presets import get_preset
from streamdet.training.batching import Collator
from streamdet.training.cli import main as train_main
from streamdet.training.dataset import DataConfig, SliceDataset, build_store
from streamdet.training.image_pretrain import PRETRAIN_RUN_FILES, PretrainConfig, pretrain
from streamdet.training.image_pretrain_cli import main as pretrain_main
from streamdet.training.run_dir import RUN_FILES, check_out_dir, open_run_log
from streamdet.training.train_config import MAX_LR, MAX_SEED, TrainConfig, resume_config_changes
from streamdet.training.trainer import train

TINY = get_preset("tiny")
SIZE = (TINY.image.width_px, TINY.image.height_px)
VERSION = "v1.0-synth"
quiet = lambda m: None  # noqa: E731


def _config(**kw) -> TrainConfig:
    return TrainConfig(**{**dict(preset="tiny", steps=3, batch_size=1, lr=1e-3, log_every=1, checkpoint_every=100, seed=0), **kw})


def _one_line(res) -> str:
    """The command's one error line (a refusal, never a traceback)."""
    assert res.exit_code != 0 and isinstance(res.exception, SystemExit), (res.output, res.exception)
    errors = [line for line in res.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, res.output
    return errors[0]


def _listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else b"" for p in sorted(folder.rglob("*"))}


@pytest.fixture(scope="module")
def store(tiny_train_data, tmp_path_factory):
    return build_store(tiny_train_data, "train", SIZE, cache_dir=tmp_path_factory.mktemp("cache"))


@pytest.fixture(scope="module")
def part(store, tmp_path_factory) -> Path:
    """A 3-step run cut by the time limit after its first step: a resumable last.pt. Copied before it is resumed."""
    out = tmp_path_factory.mktemp("part") / "run"
    result = train(_config(max_minutes=1e-9), "unused", out, store=store, echo=quiet)
    assert result.stopped_early and result.steps_done == 1
    return out


@pytest.fixture
def run(part, tmp_path) -> Path:
    return Path(shutil.copytree(part, tmp_path / "run"))


@pytest.fixture
def data(tmp_path) -> Path:
    """What the CLIs check before training: DATA/<version>/ exists. Nothing here is ever read."""
    root = tmp_path / "data"
    (root / VERSION).mkdir(parents=True)
    (root / "splits.json").write_text('{"train": [], "val": []}')
    return root


def _train(data: Path, out: Path, *args: str):
    return CliRunner().invoke(train_main, ["--data", str(data), "--out", str(out), "--preset", "tiny", "--steps", "1", *args])


def _pretrain(data: Path, out: Path, *args: str):
    return CliRunner().invoke(pretrain_main, ["--data", str(data), "--out", str(out), "--preset", "tiny", "--steps", "1", *args])


def _fake_run(folder: Path, run_files: tuple[str, ...], key: str) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({key: {}}))
    for name in run_files:
        (folder / name).write_text("finished run")
    return folder


# ---- H2: a resume never replaces another run -----------------------------------------------------------------------


@pytest.mark.parametrize("run_files, key", [(RUN_FILES, "train"), (PRETRAIN_RUN_FILES, "pretrain")])
def test_resume_into_another_runs_folder_is_refused(tmp_path, run_files, key):
    a = _fake_run(tmp_path / "a", run_files, key)
    b = _fake_run(tmp_path / "b", run_files, key)
    before = _listing(b)
    with pytest.raises(ValueError, match=f"--resume {a / 'last.pt'} continues the run in {a}, but --out {b} holds another run"):
        check_out_dir(b, run_files, a / "last.pt", False, config_key=key)
    assert _listing(b) == before
    assert check_out_dir(a, run_files, a / "last.pt", False, config_key=key) == []  # its own folder
    assert check_out_dir(tmp_path / "a" / ".." / "a", run_files, a / "last.pt", False, config_key=key) == []  # spelled otherwise
    assert check_out_dir(tmp_path / "new", run_files, a / "last.pt", False, config_key=key) == []  # a copy into a new folder
    (tmp_path / "empty").mkdir()
    assert check_out_dir(tmp_path / "empty", run_files, a / "last.pt", False, config_key=key) == []


def test_train_resume_into_a_finished_run_leaves_it_whole(run, tmp_path, store):
    finished = tmp_path / "finished"
    train(_config(steps=1), "unused", finished, store=store, echo=quiet)
    before = _listing(finished)
    with pytest.raises(ValueError, match="holds another run"):
        train(_config(), "unused", finished, resume=run / "last.pt", store=store, echo=quiet)
    assert _listing(finished) == before


def test_train_image_resume_into_another_run_is_one_line(data, tmp_path):
    a = _fake_run(tmp_path / "a", PRETRAIN_RUN_FILES, "pretrain")
    b = _fake_run(tmp_path / "b", PRETRAIN_RUN_FILES, "pretrain")
    before = _listing(b)
    line = _one_line(_pretrain(data, b, "--resume", str(a / "last.pt")))
    assert str(a) in line and str(b) in line and "holds another run" in line
    assert _listing(b) == before


# ---- H3: a sweep without a usable point ------------------------------------------------------------------------------


def _with_sweep(store, index: int, edit):
    """``store`` with sample ``index``'s sweep replaced by ``edit(sweep)`` (every sample for index None)."""
    parts = [np.asarray(store.sweep(k)) for k in range(len(store))]
    for k in range(len(parts)) if index is None else (index,):
        parts[k] = edit(parts[k]).astype(np.float32)
    offsets = np.cumsum([0] + [len(p) for p in parts]).astype(np.int64)
    return dataclasses.replace(store, points=np.concatenate(parts).reshape(-1, 5), point_offsets=offsets)


EMPTY_SWEEPS = {
    "empty": lambda p: p[:0],
    "all NaN": lambda p: np.full_like(p, np.nan),
    "outside the grid": lambda p: p + np.array([1e4, 1e4, 0, 0, 0], np.float32),
}


def test_the_collator_leaves_out_a_sample_without_pillars(store):
    bad = _with_sweep(store, 1, EMPTY_SWEEPS["empty"])
    ds = SliceDataset(bad, TINY, DataConfig(), seed=0)
    collate = Collator(TINY)
    alone = collate([ds[1]])
    assert alone.num_samples == 0 and alone.skipped == (1,) and alone.pillar_features.shape[0] == 0
    mixed = collate([ds[0], ds[1]])
    assert mixed.num_samples == 1 and mixed.skipped == (1,)
    assert mixed.images.shape[0] == len(store.rigs[0].names)  # only the kept sample's images
    whole = collate([ds[0], ds[2]])  # nothing to leave out: as before
    assert whole.num_samples == 2 and whole.skipped == ()


@pytest.mark.parametrize("kind", sorted(EMPTY_SWEEPS))
def test_training_skips_a_sample_without_a_usable_point(store, tmp_path, kind):
    bad = _with_sweep(store, 0, EMPTY_SWEEPS[kind])
    said = []
    result = train(_config(steps=len(store)), "unused", tmp_path / "run", store=bad, echo=said.append)
    assert result.steps_done == len(store) and result.skipped_samples >= 1  # the step it missed came from the next epoch
    assert any(f"sample {store.tokens[0]} holds no usable LiDAR point" in line for line in said)
    assert any(line.startswith(f"skipped {result.skipped_samples} sample(s)") for line in said)
    assert (tmp_path / "run" / "model.pt").is_file()


def test_a_split_without_any_usable_point_stops_with_one_line(store, tmp_path):
    def hang(signum, frame):
        raise TimeoutError("the trainer spun over empty batches")

    old = signal.signal(signal.SIGALRM, hang)
    signal.alarm(120)
    try:
        with pytest.raises(ValueError, match="no sample of the train split of unused holds a usable LiDAR point") as e:
            train(_config(), "unused", tmp_path / "run", store=_with_sweep(store, None, EMPTY_SWEEPS["empty"]), echo=quiet)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert "\n" not in str(e.value)
    assert not (tmp_path / "run").exists()  # nothing trained, nothing left


# ---- M1: run files that are FIFOs or symlinks ------------------------------------------------------------------------


@pytest.mark.parametrize("run_files, key", [(RUN_FILES, "train"), (PRETRAIN_RUN_FILES, "pretrain")])
@pytest.mark.parametrize("resume", [True, False])
def test_a_fifo_at_metrics_jsonl_is_refused(tmp_path, alarm, run_files, key, resume):
    out = _fake_run(tmp_path / "run", run_files, key)
    (out / "metrics.jsonl").unlink()
    os.mkfifo(out / "metrics.jsonl")
    with pytest.raises(ValueError, match="metrics.jsonl is not a regular file .*remove"):
        check_out_dir(out, run_files, out / "last.pt" if resume else None, not resume, config_key=key)


@pytest.mark.parametrize("run_files, key", [(RUN_FILES, "train"), (PRETRAIN_RUN_FILES, "pretrain")])
def test_a_symlink_at_metrics_jsonl_is_refused(tmp_path, run_files, key):
    out = _fake_run(tmp_path / "run", run_files, key)
    victim = tmp_path / "victim.json"
    victim.write_text('{"victim": true}')
    (out / "metrics.jsonl").unlink()
    (out / "metrics.jsonl").symlink_to(victim)
    with pytest.raises(ValueError, match="metrics.jsonl is a symlink"):
        check_out_dir(out, run_files, out / "last.pt", False, config_key=key)
    assert victim.read_text() == '{"victim": true}'


def test_train_with_a_fifo_log_is_refused_before_any_work(run, store, alarm):
    (run / "metrics.jsonl").unlink()
    os.mkfifo(run / "metrics.jsonl")
    with pytest.raises(ValueError, match="metrics.jsonl is not a regular file"):
        train(_config(), "no-such-data", run, resume=run / "last.pt", echo=quiet)  # the data is never read


def test_open_run_log_never_blocks_nor_follows(tmp_path, alarm):
    log = tmp_path / "metrics.jsonl"
    os.mkfifo(log)
    with pytest.raises(ValueError, match="cannot be written as the run's log"):
        open_run_log(log, append=True)
    log.unlink()
    target = tmp_path / "elsewhere"
    target.write_text("theirs")
    log.symlink_to(target)
    with pytest.raises(ValueError, match="cannot be written as the run's log"):
        open_run_log(log, append=False)
    assert target.read_text() == "theirs"
    log.unlink()
    log.write_text("first\n")
    with open_run_log(log, append=True) as f:
        f.write("second\n")
    assert log.read_text() == "first\nsecond\n"
    with open_run_log(log, append=False) as f:
        f.write("new\n")
    assert log.read_text() == "new\n"


# ---- M2: a resume keeps the run's own config ------------------------------------------------------------------------


@pytest.mark.parametrize("change, said", [
    (dict(batch_size=2), "--batch-size 1; given --batch-size 2"),
    (dict(seed=7, lr=0.5), "--lr 0.001, --seed 0; given --lr 0.5, --seed 7"),
    (dict(steps=5), "--steps 3; given --steps 5"),
    (dict(steps=None, epochs=2), "--steps 3, --epochs none; given --steps none, --epochs 2"),
    (dict(data=DataConfig(num_slices=(4, 8))), "--num-slices 8; given --num-slices 4,8"),
    (dict(data=DataConfig(camera_mode="overlapping")), "--camera-mode 'all'; given --camera-mode 'overlapping'"),
    (dict(balanced=True), "--balanced off; given --balanced on"),
    (dict(image_warmup=0.5), "--image-warmup 0; given --image-warmup 0.5"),
    (dict(weight_decay=0.5), "TrainConfig.weight_decay 0.01; given TrainConfig.weight_decay 0.5"),
])  # fmt: skip
def test_a_resume_with_another_config_is_refused_before_the_data_is_read(run, change, said):
    before = _listing(run)
    with pytest.raises(ValueError, match="was trained with ") as e:
        train(_config(**change), "no-such-data", run, resume=run / "last.pt", echo=quiet)  # the data is never read
    assert said in str(e.value) and f"--init {run / 'last.pt'}" in str(e.value) and "\n" not in str(e.value)
    assert _listing(run) == before  # config.json, last.pt and the log as they were


@pytest.mark.parametrize("value, shown", [(torch.zeros(2, 2), "tensor([[0., 0.], [0., 0.]])"), ("7" * 200, "'" + "7" * 56 + "..."),
                                          ([8, torch.zeros(3)], "[8, tensor([0., 0., 0.])]")], ids=["tensor", "long str", "list"])  # fmt: skip
def test_a_checkpoint_config_of_odd_values_is_refused_in_one_line(run, value, shown):
    state = torch.load(run / "last.pt", weights_only=True)
    state["config"]["seed"] = value
    torch.save(state, run / "edited.pt")
    with pytest.raises(ValueError, match="was trained with --seed ") as e:
        train(_config(), "no-such-data", run, resume=run / "edited.pt", echo=quiet)
    assert f"--seed {shown}; given --seed 0" in str(e.value) and "\n" not in str(e.value)


def test_what_a_resume_may_change(run, store):
    """--max-minutes (this invocation's limit), --log-every, --checkpoint-every, --workers, --amp: allowed."""
    done = train(_config(log_every=2, checkpoint_every=5, amp="off"), "unused", run, resume=run / "last.pt", store=store,
                 echo=quiet)  # fmt: skip
    assert done.steps_done == 3 and not done.stopped_early
    assert json.loads((run / "config.json").read_text())["train"]["log_every"] == 2


def test_resume_config_changes_of_a_time_plan():
    was = _config(steps=None, max_minutes=5.0).to_dict()
    assert resume_config_changes(was, _config(steps=None, max_minutes=6.0)) == [("--max-minutes", 5.0, 6.0)]  # the budget
    plan = _config(max_minutes=5.0).to_dict()
    assert resume_config_changes(plan, _config(max_minutes=None)) == []  # with --steps: this invocation's limit
    assert resume_config_changes(plan, _config(camera_dropout=0.3)) == []  # an augmentation: allowed, said


def test_a_resume_on_other_data_is_refused(run, store):
    other = dataclasses.replace(store, tokens=tuple(reversed(store.tokens)))  # another order: another split to the run
    before = _listing(run)
    with pytest.raises(ValueError, match="was trained on another train split .* than --data unused holds"):
        train(_config(), "unused", run, resume=run / "last.pt", store=other, echo=quiet)
    assert _listing(run) == before
    assert torch.load(run / "last.pt", weights_only=True)["data"]["samples"] == len(store)


def test_a_data_position_past_the_epoch_is_refused(run, store, tmp_path):
    state = torch.load(run / "last.pt", weights_only=True)
    state["epoch_step"] = 10**6
    torch.save(state, run / "last.pt")
    with pytest.raises(ValueError, match=r"data position \(batch 1000000 of epoch 0\) is past the \d+ batches"):
        train(_config(), "unused", run, resume=run / "last.pt", store=store, echo=quiet)


def test_train_cli_resume_with_another_batch_size_is_one_line(run, tiny_train_data, tmp_path):
    before = _listing(run)
    line = _one_line(CliRunner().invoke(train_main, [
        "--data", str(tiny_train_data), "--out", str(run), "--preset", "tiny", "--steps", "3", "--lr", "1e-3",
        "--batch-size", "2", "--resume", str(run / "last.pt"), "--cache-dir", str(tmp_path / "c")]))  # fmt: skip
    assert "--batch-size 1; given --batch-size 2" in line
    assert _listing(run) == before and not (tmp_path / "c").exists()  # refused before the data was read


def _ti_config(**kw) -> PretrainConfig:
    return PretrainConfig(**{**dict(preset="tiny", steps=3, batch_size=2, eval_every=10, checkpoint_every=10,
                                    warmup_steps=1), **kw})  # fmt: skip


@pytest.fixture(scope="module")
def ti_part(tiny_synth_data, tmp_path_factory) -> Path:
    """A 3-step streamdet-train-image run cut at step 1 (--stop-at-step)."""
    out = tmp_path_factory.mktemp("ti") / "run"
    result = pretrain(_ti_config(stop_at_step=1), tiny_synth_data, out, splits=(None, None), echo=quiet, max_samples=1)
    assert result["step"] == 1 and not result["finished"]
    return out


@pytest.fixture
def ti_run(ti_part, tmp_path) -> Path:
    return Path(shutil.copytree(ti_part, tmp_path / "ti"))


@pytest.mark.parametrize("change, said", [
    (dict(steps=2), "--steps 3; given --steps 2"),  # once: a run cut at step 1 of 3 marked "finished" under --steps 2
    (dict(batch_size=1, seed=4), "--batch-size 2, --seed 0; given --batch-size 1, --seed 4"),
    (dict(lr=0.01), "--lr 0.002; given --lr 0.01"),
    (dict(range_m=10.0), "--range 30; given --range 10"),
    (dict(warmup_steps=2), "PretrainConfig.warmup_steps 1; given PretrainConfig.warmup_steps 2"),
])  # fmt: skip
def test_train_image_resume_with_another_config_is_refused(ti_run, change, said):
    before = _listing(ti_run)
    with pytest.raises(ValueError, match="was pretrained with ") as e:
        pretrain(_ti_config(**change), "no-such-data", ti_run, resume=ti_run / "last.pt", splits=(None, None), echo=quiet)
    assert said in str(e.value)
    assert _listing(ti_run) == before


def test_train_image_resume_rules(ti_run, tiny_synth_data):
    with pytest.raises(ValueError, match="--stop-at-step 1: --resume .* is already at step 1"):
        pretrain(_ti_config(stop_at_step=1), tiny_synth_data, ti_run, resume=ti_run / "last.pt", splits=(None, None), echo=quiet,
                 max_samples=1)  # fmt: skip
    before = _listing(ti_run)
    with pytest.raises(ValueError, match=r"pretrained on other train images \(6 of them\) than --data gives now \(12\)"):
        pretrain(_ti_config(), tiny_synth_data, ti_run, resume=ti_run / "last.pt", splits=(None, None), echo=quiet)
    assert _listing(ti_run) == before
    # what may change: the evaluation and checkpoint intervals; then it runs to its end
    done = pretrain(_ti_config(eval_every=2, checkpoint_every=1), tiny_synth_data, ti_run, resume=ti_run / "last.pt",
                    splits=(None, None), echo=quiet, max_samples=1)  # fmt: skip
    assert done["step"] == 3 and done["finished"]
    with pytest.raises(ValueError, match="is at step 3, the end of its 3-step schedule: nothing left to train"):
        pretrain(_ti_config(), tiny_synth_data, ti_run, resume=ti_run / "last.pt", splits=(None, None), echo=quiet, max_samples=1)


# ---- M5: train-image --resume with an optimizer state of other shapes ---------------------------------------------------


def test_train_image_resume_checks_the_optimizer_state(ti_run, tiny_synth_data):
    state = torch.load(ti_run / "last.pt", weights_only=True)
    state["optimizer"] = {"state": {0: {"exp_avg": torch.zeros(3), "exp_avg_sq": torch.zeros(3), "step": torch.tensor(1.0)}},
                          "param_groups": state["optimizer"]["param_groups"]}  # fmt: skip
    torch.save(state, ti_run / "in.pt")
    with pytest.raises(ValueError, match=r"in.pt: optimizer state 'exp_avg' has shape \(3,\) for a parameter of shape"):
        pretrain(_ti_config(), tiny_synth_data, ti_run, resume=ti_run / "in.pt", splits=(None, None), echo=quiet, max_samples=1)


# ---- M6: an --out in the dataset's symlinked table folder ------------------------------------------------------------


@pytest.mark.parametrize("cli", [_train, _pretrain])
def test_out_in_a_linked_table_folder_is_refused(cli, tmp_path):
    tables = tmp_path / "tables"
    tables.mkdir()
    root = tmp_path / "data"
    root.mkdir()
    (root / VERSION).symlink_to(tables)
    line = _one_line(cli(root, tables / "run"))
    assert "--out" in line and f"--data's {VERSION} (a link to {tables})" in line
    assert list(tables.iterdir()) == []


# ---- M7: image options with --no-image -----------------------------------------------------------------------------


@pytest.mark.parametrize("args, option", [(["--image-warmup", "0.5"], "--image-warmup"), (["--camera-mode", "overlapping"], "--camera-mode")])
def test_no_image_refuses_the_image_lane_options(data, tmp_path, args, option):
    res = _train(data, tmp_path / "run", "--no-image", *args)
    assert res.exit_code == 2 and option in _one_line(res) and "--no-image" in _one_line(res)
    assert not (tmp_path / "run").exists()


def test_no_image_accepts_the_image_lane_defaults(data):
    """--image-warmup 0 / --camera-mode all change nothing: the docs/training scripts give one option string to the
    fused and the LiDAR-only runs of a comparison. Accepted (the run then stops at its --out over --data)."""
    line = _one_line(_train(data, data, "--no-image", "--image-warmup", "0", "--camera-mode", "all"))
    assert "--out" in line and "is the input --data" in line


def test_no_image_config_refuses_the_image_lane_fields():
    with pytest.raises(ValueError, match="image warm-up .* needs the image lane"):
        _config(use_image=False, image_warmup=0.5)
    with pytest.raises(ValueError, match="camera_mode 'overlapping' .* needs the image lane"):
        _config(use_image=False, data=DataConfig(camera_mode="overlapping"))
    assert not _config(use_image=False).use_image  # the defaults stay valid


# ---- L1 / L2: --lr and --seed bounds ---------------------------------------------------------------------------------


@pytest.mark.parametrize("cli", [_train, _pretrain])
@pytest.mark.parametrize("args, option", [(["--lr", "1e41"], "--lr"), (["--lr", "11"], "--lr"),
                                          (["--seed", str(2**64)], "--seed"), (["--seed", str(MAX_SEED + 1)], "--seed")])  # fmt: skip
def test_lr_and_seed_are_bounded_before_the_data_is_read(cli, tmp_path, args, option):
    res = cli(tmp_path / "no-such-data", tmp_path / "run", *args)  # a usage error, before --data is even looked at
    assert res.exit_code == 2 and f"'{option}'" in _one_line(res)


def test_lr_and_seed_bounds_in_the_configs():
    for make, name in ((_config, "TrainConfig"), (_ti_config, "PretrainConfig")):
        with pytest.raises(ValueError, match=f"{name}.lr must be a finite learning rate in \\(0, 10\\]"):
            make(lr=MAX_LR * 1.1)
        with pytest.raises(ValueError, match=f"{name}.seed must be an integer in 0..{MAX_SEED}"):
            make(seed=MAX_SEED + 1)
        assert make(lr=MAX_LR, seed=MAX_SEED).seed == MAX_SEED


# ---- L3: the cache folder, before the split is read -----------------------------------------------------------------


def _cache_cases(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "nowhere")
    file = tmp_path / "file"
    file.write_text("x")
    export = tmp_path / "export"
    export.mkdir()
    (export / "manifest.json").write_text("{}")
    det_run = _fake_run(tmp_path / "det_run", RUN_FILES, "train")
    ti_run = _fake_run(tmp_path / "ti_run", PRETRAIN_RUN_FILES, "pretrain")
    return {"loop": (loop, "a broken link or a link loop"), "dangling": (dangling, "a broken link or a link loop"),
            "file": (file, "is a file"), "export": (export, "is a streamdet export (manifest.json)"),
            "run": (det_run, "is a training run"), "image run": (ti_run, "is a training run"),
            "inside a file": (file / "sub", "is not a folder")}  # fmt: skip


@pytest.mark.parametrize("case", ["loop", "dangling", "file", "export", "run", "image run", "inside a file"])
def test_a_bad_cache_dir_is_refused_before_the_split_is_read(data, tmp_path, case):
    cache, said = _cache_cases(tmp_path)[case]
    before = _listing(tmp_path / "export")
    res = _train(data, tmp_path / "out", "--cache-dir", str(cache))
    line = _one_line(res)
    assert res.exit_code == 2 and "--cache-dir" in line and said in line
    assert _listing(tmp_path / "export") == before and not (tmp_path / "out").exists()


def test_the_default_cache_linked_into_an_export_is_refused(data, tmp_path):
    export, _ = _cache_cases(tmp_path)["export"]
    (data / ".streamdet_cache").symlink_to(export)
    line = _one_line(_train(data, tmp_path / "out"))
    assert "--cache-dir (the default, DATA/.streamdet_cache)" in line and "streamdet export" in line
    assert sorted(p.name for p in export.iterdir()) == ["manifest.json"]


# ---- L8: a failed resume into a new --out ----------------------------------------------------------------------------


def test_a_failed_resume_leaves_no_new_folder(part, store, tmp_path):
    with pytest.raises(ValueError, match="holds weights only"):
        train(_config(), "unused", tmp_path / "new" / "deeper", resume=part / "model.pt", store=store, echo=quiet)
    assert not (tmp_path / "new").exists()
    with pytest.raises(ValueError, match="is a streamdet-train checkpoint"):
        pretrain(_ti_config(), "unused", tmp_path / "ti_new", resume=part / "last.pt", echo=quiet)
    assert not (tmp_path / "ti_new").exists()


def test_a_failed_resume_in_its_own_folder_keeps_it(run):
    before = _listing(run)
    with pytest.raises(ValueError, match="--seed"):
        train(_config(seed=3), "unused", run, resume=run / "last.pt", echo=quiet)
    assert _listing(run) == before


def test_a_resume_into_a_new_folder_continues_there(part, store, tmp_path):
    before = _listing(part)
    done = train(_config(), "unused", tmp_path / "copy", resume=part / "last.pt", store=store, echo=quiet)
    assert done.steps_done == 3 and (tmp_path / "copy" / "model.pt").is_file()
    assert _listing(part) == before  # the checkpoint's own folder as it was


@pytest.mark.parametrize("kind", ["meta", "sparse"])
def test_optimizer_state_of_a_meta_or_sparse_moment_is_refused_in_one_line(kind, tmp_path):
    from streamdet.training.trainer import check_optimizer_state

    param = torch.nn.Parameter(torch.zeros(3, 2))
    optimizer = torch.optim.AdamW([param])
    moment = torch.empty(3, 2, device="meta") if kind == "meta" else torch.zeros(3, 2).to_sparse()
    optimizer.state[param] = {"step": torch.tensor(1.0), "exp_avg": moment, "exp_avg_sq": torch.zeros(3, 2)}
    with pytest.raises(ValueError, match=r"checkpoint .*last\.pt: optimizer state 'exp_avg' is a (meta|sparse) tensor"):
        check_optimizer_state(optimizer, tmp_path / "last.pt")


def test_resume_restores_the_fp16_loss_scaler(tmp_path):
    """last.pt keeps the loss scaler's state (CUDA fp16 autocast): its scale and growth tracker decide which next
    steps are skipped, so a resume without them was not the uninterrupted run. Another --amp on resume is said."""
    from types import SimpleNamespace

    from streamdet.training.trainer import _restore_scaler

    said: list[str] = []
    saved_scaler = torch.amp.GradScaler("cpu", init_scale=1024.0, growth_interval=7)
    saved_scaler._lazy_init_scale_growth_tracker(torch.device("cpu"))
    saved_scaler.update(new_scale=256.0)
    saved = saved_scaler.state_dict()
    run = SimpleNamespace(scaler=torch.amp.GradScaler("cpu", growth_interval=7), say=said.append)
    _restore_scaler(run, "last.pt", saved)
    assert run.scaler.get_scale() == 256.0 and not said
    run = SimpleNamespace(scaler=torch.amp.GradScaler("cpu"), say=said.append)
    _restore_scaler(run, "last.pt", None)  # trained without fp16 autocast
    assert run.scaler.get_scale() == 65536.0 and "fresh loss scaler" in said[-1]
    run = SimpleNamespace(scaler=torch.amp.GradScaler("cpu", enabled=False), say=said.append)
    _restore_scaler(run, "last.pt", saved)
    assert "dropped" in said[-1]
    for bad, match in ((["x"], "not the GradScaler"), ({**saved, "scale": float("nan")}, "finite"), ({**saved, "scale": -1.0}, "finite")):
        run = SimpleNamespace(scaler=torch.amp.GradScaler("cpu"), say=said.append)
        with pytest.raises(ValueError, match=match):
            _restore_scaler(run, "last.pt", bad)


@pytest.mark.parametrize("world, rank, skip", [(1, 0, 0), (1, 0, 3), (2, 1, 2), (3, 0, 5)])
def test_a_resumed_epoch_skips_indices_not_batches(world, rank, skip):
    """A resume leaves the batches already trained out at the index level (they were built, pillarised and thrown
    away: about a second a batch); what follows is the uninterrupted epoch's order, epoch after epoch."""
    from streamdet.training.trainer import ResumableSampler

    data = list(range(23))
    for epoch in (0, 4):
        full = torch.utils.data.DistributedSampler(data, num_replicas=world, rank=rank, shuffle=True, seed=9, drop_last=True)
        ours = ResumableSampler(data, num_replicas=world, rank=rank, shuffle=True, seed=9, drop_last=True)
        full.set_epoch(epoch)
        ours.set_epoch(epoch)
        ours.skip = skip
        assert list(ours) == list(full)[skip:] and len(ours) == len(full)
        ours.skip = 0
        assert list(ours) == list(full)
