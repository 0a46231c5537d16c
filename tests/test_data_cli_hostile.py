"""Hostile input to streamdet-synth (generate and stats), the sample loader and Rig.from_calibration_json.

Each test pins one finding of the CLI audit: an --out that would overwrite another dataset, a --version that is
no folder name, stats outputs over their inputs, a calibration.json that is not an object, an empty LiDAR file, and
error messages that name the wrong thing.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.cli_utils import run_edge
from streamdet.data.sample import bundled_sample_dir, load_bundled_sample
from streamdet.data.synth_cli import main as synth_main
from streamdet.data.synth_writer import SynthConfig, remove_dataset_entries, survey_root

SAMPLE_DIR = bundled_sample_dir()
CALIB = json.loads((SAMPLE_DIR / "calibration.json").read_text())
TINY = ["--scenes", "1", "--samples-per-scene", "1", "--resolution", "32x18"]


def _snapshot(root: Path) -> dict[str, bytes | None]:
    """Every path under ``root`` with its bytes (None for folders): equal snapshots mean nothing was touched."""
    return {str(p.relative_to(root)): (None if p.is_dir() else p.read_bytes()) for p in sorted(root.rglob("*"))}


def _fake_synth_dataset(root: Path, version: str = "v1.0-synth") -> Path:
    """The top-level layout of a streamdet-synth dataset, without simulating one (the survey reads names only)."""
    (root / version).mkdir(parents=True)
    for table in ("sample", "scene", "log"):
        (root / version / f"{table}.json").write_text("[]")
    (root / "samples" / "LIDAR_TOP").mkdir(parents=True)
    (root / "samples" / "LIDAR_TOP" / "a.pcd.bin").write_bytes(b"\0" * 20)
    (root / "maps").mkdir()
    (root / "splits.json").write_text(json.dumps({"train": ["synth-2-0000"], "val": ["synth-2-0001"]}))
    (root / "world.json").write_text(json.dumps({"world_version": 4, "scenes": {}}))
    (root / "trajectories.npz").write_bytes(b"PK")
    return root


def _generate(out: Path, *args: str):
    return CliRunner().invoke(synth_main, ["--out", str(out), *TINY, *args])


# ---- A6: --out that already holds something --------------------------------------------------------------------


def test_a_dataset_of_another_version_is_not_overwritten(tmp_path):
    root = _fake_synth_dataset(tmp_path / "ds")
    before = _snapshot(root)
    result = _generate(root, "--version", "v2")
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert "already holds a streamdet-synth dataset" in result.output and "splits.json" in result.output
    assert "--overwrite" in result.output
    assert _snapshot(root) == before


def test_the_same_version_names_its_table_folder(tmp_path):
    root = _fake_synth_dataset(tmp_path / "ds")
    result = _generate(root)
    assert result.exit_code == 1 and f"{root / 'v1.0-synth'} already exists" in result.output


@pytest.mark.parametrize("overwrite", [False, True])
def test_a_folder_that_is_no_synth_dataset_is_never_written_nor_deleted(tmp_path, overwrite):
    victim = tmp_path / "victim"
    (victim / "samples").mkdir(parents=True)
    (victim / "precious.txt").write_text("precious")
    before = _snapshot(victim)
    result = _generate(victim, *(["--overwrite"] if overwrite else []))
    assert result.exit_code == 1 and "not a streamdet-synth dataset" in result.output
    assert "precious.txt" in result.output and "no world.json" in result.output
    assert _snapshot(victim) == before


def test_a_real_nuscenes_root_is_not_taken_for_a_synth_dataset(tmp_path):
    """Same folder and table names as a synth dataset; only world.json tells them apart."""
    root = tmp_path / "nuscenes"
    for sub in ("samples/LIDAR_TOP", "sweeps/LIDAR_TOP", "maps"):
        (root / sub).mkdir(parents=True)
    (root / "v1.0-mini").mkdir()
    (root / "v1.0-mini" / "sample.json").write_text("[]")
    before = _snapshot(root)
    result = _generate(root, "--overwrite")
    assert result.exit_code == 1 and "deletes nothing here" in result.output
    assert _snapshot(root) == before


def test_a_world_json_of_someone_else_does_not_mark_a_dataset(tmp_path):
    root = _fake_synth_dataset(tmp_path / "ds")
    (root / "world.json").write_text(json.dumps({"level": "1-1"}))
    assert "not a streamdet-synth world file" in survey_root(root).marker_problem
    (root / "world.json").write_text("[")
    assert "not valid JSON" in survey_root(root).marker_problem


def test_overwrite_refuses_foreign_entries_beside_a_dataset(tmp_path):
    root = _fake_synth_dataset(tmp_path / "ds")
    (root / "notes.txt").write_text("mine")
    before = _snapshot(root)
    result = _generate(root, "--overwrite")
    assert result.exit_code == 1 and "notes.txt" in result.output and "move them out" in result.output
    assert _snapshot(root) == before


def test_a_half_written_table_folder_counts_as_foreign(tmp_path):
    root = _fake_synth_dataset(tmp_path / "ds")
    (root / "v2").mkdir()
    (root / "v2" / "sample.json").write_text("[]")
    (root / "v2" / "README").write_text("not a table")
    survey = survey_root(root)
    assert root / "v2" in survey.foreign and root / "v1.0-synth" in survey.dataset


def test_overwrite_replaces_the_whole_dataset_and_keeps_the_training_cache(tmp_path):
    root = tmp_path / "ds"
    assert _generate(root, "--seed", "1").exit_code == 0
    (root / ".streamdet_cache").mkdir()
    (root / ".streamdet_cache" / "meta.json").write_text("{}")
    result = _generate(root, "--seed", "2", "--version", "v2", "--overwrite")
    assert result.exit_code == 0, result.output
    assert "deleting" in result.output and "v1.0-synth/" in result.output
    assert not (root / "v1.0-synth").exists() and (root / "v2" / "sample.json").is_file()
    assert json.loads((root / "splits.json").read_text())["train"] == ["synth-2-0000"]
    assert all(p.name.startswith("synth-2-") for p in (root / "samples" / "LIDAR_TOP").iterdir())
    assert (root / ".streamdet_cache" / "meta.json").is_file()


def test_a_symlinked_layout_folder_loses_the_link_only(tmp_path):
    elsewhere = tmp_path / "disk" / "samples"
    elsewhere.mkdir(parents=True)
    (elsewhere / "keep.bin").write_bytes(b"x")
    root = _fake_synth_dataset(tmp_path / "ds")
    shutil.rmtree(root / "samples")
    (root / "samples").symlink_to(elsewhere)
    remove_dataset_entries(survey_root(root).dataset)
    assert list(root.iterdir()) == [] and (elsewhere / "keep.bin").is_file()


def test_an_interrupted_run_leaves_a_folder_overwrite_recognises(tmp_path, monkeypatch):
    import streamdet.data.synth_writer as writer

    def fail(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(writer, "_write_scene", fail)
    with pytest.raises(KeyboardInterrupt):
        writer.generate_dataset(tmp_path / "ds", SynthConfig(num_scenes=1, resolution=(32, 18)))
    assert survey_root(tmp_path / "ds").marker_problem is None


# ---- A7: --version ------------------------------------------------------------------------------------------------

BAD_VERSIONS = [".", "..", "a/b", "/abs", "a\\b", "..\\x", "a\x00b", "", "samples", "sweeps", "maps", "preview",
                "Sweeps", "splits.json", "world.json", "trajectories.npz"]  # fmt: skip


@pytest.mark.parametrize("version", BAD_VERSIONS)
def test_synth_config_refuses_a_version_that_is_no_table_folder(version):
    with pytest.raises(ValueError, match="SynthConfig.version"):
        SynthConfig(version=version)


@pytest.mark.parametrize("version", ["v1.0-synth", "v1.0-mini", "v2", "samples2", ".hidden"])
def test_plain_version_names_are_accepted(version):
    assert SynthConfig(version=version).version == version


@pytest.mark.parametrize("version", ["..", "sweeps", "a\\b"])
def test_the_cli_refuses_a_bad_version_before_writing(tmp_path, version):
    out = tmp_path / "sv"
    result = _generate(out, "--version", version)
    assert result.exit_code == 2 and "--version" in result.output and "Traceback" not in result.output
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == []


# ---- A8, C3, D1: streamdet-synth stats outputs ----------------------------------------------------------------------


def _stats(*args: str):
    return CliRunner().invoke(synth_main, ["stats", *args])


@pytest.mark.parametrize(
    "args, option, message",
    [
        (["--no-reference", "--json", "{ds}/splits.json"], "--json", "lies inside the input DATA_DIR"),
        (["--no-reference", "--plot", "{ds}/maps/x.png"], "--plot", "lies inside the input DATA_DIR"),
        (["--json", "{ref}/x.json"], "--json", "lies inside the input --reference"),
        (["--reference", "{ds}", "--json", "{ds}/x.json"], "--json", "lies inside the input"),
        (["--no-reference", "--json", "{tmp}/same.png", "--plot", "{tmp}/same.png"], "--plot", "also the --json file"),
        (["--no-reference", "--reference", "{tmp}/nonexist"], "--reference", "one of --reference and --no-reference"),
        (["--no-reference", "--json", "{tmp}/no/such/dir/y.json"], "--json", "does not exist"),
        (["--no-reference", "--plot", "{tmp}/plot.json"], "--plot", "matplotlib has no .json format"),
    ],
    ids=["json in data", "plot in data", "json in default reference", "json in reference", "json is plot",
         "reference with no-reference", "json folder missing", "plot suffix"],
)  # fmt: skip
def test_stats_refuses_bad_outputs_before_measuring(tmp_path, args, option, message):
    ds = _fake_synth_dataset(tmp_path / "ds")  # no tables to measure: any measuring would fail differently
    fill = {"ds": str(ds), "tmp": str(tmp_path), "ref": str(SAMPLE_DIR)}
    before = _snapshot(ds)
    result = _stats(str(ds), *[a.format(**fill) for a in args])
    assert result.exit_code == 2 and option in result.output and message in result.output, result.output
    assert "measuring" not in result.output and "Traceback" not in result.output
    assert _snapshot(ds) == before and not (tmp_path / "no").exists()


def test_a_symlink_to_a_dataset_file_is_refused_as_stats_output(tmp_path):
    ds = _fake_synth_dataset(tmp_path / "ds")
    (tmp_path / "link.json").symlink_to(ds / "splits.json")
    result = _stats(str(ds), "--no-reference", "--json", str(tmp_path / "link.json"))
    assert result.exit_code == 2 and "DATA_DIR" in result.output


def test_stats_errors_end_in_one_line_at_the_console_edge(tmp_path, capsys):
    ds = _fake_synth_dataset(tmp_path / "ds")
    code = run_edge("streamdet.data.synth_cli", "streamdet-synth",
                    args=["stats", str(ds), "--no-reference", "--json", str(ds / "splits.json")])  # fmt: skip
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("Error")]
    assert code == 2 and len(errors) == 1 and "--json" in errors[0] and "Traceback" not in err


# ---- B2, C3, D3, D6: a sample folder's files ------------------------------------------------------------------------


def _sample_folder(tmp_path: Path, **replace: str | bytes | None) -> Path:
    """A copy of the bundled sample (symlinks to the big files) with the named files written anew; a None value
    removes the file. Keys use '_' for '.': calibration_json, boxes_json, lidar."""
    root = tmp_path / "sample"
    root.mkdir()
    for f in SAMPLE_DIR.iterdir():
        (root / f.name).symlink_to(f)
    names = {"calibration_json": "calibration.json", "boxes_json": "boxes.json", "lidar": CALIB["lidar"]["file"]}
    for key, content in replace.items():
        path = root / names[key]
        path.unlink()
        if content is not None:
            path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return root


@pytest.mark.parametrize("text, got", [("[]", "an array"), ("5", "a number 5"), ("null", "null"),
                                       ('"/dev/zero"', "a string '/dev/zero'"),
                                       (json.dumps(str(SAMPLE_DIR / "calibration.json")), "a string")])  # fmt: skip
def test_a_calibration_that_is_no_object_is_named_not_opened(tmp_path, text, got):
    root = _sample_folder(tmp_path, calibration_json=text)
    with pytest.raises(ValueError, match="top level") as e:
        load_bundled_sample(root)
    message = str(e.value)
    assert str(root / "calibration.json") in message and got in message and "cannot read" not in message


def test_a_malformed_rig_in_a_sample_names_the_calibration_file(tmp_path):
    calib = json.loads(json.dumps(CALIB))
    calib["cameras"][0]["K"] = [[1, 0], [0, 1]]
    root = _sample_folder(tmp_path, calibration_json=json.dumps(calib))
    with pytest.raises(CalibrationError, match=rf"^{root / 'calibration.json'}: cameras\[0\]\.K"):
        load_bundled_sample(root)


def test_an_empty_lidar_file_is_refused_naming_it(tmp_path):
    root = _sample_folder(tmp_path, lidar=b"")
    with pytest.raises(ValueError, match=r"holds no points \(0 bytes\)") as e:
        load_bundled_sample(root)
    assert CALIB["lidar"]["file"] in str(e.value)


def test_a_missing_file_of_a_users_sample_is_not_called_bundled(tmp_path):
    root = _sample_folder(tmp_path, boxes_json=None)
    with pytest.raises(FileNotFoundError, match="sample file not found") as e:
        load_bundled_sample(root)
    assert "bundled" not in str(e.value) and str(root / "boxes.json") in str(e.value)


def test_a_fifo_in_a_sample_is_not_a_regular_file(tmp_path, alarm):
    root = _sample_folder(tmp_path, boxes_json=None)
    os.mkfifo(root / "boxes.json")
    with pytest.raises(ValueError, match="is not a regular file") as e:
        load_bundled_sample(root)
    assert "not found" not in str(e.value) and "bundled" not in str(e.value)


@pytest.mark.parametrize(
    "doc, message",
    [
        ([1, 2], "the top level is an array [1, 2]"),
        (None, "the top level is null"),
        ("boxes", "the top level is a string 'boxes'"),
        ({"boxes": None}, "'boxes' must be a list, got null"),
        ({}, "has no 'boxes'"),
    ],
)
def test_a_boxes_file_names_its_top_level_type(tmp_path, doc, message):
    root = _sample_folder(tmp_path, boxes_json=json.dumps(doc))
    with pytest.raises(ValueError) as e:
        load_bundled_sample(root)
    assert message in str(e.value) and str(root / "boxes.json") in str(e.value)


def test_the_bundled_sample_still_loads():
    sample = load_bundled_sample()
    assert len(sample.points) > 0 and len(sample.gt_boxes) > 0


# ---- B2, D5: Rig.from_calibration_json ------------------------------------------------------------------------------


@pytest.mark.parametrize("arg", [[], None, 5, 1.5, b"calibration.json", ["a"], ("x",)])
def test_from_calibration_json_refuses_what_is_no_path_nor_object(arg):
    with pytest.raises(CalibrationError, match="expected a path to a calibration.json or its parsed JSON object"):
        Rig.from_calibration_json(arg)


def test_calibration_errors_name_the_path_as_given(tmp_path):
    sub = tmp_path / "a" / "b"
    sub.mkdir(parents=True)
    with pytest.raises(CalibrationError, match=rf"^{sub / 'missing.json'}: cannot read: no such file"):
        Rig.from_calibration_json(sub / "missing.json")
    (sub / "calibration.json").write_text("{not json")
    with pytest.raises(CalibrationError, match=rf"^{sub / 'calibration.json'}: not valid JSON"):
        Rig.from_calibration_json(str(sub / "calibration.json"))


def test_an_empty_calibration_path_is_named(tmp_path):
    with pytest.raises(CalibrationError, match=r"calibration path is empty \(''\)"):
        Rig.from_calibration_json("")


def test_a_symlink_loop_and_a_broken_link_are_told_apart(tmp_path):
    (tmp_path / "loop1").symlink_to(tmp_path / "loop2")
    (tmp_path / "loop2").symlink_to(tmp_path / "loop1")
    (tmp_path / "dangling").symlink_to(tmp_path / "gone.json")
    with pytest.raises(CalibrationError, match=rf"^{tmp_path / 'loop1'}: cannot read: a symlink loop"):
        Rig.from_calibration_json(tmp_path / "loop1")
    with pytest.raises(CalibrationError, match=r"dangling: cannot read: a broken symlink \(to '.*gone\.json'"):
        Rig.from_calibration_json(tmp_path / "dangling")


def test_a_parsed_calibration_names_its_source():
    calib = json.loads(json.dumps(CALIB))
    del calib["cameras"]
    with pytest.raises(CalibrationError, match=r"^where/calibration\.json: .*cameras"):
        Rig.from_calibration_json(calib, source="where/calibration.json")
    with pytest.raises(CalibrationError, match=r"^calibration: .*cameras"):
        Rig.from_calibration_json(calib)


def test_valid_calibrations_still_load():
    import importlib.resources

    by_path = Rig.from_calibration_json(SAMPLE_DIR / "calibration.json")
    by_resource = Rig.from_calibration_json(importlib.resources.files("streamdet.data") / "nuscenes_sample" / "calibration.json")
    by_dict = Rig.from_calibration_json(CALIB)
    assert by_path.sha256() == by_resource.sha256() == by_dict.sha256()
    np.testing.assert_array_equal(by_path.lidar2ego, by_dict.lidar2ego)
