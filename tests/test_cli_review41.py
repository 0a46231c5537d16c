"""Review 41 (docs area), findings D1, D2, D3 and D5.

- D1: ``--image-precision`` with a LiDAR-only export is a usage error (exit 2) naming the option in streamdet-run,
  streamdet-eval --data, streamdet-bag run and streamdet-replay alike (``cli_utils.refuse_image_lane_options``), not
  DetectorConfig's refusal in its own field names (exit 1).
- D2: streamdet-train --no-crop without --no-image is a usage error (exit 2), as its sibling --no-image checks.
- D3: benchmarks/lane_sim.py's play_events docstring holds no measured number: it points to docs/replay.md.
- D5: streamdet-eval's files mode writes no --json into the saved run its --gt / --results come from.
"""

from __future__ import annotations

import re
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from streamdet.cli_utils import options_given, refuse_image_lane_options

ROOT = Path(__file__).resolve().parents[1]
TABLES = "v1.0-synth"  # the default --version


# ---- D1: the helper on its own ------------------------------------------------------------------------------------


def _command(reads_images, names=("image_precision",)):
    """A command with an image-lane option and a slice-lane one, refusing as the tools do."""
    asked: list[Path] = []

    def modality(export_dir: Path):
        asked.append(export_dir)
        return reads_images

    @click.command()
    @click.option("--image-precision", type=click.Choice(["fp32", "fp16", "int8"]), default=None)
    @click.option("--fallback-export", "fallback_export_dir", default=None)
    @click.option("--precision", default="fp32")
    def cmd(image_precision, fallback_export_dir, precision):
        refuse_image_lane_options(click.get_current_context(), Path("EXP"), names, modality)
        click.echo("reached")

    return cmd, asked


@pytest.mark.parametrize("args", [["--image-precision", "int8"], ["--image-precision", "fp32"],
                                  ["--image-precision=fp16", "--precision", "fp16"]])  # fmt: skip
def test_helper_refuses_a_given_option_with_a_lidar_only_export(args):
    cmd, asked = _command(False)
    res = CliRunner().invoke(cmd, args)
    assert res.exit_code == 2 and "reached" not in res.output, res.output
    assert "Usage:" in res.output and "EXP is a LiDAR-only export" in res.output
    assert "--image-precision only applies to an export with cameras; drop it" in res.output
    assert asked == [Path("EXP")]


def test_helper_names_every_option_given_at_once():
    cmd, _ = _command(False, names=("image_precision", "fallback_export_dir"))
    res = CliRunner().invoke(cmd, ["--fallback-export", "L", "--image-precision", "int8", "--precision", "fp16"])
    assert res.exit_code == 2
    assert "--image-precision, --fallback-export only apply to an export with cameras; drop them" in res.output
    assert "--precision" not in res.output.split("Error:")[1]


@pytest.mark.parametrize("reads_images, args", [
    (True, ["--image-precision", "int8"]),  # an export with cameras
    (None, ["--image-precision", "int8"]),  # no readable export: the tool's own opening says what is wrong
    (False, []),                            # the default is not given
    (False, ["--precision", "fp16"]),       # a slice-lane option
])  # fmt: skip
def test_helper_passes(reads_images, args):
    cmd, asked = _command(reads_images)
    res = CliRunner().invoke(cmd, args)
    assert res.exit_code == 0 and "reached" in res.output, res.output
    assert len(asked) == (1 if args[:1] == ["--image-precision"] else 0)  # the manifest is read only when needed


def test_options_given_counts_the_environment_not_a_default(monkeypatch):
    seen = []

    @click.command()
    @click.option("--image-precision", envvar="R41_IMAGE_PRECISION", default=None)
    @click.option("--precision", default="fp32")
    def cmd(image_precision, precision):
        seen.append(options_given(click.get_current_context(), ("image_precision", "precision")))

    CliRunner().invoke(cmd, [])
    monkeypatch.setenv("R41_IMAGE_PRECISION", "int8")
    CliRunner().invoke(cmd, ["--precision", "fp32"])
    assert seen == [[], ["--image-precision", "--precision"]]


