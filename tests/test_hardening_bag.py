"""Hostile bags and clouds: a truncated or corrupted .mcap is one ValueError naming the bag (and one CLI line), not a
traceback from mcap / struct / zstandard; absurd per-point times are dropped and counted instead of becoming an
unencodable stamp; absurd intensities pass through the ROS side without an error or a warning."""

from __future__ import annotations

import json
import logging
import random
import re
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("mcap_ros2.writer")

from streamdet.bag.cli import main as bag_main  # noqa: E402
from streamdet.bag.source import BagReadError, BagSource, SourceConfig  # noqa: E402
from streamdet.bag.writer import BagWriter  # noqa: E402
from streamdet.runtime_ort.ros.detections import detection3d_array_message  # noqa: E402
from streamdet.runtime_ort.ros.header import INT32_MAX, NS_PER_S, duration_msg, header_msg, time_msg  # noqa: E402
from streamdet.runtime_ort.ros.pointcloud2 import (  # noqa: E402
    MAX_POINT_TIME_OFFSET_S,
    CloudFields,
    decode_pointcloud2,
    pointcloud2_message,
    slice_from_message,
    split_cloud,
)

STAMP_NS = 1_700_000_000_123_456_789
LIDAR = "/LIDAR_TOP"
CORRUPT = "not a readable MCAP bag (truncated or corrupted)"
# a config that needs no TF: the ego frame is the cloud's own frame, no global frame
NO_TF = SourceConfig(global_frame=None, ego_frame="LIDAR_TOP")


def as_msg(value):
    """A message dict as an object with ROS field attributes (what the readers give)."""
    if isinstance(value, dict):
        return SimpleNamespace(**{k: as_msg(v) for k, v in value.items()})
    if isinstance(value, list):
        return [as_msg(v) for v in value]
    return value


