"""Review 41, area synth: SIGTERM stops `streamdet-synth generate` as Ctrl-C does (S1); the per-point time bound of
docs/synth/timing.md (S2); the camera rate with key-frame exposures added (S3); the summary line's file folders (S4);
a mistyped subcommand is "No such command", not a generate run without --out (S5)."""

from __future__ import annotations

import gc
import os
import signal
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import streamdet.data.synth_cli as synth_cli
import streamdet.data.synth_writer as writer
from streamdet.data.synth_cli import EXIT_TERMINATED, _SigtermStopsRun, _terminated
from streamdet.data.synth_cli import main as synth_main
from streamdet.data.synth_lidar import scan_fraction
from streamdet.data.synth_staging import STAGING_PREFIX, StagedDataset
from streamdet.data.synth_world import WorldConfig, make_scene
from streamdet.data.synth_writer import SynthConfig, real_rig_records, scene_camera_frames, survey_root

REPO = Path(__file__).resolve().parents[1]
TINY = ["--scenes", "2", "--samples-per-scene", "1", "--resolution", "32x18"]


def _snapshot(root: Path) -> dict[str, bytes | None]:
    return {str(p.relative_to(root)): (None if p.is_dir() else p.read_bytes()) for p in sorted(root.rglob("*"))}


def _sentinel(signum, frame) -> None:  # a caller's own SIGTERM handler: generate must put it back
    _sentinel.calls.append(signum)


_sentinel.calls = []


@pytest.fixture
def own_sigterm_handler():
    previous = signal.signal(signal.SIGTERM, _sentinel)
    _sentinel.calls.clear()
    yield
    signal.signal(signal.SIGTERM, previous)


def _sigterm_self_on_second_scene(monkeypatch) -> None:
    """Scene 0 is written into the staging folder; scene 1 sends this process SIGTERM and would then run on."""
    original = writer._write_scene

    def write_scene(out, config, index, progress):
        if index == 1:
            assert any((out / "samples").rglob("*.pcd.bin"))
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(500):  # the handler raises at the next bytecode; without one the run goes on
                time.sleep(0.01)
        return original(out, config, index, progress)

    monkeypatch.setattr(writer, "_write_scene", write_scene)


# ---- S1: SIGTERM -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("state", ["absent", "empty"])
def test_sigterm_mid_generation_removes_what_the_run_wrote_and_exits_143(tmp_path, monkeypatch, own_sigterm_handler,
                                                                        state):
    parent = tmp_path / "parent"
    parent.mkdir()
    out = parent / "ds"
    if state == "empty":
        out.mkdir()
    before = _snapshot(tmp_path)
    _sigterm_self_on_second_scene(monkeypatch)
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(out), *TINY])
    assert result.exit_code == EXIT_TERMINATED == 143, result.output
    assert "Traceback" not in result.output
    (note,) = [line for line in result.output.splitlines() if "SIGTERM" in line]
    assert note.startswith("streamdet-synth: stopped by SIGTERM: removed what this run had written")
    assert _snapshot(tmp_path) == before  # no staging folder, and an --out this run made is gone
    assert signal.getsignal(signal.SIGTERM) is _sentinel and _sentinel.calls == []  # put back, never called


def test_sigterm_with_overwrite_says_the_previous_dataset_went(tmp_path, monkeypatch, own_sigterm_handler):
    out = tmp_path / "ds"
    assert CliRunner().invoke(synth_main, ["generate", "--out", str(out), *TINY]).exit_code == 0
    _sigterm_self_on_second_scene(monkeypatch)
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(out), *TINY, "--overwrite"])
    assert result.exit_code == EXIT_TERMINATED, result.output
    assert "stopped by SIGTERM" in result.output and "the previous dataset (" in result.output
    assert sorted(os.listdir(tmp_path)) == ["ds"] and os.listdir(out) == []  # staging gone, the old dataset too
    assert signal.getsignal(signal.SIGTERM) is _sentinel


def test_sigterm_while_overwrite_deletes_removes_the_staging_folder(tmp_path, monkeypatch, own_sigterm_handler):
    out = tmp_path / "ds"
    assert CliRunner().invoke(synth_main, ["generate", "--out", str(out), *TINY]).exit_code == 0
    original = synth_cli.remove_dataset_entries

    def remove(entries):
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(500):
            time.sleep(0.01)
        original(entries)

    monkeypatch.setattr(synth_cli, "remove_dataset_entries", remove)
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(out), *TINY, "--overwrite"])
    assert result.exit_code == EXIT_TERMINATED, result.output
    assert not [n for n in os.listdir(tmp_path) if n.startswith(STAGING_PREFIX)]


