"""`streamdet-bag` on hostile inputs (review 36): `export` reads the nuScenes tables through `NuScenesReader` and the
bundled layout through `Rig.from_calibration_json`, so a malformed field is one line naming the table or file, the row
and the field, as eval and replay say it, never a traceback, and no bag is left behind; a file a table names outside
the dataset is refused; an image the runtime would not decode, or of another size than its camera's, is refused at
export. `calibration` writes through no symlink at OUT.tmp and refuses a camera `--topics` maps to a missing topic;
`run` on its own output bag does not mix the old detections with the new ones."""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("mcap_ros2.writer")

from streamdet.bag.calibration import rig_from_bag, write_calibration_json  # noqa: E402
from streamdet.bag.run import OUTPUT_TOPICS, RunConfig, run_bag  # noqa: E402
from streamdet.bag.source import BagSource, SourceConfig  # noqa: E402
from streamdet.calibration.camera import Rig  # noqa: E402
from streamdet.data.sample import bundled_sample_dir, load_bundled_sample  # noqa: E402

from test_bag_cli_outputs import invoke, one_line_error  # noqa: E402  # the bag CLI checks' own helpers

VERSION = "v1.0-synth"


def assert_nothing_written(out: Path) -> None:
    """Neither the bag nor a temporary of it (BagWriter's hidden .partial) is left."""
    assert not out.exists()
    assert not out.parent.exists() or not any(out.parent.iterdir()), sorted(out.parent.iterdir())


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def topic_counts(path: Path) -> dict[str, int]:
    counts: dict[str, int] = {}
    for message in BagSource(path, SourceConfig()).messages():
        counts[message.topic] = counts.get(message.topic, 0) + 1
    return counts


