"""`streamdet-bag` outputs never replace or land inside its inputs (the bag, a rosbag2 folder, the exports, the
dataset), a failed bag write leaves the old file as it was, `--slice-per-message` refuses full sweeps, `--cameras`
and `--topics` refuse empty and repeated entries, and a LiDAR topic of another message type is named as such.

Every refusal comes before any work, so the `run` cases need no real export: a folder holding a manifest.json
is enough to reach the checks (a check that did not fire would fail loading it, and the test with it)."""

from __future__ import annotations

import re

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("mcap_ros2.writer")

from streamdet.bag import topics as T  # noqa: E402
from streamdet.bag.cli import main as bag_main  # noqa: E402
from streamdet.bag.source import BagSource, SourceConfig, min_slice_share, slice_arc_share  # noqa: E402
from streamdet.bag.topics import TopicMap  # noqa: E402
from streamdet.bag.writer import BagWriter  # noqa: E402
from streamdet.core.sectors import slice_index_of  # noqa: E402
from streamdet.runtime_ort.ros.images import compressed_image_message  # noqa: E402
from streamdet.runtime_ort.ros.pointcloud2 import pointcloud2_message  # noqa: E402

STAMP_NS = 1_700_000_000_000_000_000
SWEEP_NS = 50_000_000
NO_TF = {"global_frame": None, "ego_frame": "LIDAR_TOP"}  # the cloud's frame is the ego frame: no TF needed
CAMERA_TOPIC = "/CAM_FRONT/image_rect_compressed"


def sweep_points(n: int = 4000, seed: int = 0) -> np.ndarray:
    """(N, 5) points all around the car: a full sweep."""
    rng = np.random.default_rng(seed)
    points = np.zeros((n, 5), np.float32)
    points[:, :3] = rng.uniform(-40, 40, (n, 3))
    points[:, 3] = rng.integers(0, 256, n)
    return points


def write_bag(path: Path, clouds: list[np.ndarray], camera: bool = False) -> Path:
    """One PointCloud2 on /LIDAR_TOP per entry of ``clouds`` (50 ms apart), and a CompressedImage on CAM_FRONT's topic."""
    with BagWriter(path) as writer:
        for i, points in enumerate(clouds):
            stamp = STAMP_NS + i * SWEEP_NS
            writer.write(T.LIDAR_TOPIC, T.POINTCLOUD2, pointcloud2_message(points, stamp, "LIDAR_TOP"), stamp)
        if camera:
            writer.write(CAMERA_TOPIC, T.COMPRESSED_IMAGE, compressed_image_message(b"\xff\xd8\xff", STAMP_NS, "CAM_FRONT"), STAMP_NS)
    return path


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def one_line_error(result, *needles: str) -> str:
    """The command failed before any work with one `Error:` line holding every needle; no traceback."""
    assert result.exit_code != 0, result.output
    assert "Traceback" not in result.output and not isinstance(result.exception, (AssertionError, TypeError)), result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, result.output
    for needle in needles:
        assert needle in errors[0], result.output
    return errors[0]


def invoke(*args) -> object:
    return CliRunner().invoke(bag_main, [str(a) for a in args])


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    return write_bag(tmp_path / "drive.mcap", [sweep_points(seed=i) for i in range(2)], camera=True)


@pytest.fixture
def export_dir(tmp_path: Path) -> Path:
    """Looks like an export to the CLI's first check; loading it would fail."""
    folder = tmp_path / "exp"
    folder.mkdir()
    (folder / "manifest.json").write_text("{}")
    (folder / "lut.npz").write_bytes(b"not a lut")
    return folder


# ---- A3: run --out / --results ---------------------------------------------------------------------------------


def run_args(bag: Path, export_dir: Path, *extra) -> list:
    return ["run", "--bag", bag, "--export-dir", export_dir, *extra]


def test_run_results_is_not_the_input_bag(bag: Path, export_dir: Path, tmp_path: Path):
    before = digest(bag)
    result = invoke(*run_args(bag, export_dir, "--out", tmp_path / "det.mcap", "--results", bag))
    one_line_error(result, "--results", str(bag), "is the input --bag")
    assert digest(bag) == before and not (tmp_path / "det.mcap").exists()


def test_run_results_is_not_the_output_bag(bag: Path, export_dir: Path, tmp_path: Path):
    out = tmp_path / "det.mcap"
    one_line_error(invoke(*run_args(bag, export_dir, "--out", out, "--results", out)), "--results", str(out), "--out")
    # the default results path is named after --out: two runs into one folder keep both (one name overwrote the
    # other), and it is never --out itself
    from streamdet.bag.run import results_path_of

    assert results_path_of(tmp_path / "a.mcap", None) == tmp_path / "a.results_nusc.json"
    assert results_path_of(tmp_path / "b.mcap", None) == tmp_path / "b.results_nusc.json"
    for name in ("results_nusc.json", "a.results_nusc.json", "a"):
        assert results_path_of(tmp_path / name, None) != tmp_path / name


