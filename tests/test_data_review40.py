"""Review 40 of data/: the nuScenes reader's LiDAR 'prev' chain (F1), the size of a .pcd.bin (F2), world.json in
`streamdet-synth stats` (F3), an empty key-frame sweep in a sample folder (F4) and dataset files that are broken
symlinks (F5). Each test pairs a hostile input of the review's repros with the error it must give."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from test_data_cli_hostile import CALIB, _sample_folder  # a copy of the bundled sample with files replaced
from test_data_nuscenes import _write_tables  # nuScenes tables made from the bundled sample, with one past sweep

import streamdet.data.sample as sample_module
from streamdet.core.points import MAX_SWEEP_POINTS
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.sample import bundled_sample_dir, load_bundled_sample, load_points
from streamdet.data.synth_cli import main as synth_main
from streamdet.data.synth_stats import dataset_stats, open_samples
from streamdet.data.synth_world import world_version_of

VERSION = "v1.0-mini"  # the tables _write_tables writes
KEY = "sd-LIDAR_TOP"  # sample_data row 0: the key frame's LiDAR, its 'prev' the past sweep
PAST = "sd-LIDAR_TOP-past"  # row 1: 50 ms before the key frame, the end of the chain
KEY_TS = CALIB["sample_timestamp_us"]  # the key frame's timestamp


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("review40_nusc")
    return root, _write_tables(root)


def _dataset(base: Path, dst: Path, edit=None, copy_files: bool = False) -> Path:
    """``dst``: the tables of ``base`` with ``edit(rows)`` applied to sample_data (token -> row), and its files
    linked (the reader follows links) or, for tests that change them, copied."""
    dst.mkdir()
    for name in ("samples", "sweeps"):
        if copy_files:
            shutil.copytree(base / name, dst / name)
        else:
            (dst / name).symlink_to(base / name)
    shutil.copytree(base / VERSION, dst / VERSION)
    if edit is not None:
        path = dst / VERSION / "sample_data.json"
        rows = json.loads(path.read_text())
        edit({r["token"]: r for r in rows})
        path.write_text(json.dumps(rows))
    return dst


def _sample_token(base: tuple[Path, dict]) -> str:
    return base[1]["calib"]["sample_token"]


# ---- F1: the LiDAR 'prev' chain --------------------------------------------------------------------------------------


def _set(token: str, field: str, value):
    return lambda rows: rows[token].__setitem__(field, value)


@pytest.mark.parametrize(
    "edit, sweeps, message",
    [
        # the key frame's prev names the key frame: it came back as its own past sweep, with lag 0
        (_set(KEY, "prev", KEY), 3,
         f"row 0 (token '{KEY}'): field 'prev' names '{KEY}', a sweep already on the LIDAR_TOP 'prev' chain of key "
         f"frame '{KEY}': the chain loops"),
        # the past sweep's prev leads back to the key frame: key frame and past sweep came back in turn
        (_set(PAST, "prev", KEY), 3, f"row 1 (token '{PAST}'): field 'prev' names '{KEY}', a sweep already on the LIDAR_TOP 'prev' chain"),
        # a past sweep stamped after the key frame: a negative time lag
        (_set(PAST, "timestamp", KEY_TS + 350_000), 1,
         f"row 1 (token '{PAST}'): field 'timestamp' is {KEY_TS + 350_000}, not before the {KEY_TS} of the LIDAR_TOP "
         f"sweep whose 'prev' names it ('{KEY}')"),
        (_set(PAST, "timestamp", KEY_TS), 1, f"row 1 (token '{PAST}'): field 'timestamp' is {KEY_TS}, not before the {KEY_TS}"),
        # prev names a camera's sample_data: its JPEG was read as LiDAR points
        (_set(KEY, "prev", "sd-CAM_FRONT"), 1,
         f"row 0 (token '{KEY}'): field 'prev' names 'sd-CAM_FRONT', a CAM_FRONT sample_data, not a LIDAR_TOP sweep"),
    ],
    ids=["self", "loop", "newer", "same time", "camera"],
)  # fmt: skip
def test_a_bad_prev_chain_is_refused_naming_the_row_and_value(base, tmp_path, edit, sweeps, message):
    root = _dataset(base[0], tmp_path / "ds", edit)
    reader = NuScenesReader(root, VERSION)
    assert reader.get(_sample_token(base)).sweeps == ()  # a chain not followed is not checked
    with pytest.raises(ValueError) as e:
        reader.get(_sample_token(base), num_past_sweeps=sweeps)
    assert f"nuScenes table 'sample_data' ({root / VERSION / 'sample_data'}.json) {message}" in str(e.value), str(e.value)


def test_a_sound_prev_chain_still_gives_its_sweep(base, tmp_path):
    reader = NuScenesReader(_dataset(base[0], tmp_path / "ds"), VERSION)
    (sweep,) = reader.get(_sample_token(base), num_past_sweeps=3).sweeps
    assert sweep.token == PAST and sweep.time_lag_s == pytest.approx(0.05)


# ---- F2: a .pcd.bin over any sweep's size --------------------------------------------------------------------------


def test_a_huge_pcd_bin_is_refused_before_it_is_read(tmp_path, monkeypatch):
    path = tmp_path / "huge.pcd.bin"
    with open(path, "wb") as f:  # sparse: no disk used
        f.truncate((MAX_SWEEP_POINTS + 1) * 20)

    def no_read(*args, **kwargs):
        raise AssertionError("the file was read")

    monkeypatch.setattr(np, "fromfile", no_read)
    with pytest.raises(ValueError) as e:
        load_points(path)
    text = str(e.value)
    assert str(path) in text and f"{(MAX_SWEEP_POINTS + 1) * 20} bytes" in text and str(MAX_SWEEP_POINTS) in text


def test_the_sweep_size_limit_is_inclusive(tmp_path, monkeypatch):
    monkeypatch.setattr(sample_module, "MAX_SWEEP_POINTS", 3)
    np.zeros((3, 5), dtype=np.float32).tofile(tmp_path / "three.pcd.bin")
    np.zeros((4, 5), dtype=np.float32).tofile(tmp_path / "four.pcd.bin")
    assert load_points(tmp_path / "three.pcd.bin").shape == (3, 5)
    with pytest.raises(ValueError, match=r"four\.pcd\.bin is 80 bytes \(4 points\), over the 3 points"):
        load_points(tmp_path / "four.pcd.bin")


def test_every_reader_of_a_sweep_gets_the_size_limit(base, tmp_path, monkeypatch):
    monkeypatch.setattr(sample_module, "MAX_SWEEP_POINTS", 1000)  # the bundled sweep holds 34,688 points
    lidar = CALIB["lidar"]["file"]
    refused = rf"{re.escape(lidar)} is 693760 bytes \(34688 points\), over the 1000 points"
    with pytest.raises(ValueError, match=refused):
        load_bundled_sample()
    with pytest.raises(ValueError, match=refused):
        NuScenesReader(_dataset(base[0], tmp_path / "ds"), VERSION).get(_sample_token(base))
    result = CliRunner().invoke(synth_main, ["stats", str(bundled_sample_dir()), "--no-reference"])
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert lidar in result.output and "over the 1000 points" in result.output


# ---- F3: world.json in streamdet-synth stats ----------------------------------------------------------------------


def _world(**scene) -> bytes:
    return json.dumps({"world_version": 6, "scenes": {"scene-0061": scene}}).encode()


ROAD = {"origin_xy": [0.0, 0.0], "yaw": 0.1, "half_width_m": 7.0}


def _stats_dataset(base: Path, dst: Path) -> Path:
    """``_dataset`` with the sample holding the sweep first (_write_tables puts it between two bare neighbours), so
    that ``--max-samples 1`` measures it."""
    root = _dataset(base, dst)
    path = root / VERSION / "sample.json"
    rows = json.loads(path.read_text())
    path.write_text(json.dumps(rows[1:2] + rows[:1] + rows[2:]))
    return root


@pytest.mark.parametrize(
    "content, message",
    [
        (b'{"scenes": []}', "field 'world_version' is missing"),
        (b'{"world_version": 6, "scenes": []}', "field 'scenes' must be an object of scenes by name, got []"),
        (b'{"world_version": "6", "scenes": {}}', "field 'world_version' must be an integer (synth_world.WORLD_VERSION), got '6'"),
        (b"[]", "must be a JSON object, got []"),
        (b'{"world_version": 6, "scenes": {"scene-0061": 5}}', "scenes['scene-0061']: must be a JSON object, got 5"),
        (_world(roads=5), "scenes['scene-0061']: field 'roads' must be a list of road strips, got 5"),
        (_world(roads=[dict(ROAD, yaw="1")]), "scenes['scene-0061'] roads[0]: field 'yaw' must be a finite number, got '1'"),
        (_world(roads=[dict(ROAD, half_width_m=-1)]), "roads[0]: field 'half_width_m' must be a finite number >= 0, got -1"),
        (_world(roads=[{"yaw": 0.1, "half_width_m": 7.0}]), "roads[0]: field 'origin_xy' is missing"),
        (_world(distractors_xy="ab"), "field 'distractors_xy' must be a list of [x, y] pairs of finite numbers, got 'ab'"),
        (_world(distractors_xy=[[1, 2, 3]]), "field 'distractors_xy' must be a list of [x, y] pairs"),
        (b"not json", "is not valid JSON"),
        (b"\xff\xfe", "is not UTF-8 text"),
    ],
)
def test_a_malformed_world_json_is_refused_naming_it_and_the_field(base, tmp_path, content, message):
    root = _stats_dataset(base[0], tmp_path / "ds")
    (root / "world.json").write_bytes(content)
    with pytest.raises(ValueError) as e:
        dataset_stats(root, max_samples=1)
    assert str(root / "world.json") in str(e.value) and message in str(e.value)
    assert world_version_of(root) in (None, 6)  # the label reader stays lenient (see synth_stats.open_samples)
    result = CliRunner().invoke(synth_main, ["stats", str(root), "--no-reference", "--max-samples", "1"])
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert str(root / "world.json") in result.output and message in result.output


def test_a_world_json_that_is_no_file_is_refused_unopened(base, tmp_path, alarm):
    root = _dataset(base[0], tmp_path / "ds")
    os.mkfifo(root / "world.json")
    with pytest.raises(ValueError, match="world.json is not a regular file"):
        open_samples(root)


def test_a_sound_world_json_is_measured_and_none_is_no_world(base, tmp_path):
    root = _stats_dataset(base[0], tmp_path / "ds")
    stats = dataset_stats(root, max_samples=1)  # real nuScenes: no world
    assert stats["world_version"] is None is world_version_of(root) and stats["vehicles_heading_measured"] == 0
    (root / "world.json").write_bytes(_world(roads=[ROAD], distractors_xy=[[1.0, 2.0]], distractor_kinds=["bollard"]))
    stats = dataset_stats(root, max_samples=1)
    assert stats["world_version"] == 6 == world_version_of(root) and "world 6" in stats["label"]
    assert stats["vehicles_heading_measured"] > 0 and stats["distractors_within_40m_per_frame"] == 0


# ---- F4: an empty key-frame sweep in a sample folder -----------------------------------------------------------


def test_an_empty_sample_sweep_is_one_error_without_a_warning_first(tmp_path, caplog):
    root = _sample_folder(tmp_path, lidar=b"")
    with caplog.at_level(logging.WARNING, logger="streamdet.data.sample"):
        with pytest.raises(ValueError, match=r"holds no points \(0 bytes\): a sample needs its sweep"):
            load_bundled_sample(root)
        with pytest.raises(ValueError, match=r"holds no points \(0 bytes\)"):
            load_points(root / CALIB["lidar"]["file"], allow_empty=False)
    assert "read as a sweep without returns" not in caplog.text
    with caplog.at_level(logging.WARNING, logger="streamdet.data.sample"):
        assert load_points(root / CALIB["lidar"]["file"]).shape == (0, 5)  # other readers keep the devkit's leniency
    assert "read as a sweep without returns" in caplog.text


# ---- F5: a dataset file that is a symlink loop or a broken link ------------------------------------------------


def _key_lidar(root: Path) -> Path:
    rows = json.loads((root / VERSION / "sample_data.json").read_text())
    return root / rows[0]["filename"]


def test_a_lidar_file_that_is_a_symlink_loop_says_so(base, tmp_path):
    root = _dataset(base[0], tmp_path / "ds", copy_files=True)
    lidar = _key_lidar(root)
    lidar.unlink()
    lidar.symlink_to(lidar.name)
    with pytest.raises(FileNotFoundError) as e:
        NuScenesReader(root, VERSION).get(_sample_token(base))
    text = str(e.value)
    assert f"file of sample_data {KEY}" in text and str(lidar) in text and "a symlink loop" in text
    assert "not found" not in text


def test_a_lidar_file_that_is_a_broken_link_says_so(base, tmp_path):
    root = _dataset(base[0], tmp_path / "ds", copy_files=True)
    lidar = _key_lidar(root)
    lidar.unlink()
    lidar.symlink_to(tmp_path / "gone.pcd.bin")
    with pytest.raises(FileNotFoundError) as e:
        NuScenesReader(root, VERSION).get(_sample_token(base))
    text = str(e.value)
    assert str(lidar) in text and f"a broken symlink (to '{tmp_path / 'gone.pcd.bin'}', which does not exist)" in text


def test_a_samples_folder_linked_to_an_unmounted_disk_says_so(base, tmp_path):
    root = _dataset(base[0], tmp_path / "ds")
    (root / "samples").unlink()
    (root / "samples").symlink_to(tmp_path / "unmounted" / "samples")
    with pytest.raises(FileNotFoundError) as e:
        NuScenesReader(root, VERSION).get(_sample_token(base))
    text = str(e.value)
    assert f"{root / 'samples'} is a broken symlink (to '{tmp_path / 'unmounted' / 'samples'}'" in text


def test_a_missing_file_is_still_not_found(base, tmp_path):
    root = _dataset(base[0], tmp_path / "ds", copy_files=True)
    _key_lidar(root).unlink()
    with pytest.raises(FileNotFoundError, match=rf"file of sample_data {KEY} not found: "):
        NuScenesReader(root, VERSION).get(_sample_token(base))