def test_a_sigterm_whose_exception_is_lost_still_stops_the_run(tmp_path, monkeypatch, own_sigterm_handler):
    """C code that clears the errors of what it calls (numpy probing an operand's special attributes) loses the
    handler's exception when the signal lands there: the run still stops, at the next key frame."""
    original = writer._write_scene

    def write_scene(out, config, index, progress):
        if index == 1:
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(1)  # the handler raises here
            except BaseException:
                pass  # lost, as numpy's probe clears it
        return original(out, config, index, progress)

    monkeypatch.setattr(writer, "_write_scene", write_scene)
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(tmp_path / "ds"), *TINY])
    assert result.exit_code == EXIT_TERMINATED, result.output
    assert os.listdir(tmp_path) == []


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_a_file_writer_cut_by_sigterm_closes_without_a_report(tmp_path, monkeypatch, own_sigterm_handler):
    """A zip writer cut between its entry and its close (numpy writing a mask) complained of its closed file when
    collected: "Exception ignored in ZipFile.__del__" and a traceback after the one-line note."""
    original = writer._write_scene

    def write_scene(out, config, index, progress):
        if index == 1:
            with open(out / "half.npz", "wb") as f:
                zf = zipfile.ZipFile(f, "w")
                with zf.open("a.npy", "w") as entry:
                    entry.write(b"x" * 100)
                os.kill(os.getpid(), signal.SIGTERM)
                for _ in range(500):
                    time.sleep(0.01)
        return original(out, config, index, progress)

    monkeypatch.setattr(writer, "_write_scene", write_scene)
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(tmp_path / "ds"), *TINY])
    assert result.exit_code == EXIT_TERMINATED, result.output
    del result  # its exception holds the run's frames: the writer is collected now, or never was
    gc.collect()
    assert os.listdir(tmp_path) == []


def test_a_completed_run_keeps_its_handler_untouched(tmp_path, own_sigterm_handler):
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(tmp_path / "ds"), *TINY])
    assert result.exit_code == 0, result.output
    assert signal.getsignal(signal.SIGTERM) is _sentinel


def test_sigterm_after_the_dataset_was_moved_in_removes_nothing(tmp_path):
    config = SynthConfig(num_scenes=1, resolution=(32, 18), world=WorldConfig(samples_per_scene=1))
    staged = StagedDataset(tmp_path / "ds", config)
    staged.generate()
    assert staged.done
    text = _terminated(tmp_path / "ds", "", staged)
    assert "complete" in text and survey_root(tmp_path / "ds").marker_problem is None


def test_the_handler_context_installs_nothing_outside_the_main_thread():
    errors = []

    def run():
        try:
            with _SigtermStopsRun():
                pass
        except Exception as e:  # signal.signal outside the main thread: ValueError
            errors.append(e)

    before = signal.getsignal(signal.SIGTERM)
    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    assert errors == [] and signal.getsignal(signal.SIGTERM) is before


def _group_gone(pgid: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize("workers", [1, 2])
def test_sigterm_to_a_real_process_cleans_up(tmp_path, workers):
    """A real `streamdet-synth` process (1 or 2 scenes at 96x54, long enough to be mid-run), sent SIGTERM once the
    staging folder holds a sweep: exit 143, one line, and nothing left beside or in --out. With --workers 2 the
    workers are ended too (the parent alone is signalled, as `timeout` and `kill` do)."""
    out = tmp_path / "ds"
    scenes = ["--scenes", str(workers), "--workers", str(workers)]
    code = "from streamdet.cli_utils import synth_main; synth_main()"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-c", code, "--out", str(out), "--seed", "1", "--resolution", "96x54",
                             "--samples-per-scene", "40", *scenes],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                            start_new_session=True)  # its own group: whatever it leaves is ended below  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not list(tmp_path.glob(f"{STAGING_PREFIX}*/samples/LIDAR_TOP/*.bin")):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the run wrote no sweep within 60 s"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=30)
        assert _group_gone(proc.pid, timeout_s=5.0), "worker processes outlived the run"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # workers a parent ended by SIGTERM left running (before the fix)
        except ProcessLookupError:
            pass
    stderr = stderr.decode()
    assert proc.returncode == 143, (proc.returncode, stderr)
    lines = stderr.strip().splitlines()  # the progress report's start line, then the note
    assert "Traceback" not in stderr and [x for x in lines if "SIGTERM" in x] == lines[-1:]
    assert lines[-1] == (f"streamdet-synth: stopped by SIGTERM: removed what this run had written ({out} is as it was "
                         "before the run)")
    assert os.listdir(tmp_path) == []


# ---- S2: per-point times against azimuths ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("s2") / "ds"
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(out), "--scenes", "1", "--seed", "3",
                                             "--resolution", "96x54", "--samples-per-scene", "1"])
    assert result.exit_code == 0, result.output
    return out


def test_point_times_match_azimuths_within_the_documented_ego_motion_bound(small_dataset):
    """timing.md: the written azimuth's scan_fraction * 50 ms is off the firing time t by up to
    asin(v * (50 ms - t) / r) of the rotation, plus half a column; well beyond half a column for most points."""
    sweep_s, half_column_s = 0.05, 0.5 / 1080 * 0.05
    v_max = WorldConfig().ego_speed_mps[1]
    (path,) = sorted((small_dataset / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))
    points = np.fromfile(path, "<f4").reshape(-1, 5)
    t = np.fromfile(str(path) + ".time", "<f4").astype(np.float64)
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    off = np.abs(t - np.asarray(scan_fraction(azimuth)) * sweep_s)
    off = np.minimum(off, sweep_s - off)
    r = np.hypot(points[:, 0], points[:, 1])
    bound = np.arcsin(np.minimum(1.0, v_max * (sweep_s - t) / r)) / (2 * np.pi) * sweep_s + half_column_s
    assert np.all(off <= bound + 1e-6)
    assert np.mean(off > half_column_s) > 0.5  # not "a few near points": most of them