@pytest.fixture(scope="module")
def bag(tiny_synth_data: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bag") / "drive.mcap"
    result = invoke("export", "--data", tiny_synth_data, "--out", out)
    assert result.exit_code == 0, result.output
    return out


# ---- H3: the nuScenes tables through NuScenesReader ------------------------------------------------------------


def _tables(data: Path) -> dict[str, list]:
    return {name: json.loads((data / VERSION / f"{name}.json").read_text())
            for name in ("sample_data", "calibrated_sensor", "sensor")}  # fmt: skip


def _row(data: Path, table: str, which: str) -> int:
    """The index in ``table`` of the row ``which`` names: "first", or the first sample_data / calibrated_sensor row of
    a "lidar", "camera" or non-key "sweep" sample_data."""
    if which == "first":
        return 0
    t = _tables(data)
    channel = {s["token"]: s["channel"] for s in t["sensor"]}
    cs_channel = {cs["token"]: channel[cs["sensor_token"]] for cs in t["calibrated_sensor"]}
    for i, sd in enumerate(t["sample_data"]):
        ch = cs_channel[sd["calibrated_sensor_token"]]
        if (which == "lidar" and ch == "LIDAR_TOP") or (which == "camera" and ch.startswith("CAM_")) or (
                which == "sweep" and ch == "LIDAR_TOP" and not sd["is_key_frame"]):  # fmt: skip
            if table == "sample_data":
                return i
            return next(j for j, cs in enumerate(t["calibrated_sensor"]) if cs["token"] == sd["calibrated_sensor_token"])
    raise AssertionError(f"no {which} row")


def _edit(data: Path, table: str, which: str, field: str, value: object) -> int:
    path = data / VERSION / f"{table}.json"
    rows = json.loads(path.read_text())
    index = _row(data, table, which)
    rows[index][field] = value
    path.write_text(json.dumps(rows))
    return index


# (table, which row, field, bad value, what the error says); the error names table, file, row and field
TABLE_CASES = [
    ("ego_pose", "first", "rotation", None, "must be a unit quaternion"),
    ("ego_pose", "first", "rotation", [2.0, 0.0, 0.0, 0.0], "must be a unit quaternion"),
    ("ego_pose", "first", "translation", [0.0, 0.0], "must be 3 finite numbers"),
    ("ego_pose", "first", "translation", [0.0, "x", 0.0], "must be 3 finite numbers"),
    ("calibrated_sensor", "lidar", "rotation", "x", "must be a unit quaternion"),
    ("calibrated_sensor", "camera", "translation", None, "must be 3 finite numbers"),
    ("calibrated_sensor", "camera", "camera_intrinsic", [[1.0, 0.0], [0.0, 1.0]], "must be a 3x3 matrix"),
    ("sample_data", "lidar", "timestamp", "x", "must be an integer >= 0"),
    ("sample_data", "camera", "timestamp", -1, "must be an integer >= 0"),
    ("sample_data", "camera", "timestamp", 2**62, "a ROS 2 stamp holds int32 seconds"),  # past int32 seconds
    ("sample_data", "lidar", "timestamp", 1.5e15, "must be an integer >= 0"),
    ("sample_data", "lidar", "filename", "/etc/hosts", "must be a relative path inside the dataset root"),
    ("sample_data", "camera", "filename", "../escape.jpg", "must be a relative path inside the dataset root"),
    ("sample_data", "camera", "filename", None, "must be a non-empty string"),
    ("sample_data", "lidar", "ego_pose_token", None, "must be a non-empty string"),
    ("sample_data", "camera", "ego_pose_token", "nope", "names 'nope', which is no token of table 'ego_pose'"),
    ("sample_data", "camera", "calibrated_sensor_token", "nope", "names 'nope', which is no token of table 'calibrated_sensor'"),
    ("sample_data", "camera", "is_key_frame", 1, "must be true or false"),
    ("sample_data", "camera", "sample_token", ["x"], "must be a non-empty string"),
    ("sample_data", "camera", "width", "x", "must be an integer >= 0"),
    ("scene", "first", "name", None, "must be a string"),
    ("scene", "first", "token", 7, "must be a non-empty string"),
    ("sample", "first", "scene_token", "nope", "names 'nope', which is no token of table 'scene'"),
    ("sample", "first", "timestamp", None, "must be an integer >= 0"),
]


@pytest.mark.parametrize("table, which, field, value, says", TABLE_CASES,
                         ids=[f"{t}.{f}={v!r}"[:60] for t, _, f, v, _ in TABLE_CASES])  # fmt: skip
def test_a_malformed_table_field_is_one_line_naming_table_row_and_field(tiny_synth_data: Path, tmp_path: Path, table,
                                                                        which, field, value, says):  # fmt: skip
    data = tmp_path / "data"
    shutil.copytree(tiny_synth_data, data)
    index = _edit(data, table, which, field, value)
    out = tmp_path / "out" / "x.mcap"
    line = one_line_error(invoke("export", "--data", data, "--out", out), says, f"field {field!r}")
    assert f"nuScenes table {table!r} ({data / VERSION / table}.json) row {index}" in line
    assert_nothing_written(out)


@pytest.mark.parametrize("field, value, says", [
    ("camera_intrinsic", [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], "focal lengths must be > 0"),
    ("camera_intrinsic", [], "Camera 'CAM_FRONT'.K: expected shape (3, 3)"),  # a camera with a LiDAR's intrinsics
])  # fmt: skip
def test_a_camera_the_rig_would_refuse_is_refused(tiny_synth_data: Path, tmp_path: Path, field, value, says):
    """Well-formed fields that make no camera: the rig's checks (Camera) say why, naming the sample's rows."""
    data = tmp_path / "data"
    shutil.copytree(tiny_synth_data, data)
    _edit(data, "calibrated_sensor", "camera", field, value)
    out = tmp_path / "out" / "x.mcap"
    one_line_error(invoke("export", "--data", data, "--out", out), says, "nuScenes table")
    assert_nothing_written(out)


@pytest.mark.parametrize("field, value, says", [
    ("width", 0, "Camera 'CAM_FRONT'.width"),
    ("height", 70000, "Camera 'CAM_FRONT'.height"),
    ("camera_intrinsic", [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], "focal lengths must be > 0"),
    ("camera_intrinsic", [[1e9, 0.0, 80.0], [0.0, 1e9, 45.0], [0.0, 0.0, 1.0]], "a field of view under 0.06 degrees"),
])  # fmt: skip
def test_an_image_between_key_frames_gets_the_rigs_camera_checks(tiny_synth_data: Path, tmp_path: Path, field, value, says):
    """A camera image that is no key frame (nuScenes' 12 Hz images) is in no sample's rig: its size and intrinsics are
    checked as the rig checks a camera, naming its sample_data row."""
    data = tmp_path / "data"
    shutil.copytree(tiny_synth_data, data)
    tables = data / VERSION
    sample_data = json.loads((tables / "sample_data.json").read_text())
    sensors = json.loads((tables / "calibrated_sensor.json").read_text())
    front = next(sd for sd in sample_data if "CAM_FRONT__" in sd["filename"])
    extra = {**front, "token": "between", "is_key_frame": False, "timestamp": front["timestamp"] + 1, "prev": "", "next": ""}
    if field == "camera_intrinsic":  # the same mounting, other intrinsics: a calibrated_sensor row of its own
        cs = next(c for c in sensors if c["token"] == front["calibrated_sensor_token"])
        sensors.append({**cs, "token": "between_cs", field: value})
        extra["calibrated_sensor_token"] = "between_cs"
        (tables / "calibrated_sensor.json").write_text(json.dumps(sensors))
    else:
        extra[field] = value
    sample_data.append(extra)
    (tables / "sample_data.json").write_text(json.dumps(sample_data))
    out = tmp_path / "out" / "x.mcap"
    one_line_error(invoke("export", "--data", data, "--out", out), says,
                   f"nuScenes table 'sample_data' ({tables / 'sample_data'}.json) row {len(sample_data) - 1} (token 'between')")  # fmt: skip
    assert_nothing_written(out)


def test_a_sweep_file_outside_the_dataset_is_not_read(tiny_drive_data: Path, tmp_path: Path):
    """A non-key LiDAR sweep named by an absolute path (an existing file): refused as replay refuses it, unread."""
    data = tmp_path / "data"
    shutil.copytree(tiny_drive_data, data)
    rows = json.loads((data / VERSION / "sample_data.json").read_text())
    index = _row(data, "sample_data", "sweep")
    outside = tmp_path / "elsewhere.pcd.bin"
    shutil.copy(data / rows[index]["filename"], outside)
    _edit(data, "sample_data", "sweep", "filename", str(outside))
    out = tmp_path / "out" / "x.mcap"
    one_line_error(invoke("export", "--data", data, "--out", out), f"row {index}", "field 'filename'",
                   "must be a relative path inside the dataset root")  # fmt: skip
    assert_nothing_written(out)


def test_a_lidar_file_that_is_a_folder_is_named_as_such(tiny_synth_data: Path, tmp_path: Path):
    data = tmp_path / "data"
    shutil.copytree(tiny_synth_data, data)
    rows = json.loads((data / VERSION / "sample_data.json").read_text())
    lidar = data / rows[_row(data, "sample_data", "lidar")]["filename"]
    lidar.unlink()
    lidar.mkdir()
    out = tmp_path / "out" / "x.mcap"
    one_line_error(invoke("export", "--data", data, "--out", out), "is not a regular file", str(lidar))
    assert_nothing_written(out)


# ---- H3: the bundled layout through Rig.from_calibration_json --------------------------------------------------


def _sample_copy(tmp_path: Path) -> Path:
    folder = tmp_path / "sample"
    shutil.copytree(bundled_sample_dir(), folder, ignore=shutil.ignore_patterns("*.npz", "oracle_*", "*.md"))
    return folder


def _set(doc: dict, path: tuple, value: object) -> None:
    for key in path[:-1]:
        doc = doc[key]
    doc[path[-1]] = value


# (where in calibration.json, bad value, what the error says)
CALIBRATION_CASES = [
    (("cameras", 0, "timestamp_us"), -1, "cameras[0]: field 'timestamp_us' must be an integer of microseconds"),
    (("cameras", 0, "timestamp_us"), None, "cameras[0]: field 'timestamp_us' must be an integer of microseconds"),
    (("cameras", 0, "timestamp_us"), 2**62, "a ROS 2 stamp holds int32 seconds"),
    (("cameras", 0, "timestamp_us"), "x", "cameras[0].timestamp_us"),
    (("sample_timestamp_us",), -5, "field 'sample_timestamp_us'"),
    (("lidar", "sensor2ego"), {"rotation_wxyz": None, "translation": [0.0, 0.0, 0.0]}, "lidar.sensor2ego.rotation_wxyz"),
    (("lidar", "ego2global"), {"matrix": "x"}, "lidar.ego2global.matrix"),
    (("cameras", 0, "ego2global"), None, "cameras[0].ego2global"),
    (("cameras", 0, "ego2global"), {"matrix": [[1.0]]}, "cameras[0].ego2global.matrix"),
    (("cameras", 0, "ego2global"), {"rotation_wxyz": [1.0, 0.0, 0.0], "translation": [0.0, 0.0, 0.0]},
     "cameras[0].ego2global.rotation_wxyz"),
    (("cameras", 1, "lidar2cam"), {"matrix": None}, "cameras[1].lidar2cam.matrix"),
    # finite, so the rig takes it, but no float64 TF chain gives the rig's lidar2cam back beside such a pose
    (("cameras", 2, "ego2global"), {"matrix": [[1.0, 0.0, 0.0, 1e308], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0],
                                               [0.0, 0.0, 0.0, 1.0]]}, "cameras[2]: its lidar2cam cannot be carried"),
    (("cameras", 0, "K"), None, "cameras[0].K"),
    (("cameras", 0, "width"), 0, "cameras[0].width"),
    (("cameras", 0, "file"), "/etc/hosts", "must be a relative path inside the dataset root"),
    (("lidar", "file"), "../x.pcd.bin", "must be a relative path inside the dataset root"),
]  # fmt: skip


