"""CLI review 40: bags are not replaced without --overwrite (M2); eval --save-results, replay --out and run --out
refuse another tool's folder and say when they replace their own earlier results (L1); option conflicts are usage
errors naming the options typed (L3); `--json -` is refused alike by every tool (L4); help and docs nits (L7).

Every refusal comes before any work: the work (the detector, the replay, the export loading) is a stub or a stand-in
export that would fail to load, so that "refused first" (exit 2) is told from "let through" (exit 1, or the stub)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from streamdet.cli_utils import parse_resolution
import test_cli_outputs_replay_bench_study as outputs_tests
from test_cli_outputs_replay_bench_study import MANIFEST, _stub, _usage_error

# their stand-in export and dataset, a fixture: pytest registers it under the name it has here
stand_ins = outputs_tests.inputs

ROOT = Path(__file__).resolve().parents[1]
NOTE = "note: "


def _notes(result) -> list[str]:
    return [line for line in result.stderr.splitlines() if line.startswith(NOTE)]


# ---- M2: streamdet-bag export / run refuse an existing --out without --overwrite -----------------------------------


def _bag_helpers():
    pytest.importorskip("mcap_ros2.writer")
    import test_bag_cli_outputs as helpers

    return helpers


def test_bag_export_refuses_an_existing_out_unless_overwrite(tiny_synth_data: Path, tmp_path: Path):
    helpers = _bag_helpers()
    out = tmp_path / "recording.mcap"
    out.write_bytes(b"a drive recording")
    result = helpers.invoke("export", "--data", tiny_synth_data, "--out", out)
    error = _usage_error(result, "--out", str(out), "exists", "--overwrite")
    assert error.startswith("Error: Invalid value for --out")
    assert out.read_bytes() == b"a drive recording" and sorted(p.name for p in tmp_path.iterdir()) == ["recording.mcap"]
    result = helpers.invoke("export", "--data", tiny_synth_data, "--out", out, "--overwrite")
    assert result.exit_code == 0, result.output
    assert out.read_bytes()[:8] == b"\x89MCAP0\r\n"  # the new bag replaced it


def test_bag_run_refuses_an_existing_out_or_results_unless_overwrite(tmp_path: Path):
    helpers = _bag_helpers()
    bag = helpers.write_bag(tmp_path / "drive.mcap", [helpers.sweep_points()])
    export = tmp_path / "exp"
    export.mkdir()
    (export / "manifest.json").write_text("{}")  # enough for the first check; loading it fails (exit 1)
    out, beside = tmp_path / "det.mcap", tmp_path / "det.results_nusc.json"
    run = ("run", "--bag", bag, "--export-dir", export, "--out", out)
    out.write_bytes(b"another recording")
    _usage_error(helpers.invoke(*run), "--out", str(out), "exists", "--overwrite")
    out.unlink()
    beside.write_text("{}")  # the results JSON written beside --out by default
    _usage_error(helpers.invoke(*run), "--results (default: beside --out)", str(beside), "exists", "choose another --out")
    given = tmp_path / "mine.json"
    given.write_text("{}")
    _usage_error(helpers.invoke(*run, "--results", given), "--results", str(given), "choose another --results")
    assert beside.read_text() == "{}" and given.read_text() == "{}" and not out.exists()
    # --overwrite lets both through to the work: the stand-in export fails to load there
    out.write_bytes(b"another recording")
    result = helpers.invoke(*run, "--overwrite")
    assert result.exit_code == 1 and "exists" not in result.output, result.output


def test_bag_help_and_docs_name_overwrite():
    helpers = _bag_helpers()
    for command in ("export", "run"):
        assert "--overwrite" in helpers.invoke(command, "--help").output
    assert "--overwrite" in (ROOT / "docs" / "ros2.md").read_text()
    assert "`streamdet-bag export` and `streamdet-bag run` refuse an existing `--out`" in (ROOT / "docs" / "cli.md").read_text()


# ---- L1: results folders --------------------------------------------------------------------------------------------


def _dataset_root(folder: Path) -> Path:
    """A stand-in dataset root as streamdet-synth writes one (its world.json and a table folder)."""
    (folder / "v1.0-synth").mkdir(parents=True)
    (folder / "v1.0-synth" / "sample.json").write_text("[]")
    (folder / "world.json").write_text("{}")
    return folder


def _export_folder(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text(MANIFEST)
    return folder


@pytest.fixture
def eval_data(stand_ins, monkeypatch):
    """``eval_data(save_dir)`` runs streamdet-eval's dataset mode with --save-results; the detection is a stub."""
    from streamdet.evaluation import cli as eval_cli

    calls: list = []
    monkeypatch.setattr(eval_cli, "_data_inputs", _stub(calls))

    def run(save_dir: Path, export: Path):
        args = ["--data", str(stand_ins / "data"), "--export-dir", str(export), "--save-results", str(save_dir)]
        return CliRunner().invoke(eval_cli.main, args)

    run.calls = calls
    return run


