"""streamdet-synth generate writes its dataset into a staging folder and renames it into --out at the end: an error
or Ctrl-C at any point leaves --out as it was (absent, empty, a foreign file kept), so the next run is not refused
as "already holds a streamdet-synth dataset"; what can be checked before the simulation is checked before it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

import streamdet.data.synth_staging as staging
import streamdet.data.synth_writer as writer
from streamdet.cli_utils import EXIT_INTERRUPTED, run_edge
from streamdet.data.synth_cli import main as synth_main
from streamdet.data.synth_world import WorldConfig
from streamdet.data.synth_staging import STAGING_PREFIX, StagedDataset
from streamdet.data.synth_writer import SynthConfig, generate_dataset, survey_root

TINY = ["--scenes", "2", "--samples-per-scene", "1", "--resolution", "32x18"]


def _snapshot(root: Path) -> dict[str, bytes | None] | None:
    """Every path under ``root`` with its bytes (None for folders); None where ``root`` does not exist."""
    if not root.exists():
        return None
    return {str(p.relative_to(root)): (None if p.is_dir() else p.read_bytes()) for p in sorted(root.rglob("*"))}


def _generate(out: Path, *args: str):
    return CliRunner().invoke(synth_main, ["generate", "--out", str(out), *TINY, *args])


def _fail_on_second_scene(monkeypatch, exc: BaseException, calls: list[int] | None = None) -> None:
    """Scene 0 is written (its files land in the staging folder), scene 1 raises ``exc``."""
    original = writer._write_scene

    def write_scene(out, config, index, progress):
        if calls is not None:
            calls.append(index)
        if index == 1:
            assert any((out / "samples").rglob("*.pcd.bin"))  # a half-written dataset exists by now
            raise exc
        return original(out, config, index, progress)

    monkeypatch.setattr(writer, "_write_scene", write_scene)


def _prepare(tmp_path: Path, state: str) -> Path:
    out = tmp_path / "parent" / "ds"
    (tmp_path / "parent").mkdir()
    if state in ("empty", "foreign"):
        out.mkdir()
    if state == "foreign":
        (out / "notes.txt").write_text("mine")
    return out


@pytest.mark.parametrize("state", ["absent", "empty"])
def test_an_error_mid_generation_leaves_out_as_it_was_and_a_rerun_succeeds(tmp_path, monkeypatch, state):
    out = _prepare(tmp_path, state)
    before = _snapshot(tmp_path)
    _fail_on_second_scene(monkeypatch, OSError(28, "No space left on device (test)"))
    result = _generate(out)
    assert result.exit_code == 1 and "Traceback" not in result.output, result.output
    (line,) = [x for x in result.output.splitlines() if x.startswith("Error")]
    assert "No space left on device (test)" in line and "removed what this run had written" in line
    assert _snapshot(tmp_path) == before  # no staging folder left beside --out either
    monkeypatch.undo()
    result = _generate(out)
    assert result.exit_code == 0, result.output
    assert survey_root(out).marker_problem is None and (out / "v1.0-synth" / "sample.json").is_file()


@pytest.mark.parametrize("state", ["absent", "empty"])
def test_ctrl_c_mid_generation_leaves_out_as_it_was(tmp_path, monkeypatch, capsys, state):
    out = _prepare(tmp_path, state)
    before = _snapshot(tmp_path)
    _fail_on_second_scene(monkeypatch, KeyboardInterrupt())
    code = run_edge("streamdet.data.synth_cli", "streamdet-synth", args=["generate", "--out", str(out), *TINY])
    err = capsys.readouterr().err
    assert code == EXIT_INTERRUPTED and "Traceback" not in err
    assert "removed what this run had written" in err and "streamdet-synth: interrupted" in err
    assert _snapshot(tmp_path) == before
    monkeypatch.undo()
    assert _generate(out).exit_code == 0


@pytest.mark.parametrize("where", ["tables", "trajectories", "preview", "move"])
def test_a_failure_after_the_simulation_rolls_back_too(tmp_path, monkeypatch, where):
    """Late failures: the table writer, trajectories.npz, the previews, and the renames into --out (two entries
    moved already: they go again)."""
    out = _prepare(tmp_path, "empty")
    before = _snapshot(tmp_path)

    def boom(*args, **kwargs):
        raise OSError(5, f"I/O error in {where} (test)")

    if where == "tables":
        monkeypatch.setattr(writer, "write_tables", boom)
    elif where == "trajectories":
        monkeypatch.setattr(writer, "write_trajectories", boom)
    elif where == "preview":
        import streamdet.data.preview as preview

        monkeypatch.setattr(preview, "write_previews", boom)
    else:
        moved = []
        original = staging._move

        def move(src, dst):
            if len(moved) == 2:
                boom()
            moved.append(dst)
            original(src, dst)

        monkeypatch.setattr(staging, "_move", move)
    result = _generate(out, "--preview")
    assert result.exit_code == 1 and f"I/O error in {where} (test)" in result.output, result.output
    assert _snapshot(tmp_path) == before
    if where == "move":
        assert len(moved) == 2


def test_overwrite_says_the_previous_dataset_was_deleted_and_keeps_the_training_cache(tmp_path, monkeypatch):
    out = _prepare(tmp_path, "absent")
    assert _generate(out, "--scenes", "1").exit_code == 0
    (out / ".streamdet_cache").mkdir()
    (out / ".streamdet_cache" / "meta.json").write_text("{}")
    _fail_on_second_scene(monkeypatch, OSError(28, "No space left on device (test)"))
    result = _generate(out, "--overwrite")
    assert result.exit_code == 1, result.output
    assert "the previous dataset (" in result.output and "was deleted before the run started" in result.output
    assert sorted(p.name for p in out.iterdir()) == [".streamdet_cache"]
    assert sorted(p.name for p in (tmp_path / "parent").iterdir()) == ["ds"]
    monkeypatch.undo()
    assert _generate(out).exit_code == 0  # the cache is no dataset: not refused
    assert (out / ".streamdet_cache" / "meta.json").is_file()


def test_a_foreign_file_is_kept_and_one_written_during_the_run_stays(tmp_path):
    """The library: an --out with someone's file, and another file arriving while the run goes on; a failure removes
    the run's own entries only."""
    out = _prepare(tmp_path, "foreign")
    config = SynthConfig(num_scenes=2, resolution=(32, 18), world=WorldConfig(samples_per_scene=1))
    staged = StagedDataset(out, config)

    def progress(n):
        (out / "arrived.txt").write_text("theirs")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        staged.generate(progress=progress)
    assert sorted(p.name for p in out.iterdir()) == ["arrived.txt", "notes.txt"]
    assert (out / "notes.txt").read_text() == "mine" and staged.left == []
    assert sorted(p.name for p in (tmp_path / "parent").iterdir()) == ["ds"]


