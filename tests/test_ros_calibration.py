"""CameraInfo + TF -> Rig: the same rig as the nuScenes records; TF lookups (exact, chained, interpolated); refusals."""

from __future__ import annotations


import numpy as np
import pytest

from streamdet.calibration.camera import Rig, make_transform, matrix_to_quaternion, quaternion_to_matrix
from streamdet.runtime_ort.ros.camera_info import camera_info_intrinsics, camera_info_message, rig_from_ros
from streamdet.runtime_ort.ros.tf import TfBuffer, transform_stamped_msg
from test_hardening_ros_adapters import as_msg




def _record(rng: np.random.Generator, scale: float = 1.0) -> dict:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    q = q if q[0] >= 0 else -q
    return {"rotation": q.tolist(), "translation": (rng.normal(size=3) * scale).tolist()}


def _tf(records: list[tuple[str, str, dict, int]]) -> dict:
    return {"transforms": [transform_stamped_msg(p, c, r, s) for p, c, r, s in records]}


def _matrix(rec: dict) -> np.ndarray:
    return make_transform(quaternion_to_matrix(rec["rotation"]), rec["translation"])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rig_is_the_one_from_the_nuscenes_records(seed: int):
    rng = np.random.default_rng(seed)
    lidar_mount, lidar_pose = _record(rng), _record(rng, 100)
    names = ["CAM_FRONT", "CAM_BACK"]
    tf = TfBuffer()
    tf.add(as_msg(_tf([("base_link", "LIDAR_TOP", lidar_mount, 0)])), static=True)
    tf.add(as_msg(_tf([("map", "base_link", lidar_pose, 1_000)])))
    cams, infos, stamps = [], {}, {}
    for j, name in enumerate(names):
        mount, pose, stamp = _record(rng), _record(rng, 100), 500 + 10_000 * j
        K = np.array([[800.0 + j, 0, 320], [0, 790.0, 240], [0, 0, 1]])
        tf.add(as_msg(_tf([("base_link", name, mount, 0)])), static=True)
        tf.add(as_msg(_tf([("map", "base_link", pose, stamp)])))
        infos[name] = as_msg(camera_info_message(K, 640, 480, stamp, name))
        stamps[name] = stamp
        cams.append({"name": name, "calibrated_sensor": {**mount, "camera_intrinsic": K.tolist()}, "ego_pose": pose,
                     "width": 640, "height": 480, "timestamp_us": stamp // 1000})  # fmt: skip
    expected = Rig.from_nuscenes_records(lidar_mount, lidar_pose, cams)
    got = rig_from_ros(infos, tf, "LIDAR_TOP", 1_000, stamps, order=names)
    assert got == expected  # bit for bit: the same numbers through the same arithmetic
    assert got.sha256() == expected.sha256()
    no_motion = rig_from_ros(infos, tf, "LIDAR_TOP", 1_000, stamps, global_frame=None, order=names)
    assert np.allclose(no_motion.lidar2ego, expected.lidar2ego) and np.array_equal(no_motion.ego2global, np.eye(4))
    with pytest.raises(ValueError, match=r"no CameraInfo for cameras \['CAM_LEFT'\]"):
        rig_from_ros(infos, tf, "LIDAR_TOP", 1_000, stamps, order=names + ["CAM_LEFT"])


def test_tf_chains_interpolation_and_errors():
    rng = np.random.default_rng(4)
    a, b, _ = _record(rng), _record(rng), _record(rng)  # a third draw: the seeded records stay as they were
    tf = TfBuffer()
    tf.add(as_msg(_tf([("base_link", "sensor_mount", a, 0), ("sensor_mount", "cam_optical", b, 0)])), static=True)
    chained = tf.lookup("base_link", "cam_optical", 0)
    np.testing.assert_allclose(_matrix(chained), _matrix(a) @ _matrix(b), atol=1e-12)
    inverse = tf.lookup("cam_optical", "base_link", 0)
    np.testing.assert_allclose(_matrix(inverse), np.linalg.inv(_matrix(a) @ _matrix(b)), atol=1e-12)
    # time-stamped poses: exact at a stamp, interpolated between two, refused outside
    yaw0, yaw1 = 0.1, 0.5
    pose0 = {"rotation": [np.cos(yaw0 / 2), 0, 0, np.sin(yaw0 / 2)], "translation": [0.0, 0.0, 0.0]}
    pose1 = {"rotation": [np.cos(yaw1 / 2), 0, 0, np.sin(yaw1 / 2)], "translation": [10.0, 2.0, 0.0]}
    tf.add(as_msg(_tf([("map", "base_link", pose1, 2_000)])))
    tf.add(as_msg(_tf([("map", "base_link", pose0, 1_000)])))  # out of order on purpose
    assert tf.lookup("map", "base_link", 1_000) == pose0
    mid = tf.lookup("map", "base_link", 1_250)
    np.testing.assert_allclose(mid["translation"], [2.5, 0.5, 0.0])
    R = quaternion_to_matrix(mid["rotation"])
    assert np.isclose(np.arctan2(R[1, 0], R[0, 0]), 0.2)
    with pytest.raises(ValueError, match=r"'map' -> 'base_link' at 3000 ns is outside its 2 stamps \[1000, 2000\]"):
        tf.lookup("map", "base_link", 3_000)
    held = TfBuffer(max_extrapolation_ns=1_000)
    held.add(as_msg(_tf([("map", "base_link", pose1, 2_000)])))
    assert held.lookup("map", "base_link", 3_000) == pose1
    with pytest.raises(KeyError, match="no TF path from 'map' to 'radar'"):
        tf.lookup("map", "radar", 0)
    with pytest.raises(ValueError, match="frame 'cam_optical' has two parents"):
        tf.add(as_msg(_tf([("map", "cam_optical", a, 0)])), static=True)
    with pytest.raises(ValueError, match="two different frame ids"):
        tf.add(as_msg(_tf([("map", "map", a, 0)])))
    # a leading slash (ROS 1 habit) names the same frame
    assert tf.lookup("/base_link", "/sensor_mount", 0) == a

@pytest.mark.parametrize(
    "rotation, ok",
    [([0.707, 0.0, 0.0, 0.707], True), ([1.0, 0.0, 0.0, 0.004], True),  # rounded, as URDFs write them: normalised
     ([5.0, 0.0, 0.0, 0.0], False), ([0.0, 0.0, 0.0, 0.0], False), ([np.nan, 0.0, 0.0, 1.0], False), ([0.9, 0, 0, 0], False)],
)  # fmt: skip
def test_tf_quaternions_as_tf2_takes_them(rotation, ok):
    """tf2 accepts |q|^2 within 0.01 of 1 and refuses the rest; accepted ones are normalised, so that an exact
    lookup and an interpolation between two stamps give unit rotations alike."""
    tf = TfBuffer()
    pose = {"rotation": rotation, "translation": [1.0, 2.0, 3.0]}
    if not ok:
        with pytest.raises(ValueError, match=r"'map' -> 'base_link' at 1000 ns: rotation .* must be a unit quaternion"):
            tf.add(as_msg(_tf([("map", "base_link", pose, 1_000)])))
        return
    tf.add(as_msg(_tf([("map", "base_link", pose, 1_000), ("map", "base_link", pose, 2_000)])))
    for stamp in (1_000, 1_500):
        q = np.asarray(tf.lookup("map", "base_link", stamp)["rotation"])
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12
        np.testing.assert_allclose(q, np.asarray(rotation) / np.linalg.norm(rotation), atol=1e-12)


def test_camera_info_refusals_name_the_problem():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    good = camera_info_message(K, 640, 480, 0, "cam")
    assert camera_info_intrinsics(as_msg(good)) == {"camera_intrinsic": K.tolist(), "width": 640, "height": 480}
    distorted = {**good, "d": [0.1, -0.02, 0.0, 0.0, 0.0]}
    with pytest.raises(ValueError, match=r"CameraInfo of 'cam' has distortion \(plumb_bob, d=\[0.1, -0.02.*intrinsics='p'"):
        camera_info_intrinsics(as_msg(distorted))
    P = np.zeros((3, 4))
    P[:, :3] = K * [[0.9], [0.9], [1]]
    rectified = camera_info_intrinsics(as_msg({**distorted, "p": P.reshape(-1).tolist()}), intrinsics="p")
    np.testing.assert_allclose(rectified["camera_intrinsic"], P[:, :3])
    with pytest.raises(ValueError, match=r"has binning \(2, 2\)"):
        camera_info_intrinsics(as_msg({**good, "binning_x": 2, "binning_y": 2}))
    with pytest.raises(ValueError, match="has a region of interest"):
        camera_info_intrinsics(as_msg({**good, "roi": {**good["roi"], "width": 100, "height": 50}}))
    with pytest.raises(ValueError, match="k must hold 9 values, got 0"):
        camera_info_intrinsics(as_msg({**good, "k": []}))
    with pytest.raises(ValueError, match="image size 0x480 must be positive"):
        camera_info_intrinsics(as_msg({**good, "width": 0}))
    with pytest.raises(ValueError, match="intrinsics must be 'k' or 'p'"):
        camera_info_intrinsics(as_msg(good), intrinsics="q")


def test_matrix_quaternion_round_trip_of_a_chained_lookup_is_a_unit_quaternion():
    rng = np.random.default_rng(9)
    tf = TfBuffer()
    recs = [_record(rng) for _ in range(3)]
    tf.add(as_msg(_tf([("a", "b", recs[0], 0), ("b", "c", recs[1], 0), ("a", "d", recs[2], 0)])), static=True)
    q = np.asarray(tf.lookup("d", "c", 0)["rotation"])
    assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[0] >= 0
    np.testing.assert_allclose(quaternion_to_matrix(q), quaternion_to_matrix(matrix_to_quaternion(quaternion_to_matrix(q))))