def test_eval_save_results_refuses_an_export_or_a_dataset(eval_data, stand_ins):
    export = stand_ins / "exp"
    for folder, what in ((_export_folder(stand_ins / "other_export"), "is a streamdet export (manifest.json)"),
                         (_dataset_root(stand_ins / "ds"), "is a dataset (")):  # fmt: skip
        _usage_error(eval_data(folder, export), "--save-results", str(folder), what, "saved run")
    assert eval_data.calls == [] and not (stand_ins / "ds" / "results.json").exists()


def test_eval_save_results_notes_an_earlier_saved_run_once(eval_data, stand_ins):
    export, run = stand_ins / "exp", stand_ins / "runA"
    result = eval_data(run, export)  # new folder: nothing to say
    assert result.exit_code == 1 and _notes(result) == [] and len(eval_data.calls) == 1, result.output
    run.mkdir()
    for name in ("results.json", "gt.json", "samples.json"):
        (run / name).write_text("{}")
    result = eval_data(run, export)
    assert result.exit_code == 1 and len(eval_data.calls) == 2, result.output  # let through to the work
    assert _notes(result) == [f"note: --save-results {run} holds an earlier saved run (results.json, gt.json, "
                              "samples.json): this run replaces it"]  # fmt: skip
    assert NOTE not in result.stdout  # stdout is the report


@pytest.fixture
def run_tool(monkeypatch):
    """``run_tool(out, export)`` runs streamdet-run with its detection a stub."""
    from streamdet.evaluation import run_cli

    calls: list = []
    monkeypatch.setattr(run_cli, "run_sample", _stub(calls))

    def run(out: Path, export: Path):
        return CliRunner().invoke(run_cli.main, ["--export-dir", str(export), "--out", str(out)])

    run.calls = calls
    return run


def test_run_out_refuses_an_export_or_a_dataset_and_notes_its_own_output(run_tool, stand_ins):
    export = stand_ins / "exp"
    for folder, what in ((_export_folder(stand_ins / "other_export"), "is a streamdet export"),
                         (_dataset_root(stand_ins / "ds"), "is a dataset (v1.0-synth/, world.json)")):  # fmt: skip
        _usage_error(run_tool(folder, export), "--out", str(folder), what)
    assert run_tool.calls == [] and not (stand_ins / "ds" / "bev.png").exists()
    out = stand_ins / "run1"
    out.mkdir()
    (out / "bev.png").write_bytes(b"png")
    result = run_tool(out, export)
    assert result.exit_code == 1 and len(run_tool.calls) == 1, result.output
    assert _notes(result) == [f"note: --out {out} holds an earlier streamdet-run output (bev.png): this run replaces it"]


@pytest.fixture
def replay(stand_ins, monkeypatch):
    """``replay(*extra)`` runs streamdet-replay on the stand-in inputs (``stand_ins``), the
    replay a stub; ``replay.calls`` lists the replays reached."""
    from streamdet.replay import cli as replay_cli

    calls: list = []
    monkeypatch.setattr("streamdet.replay.run.run_replay", _stub(calls))

    def run(*extra: str):
        args = ["--data", str(stand_ins / "data"), "--export-dir", str(stand_ins / "exp"), *extra]
        return CliRunner().invoke(replay_cli.main, [str(a) for a in args])

    run.calls = calls
    return run