@pytest.mark.parametrize("where, value, says", CALIBRATION_CASES,
                         ids=[f"{'.'.join(map(str, w))}={v!r}"[:60] for w, v, _ in CALIBRATION_CASES])  # fmt: skip
def test_a_malformed_calibration_json_is_one_line_naming_the_field(tmp_path: Path, where, value, says):
    folder = _sample_copy(tmp_path)
    calib = folder / "calibration.json"
    doc = json.loads(calib.read_text())
    _set(doc, where, value)
    calib.write_text(json.dumps(doc))
    out = tmp_path / "out" / "x.mcap"
    one_line_error(invoke("export", "--data", folder, "--out", out), str(calib), says)
    assert_nothing_written(out)


def _matrices_only(doc: dict) -> dict:
    """calibration.json with every transform as {"matrix": ...} alone, a form the Rig takes (and to_dict writes)."""
    doc = copy.deepcopy(doc)
    for entry in [doc["lidar"], *doc["cameras"]]:
        for key in ("sensor2ego", "ego2global", "lidar2cam"):
            if key in entry:
                entry[key] = {"matrix": entry[key]["matrix"]}
    return doc


def _rig_to_dict_form(doc: dict) -> dict:
    """What Rig.to_dict writes (no camera mountings or ego poses at all), plus the sample's files and stamps."""
    rig = Rig.from_calibration_json(doc)
    out = rig.to_dict()
    out.update({k: doc[k] for k in ("sample_token", "sample_timestamp_us", "scene")})
    out["lidar"]["file"] = doc["lidar"]["file"]
    for cam, entry in zip(out["cameras"], doc["cameras"]):
        cam["file"] = entry["file"]
    return out


