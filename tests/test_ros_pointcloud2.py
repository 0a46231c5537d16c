"""sensor_msgs/PointCloud2 -> the runtime's sweep and slices, against a naive per-point decoder (struct.unpack)."""

from __future__ import annotations

import array
import struct
from types import SimpleNamespace

import numpy as np
import pytest

from streamdet.core.slicing import split_sweep
from streamdet.runtime_ort.ros.pointcloud2 import (
    POINT_FIELD_TYPES,
    CloudFields,
    decode_pointcloud2,
    pointcloud2_message,
    slice_from_message,
    split_cloud,
)

STAMP_NS = 1_700_000_000_123_456_789
STRUCT_CODES = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "f", 8: "d"}
SIZES = {k: np.dtype(v).itemsize for k, v in POINT_FIELD_TYPES.items()}
FLOAT32, FLOAT64, UINT8, UINT16, UINT32 = 7, 8, 2, 4, 6


def ns(**kw) -> SimpleNamespace:
    return SimpleNamespace(**kw)


def as_msg(value):
    """A message dict (what the adapters write) as an object with ROS field attributes (what the readers give)."""
    if isinstance(value, dict):
        return SimpleNamespace(**{k: as_msg(v) for k, v in value.items()})
    if isinstance(value, list):
        return [as_msg(v) for v in value]
    return value