def test_replay_out_refuses_an_export_or_a_dataset_and_notes_its_own_report(replay, stand_ins):
    for folder, what in ((_export_folder(stand_ins / "other_export"), "is a streamdet export"),
                         (_dataset_root(stand_ins / "ds"), "is a dataset")):  # fmt: skip
        _usage_error(replay("--out", folder), "--out", str(folder), what, "replay report")
    assert replay.calls == []
    out = stand_ins / "rp1"
    out.mkdir()
    (out / "replay.json").write_text("{}")
    (out / "report.md").write_text("# a report")
    result = replay("--out", out)
    assert result.exit_code == 1 and len(replay.calls) == 1, result.output
    assert _notes(result) == [f"note: --out {out} holds an earlier replay report (replay.json, report.md): this run "
                              "replaces it"]  # fmt: skip


# ---- L3: option conflicts are usage errors in the options' names ----------------------------------------------------


@pytest.mark.parametrize(
    "args, option, needles",
    [
        (["--fallback-after-ms", "100"], "--fallback-after-ms 100", ["needs --fallback-export"]),
        (["--pair-hold-load", "0.5", "--coalesce-slices", "1"], "--pair-hold-load 0.5", ["--coalesce-slices 1"]),
        (["--image-lane-yield", "2"], "--image-lane-yield 2", ["needs --schedule phase-locked", "--schedule full"]),
    ],
)
def test_replay_option_conflicts_are_usage_errors(replay, args, option, needles):
    error = _usage_error(replay(*args), option, *needles)
    assert "Config" not in error and "_" not in error.split(":", 1)[1]  # no API field names (fallback_after_s)
    assert replay.calls == []


def test_replay_option_pairs_that_fit_reach_the_replay(replay, stand_ins):
    for args in (["--pair-hold-load", "0.5"], ["--image-lane-yield", "2", "--schedule", "phase-locked"],
                 ["--fallback-after-ms", "100", "--fallback-export", stand_ins / "fallback"]):  # fmt: skip
        result = replay(*args)
        assert result.exit_code == 1 and "stub: the work was reached" in result.output, (args, result.output)


def test_bag_run_fallback_after_without_fallback_is_a_usage_error(tmp_path: Path):
    from streamdet.bag.cli import main as bag_main

    bag = tmp_path / "b.mcap"
    bag.write_bytes(b"not read: the options are checked first")
    result = CliRunner().invoke(bag_main, ["run", "--bag", str(bag), "--export-dir", str(tmp_path / "nope"),
                                           "--out", str(tmp_path / "d.mcap"), "--fallback-after-ms", "100"])  # fmt: skip
    _usage_error(result, "--fallback-after-ms 100", "needs --fallback-export")


def test_study_counts_and_repeated_camera_are_usage_errors(tmp_path: Path):
    from streamdet.studies.cli import main as study_main

    data = ["--data", str(tmp_path), "--export-dir", str(tmp_path / "nope")]
    error = _usage_error(CliRunner().invoke(study_main, ["slices", *data, "--counts", "4,6"]), "--counts", "slice count 6",
                         "multiple of 4")  # fmt: skip
    assert error.startswith("Error: Invalid value for --counts")
    _usage_error(CliRunner().invoke(study_main, ["drop-camera", *data, "--camera", "CAM_BACK", "--camera", "CAM_BACK"]),
                 "--camera", "'CAM_BACK' is given twice")  # fmt: skip


# ---- L4: --json - -------------------------------------------------------------------------------------------------


def _json_dash_commands(stand_ins: Path) -> dict[str, tuple]:
    from streamdet.benchmarks.cli import main as bench_main
    from streamdet.data.synth_cli import main as synth_main
    from streamdet.evaluation.cli import main as eval_main
    from streamdet.replay.cli import main as replay_main
    from streamdet.studies.cli import main as study_main

    gt = stand_ins / "gt.json"
    gt.write_text("{}")
    data, export = str(stand_ins / "data"), str(stand_ins / "exp")
    return {
        "eval": (eval_main, ["--gt", str(gt), "--results", str(gt)]),
        "eval --compare": (eval_main, ["--compare", data, export]),
        "bench": (bench_main, ["--flops-only"]),
        "study": (study_main, ["slices", "--data", data, "--export-dir", export]),
        "replay": (replay_main, ["--data", data, "--export-dir", export]),
        "synth stats": (synth_main, ["stats", data]),
    }


