"""Review 40 of the training tools (training/, models/): checkpoint read errors that name what a file holds, the image
encoder's NCHW input, metrics.jsonl trimmed on resume, Ctrl-C saving the last step, a finished run's missing model.pt,
stale temp files, checks before the data is read, dropped targets counted, the log kept on divergence, --init of a
streamdet-train-image last.pt, --resume taking the run's options, train-image's batch size, progress on stderr."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

import streamdet.training.image_pretrain as image_pretrain
import streamdet.training.trainer as trainer
from streamdet.training.interrupts import InterruptedMidStep
from streamdet.models.image_encoder import ImageEncoder
from streamdet.models.presets import get_preset
from streamdet.models.torch_files import read_torch_file
from streamdet.training.batching import Collator
from streamdet.training.checkpoint import load_checkpoint, save_atomic
from streamdet.training.cli import main as train_main
from streamdet.training.dataset import DataConfig, SliceDataset, build_store
from streamdet.training.image_pretrain import PretrainConfig, pretrain
from streamdet.training.image_pretrain_cli import main as pretrain_main
from streamdet.training.run_dir import remove_stale_temps, trim_run_log
from streamdet.training.targets import TargetConfig
from streamdet.training.trainer import TrainConfig, train

TINY = get_preset("tiny")
SIZE = (TINY.image.width_px, TINY.image.height_px)
QUIET = dict(echo=lambda m: None)


@pytest.fixture(scope="module")
def data_dir(tiny_train_data) -> Path:
    return tiny_train_data  # 4 train samples at the tiny preset's 128x72


@pytest.fixture(scope="module")
def store(data_dir, tmp_path_factory):
    return build_store(data_dir, "train", SIZE, cache_dir=tmp_path_factory.mktemp("cache"))


def _config(**kw) -> TrainConfig:
    base = dict(preset="tiny", steps=3, batch_size=1, lr=1e-3, log_every=1, checkpoint_every=100, seed=0)
    return TrainConfig(**{**base, **kw})


@pytest.fixture(scope="module")
def full_run(store, tmp_path_factory) -> Path:
    """The uninterrupted 3-step run the interrupted ones must equal."""
    out = tmp_path_factory.mktemp("full") / "run"
    train(_config(), "unused", out, store=store, **QUIET)
    return out


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _assert_same_weights(a: Path, b: Path) -> None:
    wa, wb = load_checkpoint(a)["model"], load_checkpoint(b)["model"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


# ---- M3 / CLI M1: a file torch cannot read as weights is named for what it is ----------------------------------


class _System:
    """A pickle that would run os.system when unpickled without weights_only."""

    def __reduce__(self):
        return (os.system, ("true",))


@pytest.mark.parametrize(
    "content, reason",
    [
        ("evil", r"names the Python global (posix|nt)\.system"),
        (b"not a checkpoint\n", r"a text file \(it starts 'not a checkpoint'\), not a file torch.save wrote"),
        (b"", "an empty file"),
        (b"\x08\x07\x12\x07pytorch\xff\xfe", "neither a zip archive nor a pickle"),
    ],
)
def test_an_unreadable_file_is_named_for_what_it_holds_never_with_torchs_advice(tmp_path, content, reason):
    path = tmp_path / "x.pt"
    if content == "evil":
        torch.save({"model": _System()}, path)
    else:
        path.write_bytes(content)
    with pytest.raises(ValueError, match=rf"checkpoint .*x.pt cannot be read with weights_only=True: .*{reason}") as e:
        read_torch_file(path)
    text = str(e.value)
    assert "weights_only=False" not in text and "`False`" not in text and "\n" not in text


def test_cli_init_of_a_text_file_says_so_before_reading_the_data(data_dir, tmp_path):
    bad = tmp_path / "notckpt.pt"
    bad.write_text("not a checkpoint\n")
    res = CliRunner().invoke(train_main, ["--data", str(data_dir), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                          "--steps", "1", "--init", str(bad), "--cache-dir", str(tmp_path / "c")])  # fmt: skip
    assert res.exit_code == 1 and "a text file" in res.output and "weights_only=False" not in res.output
    assert "reading the train split" not in res.output  # L4: refused before the data is read
    assert not (tmp_path / "o").exists()


# ---- M2: the image encoder runs its backbone on NCHW-contiguous input ---------------------------------------------


def test_image_encoder_feeds_its_backbone_contiguous_input_with_the_same_features():
    torch.manual_seed(0)
    enc = ImageEncoder(TINY.image, TINY.channels).eval()
    seen = []
    enc.backbone.register_forward_pre_hook(lambda _m, args: seen.append(args[0].is_contiguous()))
    images = torch.randint(0, 256, (3, SIZE[1], SIZE[0], 3), dtype=torch.uint8)
    with torch.no_grad():
        got = enc(images)
        channels_last = images.permute(0, 3, 1, 2).float() * enc.scale + enc.shift  # what it ran on before
        ref = enc.neck(enc.backbone(channels_last))
    assert seen[0] is True  # the channels-last view crashed backward under torch 2.13 CPU (tiny, odd batch)
    torch.testing.assert_close(got, ref, rtol=1e-4, atol=1e-4)  # other kernels, the same features


def test_image_encoder_backward_at_odd_batch_sizes_does_not_kill_the_process():
    # in a process of its own: the heap corruption killed the interpreter (SIGABRT / SIGSEGV / SIGFPE)
    code = (
        "import torch\n"
        "from streamdet.models.presets import get_preset\n"
        "from streamdet.models.image_encoder import ImageEncoder\n"
        "torch.manual_seed(0)\n"
        "p = get_preset('tiny'); enc = ImageEncoder(p.image, p.channels)\n"
        "for b in (3, 5):\n"
        "    for _ in range(5):\n"
        "        enc(torch.randint(0, 255, (b, 72, 128, 3), dtype=torch.uint8)).sum().backward()\n"
        "print('ok')\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and "ok" in run.stdout, (run.returncode, run.stderr[-2000:])


# ---- M1: a resume trims the records logged after its checkpoint -------------------------------------------------


def test_trim_run_log_keeps_records_up_to_the_step(tmp_path):
    log = tmp_path / "metrics.jsonl"
    log.write_text('{"step": 1}\n{"step": 2}\n{"step": 3}\n{"step": 2, "val": 1}\n{"step": 4, "lo')  # a line cut by a kill
    assert trim_run_log(log, 2) == 2
    assert [r["step"] for r in _records(log)] == [1, 2, 2]
    assert trim_run_log(log, 2) == 0 and trim_run_log(tmp_path / "none.jsonl", 5) == 0
    assert not list(tmp_path.glob(".*tmp"))


def test_a_resume_after_a_kill_logs_each_step_once(store, tmp_path, full_run):
    out = tmp_path / "run"
    part = train(_config(max_minutes=1e-9), "unused", out, store=store, **QUIET)  # last.pt at step 1
    assert part.steps_done == 1
    with open(out / "metrics.jsonl", "a") as f:  # what a run killed at step 2 had logged past its checkpoint
        f.write(json.dumps({"step": 2, "loss": 9.0}) + "\n" + '{"step": 3, "lo')
    said = []
    train(_config(), "unused", out, resume=out / "last.pt", store=store, echo=said.append)
    assert any("dropped 2 record(s) logged after step 1" in m for m in said)
    got, want = _records(out / "metrics.jsonl"), _records(full_run / "metrics.jsonl")
    assert [r["step"] for r in got] == [1, 2, 3]
    assert [r["loss"] for r in got] == [r["loss"] for r in want]  # the uninterrupted run's log
    _assert_same_weights(out / "model.pt", full_run / "model.pt")


def test_pretrain_resume_trims_its_log(tiny_synth_data, tmp_path):
    cfg = PretrainConfig(preset="tiny", steps=3, batch_size=2, eval_every=10, checkpoint_every=10, warmup_steps=1, stop_at_step=1)
    pretrain(cfg, tiny_synth_data, tmp_path, splits=(None, None), **QUIET)
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"step": 2, "loss": 9.0}) + "\n")
    whole = PretrainConfig(preset="tiny", steps=3, batch_size=2, eval_every=10, checkpoint_every=10, warmup_steps=1)
    pretrain(whole, tiny_synth_data, tmp_path, resume=tmp_path / "last.pt", splits=(None, None), **QUIET)
    steps = [r["step"] for r in _records(tmp_path / "metrics.jsonl") if "loss" in r]
    assert steps == [1] and 9.0 not in [r.get("loss") for r in _records(tmp_path / "metrics.jsonl")]


# ---- L1: Ctrl-C writes the checkpoint of the last step done ------------------------------------------------------


def test_ctrl_c_during_an_update_saves_that_step_and_resume_loses_nothing(store, tmp_path, full_run, monkeypatch):
    update = trainer._update
    calls = {"n": 0}

    def interrupted_update(run):
        calls["n"] += 1
        if calls["n"] == 2:  # a Ctrl-C arrives mid-update of step 2: the update and its step count finish first
            os.kill(os.getpid(), signal.SIGINT)
        update(run)

    monkeypatch.setattr(trainer, "_update", interrupted_update)
    out = tmp_path / "run"
    said = []
    with pytest.raises(KeyboardInterrupt):
        train(_config(), "unused", out, store=store, echo=said.append)
    assert load_checkpoint(out / "last.pt")["step"] == 2 and load_checkpoint(out / "model.pt")["meta"]["steps"] == 2
    assert [r["step"] for r in _records(out / "metrics.jsonl")] == [1, 2]
    assert any("interrupted after step 2" in m for m in said)
    monkeypatch.setattr(trainer, "_update", update)
    train(_config(), "unused", out, resume=out / "last.pt", store=store, **QUIET)
    _assert_same_weights(out / "model.pt", full_run / "model.pt")
    assert [r["loss"] for r in _records(out / "metrics.jsonl")] == [r["loss"] for r in _records(full_run / "metrics.jsonl")]


def test_a_second_ctrl_c_mid_step_writes_nothing_of_that_step(store, tmp_path, monkeypatch):
    step = trainer._step
    calls = {"n": 0}

    def twice(run, batch, use_image):
        calls["n"] += 1
        if calls["n"] == 2:  # the first Ctrl-C waits for the step's end, the second one ends it at once
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
        return step(run, batch, use_image)

    monkeypatch.setattr(trainer, "_step", twice)
    out = tmp_path / "run"
    said = []
    with pytest.raises(InterruptedMidStep):
        train(_config(checkpoint_every=1), "unused", out, store=store, echo=said.append)
    assert load_checkpoint(out / "last.pt")["step"] == 1 and not (out / "model.pt").exists()
    assert any("interrupted again in the middle of step 2" in m for m in said)


def test_ctrl_c_before_the_first_step_leaves_a_new_run_nothing(store, tmp_path, monkeypatch):
    def interrupted(*_a, **_k):
        raise KeyboardInterrupt

    monkeypatch.setattr(trainer, "_step", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train(_config(), "unused", tmp_path / "run", store=store, **QUIET)
    assert not (tmp_path / "run").exists()


def test_a_second_ctrl_c_during_the_save_leaves_the_previous_checkpoint_whole(tmp_path, monkeypatch):
    path = tmp_path / "last.pt"
    save_atomic({"step": 1}, path)

    def cut_save(obj, f):
        f.write(b"PK\x03\x04 half a checkpoint")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", cut_save)
    with pytest.raises(KeyboardInterrupt):
        save_atomic({"step": 2}, path)
    monkeypatch.undo()
    assert read_torch_file(path) == {"step": 1} and sorted(p.name for p in tmp_path.iterdir()) == ["last.pt"]


def test_pretrain_ctrl_c_saves_the_last_step_and_resume_equals_the_straight_run(tiny_synth_data, tmp_path, monkeypatch):
    cfg = PretrainConfig(preset="tiny", steps=4, batch_size=2, eval_every=10, checkpoint_every=10, warmup_steps=1)
    straight = tmp_path / "straight"
    pretrain(cfg, tiny_synth_data, straight, splits=(None, None), **QUIET)
    loss = image_pretrain.F.cross_entropy
    calls = {"n": 0}

    def interrupted(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:  # a Ctrl-C in step 3's forward pass: the step ends first
            os.kill(os.getpid(), signal.SIGINT)
        return loss(*a, **k)

    monkeypatch.setattr(image_pretrain.F, "cross_entropy", interrupted)
    cut = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        pretrain(cfg, tiny_synth_data, cut, splits=(None, None), **QUIET)
    monkeypatch.undo()
    assert read_torch_file(cut / "last.pt")["step"] == 3 and (cut / "encoder.pt").is_file()
    pretrain(cfg, tiny_synth_data, cut, resume=cut / "last.pt", splits=(None, None), **QUIET)
    a, b = read_torch_file(cut / "encoder.pt"), read_torch_file(straight / "encoder.pt")
    assert all(torch.equal(a[k], b[k]) for k in b)


# ---- L2 / L4: a finished schedule, and checks before the data ----------------------------------------------------


def test_a_finished_run_without_model_pt_gets_it_from_last_pt_before_any_data(full_run, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    for name in ("last.pt", "metrics.jsonl", "config.json"):
        (run / name).write_bytes((full_run / name).read_bytes())
    said = []
    # "unused" data and no store: the answer comes before the train split would be read
    result = train(_config(), "/nonexistent/data", run, resume=run / "last.pt", echo=said.append)
    assert result.weights == run / "model.pt" and result.steps_done == 3
    assert any("wrote" in m and "model.pt" in m for m in said)
    _assert_same_weights(run / "model.pt", full_run / "model.pt")
    with pytest.raises(ValueError, match=rf"finished its schedule \(3 steps\): nothing left to train; its weights are {run}/model.pt"):
        train(_config(), "/nonexistent/data", run, resume=run / "last.pt", **QUIET)
    (run / "model.pt").unlink()
    with pytest.raises(ValueError, match=rf"its folder has no model.pt of it: resume it there \(--out {run}\)"):
        train(_config(), "/nonexistent/data", tmp_path / "elsewhere", resume=run / "last.pt", **QUIET)
    assert not (tmp_path / "elsewhere").exists()


def test_init_and_teacher_are_read_before_the_train_split(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_text("{}\n")
    with pytest.raises(ValueError, match="init checkpoint .*bad.pt cannot be read .*a text file"):
        train(_config(), "/nonexistent/data", tmp_path / "a", init=bad, **QUIET)
    with pytest.raises(ValueError, match="checkpoint .*bad.pt cannot be read .*a text file"):
        train(_config(teacher=str(bad)), "/nonexistent/data", tmp_path / "b", **QUIET)


# ---- L3: temp files of a killed save ------------------------------------------------------------------------------


def test_stale_temps_of_a_dead_save_are_removed_and_a_live_ones_kept(full_run, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    for name in ("last.pt", "model.pt", "metrics.jsonl", "config.json"):
        (run / name).write_bytes((full_run / name).read_bytes())
    dead = run / f".last.pt.abcd1234.{_dead_pid()}.tmp"
    live = run / f".model.pt.abcd1234.{os.getpid()}.tmp"
    other = [run / ".last.pt.abcd1234.tmp", run / f".notes.txt.abcd1234.{_dead_pid()}.tmp"]  # not this tool's pattern
    for path in (dead, live, *other):
        path.write_bytes(b"x")
    said = []
    with pytest.raises(ValueError, match="nothing left to train"):
        train(_config(), "/nonexistent/data", run, resume=run / "last.pt", echo=said.append)
    assert not dead.exists() and live.exists() and all(p.exists() for p in other)
    assert any(str(dead) in m for m in said)
    assert remove_stale_temps(run, ("last.pt",)) == []


def test_checkpoints_are_staged_under_a_name_holding_the_pid(tmp_path, monkeypatch):
    names = []
    from streamdet.core import file_output

    opened = file_output.open_beside

    def recorded(path, suffix):
        tmp, f = opened(path, suffix)
        names.append(tmp.name)
        return tmp, f

    monkeypatch.setattr(file_output, "open_beside", recorded)
    save_atomic({"a": 1}, tmp_path / "last.pt")
    assert names[0].startswith(".last.pt.") and names[0].endswith(f".{os.getpid()}.tmp")


# ---- L5: targets beyond the cap are counted ------------------------------------------------------------------------


def test_dropped_targets_are_counted_warned_once_and_logged(store, tmp_path):
    data = DataConfig(targets=TargetConfig(max_objects=1))  # a map with two objects drops one
    items = [SliceDataset(store, TINY, data)[i] for i in range(len(store))]
    batch = Collator(TINY)(items)
    want = sum(t.num_dropped for it in items for sl in it.slices for t in sl.targets)
    assert batch.num_dropped == want > 0
    said = []
    result = train(_config(data=data), "unused", tmp_path / "run", store=store, echo=said.append)
    warnings = [m for m in said if m.startswith("warning:") and "target box(es) left out" in m]
    assert len(warnings) == 1 and f"{result.dropped_targets} target" in warnings[0] and "cap of 1 objects" in warnings[0]
    logged = sum(r.get("dropped_targets", 0) for r in _records(tmp_path / "run" / "metrics.jsonl"))
    assert logged == result.dropped_targets > 0


# ---- L6: on divergence the steps before it are logged -------------------------------------------------------------


def test_divergence_logs_the_unlogged_steps_before_it(store, tmp_path, monkeypatch):
    step = trainer._step
    calls = {"n": 0}

    def nan_at_3(run, batch, use_image):
        loss, parts = step(run, batch, use_image)
        calls["n"] += 1
        return (loss * float("nan"), parts) if calls["n"] == 3 else (loss, parts)

    monkeypatch.setattr(trainer, "_step", nan_at_3)
    out = tmp_path / "run"
    with pytest.raises(ValueError, match="diverged: the loss is nan at step 3"):
        train(_config(steps=5, log_every=5), "unused", out, store=store, **QUIET)
    assert [r["step"] for r in _records(out / "metrics.jsonl")] == [2]  # steps 1-2, before the NaN


def test_pretrain_divergence_logs_the_last_finite_step(tiny_synth_data, tmp_path, monkeypatch):
    loss = image_pretrain.F.cross_entropy
    calls = {"n": 0}

    def nan_at_3(*a, **k):
        calls["n"] += 1
        value = loss(*a, **k)
        return value * float("nan") if calls["n"] == 3 else value

    monkeypatch.setattr(image_pretrain.F, "cross_entropy", nan_at_3)
    cfg = PretrainConfig(preset="tiny", steps=5, batch_size=2, eval_every=10, checkpoint_every=10, warmup_steps=1)
    with pytest.raises(ValueError, match="diverged"):
        pretrain(cfg, tiny_synth_data, tmp_path, splits=(None, None), **QUIET)
    assert [r["step"] for r in _records(tmp_path / "metrics.jsonl")] == [1, 2]


# ---- L7: --init of streamdet-train-image's last.pt ----------------------------------------------------------------


def test_init_of_a_pretrain_last_pt_names_the_files_to_use(tmp_path):
    path = tmp_path / "last.pt"
    torch.save({"model": {}, "optimizer": {}, "step": 3, "config": {"preset": "tiny"}}, path)
    with pytest.raises(ValueError, match=rf"is a streamdet-train-image last.pt .*takes {tmp_path}/detector_init.pt .* or "
                                         rf"{tmp_path}/encoder.pt"):  # fmt: skip
        load_checkpoint(path, "init checkpoint")


# ---- CLI L2 / L5 / L6 ---------------------------------------------------------------------------------------------


def test_cli_resume_alone_takes_the_runs_options_and_refuses_contradicting_ones(data_dir, store, tmp_path, full_run):
    out = tmp_path / "run"
    train(_config(max_minutes=1e-9), "unused", out, store=store, **QUIET)  # a tiny 3-step run cut after step 1
    base = ["--data", str(data_dir), "--out", str(out), "--resume", str(out / "last.pt"), "--cache-dir", str(tmp_path / "c")]
    for extra, flag, values in [(["--preset", "small"], "--preset", ("--preset tiny; given --preset small",)),
                                (["--steps", "5"], "--steps", ("--steps 3; given --steps 5",)),
                                (["--no-image"], "--no-image", ("--no-image off; given --no-image on",))]:  # fmt: skip
        res = CliRunner().invoke(train_main, [*base, *extra])
        assert res.exit_code == 2 and flag in res.output and all(v in res.output for v in values), res.output
    res = CliRunner().invoke(train_main, [*base, "--overwrite"])
    assert res.exit_code == 2 and "--overwrite" in res.output
    # a resume may change how it logs and its wall-time limit (which it would take from the run: 1e-9 min here)
    res = CliRunner().invoke(train_main, [*base, "--log-every", "2", "--max-minutes", "600"])
    assert res.exit_code == 0, res.output
    # CLI L6: the run's description and its result on stdout, the progress on stderr
    lines = res.stdout.splitlines()
    assert len(lines) == 2 and lines[0].startswith("training tiny") and lines[1].startswith("done after 3 steps"), lines
    assert "resumed" in res.stderr and "step      2/3" in res.stderr
    _assert_same_weights(out / "model.pt", full_run / "model.pt")


def test_resume_with_another_preset_names_the_saved_one(store, tmp_path):
    out = tmp_path / "run"
    train(_config(max_minutes=1e-9), "unused", out, store=store, **QUIET)
    with pytest.raises(ValueError, match=r"was trained with --preset tiny, given --preset small"):
        train(_config(preset="small"), "unused", tmp_path / "other", resume=out / "last.pt", store=store, **QUIET)


def test_cli_train_image_resume_takes_the_runs_options(data_dir, tmp_path):
    out = tmp_path / "run"
    first = ["--data", str(data_dir), "--out", str(out), "--preset", "tiny", "--steps", "2", "--batch-size", "2",
             "--eval-every", "10", "--stop-at-step", "1", "--max-samples", "1"]  # fmt: skip
    res = CliRunner().invoke(pretrain_main, first)
    assert res.exit_code == 0, res.output
    lines = res.stdout.splitlines()
    assert lines == ["6 train images, 6 val images", lines[1]] and lines[1].startswith("stopped (--max-minutes / --stop-at-step) at step 1")
    assert "train images" in res.stderr
    again = ["--data", str(data_dir), "--out", str(out), "--resume", str(out / "last.pt"), "--max-samples", "1"]
    res = CliRunner().invoke(pretrain_main, [*again, "--batch-size", "4"])
    assert res.exit_code == 2 and "was trained with --batch-size 2; given --batch-size 4" in res.output
    res = CliRunner().invoke(pretrain_main, [*again, "--overwrite"])
    assert res.exit_code == 2 and "--overwrite" in res.output
    res = CliRunner().invoke(pretrain_main, again)
    assert res.exit_code == 0, res.output
    assert res.stdout.splitlines()[-1].startswith("finished at step 2"), res.stdout


def test_cli_train_image_refuses_a_batch_larger_than_the_images(data_dir, tmp_path):
    res = CliRunner().invoke(pretrain_main, ["--data", str(data_dir), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                             "--steps", "1", "--batch-size", "1000", "--max-samples", "1"])  # fmt: skip
    assert res.exit_code == 1 and "batch_size 1000 (--batch-size) is more than the 6 train images" in res.output, res.output
    assert "train images, " not in res.output and not (tmp_path / "o").exists()  # refused before the val images


def test_sigint_deferral_steps_aside_for_a_handler_installed_from_c(monkeypatch):
    """signal.getsignal gives None for a handler set outside Python (an embedding host); it cannot be put back, so
    the block runs undeferred rather than failing every step in its finally."""
    from streamdet.training import interrupts

    monkeypatch.setattr(interrupts.signal, "getsignal", lambda signum: None)
    ran = []
    with interrupts.sigint_deferred():
        ran.append(True)
    assert ran == [True]