def test_export_reads_images(tiny_lidar_export, tiny_export, tmp_path):
    from streamdet.evaluation.run_cli import export_reads_images

    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "manifest.json").write_text("{not json")
    assert export_reads_images(tiny_lidar_export) is False
    assert export_reads_images(tiny_export) is True
    assert export_reads_images(tmp_path / "broken") is None
    assert export_reads_images(tmp_path / "absent") is None


# ---- D1: the four tools ---------------------------------------------------------------------------------------------


def _tool_args(tool: str, export: Path, tmp_path: Path, extra: list[str]) -> tuple[click.Command, list[str]]:
    """The tool's command and arguments up to its work, with ``extra``: nothing beyond the export is real."""
    data = tmp_path / "data"
    (data / TABLES).mkdir(parents=True, exist_ok=True)  # a table folder: replay checks it first
    if tool == "run":
        from streamdet.evaluation.run_cli import main

        return main, ["--export-dir", str(export), "--out", str(tmp_path / "out"), *extra]
    if tool == "eval":
        from streamdet.evaluation.cli import main

        return main, ["--data", str(data), "--export-dir", str(export), "--split", "all", *extra]
    if tool == "bag":
        from streamdet.bag.cli import main

        bag = tmp_path / "in.mcap"
        bag.write_bytes(b"not a bag")
        return main, ["run", "--bag", str(bag), "--export-dir", str(export), "--out", str(tmp_path / "o.mcap"), *extra]
    from streamdet.replay.cli import main

    return main, ["--data", str(data), "--split", "all", "--export-dir", str(export), "--max-seconds", "0.1", *extra]


TOOLS = ["run", "eval", "bag", "replay"]