@pytest.mark.parametrize("tool", ["eval", "eval --compare", "bench", "study", "replay", "synth stats"])
def test_json_dash_is_refused_alike_by_every_tool(tool, stand_ins, monkeypatch):
    command, args = _json_dash_commands(stand_ins)[tool]
    monkeypatch.chdir(stand_ins)
    error = _usage_error(CliRunner().invoke(command, [*args, "--json", "-"]), "--json", "'-' is not a path here",
                         "stdout carries the report")  # fmt: skip
    assert error.startswith("Error: Invalid value for --json:")
    assert not (stand_ins / "-").exists()


def test_every_json_option_is_the_shared_one():
    """Each tool declares --json through json_output_option: one callback refuses '-', one sentence in the help."""
    from streamdet.benchmarks.cli import main as bench_main
    from streamdet.cli_outputs import JSON_DASH_HELP, _refuse_stdout_dash
    from streamdet.data.synth_cli import stats
    from streamdet.evaluation.cli import main as eval_main
    from streamdet.replay.cli import main as replay_main
    from streamdet.studies.cli import main as study_main

    for command in [bench_main, stats, eval_main, replay_main, *study_main.commands.values()]:
        (param,) = [p for p in command.params if "--json" in p.opts]
        assert param.callback is _refuse_stdout_dash and param.help.endswith(JSON_DASH_HELP), command.name


# ---- L7: help and docs ----------------------------------------------------------------------------------------------


def test_help_nits():
    from streamdet.data.synth_cli import main as synth_main
    from streamdet.evaluation.run_cli import main as run_main

    synth = CliRunner().invoke(synth_main, ["generate", "--help"]).output
    assert "--resolution WxH" in synth and "--resolution TEXT" not in synth
    run = " ".join(CliRunner().invoke(run_main, ["--help"]).output.split())
    assert "--slices INTEGER RANGE" in run and "[1<=x<=4096]" in run


def test_bench_names_one_timing_option_in_the_singular():
    from streamdet.benchmarks.cli import main as bench_main

    error = _usage_error(CliRunner().invoke(bench_main, ["--flops-only", "--repeat", "3"]), "--repeat")
    assert "--repeat only applies to timing; drop it or drop --flops-only" in error
    error = _usage_error(CliRunner().invoke(bench_main, ["--flops-only", "--repeat", "3", "--quick"]), "--repeat")
    assert "--repeat, --quick only apply to timing; drop them" in error


def test_docs_say_what_resolution_reads():
    text = (ROOT / "docs" / "cli.md").read_text()
    assert "ASCII digits only" not in text  # parse_resolution reads any decimal digits, as said now
    assert "`８００x４５０` is 800x450" in text and parse_resolution("８００x４５０") == (800, 450)
    assert "`--json -` is refused" in text


def test_run_slices_out_of_range_is_a_usage_error(stand_ins):
    from streamdet.evaluation.run_cli import main as run_main

    result = CliRunner().invoke(run_main, ["--export-dir", str(stand_ins / "exp"), "--slices", "0"])
    _usage_error(result, "--slices", "1<=x<=4096")


def test_json_dot_slash_dash_is_a_file(stand_ins, monkeypatch):
    """`./-` names a file `-` in the working folder: written, as any path."""
    from streamdet.benchmarks.cli import main as bench_main

    monkeypatch.chdir(stand_ins)
    result = CliRunner().invoke(bench_main, ["--flops-only", "--preset", "tiny", "--resolution", "160x90", "--json", "./-"])
    assert result.exit_code == 0, result.output
    assert json.loads((stand_ins / "-").read_text())["meta"]["mode"] == "flops-only"