def sweep(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 5) points around the car and per-point times over one 50 ms sweep before the stamp."""
    rng = np.random.default_rng(seed)
    points = np.zeros((n, 5), np.float32)
    points[:, :3] = rng.uniform(-40, 40, (n, 3))
    points[:, 3] = rng.integers(0, 256, n)
    return points, np.linspace(-0.05, 0.0, n).astype(np.float32)


def write_bag(path: Path, clouds: int = 3, n: int = 2000, time_s: np.ndarray | None = None, metadata: dict | None = None) -> Path:
    with BagWriter(path) as writer:
        for i in range(clouds):
            points, times = sweep(n, i)
            stamp = STAMP_NS + i * 50_000_000
            msg = pointcloud2_message(points, stamp, "LIDAR_TOP", times if time_s is None else time_s)
            writer.write(LIDAR, "sensor_msgs/msg/PointCloud2", msg, stamp)
        writer.metadata("streamdet", metadata if metadata is not None else {"scene": "s", "sample_tokens": "{}"})
    return path


def read_all(path: Path) -> int:
    """Everything `streamdet-bag run` reads: metadata, topics, every message and sweep."""
    source = BagSource(path, NO_TF)
    source.metadata()
    source.topics()
    return sum(1 for _, event in source.events() if event is not None)


@pytest.fixture(scope="module")
def good_bag(tmp_path_factory) -> Path:
    return write_bag(tmp_path_factory.mktemp("bag") / "good.mcap")


def test_the_intact_bag_reads(good_bag: Path):
    assert read_all(good_bag) == 3
    assert BagSource(good_bag, NO_TF).topics() == {LIDAR: "sensor_msgs/msg/PointCloud2"}


@pytest.mark.parametrize("cut", [0, 4, 8, 20, 100, 1000, 0.5, -30, -8, -1])
def test_a_truncated_bag_is_one_error_naming_it(good_bag: Path, tmp_path: Path, cut: float):
    data = good_bag.read_bytes()
    keep = int(len(data) * cut) if isinstance(cut, float) else (cut if cut >= 0 else len(data) + cut)
    bad = tmp_path / f"cut{keep}.mcap"
    bad.write_bytes(data[:keep])
    with pytest.raises(BagReadError, match="truncated or corrupted") as info:
        read_all(bad)
    assert str(info.value).startswith(f"{bad}: {CORRUPT}: ")
    assert "\n" not in str(info.value)


def test_flipped_bytes_in_a_chunk_fail_its_crc(good_bag: Path, tmp_path: Path):
    data = bytearray(good_bag.read_bytes())
    data[len(data) // 2] ^= 0xFF  # inside the (zstd) chunk of the clouds
    bad = tmp_path / "flip.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(BagReadError, match=r"(CRCValidationError|ZstdError)"):
        read_all(bad)


@pytest.mark.parametrize("seed", range(6))
def test_random_byte_flips_read_or_fail_cleanly(good_bag: Path, tmp_path: Path, seed: int):
    """Anywhere in the file (header, schemas, chunk, summary, footer): it reads, or a ValueError says why."""
    rng = random.Random(seed)
    data = bytearray(good_bag.read_bytes())
    region = [(0, 600), (len(data) - 1500, len(data)), (0, len(data))][seed % 3]
    for _ in range(rng.choice([1, 4, 16])):
        data[rng.randrange(*region)] = rng.randrange(256)
    bad = tmp_path / "flips.mcap"
    bad.write_bytes(bytes(data))
    try:
        read_all(bad)
    except ValueError as e:  # BagReadError, or the source's own refusal of what decoded (no LiDAR message, ...)
        assert str(bad) in str(e)


@pytest.mark.parametrize("old, new, kind", [
    (b"uint32 height", b"uint32 he!ght", "NameError"),  # how the vendored rosidl parser refuses a name...
    (b"uint8 INT8", b"Point INT8", "TypeError"),  # ...a constant's type...
    (b"bool is_dense", b"bo=l is_dense", "InvalidResourceName"),  # ...and a type name
])  # fmt: skip
def test_a_corrupted_schema_is_one_error_naming_the_bag(good_bag: Path, tmp_path: Path, old: bytes, new: bytes, kind: str):
    data = good_bag.read_bytes()
    assert data.count(old) == 1  # the summary's copy of the PointCloud2 schema, which the reader uses
    bad = tmp_path / "schema.mcap"
    bad.write_bytes(data.replace(old, new))
    with pytest.raises(BagReadError, match=rf"schema\.mcap: {re.escape(CORRUPT)} \(message on /LIDAR_TOP at log time \d+ ns\): {kind}: "):
        read_all(bad)


def test_a_programming_error_in_decoding_is_not_swallowed(good_bag: Path, monkeypatch):
    import mcap_ros2.decoder

    def decoder_raising(error: Exception):
        monkeypatch.setattr(mcap_ros2.decoder.DecoderFactory, "decoder_for", lambda self, enc, schema: lambda data: _raise(error))

    decoder_raising(TypeError("a bug"))
    with pytest.raises(TypeError, match="a bug"):
        list(BagSource(good_bag, NO_TF).messages())
    decoder_raising(RuntimeError("not lz4"))
    with pytest.raises(RuntimeError, match="not lz4"):
        list(BagSource(good_bag, NO_TF).messages())
    # lz4.frame's own failures are bare RuntimeErrors naming the LZ4F_ call: those are corruption
    decoder_raising(RuntimeError("LZ4F_decompress failed with code: ERROR_corruptionDetected"))
    with pytest.raises(BagReadError, match=rf"{re.escape(CORRUPT)} \(message on /LIDAR_TOP at log time \d+ ns\): RuntimeError: LZ4F_"):
        list(BagSource(good_bag, NO_TF).messages())


def test_a_consumer_error_is_not_reported_as_corruption(good_bag: Path):
    """Only the libraries' work is guarded: an error raised by the code iterating the messages stays what it is."""
    messages = BagSource(good_bag, NO_TF).messages()
    next(messages)
    with pytest.raises(KeyError):
        messages.throw(KeyError("the consumer's"))


def _raise(error: Exception):
    raise error


@pytest.mark.parametrize("tokens", ["{not json", "[1, 2]", '{"1": 2}', "1" * 5000])
def test_malformed_sample_token_metadata_is_refused_naming_the_bag(tmp_path: Path, tokens: str):
    bag = write_bag(tmp_path / "meta.mcap", clouds=1, n=10, metadata={"sample_tokens": tokens})
    with pytest.raises(BagReadError, match=r"meta\.mcap: metadata streamdet\.sample_tokens"):
        read_all(bag)


def test_a_malformed_cloud_is_named_by_bag_topic_and_stamp(tmp_path: Path):
    path = tmp_path / "nointensity.mcap"
    msg = pointcloud2_message(*sweep(10)[:1], STAMP_NS, "LIDAR_TOP")
    msg["fields"] = [f for f in msg["fields"] if f["name"] != "intensity"]
    with BagWriter(path) as writer:
        writer.write(LIDAR, "sensor_msgs/msg/PointCloud2", msg, STAMP_NS)
    with pytest.raises(ValueError, match=rf"nointensity\.mcap: /LIDAR_TOP message at stamp {STAMP_NS} ns: PointCloud2 has no 'intensity'"):
        read_all(path)


