"""Hostile dataset input (audit findings 10, 11, 12): every malformed nuScenes table row, bundled-sample field or
raw point file is a ValueError naming the file, the row or box and the field, never a TypeError / OverflowError /
bare KeyError or silently wrong data; every file a dataset names is a relative path inside its root (symlinks the dataset holds are followed)."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from streamdet.cli_utils import run_edge
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.sample import bundled_sample_dir, dataset_file, load_bundled_sample, load_point_times, load_points

VERSION = "v1.0-synth"  # the tables of tiny_synth_data (conftest)
BIG = 10**400  # a JSON integer past float64


# ---- a private, editable copy of the tiny synthetic dataset ------------------------------------------------------


def _link_tree(src: Path, dst: Path) -> None:
    """Hard links where the file system allows (fast, no bytes copied), copies elsewhere: the tests edit the copy's
    files, which a symlink would pass on to the shared fixture."""

    def link(s, d):
        try:
            os.link(s, d)
        except OSError:
            shutil.copy2(s, d)

    shutil.copytree(src, dst, copy_function=link)


def _dataset(src: Path, dst: Path, mutate=None) -> Path:
    """``dst``: the files of ``src`` and its tables, changed by ``mutate(tables)`` (table name -> list of rows)."""
    tables = {p.stem: json.loads(p.read_text()) for p in (src / VERSION).glob("*.json")}
    if mutate is not None:
        mutate(tables)
    for name in ("samples", "sweeps"):
        if (src / name).is_dir():
            _link_tree(src / name, dst / name)
    shutil.copy2(src / "splits.json", dst / "splits.json")
    (dst / VERSION).mkdir(parents=True)
    for name, rows in tables.items():
        (dst / VERSION / f"{name}.json").write_text(json.dumps(rows))
    return dst


def _read_all(root: Path) -> None:
    reader = NuScenesReader(root, VERSION)
    for i in range(len(reader)):
        reader.get(i, num_past_sweeps=10)
        reader.scene_name(reader.sample_tokens[i])


def _lidar_key(t: dict, with_prev: bool = False) -> dict:
    return next(r for r in t["sample_data"] if r["is_key_frame"] and "LIDAR_TOP" in r["filename"] and (r["prev"] or not with_prev))


def _camera_key(t: dict) -> dict:
    return next(r for r in t["sample_data"] if r["is_key_frame"] and "CAM_FRONT" in r["filename"])


def _set(table: str, field: str, value, row=0):
    """A mutation: ``tables[table][row][field] = value`` (``row`` an index or a function of the tables)."""

    def mutate(t):
        (t[table][row] if isinstance(row, int) else row(t))[field] = value

    return mutate


def _drop(table: str, field: str, row=0):
    return lambda t: t[table][row].pop(field)


ROW_CASES = {
    # sample_annotation, the table the audit fuzzed first
    "ann size {}": (_set("sample_annotation", "size", {}),
                    r"'sample_annotation' \(.*sample_annotation\.json\) row 0 \(token '.+'\): field 'size' must be 3 positive finite numbers, got \{\}"),
    "ann size 2 numbers": (_set("sample_annotation", "size", [1.0, 2.0]), r"row 0 .*field 'size' must be 3"),
    "ann size zero": (_set("sample_annotation", "size", [0.0, 1.0, 1.0]), r"field 'size' must be 3 positive"),
    "ann size huge int": (_set("sample_annotation", "size", [BIG, 1, 1]), r"field 'size' .*got \[1000"),
    "ann translation missing": (_drop("sample_annotation", "translation"), r"row 0 .*field 'translation' is missing"),
    "ann translation NaN": (_set("sample_annotation", "translation", [float("nan"), 0, 0]), r"field 'translation' must be 3 finite"),
    "ann rotation not unit": (_set("sample_annotation", "rotation", [1.0, 0, 0, 0.5]), r"field 'rotation' must be a unit quaternion"),
    "ann rotation string": (_set("sample_annotation", "rotation", "x"), r"field 'rotation'"),
    "ann attribute_tokens int": (_set("sample_annotation", "attribute_tokens", 1), r"field 'attribute_tokens' must be a list of strings, got 1"),
    "ann attribute dangling": (_set("sample_annotation", "attribute_tokens", ["nope"]),
                               r"field 'attribute_tokens' names 'nope', which is no token of table 'attribute'"),
    "ann num_lidar_pts null": (_set("sample_annotation", "num_lidar_pts", None), r"field 'num_lidar_pts' must be an integer >= 0"),
    "ann num_lidar_pts huge": (_set("sample_annotation", "num_lidar_pts", 10**30), r"field 'num_lidar_pts'"),
    "ann num_radar_pts negative": (_set("sample_annotation", "num_radar_pts", -1), r"field 'num_radar_pts'"),
    "ann num_radar_pts bool": (_set("sample_annotation", "num_radar_pts", True), r"field 'num_radar_pts'"),
    "ann prev dangling": (_set("sample_annotation", "prev", "nowhere"),
                          r"field 'prev' names 'nowhere', which is no token of table 'sample_annotation'"),
    "ann next null": (_set("sample_annotation", "next", None), r"field 'next' must be a string"),
    "ann instance dangling": (_set("sample_annotation", "instance_token", "nope"), r"field 'instance_token' names 'nope'"),
    "ann sample dangling": (_set("sample_annotation", "sample_token", "nope"),
                            r"'sample_annotation' .*row 0 .*field 'sample_token' names 'nope', which is no token of table 'sample'"),
    "ann sample unhashable": (_set("sample_annotation", "sample_token", []), r"field 'sample_token' must be a non-empty string, got \[\]"),
    "ann row 3 bad": (_set("sample_annotation", "size", None, row=3), r"'sample_annotation' .*row 3 \(token"),
    # tokens and rows
    "row not an object": (lambda t: t["sensor"].__setitem__(0, 1), r"'sensor' .*row 0: must be a JSON object, got 1"),
    "row a list": (lambda t: t["sample"].__setitem__(0, []), r"'sample' .*row 0: must be a JSON object"),
    "token missing": (_drop("category", "token"), r"'category' .*row 0: field 'token' is missing"),
    "token unhashable": (_set("instance", "token", {}), r"'instance' .*row 0: field 'token' must be a non-empty string"),
    "token empty": (_set("ego_pose", "token", ""), r"'ego_pose' .*row 0 .*field 'token' must be a non-empty string, got ''"),
    "token duplicate": (lambda t: t["scene"].append(dict(t["scene"][0])), r"'scene' .*row 1 .*the token is also that of row 0"),
    # sample, scene, category, instance
    "sample timestamp huge": (_set("sample", "timestamp", BIG),
                              r"'sample' .*field 'timestamp' must be an integer >= 0 \(int64\), got an integer of 401 digits"),
    "sample timestamp string": (_set("sample", "timestamp", "1"), r"field 'timestamp'"),
    "sample timestamp float": (_set("sample", "timestamp", 1.5), r"field 'timestamp'"),
    "sample scene dangling": (_set("sample", "scene_token", "nope"), r"'sample' .*field 'scene_token' names 'nope'"),
    "scene name int": (_set("scene", "name", 5), r"'scene' .*field 'name' must be a string"),
    "category name null": (_set("category", "name", None), r"'category' .*field 'name'"),
    "instance category dangling": (_set("instance", "category_token", "nope"), r"'instance' .*field 'category_token' names 'nope'"),
    # sensors and poses
    "sensor channel list": (_set("sensor", "channel", []), r"'sensor' .*field 'channel'"),
    "calibrated_sensor translation short": (_set("calibrated_sensor", "translation", [1, 2]), r"'calibrated_sensor' .*field 'translation' must be 3"),
    "calibrated_sensor intrinsic ragged": (_set("calibrated_sensor", "camera_intrinsic", [[1, 2, 3]]), r"field 'camera_intrinsic' must be a 3x3"),
    "calibrated_sensor sensor dangling": (_set("calibrated_sensor", "sensor_token", "nope"),
                                          r"'calibrated_sensor' .*field 'sensor_token' names 'nope'"),
    "ego_pose rotation string": (_set("ego_pose", "rotation", "x"), r"'ego_pose' .*field 'rotation'"),
    "ego_pose translation huge": (_set("ego_pose", "translation", [BIG, 0, 0]), r"'ego_pose' .*field 'translation'"),
    # sample_data
    "sd is_key_frame string": (_set("sample_data", "is_key_frame", "yes", _lidar_key),
                               r"'sample_data' .*field 'is_key_frame' must be true or false, got 'yes'"),
    "sd calibrated_sensor dangling": (_set("sample_data", "calibrated_sensor_token", "nope", _lidar_key),
                                      r"field 'calibrated_sensor_token' names 'nope'"),
    "sd ego_pose dangling": (_set("sample_data", "ego_pose_token", "nope", _lidar_key), r"'sample_data' .*field 'ego_pose_token' names 'nope'"),
    "sd timestamp null": (_set("sample_data", "timestamp", None, _lidar_key), r"'sample_data' .*field 'timestamp'"),
    "sd timestamp huge": (_set("sample_data", "timestamp", BIG, _lidar_key), r"'sample_data' .*field 'timestamp'"),
    "sd prev dangling": (_set("sample_data", "prev", "nope", lambda t: _lidar_key(t, with_prev=True)),
                         r"field 'prev' names 'nope', which is no token of table 'sample_data'"),
    "sd width string": (_set("sample_data", "width", "1600", _camera_key), r"'sample_data' .*field 'width'"),
    "sd width zero": (_set("sample_data", "width", 0, _camera_key), r"'sample' .*do not form a camera rig"),
    "sd filename null": (_set("sample_data", "filename", None, _lidar_key), r"'sample_data' .*field 'filename' must be a non-empty string"),
    "sd filename empty": (_set("sample_data", "filename", "", _lidar_key), r"field 'filename'"),
    "sd filename absolute": (_set("sample_data", "filename", str(Path(bundled_sample_dir(), "calibration.json")), _lidar_key),
                             r"field 'filename': file '/.+' must be a relative path inside the dataset root"),
    "sd filename dotdot": (_set("sample_data", "filename", "samples/../../outside.pcd.bin", _lidar_key), r"without '\.\.'"),
    "sd filename NUL": (_set("sample_data", "filename", "samples/a\x00b", _lidar_key), r"field 'filename'"),
}


@pytest.mark.parametrize("mutate, message", list(ROW_CASES.values()), ids=list(ROW_CASES))
def test_a_malformed_table_row_is_a_value_error_naming_table_row_and_field(tiny_synth_data, tmp_path, mutate, message):
    root = _dataset(tiny_synth_data, tmp_path / "ds", mutate)
    with pytest.raises(ValueError, match=message) as e:
        _read_all(root)
    assert e.type is ValueError  # not a KeyError / TypeError subclass a CLI would print as a traceback
    assert "\n" not in str(e.value)


def test_the_unchanged_copy_reads(tiny_synth_data, tmp_path):
    _read_all(_dataset(tiny_synth_data, tmp_path / "ds"))


def test_optional_fields_keep_their_devkit_defaults(tiny_synth_data, tmp_path):
    def mutate(t):
        for a in t["sample_annotation"]:
            for k in ("attribute_tokens", "num_lidar_pts", "num_radar_pts"):
                a.pop(k, None)
        for cs in t["calibrated_sensor"]:
            if cs["camera_intrinsic"] == []:
                cs.pop("camera_intrinsic")

    s = NuScenesReader(_dataset(tiny_synth_data, tmp_path / "ds", mutate), VERSION).get(0)
    assert set(s.attribute_names) == {""} and not s.num_lidar_pts.any() and not s.num_radar_pts.any()


@pytest.mark.parametrize(
    "text, message",
    [
        ("[" * 100_000 + "]" * 100_000, "nests too deeply"),
        ("[" + "9" * 5000 + "]", "is not valid JSON: Exceeds the limit"),
        (b"\xff\xfe[]", "is not UTF-8 text"),
    ],
    ids=["deep", "5000-digit int", "not UTF-8"],
)
def test_an_unreadable_table_file_is_named(tiny_synth_data, tmp_path, text, message):
    root = _dataset(tiny_synth_data, tmp_path / "ds")
    path = root / VERSION / "sample_annotation.json"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ValueError, match=rf"nuScenes table {re.escape(str(path))} {message}"):
        NuScenesReader(root, VERSION)


# ---- files stay inside the dataset root ---------------------------------------------------------------------------


def _lidar_file(root: Path) -> Path:
    reader = NuScenesReader(root, VERSION)
    return reader.root / reader._by_token["sample_data"][reader._key_data[reader.sample_tokens[0]]["LIDAR_TOP"]]["filename"]


def test_a_symlinked_dataset_root_reads(tiny_synth_data, tmp_path):
    root = _dataset(tiny_synth_data, tmp_path / "ds")
    (tmp_path / "link").symlink_to(root)
    s = NuScenesReader(tmp_path / "link", VERSION).get(0)
    assert str(s.image_paths["CAM_FRONT"]).startswith(str(tmp_path / "link"))


def test_a_symlink_to_a_file_inside_the_dataset_is_followed(tiny_synth_data, tmp_path):
    root = _dataset(tiny_synth_data, tmp_path / "ds")
    lidar = _lidar_file(root)
    kept = root / "moved" / lidar.name
    kept.parent.mkdir()
    lidar.rename(kept)
    lidar.symlink_to(os.path.relpath(kept, lidar.parent))
    assert len(NuScenesReader(root, VERSION).get(0).points) > 0


@pytest.mark.parametrize("what", ["file", "folder"])
def test_a_symlink_out_of_the_dataset_is_followed(tiny_synth_data, tmp_path, what):
    """The usual nuScenes set-up: samples/ (or a file) linked to another disk. Only the tables' names are confined."""
    root = _dataset(tiny_synth_data, tmp_path / "ds")
    lidar = _lidar_file(root)
    outside = tmp_path / "outside"
    if what == "file":
        outside.mkdir()
        lidar.rename(outside / lidar.name)
        lidar.symlink_to(outside / lidar.name)
    else:  # the whole samples/ folder lives elsewhere
        (root / "samples").rename(outside)
        (root / "samples").symlink_to(outside)
    assert len(NuScenesReader(root, VERSION).get(0).points) > 0