def test_run_outputs_stay_out_of_the_export(bag: Path, export_dir: Path, tmp_path: Path):
    before = {p.name: digest(p) for p in export_dir.iterdir()}
    one_line_error(invoke(*run_args(bag, export_dir, "--out", export_dir / "lut.npz")), "--out", "--export-dir", str(export_dir))
    one_line_error(invoke(*run_args(bag, export_dir, "--out", tmp_path / "d.mcap", "--results", export_dir / "manifest.json")),
                   "--results", "--export-dir")  # fmt: skip
    fallback = tmp_path / "lidar_exp"
    fallback.mkdir()
    one_line_error(invoke(*run_args(bag, export_dir, "--fallback-export", fallback, "--out", fallback / "d.mcap")),
                   "--out", "--fallback-export", str(fallback))  # fmt: skip
    assert {p.name: digest(p) for p in export_dir.iterdir()} == before
    assert not any(fallback.iterdir())


def test_run_output_stays_out_of_a_rosbag2_folder(bag: Path, export_dir: Path, tmp_path: Path):
    folder = tmp_path / "rosbag2_drive"
    folder.mkdir()
    shutil.copy(bag, folder / "drive_0.mcap")
    (folder / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    one_line_error(invoke(*run_args(folder, export_dir, "--out", folder / "det.mcap")), "--out", "lies inside the input --bag")
    # the .mcap named itself: its folder is still the recording (a second .mcap there makes it unreadable as one bag)
    one_line_error(invoke(*run_args(folder / "drive_0.mcap", export_dir, "--out", folder / "det.mcap")),
                   "--out", "rosbag2 folder", str(folder))  # fmt: skip
    assert sorted(p.name for p in folder.iterdir()) == ["drive_0.mcap", "metadata.yaml"]


def test_run_output_folder_that_cannot_be_made_is_refused_first(bag: Path, export_dir: Path, tmp_path: Path):
    (tmp_path / "afile").write_text("x")
    one_line_error(invoke(*run_args(bag, export_dir, "--out", tmp_path / "afile" / "d.mcap")), "--out", "is not a folder")
    one_line_error(invoke(*run_args(bag, export_dir, "--out", tmp_path / "d.mcap", "--results", tmp_path)), "--results")


def test_run_bag_refuses_results_over_its_bags(bag: Path, export_dir: Path, tmp_path: Path):
    from streamdet.bag.run import run_bag

    out = tmp_path / "det.mcap"
    with pytest.raises(ValueError, match="is the output bag"):
        run_bag(bag, export_dir, out, out)


# ---- A4: calibration --out -------------------------------------------------------------------------------------


def test_calibration_out_is_not_the_bag(bag: Path):
    before = digest(bag)
    one_line_error(invoke("calibration", "--bag", bag, "--out", bag), "--out", str(bag), "is the input --bag")
    assert digest(bag) == before


def test_calibration_out_stays_out_of_a_rosbag2_folder(bag: Path, tmp_path: Path):
    folder = tmp_path / "rosbag2_drive"
    folder.mkdir()
    shutil.copy(bag, folder / "drive_0.mcap")
    (folder / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    one_line_error(invoke("calibration", "--bag", folder, "--out", folder / "c.json"), "--out", "lies inside the input --bag")
    one_line_error(invoke("calibration", "--bag", folder / "drive_0.mcap", "--out", folder / "c.json"), "--out", "rosbag2 folder")
    assert sorted(p.name for p in folder.iterdir()) == ["drive_0.mcap", "metadata.yaml"]


# ---- A5: export --out, and the bag written through a temporary -------------------------------------------------


def test_export_out_is_not_a_file_of_the_dataset(tiny_synth_data: Path, tmp_path: Path):
    """The audit's case: --out one of the scene's own LiDAR files, which the export reads (and truncated)."""
    data = tmp_path / "data"
    shutil.copytree(tiny_synth_data, data)
    victim = sorted((data / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))[0]
    before = digest(victim)
    one_line_error(invoke("export", "--data", data, "--out", victim), "--out", str(victim), "--data", str(data))
    one_line_error(invoke("export", "--data", data, "--out", data / "drive.mcap"), "--out", "lies inside the input --data")
    assert digest(victim) == before and not (data / "drive.mcap").exists()


def test_export_out_is_not_inside_the_bundled_sample(tmp_path: Path, monkeypatch):
    """Without --data the input is the bundled sample (stood in for by a copy: a failing check must not write into
    the package)."""
    from streamdet.data.sample import bundled_sample_dir

    stand_in = tmp_path / "sample"
    shutil.copytree(bundled_sample_dir(), stand_in)
    files = sorted(p.name for p in stand_in.iterdir())
    monkeypatch.setattr("streamdet.data.sample.bundled_sample_dir", lambda: stand_in)
    one_line_error(invoke("export", "--out", stand_in / "real.mcap"), "--out", "--data (default: the bundled sample)")
    assert sorted(p.name for p in stand_in.iterdir()) == files


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path: Path):
    out = tmp_path / "drive.mcap"
    out.write_bytes(b"the previous bag")
    with pytest.raises(RuntimeError, match="mid-write"):
        with BagWriter(out) as writer:
            writer.write(T.LIDAR_TOPIC, T.POINTCLOUD2, pointcloud2_message(sweep_points(), STAMP_NS, "LIDAR_TOP"), STAMP_NS)
            raise RuntimeError("mid-write")
    assert out.read_bytes() == b"the previous bag"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drive.mcap"]
    write_bag(out, [sweep_points()])  # a complete write replaces it
    assert sum(1 for _ in BagSource(out, SourceConfig(**NO_TF)).sweeps()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drive.mcap"]


def test_a_corrupt_lidar_file_mid_export_leaves_no_partial_mcap(tiny_synth_data: Path, tmp_path: Path):
    data = tmp_path / "data"
    shutil.copytree(tiny_synth_data, data)
    sweeps = sorted((data / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))
    sweeps[-1].write_bytes(sweeps[-1].read_bytes()[:1000])  # the last sweep: read after the others were written
    out = tmp_path / "drive.mcap"
    result = invoke("export", "--data", data, "--out", out)
    assert result.exit_code != 0 and "Traceback" not in result.output
    assert not out.exists() and list(tmp_path.glob(".*partial")) == []
    out.write_bytes(b"the previous bag")
    # --overwrite: the existing bag is refused without it (CLI review 40, M2); with it the failed write must keep it
    assert invoke("export", "--data", data, "--out", out, "--overwrite").exit_code == 1
    assert out.read_bytes() == b"the previous bag" and list(tmp_path.glob(".*partial")) == []


# ---- C2: --slice-per-message on full sweeps --------------------------------------------------------------------


def test_slice_per_message_on_full_sweeps_is_refused(bag: Path):
    source = BagSource(bag, SourceConfig(slice_per_message=True, num_slices=8, **NO_TF))
    with pytest.raises(ValueError, match="is not one slice.*drop --slice-per-message") as info:
        list(source.sweeps())
    assert "\n" not in str(info.value) and str(bag) in str(info.value)


@pytest.mark.parametrize("num_slices", [2, 4, 8, 32])
@pytest.mark.parametrize("phase", [0.0, 0.5])  # the driver's slices cut at streamdet's sector borders, or half a sector off
def test_slice_per_message_accepts_a_driver_publishing_slices(tmp_path: Path, num_slices: int, phase: float):
    points = sweep_points(8000)
    shift = np.radians(phase * 360.0 / num_slices)
    x, y = points[:, 0], points[:, 1]
    k_of = slice_index_of(x * np.cos(shift) + y * np.sin(shift), y * np.cos(shift) - x * np.sin(shift), num_slices)
    sliced = write_bag(tmp_path / "sliced.mcap", [points[k_of == k] for k in range(num_slices)])
    source = BagSource(sliced, SourceConfig(slice_per_message=True, num_slices=num_slices, **NO_TF))
    assert sum(1 for _ in source.sweeps()) == num_slices


@pytest.mark.parametrize("num_slices", [2, 4, 8, 32])
def test_a_full_sweep_is_never_one_slice(num_slices: int):
    assert slice_arc_share(sweep_points(8000), num_slices) < min_slice_share(num_slices)


def test_one_slice_per_sweep_takes_any_message():
    assert slice_arc_share(sweep_points(), 1) == 1.0 and slice_arc_share(np.zeros((0, 5), np.float32), 8) == 1.0


def test_the_flag_says_what_it_refuses():
    option = next(p for p in bag_main.commands["run"].params if p.name == "slice_per_message")
    assert "full sweep" in option.help and "refused" in option.help


# ---- C3: --cameras and --topics entries ------------------------------------------------------------------------


@pytest.mark.parametrize("cameras, needle", [(",,,", "no camera given in ',,,'"), ("CAM_FRONT,,CAM_BACK", "entry 2"),
                                             ("CAM_FRONT,CAM_FRONT", "'CAM_FRONT' is given twice"), ("", "no camera")])  # fmt: skip
def test_calibration_cameras_refuses_empty_and_repeated_entries(bag: Path, tmp_path: Path, cameras: str, needle: str):
    result = invoke("calibration", "--bag", bag, "--out", tmp_path / "c.json", "--cameras", cameras)
    one_line_error(result, "--cameras", needle)
    assert not (tmp_path / "c.json").exists()


@pytest.mark.parametrize("command", ["calibration", "run"])
def test_topics_refuses_a_repeated_key(bag: Path, export_dir: Path, tmp_path: Path, command: str):
    args = ["--bag", bag, "--out", tmp_path / "x.out", "--topics", "lidar=/a,lidar=/b"]
    result = invoke(command, *args, *(["--export-dir", export_dir] if command == "run" else []))
    one_line_error(result, "--topics", "'lidar' twice", "'lidar=/a'", "'lidar=/b'")


@pytest.mark.parametrize("text, needle", [("lidar=/a,,tf=/b", "entry 2"), ("lidar=/a,", "entry 2"), ("", "entry 1"),
                                          ("CAM_FRONT.info=/i,CAM_FRONT.info=/j", "'CAM_FRONT.info' twice")])  # fmt: skip
def test_topic_map_refuses_empty_entries_and_repeated_keys(text: str, needle: str):
    with pytest.raises(ValueError, match=needle):
        TopicMap.parse(text)


@pytest.mark.parametrize("text, needle", [
    ("lidar=/x,CAM_FRONT=/x", "lidar and CAM_FRONT both read '/x'"),
    ("CAM_FRONT=/cam,CAM_BACK=/cam", "CAM_FRONT and CAM_BACK both read '/cam'"),
    ("CAM_BACK=/CAM_FRONT/image_rect_compressed,CAM_FRONT.info=/f", "CAM_BACK and CAM_FRONT both read"),
    ("CAM_FRONT=/front/image,CAM_FRONT_LEFT=/front/left", "CAM_FRONT.info and CAM_FRONT_LEFT.info both read '/front/camera_info'"),
    ("tf=/tf_static", "tf and tf_static both read '/tf_static'"),
])  # fmt: skip
def test_topic_map_refuses_two_roles_on_one_topic(text: str, needle: str):
    """Two keys on one topic (or a key on another's default topic): the topic's messages would feed both."""
    with pytest.raises(ValueError, match=re.escape(needle)):
        TopicMap.parse(text).check_distinct(("CAM_FRONT", "CAM_BACK"))


def test_a_source_refuses_a_camera_on_the_lidar_topic():
    with pytest.raises(ValueError, match="lidar and CAM_FRONT both read '/LIDAR_TOP'"):
        SourceConfig(topics=TopicMap(cameras={"CAM_FRONT": "/LIDAR_TOP"}), camera_names=("CAM_FRONT",))


@pytest.mark.parametrize("command", ["calibration", "run"])
def test_topics_refuses_two_keys_on_one_topic(bag: Path, export_dir: Path, tmp_path: Path, command: str):
    args = ["--bag", bag, "--out", tmp_path / "x.out", "--topics", "CAM_FRONT=/c,CAM_BACK=/c"]
    result = invoke(command, *args, *(["--export-dir", export_dir] if command == "run" else []))
    one_line_error(result, "CAM_FRONT and CAM_BACK both read '/c'")


def test_topic_map_keeps_distinct_keys():
    topics = TopicMap.parse("lidar=/p,CAM_FRONT=/f,CAM_FRONT.info=/fi,tf=/t")
    assert (topics.lidar, topics.image_topic("CAM_FRONT"), topics.camera_info_topic("CAM_FRONT"), topics.tf) == ("/p", "/f", "/fi", "/t")
    assert TopicMap.parse(None) == TopicMap()


# ---- D9: a LiDAR topic of another message type -----------------------------------------------------------------


def test_a_lidar_topic_of_another_type_is_named(bag: Path):
    source = BagSource(bag, SourceConfig(topics=TopicMap(lidar=CAMERA_TOPIC), **NO_TF))
    with pytest.raises(ValueError, match=r"carries sensor_msgs/msg/CompressedImage messages, not sensor_msgs/msg/PointCloud2") as info:
        list(source.sweeps())
    assert "'/LIDAR_TOP'" in str(info.value)  # where the clouds are


def test_a_lidar_topic_of_another_type_through_the_cli(bag: Path, tmp_path: Path):
    result = invoke("calibration", "--bag", bag, "--out", tmp_path / "c.json", "--cameras", "CAM_FRONT",
                    "--topics", f"lidar={CAMERA_TOPIC},CAM_FRONT=/CAM_FRONT/other")  # fmt: skip
    one_line_error(result, f"the LiDAR topic '{CAMERA_TOPIC}' carries sensor_msgs/msg/CompressedImage")


def test_a_missing_lidar_topic_still_says_so(bag: Path):
    source = BagSource(bag, SourceConfig(topics=TopicMap(lidar="/points"), **NO_TF))
    with pytest.raises(ValueError, match="has no message on the LiDAR topic '/points'"):
        list(source.sweeps())