def test_cli_calibration_on_a_truncated_bag_is_one_line(good_bag: Path, tmp_path: Path):
    for keep in (0, 20, 100):
        bad = tmp_path / f"t{keep}.mcap"
        bad.write_bytes(good_bag.read_bytes()[:keep])
        result = CliRunner().invoke(bag_main, ["calibration", "--bag", str(bad), "--out", str(tmp_path / "c.json")])
        assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.output
        assert result.output.strip().splitlines() == [result.output.strip()]
        assert f"{bad}: {CORRUPT}" in result.output


def test_run_edge_on_a_truncated_bag_is_one_line(good_bag: Path, tmp_path: Path, capsys):
    """Through the console script's edge: exit 1, one line on stderr naming the bag, no traceback."""
    from streamdet.cli_utils import run_edge

    bad = tmp_path / "t20.mcap"
    bad.write_bytes(good_bag.read_bytes()[:20])
    code = run_edge("streamdet.bag.cli", "streamdet-bag", args=["calibration", "--bag", str(bad), "--out", str(tmp_path / "c.json")])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and str(bad) in err and "Invalid argument" in err


# ---- per-point times ---------------------------------------------------------------------------------------------


def test_absurd_point_times_are_dropped_and_counted():
    points, times = sweep(1000)
    times[[0, 5, 7, 9]] = [1e20, np.nan, -(MAX_POINT_TIME_OFFSET_S + 2), np.inf]
    points[11, 0] = np.nan  # a non-finite coordinate is counted apart, also when its time is absurd
    times[11] = 1e20
    cloud = decode_pointcloud2(as_msg(pointcloud2_message(points, STAMP_NS, "L", times)))
    assert cloud.num_dropped == 1 and cloud.num_time_dropped == 4 and len(cloud.points) == 995
    assert cloud.dropped_time_s == pytest.approx(1e20, rel=1e-6)
    # the other points keep their times: one corrupt value does not make the column read as a nanosecond clock
    keep = np.ones(1000, bool)
    keep[[0, 5, 7, 9, 11]] = False
    np.testing.assert_array_equal(cloud.time_s, times[keep].astype(np.float64))
    for s in split_cloud(cloud, 8) + [slice_from_message(cloud, 8)]:
        assert abs(s.scan_time_ns - STAMP_NS) <= 0.05 * NS_PER_S
        header_msg(s.scan_time_ns, "L")  # encodable


def test_times_at_the_window_edge_are_kept():
    points, _ = sweep(4)
    times = np.array([-MAX_POINT_TIME_OFFSET_S, MAX_POINT_TIME_OFFSET_S, 0.0, -0.01])
    cloud = decode_pointcloud2(as_msg(pointcloud2_message(points, STAMP_NS, "L", times)))
    assert cloud.num_time_dropped == 0 and cloud.dropped_time_s is None
    narrow = decode_pointcloud2(as_msg(pointcloud2_message(points, STAMP_NS, "L", times)), CloudFields(max_time_offset_s=0.5))
    assert narrow.num_time_dropped == 2 and len(narrow.points) == 2


def test_an_absolute_clock_with_one_corrupt_time_keeps_the_others():
    points, offsets = sweep(200)
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "timestamp"], "formats": ["<f4"] * 4 + ["<f8"]})
    rec = np.zeros(200, dt)
    for j, name in enumerate(["x", "y", "z", "intensity"]):
        rec[name] = points[:, j]
    offsets = offsets.astype(np.float64)
    rec["timestamp"] = STAMP_NS / 1e9 + offsets  # Hesai: absolute seconds
    rec["timestamp"][3] = 0.0  # a corrupt (zeroed) time
    msg = pointcloud2_message(points, STAMP_NS, "L")
    msg.update(data=rec.tobytes(), point_step=dt.itemsize, row_step=dt.itemsize * 200,
               fields=[{"name": n, "offset": dt.fields[n][1], "datatype": 8 if n == "timestamp" else 7, "count": 1} for n in dt.names])  # fmt: skip
    cloud = decode_pointcloud2(as_msg(msg))
    assert cloud.num_time_dropped == 1 and cloud.dropped_time_s == pytest.approx(-STAMP_NS / 1e9)
    np.testing.assert_allclose(cloud.time_s, np.delete(offsets, 3), atol=1e-6)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_max_time_offset_must_be_positive(bad: float):
    with pytest.raises(ValueError, match="max_time_offset_s must be a positive number"):
        CloudFields(max_time_offset_s=bad)