@pytest.mark.parametrize("form", [_matrices_only, _rig_to_dict_form], ids=["matrices", "rig_to_dict"])
def test_the_bag_carries_the_rig_the_toolkit_reads(tmp_path: Path, form):
    """Transforms in any form the Rig reads are exported, and the bag gives back that very rig (to the float32 of the
    sample's lidar2cam, which a quaternion cannot hold exactly)."""
    folder = _sample_copy(tmp_path)
    calib = folder / "calibration.json"
    calib.write_text(json.dumps(form(json.loads(calib.read_text()))))
    out = tmp_path / "out" / "x.mcap"
    result = invoke("export", "--data", folder, "--out", out)
    assert result.exit_code == 0, result.output
    expected = load_bundled_sample(folder).rig
    rig, _ = rig_from_bag(out)
    assert rig.names == expected.names
    for ours, theirs in zip(rig.cameras, expected.cameras):
        assert np.array_equal(ours.K, theirs.K) and (ours.width, ours.height) == (theirs.width, theirs.height)
        assert np.abs(ours.lidar2cam - theirs.lidar2cam).max() < 1e-6
    assert np.abs(rig.lidar2ego - expected.lidar2ego).max() < 1e-6
    assert np.abs(rig.ego2global - expected.ego2global).max() < 1e-6


