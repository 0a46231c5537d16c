"""streamdet-replay, streamdet-bench and streamdet-study refuse, before any work, outputs that would replace their
inputs or each other, outputs that cannot be written (a missing folder, a plot format matplotlib lacks), and options
that do nothing in the mode asked for (CLI audit A2, A11, C3, D1, D10, D11).

Every refusal is a click usage error: exit 2, one "Error" line naming the option and the path. The work itself
(run_replay, run_benchmark, a study's export) is replaced by a stub that records whether it was reached, so that
each test shows the check ran first and stays fast.
"""

from __future__ import annotations

import click
import pytest
from click.testing import CliRunner

from streamdet.benchmarks import cli as bench_cli
from streamdet.replay import cli as replay_cli
from streamdet.studies import cli as study_cli

MANIFEST = '{"a": "manifest"}'  # stands for an export's manifest: the checks never read it
SPLITS = '{"val": []}'


def _usage_error(result, option: str, *needles: str) -> str:
    """The result is one click usage error (exit 2, no traceback) naming ``option`` and every needle."""
    assert result.exit_code == 2, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    errors = [line for line in result.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, result.output
    for needle in (option, *needles):
        assert needle in errors[0], errors[0]
    return errors[0]


@pytest.fixture
def inputs(tmp_path):
    """A stand-in export and dataset: enough for the CLIs' cheap input checks, never read further."""
    export, data, fallback = tmp_path / "exp", tmp_path / "data", tmp_path / "fallback"
    for folder in (export, data / "v1.0-synth", data / "samples" / "CAM_FRONT", fallback):
        folder.mkdir(parents=True)
    (export / "manifest.json").write_text(MANIFEST)
    (fallback / "manifest.json").write_text(MANIFEST)
    (data / "splits.json").write_text(SPLITS)
    (data / "samples" / "CAM_FRONT" / "a.jpg").write_bytes(b"jpeg")
    (tmp_path / "afile").write_text("not a folder")
    return tmp_path


def _inputs_untouched(root) -> None:
    assert (root / "exp" / "manifest.json").read_text() == MANIFEST
    assert (root / "data" / "splits.json").read_text() == SPLITS
    assert (root / "data" / "samples" / "CAM_FRONT" / "a.jpg").read_bytes() == b"jpeg"
    assert sorted(p.name for p in (root / "exp").iterdir()) == ["manifest.json"]


def _stub(calls: list, error=ValueError):
    """Stands for the long work: records the call and stops with ``error``, which the CLI reports in one line
    (exit 1), so that a test tells "refused before the work" (exit 2, no call) from "let through"."""

    def stub(*args, **kwargs):
        calls.append(args)
        raise error("stub: the work was reached")

    return stub


# ---- streamdet-replay ---------------------------------------------------------------------------------------


@pytest.fixture
def replay(inputs, monkeypatch):
    """``replay(*extra)`` runs streamdet-replay on the stand-in inputs; ``replay.calls`` lists reached replays."""
    calls: list = []
    monkeypatch.setattr("streamdet.replay.run.run_replay", _stub(calls))

    def run(*extra: str):
        args = ["--data", str(inputs / "data"), "--export-dir", str(inputs / "exp"), *extra]
        return CliRunner().invoke(replay_cli.main, args)

    run.calls = calls
    return run


@pytest.mark.parametrize(
    "option, target, message",
    [
        ("--json", "exp/manifest.json", "lies inside the input --export-dir"),
        ("--json", "data/splits.json", "lies inside the input --data"),
        ("--plot", "data/samples/CAM_FRONT/a.jpg", "lies inside the input --data"),
        ("--out", "exp", "is the input --export-dir"),
        ("--out", "data/v1.0-synth", "lies inside the input --data"),
        ("--out", "data", "is the input --data"),
    ],
)
def test_replay_outputs_over_its_inputs_are_refused(replay, inputs, option, target, message):
    result = replay(option, str(inputs / target))
    _usage_error(result, option, str(inputs / target), message)
    assert replay.calls == []
    _inputs_untouched(inputs)


def test_replay_outputs_inside_the_fallback_export_are_refused(replay, inputs):
    result = replay("--fallback-export", str(inputs / "fallback"), "--json", str(inputs / "fallback" / "manifest.json"))
    _usage_error(result, "--json", "lies inside the input --fallback-export")
    assert (inputs / "fallback" / "manifest.json").read_text() == MANIFEST and replay.calls == []


def test_replay_links_into_an_input_are_refused(replay, inputs):
    file_link, folder_link = inputs / "link.json", inputs / "link_dir"
    file_link.symlink_to(inputs / "exp" / "manifest.json")
    folder_link.symlink_to(inputs / "data")
    _usage_error(replay("--json", str(file_link)), "--json", str(file_link), "--export-dir")
    _usage_error(replay("--out", str(folder_link)), "--out", str(folder_link), "is the input --data")
    _usage_error(replay("--plot", str(folder_link / "p.png")), "--plot", "lies inside the input --data")
    assert replay.calls == []
    _inputs_untouched(inputs)


@pytest.mark.parametrize(
    "args, option, message",
    [
        (["--json", "same.png", "--plot", "same.png"], "--plot", "is also the --json file"),
        (["--out", "r", "--json", "r/replay.json"], "--json", "is also the --out file"),
        (["--out", "r", "--plot", "r/report.md"], "--plot", "is also the --out file"),
        (["--out", "x", "--json", "x"], "--json", "is also the --out file"),  # --out made after --json is written
    ],
)
def test_replay_outputs_that_are_one_file_are_refused(replay, inputs, args, option, message):
    args = [str(inputs / a) if not a.startswith("--") else a for a in args]
    _usage_error(replay(*args), option, message)
    assert replay.calls == [] and not (inputs / "r").exists()


@pytest.mark.parametrize(
    "option, target, message",
    [
        ("--json", "nodir/r.json", "does not exist"),
        ("--plot", "nodir/r.png", "does not exist"),
        ("--plot", "r.json", "has no .json format"),
        ("--plot", "r.PNGX", "has no .pngx format"),
        ("--out", "afile/out", "is not a folder"),
    ],
)
def test_replay_unwritable_outputs_are_refused_before_the_replay(replay, inputs, option, target, message):
    pytest.importorskip("matplotlib")
    _usage_error(replay(option, str(inputs / target)), option, str(inputs / target), message)
    assert replay.calls == []


def test_replay_valid_outputs_reach_the_replay(replay, inputs):
    pytest.importorskip("matplotlib")
    out = inputs / "results"
    out.mkdir()
    (out / "replay.json").write_text("{}")  # an earlier replay's: --out replaces it, as before
    for args in (
        ["--json", "r.json", "--plot", "r.png", "--out", "new/out"],
        ["--json", "results/summary.json", "--out", "results", "--plot", "results/r.PDF"],
        ["--plot", "plot_without_suffix"],  # matplotlib writes its default, PNG
        ["--fallback-export", "fallback", "--json", "r.json"],
    ):
        result = replay(*[str(inputs / a) if not a.startswith("--") else a for a in args])
        assert result.exit_code == 1 and "stub: the work was reached" in result.output, (args, result.output)
    assert len(replay.calls) == 4


# ---- streamdet-bench ----------------------------------------------------------------------------------------


@pytest.fixture
def bench(monkeypatch):
    """``bench(*args)`` runs streamdet-bench; ``bench.calls`` lists reached benchmarks and --flops-only counts."""
    calls: list = []
    monkeypatch.setattr(bench_cli, "_flops_only", lambda *a: calls.append(("flops", *a)))

    def run(*args: str):
        return CliRunner().invoke(bench_cli.main, list(args))

    run.calls = calls
    def stub_benchmark():
        from streamdet.benchmarks.run import BenchmarkError  # torch and onnxruntime: only for the test that runs

        monkeypatch.setattr("streamdet.benchmarks.run.run_benchmark", _stub(calls, BenchmarkError))

    run.stub_benchmark = stub_benchmark
    return run


def test_bench_takes_dash_h(bench):
    result = bench("-h")
    assert result.exit_code == 0 and "--flops-only" in result.output and "--export-dir" in result.output


@pytest.mark.parametrize(
    "option, target, message",
    [
        ("--json", "exp/manifest.json", "lies inside the input --export-dir"),
        ("--plot", "exp/rows.png", "lies inside the input --export-dir"),
        ("--profile", "exp", "is the input --export-dir"),
        ("--profile", "exp/prof", "lies inside the input --export-dir"),
    ],
)
def test_bench_outputs_over_the_export_are_refused(bench, inputs, option, target, message):
    # the stand-in export is no export: a check after the manifest's reading would say "not a usable export"
    result = bench("--preset", "tiny", "--export-dir", str(inputs / "exp"), option, str(inputs / target))
    _usage_error(result, option, str(inputs / target), message)
    assert bench.calls == []
    _inputs_untouched(inputs)


def test_bench_a_link_to_the_manifest_is_refused(bench, inputs):
    link = inputs / "link.json"
    link.symlink_to(inputs / "exp" / "manifest.json")
    _usage_error(bench("--export-dir", str(inputs / "exp"), "--json", str(link)), "--json", str(link), "--export-dir")
    _inputs_untouched(inputs)


@pytest.mark.parametrize(
    "args, option, message",
    [
        (["--json", "b.png", "--plot", "b.png"], "--plot", "is also the --json file"),
        (["--profile", "b.json", "--json", "b.json"], "--json", "is also the --profile"),
        (["--profile", "prof", "--json", "prof/b.json"], "--json", "inside the --profile folder"),
        (["--profile", "prof", "--plot", "prof/sub/b.png"], "--plot", "inside the --profile folder"),
        (["--json", "nodir/b.json"], "--json", "does not exist"),
        (["--plot", "b.json"], "--plot", "has no .json format"),
        (["--profile", "afile/prof"], "--profile", "is not a folder"),
    ],
)
def test_bench_outputs_are_checked_before_any_timing(bench, inputs, args, option, message):
    pytest.importorskip("matplotlib")
    args = [str(inputs / a) if not a.startswith("--") else a for a in args]
    _usage_error(bench("--preset", "tiny", *args), option, message)
    assert bench.calls == [] and not (inputs / "prof").exists()


def test_bench_valid_outputs_reach_the_benchmark(bench, inputs):
    pytest.importorskip("matplotlib")
    bench.stub_benchmark()
    d = str(inputs)
    result = bench("--preset", "tiny", "--json", f"{d}/b.json", "--plot", f"{d}/b.png", "--profile", f"{d}/new/prof")
    assert result.exit_code == 1 and "stub: the work was reached" in result.output, result.output
    assert len(bench.calls) == 1


@pytest.mark.parametrize(
    "args, shown",
    [
        (["--repeat", "5"], "--repeat"),
        (["--threads", "2"], "--threads"),
        (["--int8"], "--int8/--no-int8"),
        (["--no-fp16"], "--fp16/--no-fp16"),
        (["--quick"], "--quick"),
        (["--slices", "8"], "--slices"),
        (["--stream-precision", "fp16"], "--stream-precision"),
        (["--stream-image-precision", "int8"], "--stream-image-precision"),
        (["--stream-slice-workers", "1"], "--stream-slice-workers"),
        (["--export-dir", "{exp}"], "--export-dir"),
        (["--profile", "{tmp}/prof"], "--profile"),
        (["--plot", "{tmp}/rows.png"], "--plot"),
    ],
)
def test_bench_flops_only_refuses_timing_options(bench, inputs, args, shown):
    args = [a.format(exp=inputs / "exp", tmp=inputs) for a in args]
    # one option: "applies ... drop it" (CLI review 40, L7)
    error = _usage_error(bench("--flops-only", "--preset", "tiny", *args), "--flops-only", shown, "only applies to timing; drop it")
    assert "--preset" not in error and bench.calls == [] and not (inputs / "prof").exists()


def test_bench_flops_only_names_every_timing_option_and_checks_slices(bench, inputs):
    # the audit's command: --slices 6 is refused as in a timed run, then the rest are named together
    audit = ["--export-dir", str(inputs / "exp"), "--int8", "--repeat", "5", "--threads", "2", "--profile", "/proc/x"]
    _usage_error(bench("--flops-only", "--slices", "6", *audit), "--slices", "multiple of 4")
    error = _usage_error(bench("--flops-only", *audit), "--flops-only")
    for option in ("--export-dir", "--int8/--no-int8", "--repeat", "--threads", "--profile"):
        assert option in error
    assert bench.calls == []


def test_bench_flops_only_keeps_its_own_options(bench, inputs):
    result = bench("--flops-only", "--preset", "tiny", "--resolution", "1200x675", "--json", str(inputs / "g.json"))
    assert result.exit_code == 0, result.output
    assert bench.calls == [("flops", "tiny", (1200, 675), inputs / "g.json")]
    assert bench("--flops-only").exit_code == 0 and bench.calls[-1] == ("flops", "paper", None, None)


# ---- streamdet-study ----------------------------------------------------------------------------------------


@pytest.fixture
def study(inputs, monkeypatch):
    """``study(name, *extra)`` runs a study on the stand-in inputs; ``study.calls`` lists studies that started."""
    calls: list = []

    def export(*args):
        calls.append(args)
        raise click.ClickException("stub: the work was reached")

    monkeypatch.setattr(study_cli, "_export", export)

    def run(name: str, *extra: str):
        args = [name, "--export-dir", str(inputs / "exp"), "--data", str(inputs / "data"), *extra]
        return CliRunner().invoke(study_cli.main, args)

    run.calls = calls
    return run


@pytest.mark.parametrize("name", ["slices", "drop-camera", "calib-noise", "resolution"])
def test_study_unwritable_plot_fails_before_the_study_and_its_json(study, inputs, name):
    pytest.importorskip("matplotlib")
    json_path, plot_path = inputs / "s.json", inputs / "s.json.txt"
    _usage_error(study(name, "--json", str(json_path), "--plot", str(plot_path)), "--plot", str(plot_path),
                 "has no .txt format")  # fmt: skip
    assert study.calls == [] and not json_path.exists()


@pytest.mark.parametrize(
    "option, target",
    [("--json", "nodir/s.json"), ("--plot", "nodir/s.png"), ("--json", "afile/s.json")],
)
def test_study_output_folder_must_exist(study, inputs, option, target):
    _usage_error(study("drop-camera", option, str(inputs / target)), option, str(inputs / target), "does not exist")
    assert study.calls == []


def test_study_json_and_plot_as_one_file_are_refused(study, inputs):
    json_path, link = inputs / "s.json", inputs / "link.json"
    json_path.write_text("earlier")
    link.symlink_to(json_path)
    for plot in (json_path, link):
        _usage_error(study("slices", "--json", str(json_path), "--plot", str(plot)), "--plot", str(plot), "also the --json")
    hard = inputs / "hard.json"
    hard.hardlink_to(json_path)  # a hard link: either name would write through to the other
    _usage_error(study("slices", "--json", str(json_path), "--plot", str(hard)), "--json", "is a hard link")
    assert study.calls == [] and json_path.read_text() == "earlier"


def test_study_valid_outputs_reach_the_study(study, inputs):
    pytest.importorskip("matplotlib")
    result = study("calib-noise", "--json", str(inputs / "c.json"), "--plot", str(inputs / "c.svg"))
    assert result.exit_code == 1 and "stub: the work was reached" in result.output, result.output
    assert len(study.calls) == 1


@pytest.mark.parametrize(
    "level",
    ["1,1e308", f"1,{study_cli.MAX_NOISE_TRANSLATION_CM * 1.01:g}", "0,1e20", "180,0", "1,-0.5", "1,nan", "1,inf"],
)
def test_study_calib_noise_levels_past_the_calibration_checks_are_refused_at_parse_time(study, level):
    _usage_error(study("calib-noise", "--level", level), "--level", repr(level), "translation in [0, 50000] cm")
    assert study.calls == []


def test_study_calib_noise_level_bound_keeps_every_camera_on_the_vehicle():
    from streamdet.calibration.camera import MAX_CAMERA_OFFSET_M

    # one bound per axis: the farthest shift is sqrt(3) times it, and the calibration checks' offset bound must hold
    assert 3**0.5 * study_cli.MAX_NOISE_TRANSLATION_CM / 100.0 < MAX_CAMERA_OFFSET_M
    levels = study_cli._parse_levels(None, None, ("0,0", "179.9,50000", "0.5,5"))
    assert levels == ((0.0, 0.0), (179.9, 500.0), (0.5, 0.05))