@pytest.mark.parametrize("name", ["", "/etc/hostname", "../x", "a/../../x", None, 5])
def test_dataset_file_refuses_names_that_leave_the_root(tmp_path, name):
    with pytest.raises(ValueError, match="where"):
        dataset_file(tmp_path, name, "where")


def test_dataset_file_allows_a_name_inside_the_root(tmp_path):
    assert dataset_file(tmp_path, "a/b.bin", "where") == tmp_path / "a" / "b.bin"


def test_a_cli_reading_a_malformed_dataset_prints_one_line(tiny_synth_data, tmp_path, capsys):
    root = _dataset(tiny_synth_data, tmp_path / "ds", _set("sample", "timestamp", BIG))
    code = run_edge("streamdet.data.synth_cli", "streamdet-synth", args=["stats", str(root), "--no-reference"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    last = err.strip().splitlines()[-1]  # after the tool's "measuring DIR" progress line
    assert last.startswith("Error: ") and "'sample'" in last and "field 'timestamp'" in last


# ---- the bundled sample's boxes.json and calibration.json ---------------------------------------------------------

SAMPLE_DIR = bundled_sample_dir()
BOXES = json.loads((SAMPLE_DIR / "boxes.json").read_text())
CALIB = json.loads((SAMPLE_DIR / "calibration.json").read_text())


def _sample_folder(tmp_path: Path, boxes=None, calib=None) -> Path:
    """A copy of the bundled sample (hard links) with its boxes.json / calibration.json replaced."""
    root = tmp_path / "sample"
    _link_tree(SAMPLE_DIR, root)
    for name, doc in (("boxes.json", boxes), ("calibration.json", calib)):
        if doc is not None:
            (root / name).unlink()
            (root / name).write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return root


def _box(field: str, value, index: int = 0) -> dict:
    doc = json.loads(json.dumps(BOXES))
    if value is _MISSING:
        doc["boxes"][index].pop(field)
    else:
        doc["boxes"][index][field] = value
    return doc


_MISSING = object()
BOX_CASES = {
    "center null": ("center_xyz", None, r"field 'center_xyz' must be 3 finite numbers, got None"),
    "center one value": ("center_xyz", [1], r"field 'center_xyz' must be 3 finite numbers, got \[1\]"),  # would broadcast
    "center four values": ("center_xyz", [1, 2, 3, 4], r"field 'center_xyz'"),
    "center NaN": ("center_xyz", [float("nan"), 0, 0], r"field 'center_xyz'"),
    "center huge": ("center_xyz", [BIG, 0, 0], r"field 'center_xyz'"),
    "size null": ("size_wlh", None, r"field 'size_wlh' must be 3 positive finite numbers"),
    "size negative": ("size_wlh", [-1, 1, 1], r"field 'size_wlh'"),
    "yaw string": ("yaw", "0", r"field 'yaw' must be a finite number"),
    "yaw huge": ("yaw", BIG, r"field 'yaw' .*401 digits"),
    "label 99": ("label", 99, r"field 'label' must be an integer in -1\.\.9"),
    "label -2": ("label", -2, r"field 'label'"),
    "label float": ("label", 1.0, r"field 'label'"),
    "label bool": ("label", True, r"field 'label'"),
    "velocity 5": ("velocity_xy", 5, r"field 'velocity_xy' must be null or 2 numbers"),
    "velocity one value": ("velocity_xy", [1.0], r"field 'velocity_xy'"),
    "velocity string": ("velocity_xy", ["a", "b"], r"field 'velocity_xy'"),
    "num_lidar_pts null": ("num_lidar_pts", None, r"field 'num_lidar_pts' must be an integer >= 0"),
    "num_lidar_pts huge": ("num_lidar_pts", 10**30, r"field 'num_lidar_pts'"),
    "num_radar_pts float": ("num_radar_pts", 1.5, r"field 'num_radar_pts'"),
    "center_global missing": ("center_global", _MISSING, r"field 'center_global' is missing"),
}


@pytest.mark.parametrize("field, value, message", list(BOX_CASES.values()), ids=list(BOX_CASES))
def test_a_malformed_box_is_a_value_error_naming_box_and_field(tmp_path, field, value, message):
    root = _sample_folder(tmp_path, boxes=_box(field, value))
    with pytest.raises(ValueError, match=rf"{re.escape(str(root / 'boxes.json'))} boxes\[0\]: {message}") as e:
        load_bundled_sample(root)
    assert e.type is ValueError


def test_a_box_in_the_middle_is_named_by_its_index(tmp_path):
    with pytest.raises(ValueError, match=r"boxes\[7\]: field 'label'"):
        load_bundled_sample(_sample_folder(tmp_path, boxes=_box("label", 10, index=7)))


@pytest.mark.parametrize("value", [None, [None, None], [float("nan"), 1.0], [1.0, None]])
def test_an_unknown_velocity_is_flagged_not_refused(tmp_path, value):
    s = load_bundled_sample(_sample_folder(tmp_path, boxes=_box("velocity_xy", value)))
    assert not s.velocity_valid[0] and np.all(s.gt_boxes[0, 7:9] == 0)


@pytest.mark.parametrize(
    "doc, message",
    [
        ({"boxes": 5}, "'boxes' must be a list"),
        ([], "'boxes' must be a list"),
        ({"boxes": [5]}, r"boxes\[0\]: must be a JSON object, got 5"),
        ("{not json", "not valid JSON"),
        ("[" * 100_000, "nests too deeply"),
    ],
)
def test_a_malformed_boxes_file_is_named(tmp_path, doc, message):
    root = _sample_folder(tmp_path, boxes=doc)
    with pytest.raises(ValueError, match=message) as e:
        load_bundled_sample(root)
    assert "boxes.json" in str(e.value)


def _calib(change) -> dict:
    doc = json.loads(json.dumps(CALIB))
    change(doc)
    return doc


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda c: c["lidar"].update(file=str(SAMPLE_DIR / CALIB["lidar"]["file"])), r"lidar: file '/.+' must be a relative path"),
        (lambda c: c["lidar"].update(file="../" + CALIB["lidar"]["file"]), r"lidar: file .* without '\.\.'"),
        (lambda c: c["lidar"].update(file=5), r"lidar: field 'file' must be a non-empty string, got 5"),
        (lambda c: c["lidar"].pop("file"), r"lidar: field 'file' is missing"),
        (lambda c: c["cameras"][2].update(file="/etc/hostname"), r"cameras\[2\]: file '/etc/hostname' must be a relative path"),
        (lambda c: c.update(sample_timestamp_us=BIG), r"field 'sample_timestamp_us'"),
        (lambda c: c.update(sample_token=None), r"field 'sample_token' must be a string"),
    ],
    ids=["lidar absolute", "lidar dotdot", "lidar int", "lidar missing", "camera absolute", "timestamp huge", "token null"],
)
def test_calibration_files_are_confined_and_checked(tmp_path, change, message):
    root = _sample_folder(tmp_path, calib=_calib(change))
    with pytest.raises(ValueError, match=message) as e:
        load_bundled_sample(root)
    assert "calibration.json" in str(e.value)