@pytest.mark.parametrize("precision", ["int8", "fp32"])
@pytest.mark.parametrize("tool", TOOLS)
def test_image_precision_with_a_lidar_only_export_is_a_usage_error(tool, precision, tiny_lidar_export, tmp_path):
    cmd, args = _tool_args(tool, tiny_lidar_export, tmp_path, ["--image-precision", precision])
    res = CliRunner().invoke(cmd, args)
    assert res.exit_code == 2, (tool, res.output)
    assert "Usage:" in res.output and "Traceback" not in res.output
    errors = [line for line in res.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, res.output
    assert f"{tiny_lidar_export} is a LiDAR-only export" in errors[0]
    assert "--image-precision only applies to an export with cameras; drop it" in errors[0]
    assert "DetectorConfig" not in res.output  # the option typed, not the API field
    assert not (tmp_path / "out").exists() and not (tmp_path / "o.mcap").exists()  # refused before any work


def test_bag_run_names_a_fallback_of_a_lidar_only_export(tiny_lidar_export, tmp_path):
    cmd, args = _tool_args("bag", tiny_lidar_export, tmp_path, ["--fallback-export", str(tiny_lidar_export),
                                                                  "--fallback-after-ms", "50"])  # fmt: skip
    res = CliRunner().invoke(cmd, args)
    assert res.exit_code == 2, res.output
    assert "--fallback-export, --fallback-after-ms only apply to an export with cameras; drop them" in res.output


@pytest.mark.parametrize("tool", TOOLS)
def test_a_broken_manifest_is_left_to_the_tool(tool, tmp_path):
    """The check reads only the modality; an export that is none fails as it did without the option (exit 1)."""
    export = tmp_path / "exp"
    export.mkdir()
    (export / "manifest.json").write_text("{not json")
    cmd, args = _tool_args(tool, export, tmp_path, ["--image-precision", "int8"])
    res = CliRunner().invoke(cmd, args)
    assert res.exit_code == 1 and "LiDAR-only" not in res.output, (tool, res.output)


@pytest.mark.parametrize("tool", ["run", "eval"])
def test_image_precision_still_runs_with_cameras(tool, tiny_export, tiny_synth_data, tmp_path):
    from streamdet.evaluation.cli import main as eval_main
    from streamdet.evaluation.run_cli import main as run_main

    if tool == "run":
        res = CliRunner().invoke(run_main, ["--export-dir", str(tiny_export), "--out", str(tmp_path / "out"),
                                            "--image-precision", "fp16"])  # fmt: skip
    else:
        res = CliRunner().invoke(eval_main, ["--data", str(tiny_synth_data), "--export-dir", str(tiny_export), "--split",
                                             "all", "--max-samples", "1", "--image-precision", "fp16"])  # fmt: skip
    assert res.exit_code == 0, res.output


# ---- D2: --no-crop without --no-image -------------------------------------------------------------------------------


@pytest.mark.parametrize("extra", [["--no-crop"], ["--no-crop", "--camera-mode", "all"], ["--no-crop", "--image-warmup", "0"]])
def test_train_no_crop_without_no_image_is_a_usage_error(tmp_path, extra):
    from streamdet.training.cli import main as train_main

    (tmp_path / "ds" / TABLES).mkdir(parents=True)
    res = CliRunner().invoke(train_main, ["--data", str(tmp_path / "ds"), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                          "--steps", "1", *extra])  # fmt: skip
    assert res.exit_code == 2, res.output
    assert "Usage:" in res.output and "Traceback" not in res.output
    assert "--no-crop" in res.output and "add --no-image" in res.output
    assert not (tmp_path / "o").exists()


def test_train_no_crop_with_no_image_passes_the_check(tmp_path):
    """--no-image --no-crop gets past the option checks (it fails later here: the dataset is an empty folder)."""
    from streamdet.training.cli import main as train_main

    (tmp_path / "ds" / TABLES).mkdir(parents=True)
    res = CliRunner().invoke(train_main, ["--data", str(tmp_path / "ds"), "--out", str(tmp_path / "o"), "--preset", "tiny",
                                          "--steps", "1", "--no-image", "--no-crop", "--cache-dir", str(tmp_path / "c")])  # fmt: skip
    assert res.exit_code != 2 and "add --no-image" not in res.output, res.output


# ---- D3: no measured number in lane_sim's docstring -----------------------------------------------------------------


def test_play_events_docstring_points_to_its_measurement():
    from streamdet.benchmarks import lane_sim

    doc = " ".join(lane_sim.play_events.__doc__.split())
    assert not re.search(r"\d\s*(ms|x)\b", doc), doc  # no latency or cost scale quoted
    assert "session" not in doc  # a file and section, not a session, says where it was measured
    assert "docs/replay.md" in doc
    section = re.search(r'"([^"]+)"', doc).group(1)
    assert f"## {section}" in (ROOT / "docs" / "replay.md").read_text()


# ---- D5: files mode --json into a saved run -------------------------------------------------------------------------


def _saved_run(folder: Path, samples: bool = True) -> Path:
    from streamdet.evaluation.results import write_results_json

    folder.mkdir(parents=True)
    entry = {"sample_token": "s0", "translation": [5.0, 0.0, 1.0], "size": [1.9, 4.5, 1.6], "rotation": [1.0, 0.0, 0.0, 0.0],
             "velocity": [0.0, 0.0], "detection_name": "car", "attribute_name": "", "detection_score": 0.9}  # fmt: skip
    meta = {"use_camera": False, "use_lidar": True}
    write_results_json(folder / "results.json", {"s0": [entry]}, meta)
    gt = {k: v for k, v in entry.items() if k != "detection_score"} | {"num_pts": 10}
    write_results_json(folder / "gt.json", {"s0": [gt]}, meta, ego_positions={"s0": [0.0, 0.0, 0.0]})
    if samples:
        (folder / "samples.json").write_text("{}")
    return folder


def _eval(gt: Path, results: Path, json_path: Path):
    from streamdet.evaluation.cli import main as eval_main

    return CliRunner().invoke(eval_main, ["--gt", str(gt), "--results", str(results), "--classes", "car",
                                          "--json", str(json_path)])  # fmt: skip


@pytest.mark.parametrize("json_name", ["new.json", "sub/new.json", "metrics.JSON"])
def test_files_mode_json_into_the_saved_run_is_refused(tmp_path, json_name):
    run = _saved_run(tmp_path / "run")
    (run / "sub").mkdir()
    before = sorted(p.name for p in run.rglob("*"))
    res = _eval(run / "gt.json", run / "results.json", run / json_name)
    assert res.exit_code == 2, res.output
    assert "--json" in res.output and "lies inside the input --gt's saved run" in res.output
    assert sorted(p.name for p in run.rglob("*")) == before  # nothing written into the run


@pytest.mark.parametrize("which", ["gt", "results"])
def test_either_input_from_a_saved_run_guards_it(tmp_path, which):
    run = _saved_run(tmp_path / "run")
    other = _saved_run(tmp_path / "elsewhere")
    (other / "gt.json").rename(tmp_path / "g.json")  # "elsewhere" is no saved run any more
    (other / "results.json").rename(tmp_path / "r.json")
    gt, results = (run / "gt.json", tmp_path / "r.json") if which == "gt" else (tmp_path / "g.json", run / "results.json")
    res = _eval(gt, results, run / "new.json")
    assert res.exit_code == 2 and f"--{which}'s saved run" in res.output, res.output


def test_a_link_into_a_saved_run_guards_it(tmp_path):
    run = _saved_run(tmp_path / "run")
    (tmp_path / "gt.json").symlink_to(run / "gt.json")
    (tmp_path / "results.json").symlink_to(run / "results.json")
    res = _eval(tmp_path / "gt.json", tmp_path / "results.json", run / "new.json")
    assert res.exit_code == 2 and "saved run" in res.output and not (run / "new.json").exists(), res.output


def test_a_saved_runs_own_file_keeps_its_message(tmp_path):
    run = _saved_run(tmp_path / "run")
    res = _eval(run / "gt.json", run / "results.json", run / "samples.json")
    assert res.exit_code == 2 and "is a file of the saved run beside --gt" in res.output


@pytest.mark.parametrize("layout", ["no_samples", "samples_is_a_folder", "other_names", "gt_only", "results_is_a_folder"])
def test_a_folder_that_is_no_saved_run_takes_the_json(tmp_path, layout):
    """Only a folder holding every file --save-results writes (results.json, gt.json, samples.json; regular files) is
    guarded: a user's own gt.json and results.json, or a run saved before samples.json existed, may take it."""
    run = _saved_run(tmp_path / "run", samples=False)
    folder = tmp_path / "f"
    folder.mkdir()
    if layout in ("no_samples", "samples_is_a_folder"):
        folder = run
        gt, results = run / "gt.json", run / "results.json"
        if layout == "samples_is_a_folder":
            (run / "samples.json").mkdir()
    elif layout == "other_names":
        gt, results = folder / "g.json", folder / "r.json"
        (run / "gt.json").rename(gt)
        (run / "results.json").rename(results)
    elif layout == "gt_only":
        gt, results = folder / "gt.json", tmp_path / "r.json"
        (run / "gt.json").rename(gt)
        (run / "results.json").rename(results)
    else:
        gt, results = folder / "gt.json", tmp_path / "r.json"
        (run / "gt.json").rename(gt)
        (run / "results.json").rename(results)
        (folder / "results.json").mkdir()
    res = _eval(gt, results, folder / "m.json")
    assert res.exit_code == 0, res.output
    assert (folder / "m.json").is_file()


def test_outside_the_saved_run_the_json_is_written(tmp_path):
    run = _saved_run(tmp_path / "run")
    res = _eval(run / "gt.json", run / "results.json", tmp_path / "m.json")
    assert res.exit_code == 0 and (tmp_path / "m.json").is_file(), res.output