def make_cloud(
    columns: dict[str, np.ndarray], datatypes: dict[str, int], order: list[str], gap: int = 0, tail: int = 0,
    bigendian: bool = False, height: int = 1, row_pad: int = 0, dense: bool = True, data_kind: str = "bytes",
) -> SimpleNamespace:  # fmt: skip
    """A PointCloud2 message object packed point by point with struct (the reference layout)."""
    n = len(next(iter(columns.values())))
    offsets, off = {}, 0
    for name in order:
        offsets[name] = off
        off += SIZES[datatypes[name]] * 1 + gap
    point_step = off + tail
    width = n // height
    row_step = width * point_step + row_pad
    buf = bytearray(row_step * height)
    e = ">" if bigendian else "<"
    for i in range(n):
        r, c = divmod(i, width)
        for name in order:
            code = STRUCT_CODES[datatypes[name]]
            value = columns[name][i]
            value = int(value) if code not in "fd" else float(value)
            struct.pack_into(e + code, buf, r * row_step + c * point_step + offsets[name], value)
    fields = [ns(name=nm, offset=offsets[nm], datatype=datatypes[nm], count=1) for nm in order]
    data = {"bytes": bytes(buf), "numpy": np.frombuffer(bytes(buf), np.uint8).copy(), "list": list(buf),
            "array": array.array("B", bytes(buf))}[data_kind]  # fmt: skip
    return ns(header=ns(stamp=ns(sec=STAMP_NS // 10**9, nanosec=STAMP_NS % 10**9), frame_id="lidar"), height=height, width=width,
              fields=fields, is_bigendian=bigendian, point_step=point_step, row_step=row_step, data=data, is_dense=dense)  # fmt: skip


def naive_decode(msg, names: dict[str, str]) -> dict[str, np.ndarray]:
    """Per point, per field: struct.unpack_from at row * row_step + col * point_step + offset."""
    e = ">" if msg.is_bigendian else "<"
    data = bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data.tobytes()
    by_name = {f.name: f for f in msg.fields}
    out = {role: [] for role in names}
    for r in range(msg.height):
        for c in range(msg.width):
            base = r * msg.row_step + c * msg.point_step
            for role, name in names.items():
                f = by_name[name]
                out[role].append(struct.unpack_from(e + STRUCT_CODES[f.datatype], data, base + f.offset)[0])
    return {role: np.array(v, dtype=np.float64) for role, v in out.items()}


def random_columns(rng: np.random.Generator, n: int, datatypes: dict[str, int], time_name: str | None) -> dict[str, np.ndarray]:
    cols = {name: rng.uniform(-60, 60, n) for name in ("x", "y", "z")}
    cols["intensity"] = rng.integers(0, 256, n).astype(np.float64)
    cols["ring"] = rng.integers(0, 32, n).astype(np.float64)
    if time_name:
        kind = datatypes[time_name]
        cols[time_name] = rng.integers(0, 50_000_000, n) if kind in (UINT32,) else rng.uniform(-0.05, 0.0, n)
    for name, kind in datatypes.items():
        if kind in (FLOAT32,) and name in cols:
            cols[name] = cols[name].astype(np.float32).astype(np.float64)  # representable values
    return cols


LAYOUTS = [
    # (order, datatypes, gap, tail, bigendian, height, row_pad, time name)
    (["x", "y", "z", "intensity", "t", "ring"], {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "intensity": FLOAT32, "t": UINT32, "ring": UINT16}, 0, 0, False, 1, 0, "t"),
    (["t", "intensity", "z", "y", "x"], {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "intensity": UINT8, "t": UINT32}, 0, 0, False, 1, 0, "t"),
    (["x", "y", "z", "intensity", "time", "ring"], {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "intensity": FLOAT32, "time": FLOAT32, "ring": UINT16}, 4, 0, False, 1, 0, "time"),
    (["x", "y", "z", "intensity", "timestamp"], {"x": FLOAT64, "y": FLOAT64, "z": FLOAT64, "intensity": UINT16, "timestamp": FLOAT64}, 0, 16, False, 1, 0, "timestamp"),
    (["ring", "x", "y", "z", "time_stamp", "intensity"], {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "intensity": UINT8, "time_stamp": FLOAT64, "ring": UINT8}, 1, 3, True, 1, 0, "time_stamp"),
    (["x", "y", "z", "intensity", "t"], {"x": FLOAT64, "y": FLOAT64, "z": FLOAT64, "intensity": UINT32, "t": UINT32}, 0, 8, True, 4, 12, "t"),
    (["x", "y", "z", "intensity", "time"], {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "intensity": FLOAT32, "time": FLOAT32}, 0, 4, False, 3, 0, "time"),
]


@pytest.mark.parametrize("layout", range(len(LAYOUTS)))
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("dense", [True, False])
def test_decode_matches_the_naive_decoder(layout: int, seed: int, dense: bool):
    order, datatypes, gap, tail, big, height, row_pad, time_name = LAYOUTS[layout]
    rng = np.random.default_rng([seed, layout])
    n = 12 * height
    cols = random_columns(rng, n, datatypes, time_name)
    if not dense:  # a non-dense cloud: NaN returns where the float fields allow them
        holes = rng.choice(n, 3, replace=False)
        for name in ("x", "y", "z"):
            if datatypes[name] in (FLOAT32, FLOAT64):
                cols[name][holes] = np.nan
    msg = make_cloud(cols, datatypes, order, gap, tail, big, height, row_pad, dense)
    cloud = decode_pointcloud2(msg)
    names = {"x": "x", "y": "y", "z": "z", "intensity": "intensity", "time": time_name}
    if "ring" in order:
        names["ring"] = "ring"
    ref = naive_decode(msg, names)
    keep = np.isfinite(ref["x"]) & np.isfinite(ref["y"]) & np.isfinite(ref["z"])
    assert cloud.num_dropped == int((~keep).sum()) == (0 if dense else 3)
    assert cloud.points.dtype == np.float32 and cloud.points.shape == (int(keep.sum()), 5)
    for j, role in enumerate(("x", "y", "z", "intensity")):
        np.testing.assert_array_equal(cloud.points[:, j], ref[role][keep].astype(np.float32))
    np.testing.assert_array_equal(cloud.points[:, 4], ref["ring"][keep].astype(np.float32) if "ring" in order else 0)
    expected_time = ref["time"][keep] * (1e-9 if datatypes[time_name] == UINT32 else 1.0)
    np.testing.assert_allclose(cloud.time_s, expected_time, rtol=0, atol=1e-12)
    assert cloud.stamp_ns == STAMP_NS and cloud.frame_id == "lidar"


@pytest.mark.parametrize("data_kind", ["bytes", "numpy", "array", "list"])
def test_payload_types_of_the_three_libraries(data_kind: str):
    """bytes (mcap-ros2-support), numpy uint8 (rosbags), array.array (rclpy), a plain list."""
    dt = {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "intensity": FLOAT32, "t": UINT32}
    cols = random_columns(np.random.default_rng(3), 10, dt, "t")
    ref = decode_pointcloud2(make_cloud(cols, dt, list(dt)))
    got = decode_pointcloud2(make_cloud(cols, dt, list(dt), data_kind=data_kind))
    np.testing.assert_array_equal(got.points, ref.points)


def test_absolute_clock_times_become_relative_to_the_stamp():
    dt = {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "intensity": FLOAT32, "timestamp": FLOAT64}
    cols = random_columns(np.random.default_rng(4), 6, dt, None)
    offsets = np.array([-0.05, -0.04, -0.01, 0.0, 0.002, -0.03])
    cols["timestamp"] = STAMP_NS / 1e9 + offsets  # Hesai: absolute seconds
    cloud = decode_pointcloud2(make_cloud(cols, dt, list(dt)))
    np.testing.assert_allclose(cloud.time_s, offsets, atol=1e-6)
    cols["timestamp"] = STAMP_NS + offsets * 1e9  # Livox: absolute nanoseconds in a float64
    cloud = decode_pointcloud2(make_cloud(cols, dt, list(dt)))
    np.testing.assert_allclose(cloud.time_s, offsets, atol=1e-6)
    cloud = decode_pointcloud2(make_cloud(cols, dt, list(dt)), CloudFields(time_unit="ns"))
    np.testing.assert_allclose(cloud.time_s, offsets, atol=1e-6)


def test_intensity_scale_and_named_fields():
    dt = {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "reflectivity": FLOAT32, "offset_time": UINT32, "channel": UINT16}
    cols = random_columns(np.random.default_rng(5), 8, {**dt, "t": UINT32}, None)
    cols["reflectivity"] = np.linspace(0, 1, 8, dtype=np.float32).astype(np.float64)
    cols["offset_time"] = np.arange(8) * 1000
    cols["channel"] = np.arange(8)
    msg = make_cloud(cols, dt, list(dt))
    cloud = decode_pointcloud2(msg, CloudFields(intensity="reflectivity", intensity_scale=255.0, time="offset_time"))
    np.testing.assert_allclose(cloud.points[:, 3], np.linspace(0, 255, 8), rtol=1e-6)
    np.testing.assert_array_equal(cloud.points[:, 4], np.arange(8))  # "channel" is a ring name
    np.testing.assert_allclose(cloud.time_s, np.arange(8) * 1e-6)


@pytest.mark.parametrize("missing", ["x", "y", "z", "intensity"])
def test_a_missing_coordinate_or_intensity_field_is_named(missing: str):
    dt = {k: FLOAT32 for k in ("x", "y", "z", "intensity", "t") if k != missing}
    cols = {k: np.zeros(3) for k in dt}
    with pytest.raises(ValueError, match=f"PointCloud2 has no '{missing}' field .*it has"):
        decode_pointcloud2(make_cloud(cols, dt, list(dt)))


def test_a_field_named_twice_is_refused_not_guessed():
    dt = {k: FLOAT32 for k in ("x", "y", "z", "intensity", "t")}
    msg = make_cloud({k: np.zeros(3) for k in dt}, dt, list(dt))
    msg.fields.append(ns(name="x", offset=msg.fields[1].offset, datatype=FLOAT32, count=1))
    with pytest.raises(ValueError, match=r"PointCloud2 names a field twice: \['x'\]"):
        decode_pointcloud2(msg)


def test_a_missing_time_field_is_named_unless_not_required():
    dt = {k: FLOAT32 for k in ("x", "y", "z", "intensity")}
    msg = make_cloud({k: np.zeros(3) for k in dt}, dt, list(dt))
    with pytest.raises(ValueError, match=r"no per-point time field \(looked for \['t', 'time', 'timestamp', 'time_stamp'\]\)"):
        decode_pointcloud2(msg)
    assert decode_pointcloud2(msg, CloudFields(require_time=False)).time_s is None
    assert decode_pointcloud2(msg, CloudFields(time=None)).time_s is None
    with pytest.raises(ValueError, match="no 'stamp_us' field"):
        decode_pointcloud2(msg, CloudFields(time="stamp_us"))


def test_malformed_clouds_are_refused_with_the_reason():
    dt = {k: FLOAT32 for k in ("x", "y", "z", "intensity", "t")}
    good = make_cloud({k: np.zeros(4) for k in dt}, dt, list(dt))
    short = ns(**{**vars(good), "data": good.data[:-1]})
    with pytest.raises(ValueError, match="data holds 79 bytes; 1 rows of 4 points need 80"):
        decode_pointcloud2(short)
    bad_type = ns(**{**vars(good), "fields": [ns(**{**vars(f), "datatype": 9}) if f.name == "x" else f for f in good.fields]})
    with pytest.raises(ValueError, match="field 'x' has unknown datatype 9"):
        decode_pointcloud2(bad_type)
    counted = ns(**{**vars(good), "fields": [ns(**{**vars(f), "count": 3}) if f.name == "x" else f for f in good.fields]})
    with pytest.raises(ValueError, match="field 'x' has count 3"):
        decode_pointcloud2(counted)
    outside = ns(**{**vars(good), "point_step": 16})
    with pytest.raises(ValueError, match="field 't' at offset 16 .* does not fit point_step 16"):
        decode_pointcloud2(outside)
    with pytest.raises(ValueError, match="time_unit must be"):
        CloudFields(time_unit="minutes")


def test_empty_cloud():
    dt = {k: FLOAT32 for k in ("x", "y", "z", "intensity", "t")}
    msg = make_cloud({k: np.zeros(0) for k in dt}, dt, list(dt))
    cloud = decode_pointcloud2(msg)
    assert cloud.points.shape == (0, 5) and cloud.time_s.shape == (0,)
    assert [len(s.points) for s in split_cloud(cloud, 4)] == [0, 0, 0, 0]


@pytest.mark.parametrize("n", [1, 4, 8])
def test_split_cloud_is_split_sweep_with_scan_times(n: int):
    rng = np.random.default_rng(n)
    points = np.zeros((500, 5), np.float32)
    points[:, :3] = rng.uniform(-40, 40, (500, 3))
    points[:, 3] = rng.integers(0, 256, 500)
    times = rng.uniform(-0.05, 0, 500).astype(np.float32)
    cloud = decode_pointcloud2(as_msg(pointcloud2_message(points, STAMP_NS, "LIDAR_TOP", times)))
    slices = split_cloud(cloud, n)
    for got, ref in zip(slices, split_sweep(points, n)):
        np.testing.assert_array_equal(got.points, ref)
    for s in slices:
        mask = _sector_mask(points, s.index, n)
        expected = STAMP_NS + int(round(float(times[mask].astype(np.float64).max()) * 1e9))
        assert s.scan_time_ns == expected and s.cloud_stamp_ns == STAMP_NS and s.num_slices == n


def _sector_mask(points: np.ndarray, k: int, n: int) -> np.ndarray:
    from streamdet.core.sectors import slice_index_of

    return slice_index_of(points[:, 0], points[:, 1], n, 0.0) == k


def test_split_cloud_without_times_stamps_every_slice_with_the_cloud():
    points = np.array([[1, 1, 0, 10, 0], [-1, 1, 0, 20, 0], [-1, -1, 0, 30, 0], [1, -1, 0, 40, 0]], np.float32)
    cloud = decode_pointcloud2(as_msg(pointcloud2_message(points, STAMP_NS, "l")), CloudFields(require_time=False))
    slices = split_cloud(cloud, 4)
    assert [len(s.points) for s in slices] == [1, 1, 1, 1]
    assert {s.scan_time_ns for s in slices} == {STAMP_NS}


def test_slice_from_message_takes_the_sector_of_most_points():
    # three points in sector 1 of 4 (90..180 deg), one just over the border in sector 0
    points = np.array([[-1, 1, 0, 255, 0], [-2, 1, 0, 0, 0], [-1, 3, 0, 0, 0], [1, 5, 0, 0, 0]], np.float32)
    times = np.array([-0.03, -0.02, -0.01, -0.04], np.float32)
    cloud = decode_pointcloud2(as_msg(pointcloud2_message(points, STAMP_NS, "l", times)))
    s = slice_from_message(cloud, 4)
    assert s.index == 1 and s.points.shape == (4, 6)
    np.testing.assert_array_equal(s.points[:, 5], 1)
    np.testing.assert_allclose(s.points[:, 3], points[:, 3] / 255)
    assert s.scan_time_ns == STAMP_NS + int(round(float(np.float32(-0.01)) * 1e9))
    assert slice_from_message(cloud, 4, index=2).index == 2
    with pytest.raises(ValueError, match="slice index must be in 0..3"):
        slice_from_message(cloud, 4, index=4)
    empty = decode_pointcloud2(as_msg(pointcloud2_message(points[:0], STAMP_NS, "l", times[:0])))
    with pytest.raises(ValueError, match="empty cloud names no sector"):
        slice_from_message(empty, 4)


def test_message_round_trip_is_bit_identical():
    rng = np.random.default_rng(7)
    points = rng.normal(0, 20, (300, 5)).astype(np.float32)
    points[:, 4] = rng.integers(0, 65536, 300)  # ring: a uint16 field, as drivers publish it
    times = rng.uniform(-0.05, 0, 300).astype(np.float32)
    msg = pointcloud2_message(points, STAMP_NS, "LIDAR_TOP", times)
    cloud = decode_pointcloud2(as_msg(msg))
    assert cloud.points.tobytes() == points.tobytes()
    assert cloud.time_s.astype(np.float32).tobytes() == times.tobytes()
    assert msg["point_step"] == 24 and msg["row_step"] == 24 * 300 and msg["is_dense"]
    # the Velodyne / Ouster drivers' layout: float32 x y z intensity, uint16 ring at 16, float32 time at 20
    assert [(f["name"], f["offset"], f["datatype"]) for f in msg["fields"]] == [
        ("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("ring", 16, 4), ("time", 20, 7)]
    raw = np.frombuffer(msg["data"], np.uint8).reshape(300, 24)
    np.testing.assert_array_equal(raw[:, 16:18].copy().view("<u2")[:, 0], points[:, 4].astype(np.uint16))
    plain = pointcloud2_message(points, STAMP_NS, "LIDAR_TOP")
    assert plain["point_step"] == 20 and [f["name"] for f in plain["fields"]] == ["x", "y", "z", "intensity", "ring"]
    assert decode_pointcloud2(as_msg(plain), CloudFields(require_time=False)).points.tobytes() == points.tobytes()
    with pytest.raises(ValueError, match=r"points must be \(N, 5\)"):
        pointcloud2_message(points[:, :4], STAMP_NS, "l")
    with pytest.raises(ValueError, match=r"time_s must be \(300,\)"):
        pointcloud2_message(points, STAMP_NS, "l", times[:5])


def test_integer_clock_in_whole_units_is_made_relative_exactly():
    dt = {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "intensity": FLOAT32, "time": UINT32}
    cols = random_columns(np.random.default_rng(6), 3, dt, None)
    cols["time"] = np.array([STAMP_NS // 10**9 - 1, STAMP_NS // 10**9, STAMP_NS // 10**9 + 2])  # absolute seconds
    cloud = decode_pointcloud2(make_cloud(cols, dt, list(dt)), CloudFields(time_unit="s"))
    frac = (STAMP_NS % 10**9) * 1e-9  # the header stamp's fraction of a second
    np.testing.assert_allclose(cloud.time_s, np.array([-1.0, 0.0, 2.0]) - frac, rtol=0, atol=1e-9)


@pytest.mark.parametrize("ring", [1.5, -1.0, 65536.0, np.nan, np.inf])
def test_a_ring_that_is_no_uint16_is_refused(ring):
    points = np.zeros((3, 5), np.float32)
    points[1, 4] = ring
    with pytest.raises(ValueError, match=r"ring column must hold whole numbers in 0..65535 \(a uint16 field\), got .* at row 1"):
        pointcloud2_message(points, STAMP_NS, "l")