def test_a_sample_file_symlinked_out_of_the_folder_is_followed(tmp_path):
    root = _sample_folder(tmp_path)
    lidar = root / CALIB["lidar"]["file"]
    lidar.unlink()
    lidar.symlink_to(SAMPLE_DIR / CALIB["lidar"]["file"])
    assert len(load_bundled_sample(root).points) > 0


def test_a_copy_of_the_bundled_sample_reads_as_the_original(tmp_path):
    a, b = load_bundled_sample(), load_bundled_sample(_sample_folder(tmp_path))
    np.testing.assert_array_equal(a.gt_boxes, b.gt_boxes)
    np.testing.assert_array_equal(a.points, b.points)


# ---- raw point files -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("extra", [1, 2, 3])
def test_a_point_file_with_a_partial_float_is_refused(tmp_path, extra):
    path = tmp_path / "odd.pcd.bin"
    path.write_bytes(np.arange(50, dtype=np.float32).tobytes() + b"\x01" * extra)
    with pytest.raises(ValueError, match=rf"{path}: {200 + extra} bytes is not a whole number of float32"):
        load_points(path)


@pytest.mark.parametrize("nbytes", [43, 36, 44, 0])
def test_a_point_time_file_must_hold_one_float_per_point(tmp_path, nbytes):
    path = tmp_path / "p.pcd.bin"
    np.zeros((10, 5), dtype=np.float32).tofile(path)
    Path(str(path) + ".time").write_bytes(b"\x00" * nbytes)
    with pytest.raises(ValueError, match=rf"point-time file .*p\.pcd\.bin\.time.* {nbytes} bytes"):
        load_point_times(path, 10)