def test_a_parallel_run_interrupted_cancels_its_scenes_and_leaves_nothing(tmp_path):
    out = _prepare(tmp_path, "absent")
    config = SynthConfig(num_scenes=4, resolution=(32, 18), world=WorldConfig(samples_per_scene=1))

    def progress(n):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        StagedDataset(out, config).generate(progress=progress, workers=2)
    assert list((tmp_path / "parent").iterdir()) == []


def test_a_finished_run_has_the_layout_of_generate_dataset(tmp_path):
    config = SynthConfig(num_scenes=2, resolution=(32, 18), sweeps_per_sample=2, world=WorldConfig(samples_per_scene=1))
    generate_dataset(tmp_path / "plain", config)
    summary = StagedDataset(tmp_path / "staged", config).generate()
    assert summary.out_dir == tmp_path / "staged"
    assert _snapshot(tmp_path / "staged") == _snapshot(tmp_path / "plain")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(STAGING_PREFIX)]


def test_an_out_holding_a_dataset_name_is_refused_before_the_simulation(tmp_path, monkeypatch):
    calls: list[int] = []
    _fail_on_second_scene(monkeypatch, AssertionError("never simulated"), calls)
    out = tmp_path / "ds"
    out.mkdir()
    (out / "samples").mkdir()
    config = SynthConfig(num_scenes=1, resolution=(32, 18), world=WorldConfig(samples_per_scene=1))
    with pytest.raises(FileExistsError, match="already holds samples"):
        StagedDataset(out, config).generate()
    assert calls == [] and [p.name for p in out.iterdir()] == ["samples"] and [p.name for p in tmp_path.iterdir()] == ["ds"]


@pytest.mark.parametrize(
    "args, code, message",
    [
        (["--version", "v" * 300], 2, "at most 255 bytes"),
        (["--version", "é" * 128], 2, "at most 255 bytes"),  # 256 bytes in UTF-8
    ],
)
def test_an_over_long_version_is_refused_before_any_simulation(tmp_path, monkeypatch, args, code, message):
    calls: list[int] = []
    _fail_on_second_scene(monkeypatch, AssertionError("never simulated"), calls)
    out = tmp_path / "g2"
    result = _generate(out, *args)
    assert result.exit_code == code and message in result.output and "--version" in result.output, result.output
    assert "simulating" not in result.output and calls == []
    assert list(tmp_path.iterdir()) == []


def test_an_out_the_file_system_refuses_fails_before_any_simulation(tmp_path, monkeypatch):
    calls: list[int] = []
    _fail_on_second_scene(monkeypatch, AssertionError("never simulated"), calls)
    out = tmp_path / "parent" / ("o" * 300)  # a name of 300 bytes: ENAMETOOLONG
    result = _generate(out)
    assert result.exit_code == 1 and "cannot write the dataset under" in result.output, result.output
    assert "simulating" not in result.output and calls == []
    assert list(tmp_path.iterdir()) == []  # the parent it made is gone again


def test_a_run_with_a_version_of_255_bytes_completes(tmp_path):
    out = tmp_path / "ds"
    result = _generate(out, "--scenes", "1", "--version", "v" * 255)
    assert result.exit_code == 0, result.output
    assert (out / ("v" * 255) / "sample.json").is_file()
    assert json.loads((out / "splits.json").read_text())["train"] == ["synth-0-0000"]