def test_timing_doc_states_the_ego_motion_bound_not_a_column():
    text = (REPO / "docs" / "synth" / "timing.md").read_text()
    assert "to within half a column (23 us), apart from the few near points" not in text
    assert "asin(v * (50 ms - t) / r)" in text


# ---- S3: --camera-hz with the key frames' exposures added --------------------------------------------------------

@pytest.mark.parametrize("sweeps_per_sample", [1, 10])
@pytest.mark.parametrize("camera_hz", [1.0, 2.0, 3.0, 6.0, 10.0, 12.0, 20.0])
def test_camera_rate_is_at_least_the_asked_one_and_at_most_two_hz_more(sweeps_per_sample, camera_hz):
    config = SynthConfig(num_scenes=1, resolution=(96, 54), sweeps_per_sample=sweeps_per_sample, camera_hz=camera_hz,
                         world=WorldConfig(samples_per_scene=41))  # fmt: skip
    frames = scene_camera_frames(make_scene(0, 0, config.world), real_rig_records((96, 54)), config)
    for name, camera in frames.items():
        t = np.array([f.t_s for f in camera])
        rate = (len(t) - 1) / (t[-1] - t[0])
        assert max(camera_hz, 2.0) - 0.1 <= rate <= min(camera_hz + 2.0, 20.0) + 0.1, (name, rate)


def test_ten_hz_gives_as_many_frames_as_twelve_with_ten_sweeps_per_sample():
    def count(hz: float) -> int:
        config = SynthConfig(num_scenes=1, resolution=(96, 54), sweeps_per_sample=10, camera_hz=hz,
                             world=WorldConfig(samples_per_scene=3))  # fmt: skip
        return len(scene_camera_frames(make_scene(0, 0, config.world), real_rig_records((96, 54)), config)["CAM_FRONT"])

    assert count(10.0) == count(12.0) == 18  # the documented example


def test_camera_hz_help_says_key_frames_add_up_to_two_hz():
    text = " ".join(CliRunner().invoke(synth_main, ["generate", "--help"], terminal_width=200).output.split())
    assert "key frames' own exposures are added" in text and "up to 2 Hz more" in text


# ---- S4: the summary line names only the folders written ---------------------------------------------------------

@pytest.mark.parametrize(("extra", "sweeps"), [([], False), (["--sweeps-per-sample", "2"], True),
                                               (["--camera-hz", "4", "--samples-per-scene", "2"], True)])
def test_summary_names_sweeps_only_where_written(tmp_path, extra, sweeps):
    out = tmp_path / "ds"
    result = CliRunner().invoke(synth_main, ["generate", "--out", str(out), "--scenes", "1", "--resolution", "32x18",
                                             "--samples-per-scene", "1", *extra])  # fmt: skip
    assert result.exit_code == 0, result.output
    (line,) = [x for x in result.output.splitlines() if "files:" in x]
    assert (f"{out / 'sweeps'}/" in line) == sweeps == (out / "sweeps").is_dir()
    assert f"{out / 'samples'}/" in line


# ---- S5: the default command only for an option first -----------------------------------------------------------

@pytest.mark.parametrize("args", [["stat", "d1"], ["stat", "--out", "x"], ["generat", "--out", "x"], ["d1"]])
def test_an_unknown_subcommand_is_no_such_command(tmp_path, args):
    result = CliRunner().invoke(synth_main, args)
    assert result.exit_code == 2
    assert f"No such command '{args[0]}'" in result.output and "Missing option" not in result.output
    assert os.listdir(tmp_path) == []


def test_a_near_miss_gets_clicks_hint():
    assert "Did you mean 'stats'?" in CliRunner().invoke(synth_main, ["stat", "d1"]).output


@pytest.mark.parametrize(("args", "error"), [(["--seed", "3"], "Missing option '--out'"),
                                             (["--scenes", "0", "--out", "x"], "Invalid value for '--scenes'"),
                                             (["--out"], "Option '--out' requires an argument")])
def test_an_option_first_is_still_the_generate_command(tmp_path, monkeypatch, args, error):
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(synth_main, args)
    assert result.exit_code == 2 and error in result.output and "No such command" not in result.output, result.output
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("args", [["--help"], ["-h"]])
def test_help_is_the_groups(args):
    result = CliRunner().invoke(synth_main, args, prog_name="streamdet-synth")
    assert result.exit_code == 0 and "Commands:" in result.output and "stats" in result.output


def test_out_without_a_subcommand_generates(tmp_path):
    out = tmp_path / "ds"
    result = CliRunner().invoke(synth_main, ["--out", str(out), *TINY])
    assert result.exit_code == 0, result.output
    assert (out / "v1.0-synth" / "sample.json").is_file()