def test_a_whole_point_time_file_reads(tmp_path):
    path = tmp_path / "p.pcd.bin"
    Path(str(path) + ".time").write_bytes(np.arange(10, dtype="<f4").tobytes())
    np.testing.assert_array_equal(load_point_times(path, 10), np.arange(10, dtype=np.float32))


def test_a_fifo_is_named_not_missing(tmp_path, alarm):
    from streamdet.data.sample import load_points
    from streamdet.data.synth_trajectories import TRAJECTORIES_FILE, load_trajectories

    os.mkfifo(tmp_path / "sweep.pcd.bin")
    with pytest.raises(ValueError, match="is not a regular file"):
        load_points(tmp_path / "sweep.pcd.bin")
    os.mkfifo(tmp_path / TRAJECTORIES_FILE)  # was taken for "no sidecar": key-frame interpolation, silently
    with pytest.raises(ValueError, match="is not a regular file"):
        load_trajectories(tmp_path, "scene-0001")
    with pytest.raises(FileNotFoundError, match="LiDAR file not found"):
        load_points(tmp_path / "nothing.pcd.bin")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")
@pytest.mark.parametrize("which", ["splits.json", "table", "camera image"])
def test_a_fifo_in_a_dataset_is_named_as_one_not_as_missing(tiny_synth_data, tmp_path, which):
    from streamdet.data.splits import split_scenes

    data = tmp_path / "d"
    shutil.copytree(tiny_synth_data, data)
    if which == "splits.json":
        target = data / "splits.json"
    elif which == "table":
        target = data / "v1.0-synth" / "sample_annotation.json"
    else:  # a key frame's image, as the reader names it
        reader = NuScenesReader(data, "v1.0-synth")
        target = reader.get(reader.sample_tokens[0]).image_paths["CAM_FRONT"]
    target.unlink()
    os.mkfifo(target)
    with pytest.raises(ValueError, match="is not a regular file"):  # never opened: nothing blocks
        if which == "splits.json":
            split_scenes(data, "val")
        else:
            reader = NuScenesReader(data, "v1.0-synth")
            for token in reader.sample_tokens:
                reader.get(token).load_images((64, 36))