def test_a_bag_with_an_absurd_point_time_reads_and_warns_once(tmp_path: Path, caplog):
    _, times = sweep(2000)
    times[0] = 1e20
    bag = write_bag(tmp_path / "time.mcap", time_s=times)
    source = BagSource(bag, NO_TF)
    with caplog.at_level(logging.WARNING, logger="streamdet.bag.source"):
        events = list(source.sweeps())
    assert len(events) == 3 and source.num_time_dropped == 3
    warned = [r.getMessage() for r in caplog.records if "per-point time" in r.getMessage()]
    assert len(warned) == 1 and "dropped 1 of 2000 points" in warned[0] and "1e+20 s" in warned[0]
    for event in events:
        assert all(abs(s.scan_time_ns - event.cloud.stamp_ns) <= 0.05 * NS_PER_S for s in event.slices)


def test_a_stamp_beyond_int32_seconds_is_a_value_error_not_struct_error():
    assert time_msg(INT32_MAX * NS_PER_S + NS_PER_S - 1) == {"sec": INT32_MAX, "nanosec": NS_PER_S - 1}
    assert time_msg(-(2**31) * NS_PER_S) == {"sec": -(2**31), "nanosec": 0}
    for ns in (int(1e29), (INT32_MAX + 1) * NS_PER_S, -(2**31) * NS_PER_S - 1):
        with pytest.raises(ValueError, match=rf"time {ns} ns does not fit a ROS 2 stamp"):
            time_msg(ns)
    with pytest.raises(ValueError, match="does not fit a ROS 2 stamp"):
        detection3d_array_message(np.zeros((0, 9), np.float32), np.zeros(0), np.zeros(0, int), int(1e29), "L")
    for seconds in (1e20, float("inf")):
        with pytest.raises(ValueError, match="Duration holds at most 2147483647 s"):
            duration_msg(seconds)
    assert duration_msg(1.5) == {"sec": 1, "nanosec": 500_000_000}


def test_a_huge_stamp_never_reaches_the_writer_as_struct_error(tmp_path: Path):
    with BagWriter(tmp_path / "x.mcap") as writer, pytest.raises(ValueError, match="does not fit a ROS 2 stamp"):
        writer.write("/d", "vision_msgs/msg/Detection3DArray",
                     detection3d_array_message(np.zeros((0, 9), np.float32), np.zeros(0), np.zeros(0, int), 10**29, "L"), 1)  # fmt: skip


# ---- intensities -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [1.0, 255.0])
def test_absurd_intensities_pass_the_ros_side_without_error_or_warning(scale: float):
    """Range checks on reflectance are pillarize's (it drops and counts them); here nothing may fail or warn."""
    points, times = sweep(8)
    intensity = np.array([1e30, -1e30, -5.0, 3e38, 0.0, 255.0, 1e-30, -0.0], np.float32)
    points[:, 3] = intensity
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cloud = decode_pointcloud2(as_msg(pointcloud2_message(points, STAMP_NS, "L", times)), CloudFields(intensity_scale=scale))
        slices = split_cloud(cloud, 4)
        one = slice_from_message(cloud, 4)
    with np.errstate(over="ignore"):
        expected = intensity * np.float32(scale)
    np.testing.assert_array_equal(cloud.points[:, 3], expected)
    assert sum(len(s.points) for s in slices) == 8 and len(one.points) == 8
    np.testing.assert_array_equal(np.sort(one.points[:, 3]), np.sort(expected / np.float32(255)))


def test_float64_values_beyond_float32_become_inf_quietly():
    """A float64 coordinate beyond float32 is inf, so dropped as non-finite; an intensity is inf, left to pillarize."""
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "time"], "formats": ["<f8"] * 5})
    rec = np.zeros(3, dt)
    rec["x"] = [1.0, 1e300, 2.0]
    rec["y"] = 1.0
    rec["intensity"] = [1e300, 5.0, -1e300]
    msg = {"header": header_msg(STAMP_NS, "L"), "height": 1, "width": 3, "is_bigendian": False, "point_step": 40,
           "row_step": 120, "data": rec.tobytes(), "is_dense": True,
           "fields": [{"name": n, "offset": 8 * j, "datatype": 8, "count": 1} for j, n in enumerate(dt.names)]}  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cloud = decode_pointcloud2(as_msg(msg))
    assert cloud.num_dropped == 1 and len(cloud.points) == 2
    np.testing.assert_array_equal(cloud.points[:, 3], np.array([np.inf, -np.inf], np.float32))


def test_results_of_the_hardening_read_as_json(tmp_path: Path):
    """sample_tokens written by export still read (the validation accepts the export's own format)."""
    tokens = {str(STAMP_NS): "token-a"}
    bag = write_bag(tmp_path / "tok.mcap", clouds=1, n=10, metadata={"sample_tokens": json.dumps(tokens)})
    assert BagSource(bag, NO_TF).sample_tokens() == tokens
    assert [e.sample_token for e in BagSource(bag, NO_TF).sweeps()] == ["token-a"]