# ---- L5: images the runtime would refuse ------------------------------------------------------------------------


def _first_image(data: Path, camera: str = "CAM_FRONT") -> Path:
    return sorted((data / "samples" / camera).glob("*.jpg"))[0]


def test_a_truncated_jpeg_is_refused_at_export(tiny_synth_data: Path, tmp_path: Path):
    data = tmp_path / "data"
    shutil.copytree(tiny_synth_data, data)
    image = _first_image(data)
    image.write_bytes(image.read_bytes()[: image.stat().st_size // 2])
    out = tmp_path / "out" / "x.mcap"
    one_line_error(invoke("export", "--data", data, "--out", out), f"image {image}", "could not be decoded")
    assert_nothing_written(out)


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_an_image_of_another_size_than_its_camera_is_refused_at_export(tiny_synth_data: Path, tmp_path: Path, ext):
    data = tmp_path / "data"
    shutil.copytree(tiny_synth_data, data)
    image = _first_image(data, "CAM_BACK")
    ok, buf = cv2.imencode(ext, np.full((24, 24, 3), 128, np.uint8))
    image.write_bytes(buf.tobytes())
    out = tmp_path / "out" / "x.mcap"
    one_line_error(invoke("export", "--data", data, "--out", out), f"image {image} is 24x24 px",
                   "its camera CAM_BACK is calibrated for 160x90")  # fmt: skip
    assert_nothing_written(out)


def test_a_bundled_image_of_another_size_is_refused(tmp_path: Path):
    folder = _sample_copy(tmp_path)
    image = next(folder.glob("*CAM_BACK__*.jpg"))
    ok, buf = cv2.imencode(".jpg", np.zeros((90, 160, 3), np.uint8))
    image.write_bytes(buf.tobytes())
    out = tmp_path / "out" / "x.mcap"
    one_line_error(invoke("export", "--data", folder, "--out", out), f"image {image} is 160x90 px",
                   "calibrated for 1600x900")  # fmt: skip
    assert_nothing_written(out)


# ---- H2: calibration writes through no symlink at OUT.tmp ------------------------------------------------------


def test_calibration_does_not_write_through_out_tmp(bag: Path, tmp_path: Path):
    victim = tmp_path / "victim.json"
    victim.write_text('{"keep": true}')
    out = tmp_path / "cal.json"
    (tmp_path / "cal.json.tmp").symlink_to(victim)
    result = invoke("calibration", "--bag", bag, "--out", out)
    assert result.exit_code == 0, result.output
    assert victim.read_text() == '{"keep": true}'
    assert (tmp_path / "cal.json.tmp").is_symlink() and not out.is_symlink()
    assert Rig.from_calibration_json(out).names[0] == "CAM_FRONT"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.json", "cal.json.tmp", "victim.json"]  # no temporary left


def test_calibration_with_a_folder_at_out_tmp(bag: Path, tmp_path: Path):
    (tmp_path / "cal.json.tmp").mkdir()
    result = invoke("calibration", "--bag", bag, "--out", tmp_path / "cal.json")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "cal.json").is_file()


def test_write_calibration_json_failure_leaves_the_target(tmp_path: Path, monkeypatch):
    rig = load_bundled_sample().rig
    out = tmp_path / "cal.json"
    out.write_text("old")

    def full_disk(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("os.fsync", full_disk)  # the write fails after the bytes went to the temporary
    with pytest.raises(OSError, match="No space left"):
        write_calibration_json(rig, out)
    assert out.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["cal.json"]


# ---- M6: a camera --topics maps to a topic the bag lacks -----------------------------------------------------------


@pytest.mark.parametrize("extra", [[], ["--cameras", "CAM_FRONT,CAM_BACK"]], ids=["default cameras", "--cameras"])
def test_calibration_refuses_a_mapped_camera_whose_topic_is_missing(bag: Path, tmp_path: Path, extra):
    out = tmp_path / "c.json"
    result = invoke("calibration", "--bag", bag, "--out", out, "--topics", "CAM_FRONT=/nonexistent", *extra)
    one_line_error(result, "'/nonexistent'", "CAM_FRONT", "its topics:", "/CAM_FRONT/image_rect_compressed")
    assert not out.exists()


def test_calibration_refuses_an_unknown_camera_on_a_missing_topic(bag: Path, tmp_path: Path):
    result = invoke("calibration", "--bag", bag, "--out", tmp_path / "c.json", "--topics", "foo=/bar")
    one_line_error(result, "'/bar'", "foo", "its topics:")


def test_calibration_with_a_mapped_camera_that_is_there(bag: Path, tmp_path: Path):
    out = tmp_path / "c.json"
    result = invoke("calibration", "--bag", bag, "--out", out, "--topics", "CAM_BACK=/CAM_BACK/image_rect_compressed")
    assert result.exit_code == 0, result.output
    assert len(Rig.from_calibration_json(out)) == 6


def test_run_refuses_a_mapped_camera_whose_topic_is_missing(bag: Path, tiny_export: Path, tmp_path: Path):
    out = tmp_path / "out" / "det.mcap"
    result = invoke("run", "--bag", bag, "--export-dir", tiny_export, "--out", out, "--topics", "CAM_FRONT=/nonexistent")
    one_line_error(result, "'/nonexistent'", "CAM_FRONT", "its topics:")
    assert_nothing_written(out)


# ---- M7: run on its own output ------------------------------------------------------------------------------------


def test_run_on_its_own_output_replaces_the_detections(bag: Path, tiny_export: Path, tmp_path: Path, caplog):
    first = run_bag(bag, tiny_export, tmp_path / "first.mcap", config=RunConfig())
    assert first.input_dropped == {}
    with caplog.at_level(logging.WARNING, logger="streamdet.bag.run"):
        second = run_bag(tmp_path / "first.mcap", tiny_export, tmp_path / "second.mcap", config=RunConfig())
    once, twice = topic_counts(tmp_path / "first.mcap"), topic_counts(tmp_path / "second.mcap")
    assert once["/streamdet/detections"] == once["/streamdet/markers"] == first.num_slices == 16
    assert twice == once  # the input's topics copied, its detections replaced by this run's: not 32 of them
    assert second.input_dropped == {topic: 16 for topic in OUTPUT_TOPICS}
    said = [r.getMessage() for r in caplog.records if "already holds" in r.getMessage()]
    assert len(said) == 1 and "/streamdet/detections, /streamdet/markers" in said[0] and "not copied" in said[0]


def test_the_cli_says_what_it_did_not_copy(bag: Path, tiny_export: Path, tmp_path: Path):
    assert invoke("run", "--bag", bag, "--export-dir", tiny_export, "--out", tmp_path / "first.mcap").exit_code == 0
    result = invoke("run", "--bag", tmp_path / "first.mcap", "--export-dir", tiny_export, "--out", tmp_path / "second.mcap")
    assert result.exit_code == 0, result.output
    assert "not copied from the input (this run writes these topics): 16 messages on /streamdet/detections" in result.output


def test_run_refuses_a_topics_key_that_is_no_camera_of_the_export(bag: Path, tiny_export: Path, tmp_path: Path):
    """`--topics foo=/elsewhere/image` mapped nothing and ran silently."""
    out = tmp_path / "out" / "det.mcap"
    for key in ("foo", "foo.info", "CAM_FRONTT"):
        result = invoke("run", "--bag", bag, "--export-dir", tiny_export, "--out", out, "--topics", f"{key}=/elsewhere/image")
        one_line_error(result, "--topics names", "no camera of the export")
        assert_nothing_written(out)
