"""Camera / Rig types and loaders (calibration/camera.py) on the bundled nuScenes sample, with naive references."""

from __future__ import annotations

import copy
import json
import math
import re
from importlib.resources import files

import numpy as np
import pytest

from streamdet.calibration import (
    CalibrationError,
    Camera,
    Rig,
    make_transform,
    matrix_to_quaternion,
    quaternion_to_matrix,
)

SAMPLE = files("streamdet.data") / "nuscenes_sample"
CALIB = SAMPLE / "calibration.json"
NAMES = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")


@pytest.fixture(scope="module")
def doc() -> dict:
    return json.loads(CALIB.read_text())


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.from_calibration_json(CALIB)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return quaternion_to_matrix(q / np.linalg.norm(q))


def _naive_quaternion_rotate(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """q p q* with explicit Hamilton products: an independent route to the rotation matrix."""

    def mul(a, b):
        w1, x1, y1, z1 = a
        w2, x2, y2, z2 = b
        return (
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        )

    conj = (q[0], -q[1], -q[2], -q[3])
    return np.array(mul(mul(q, (0.0, *p)), conj)[1:])


# ---- calibration.json -------------------------------------------------------------------------------

def test_loads_six_cameras_with_file_values(rig: Rig, doc: dict) -> None:
    assert rig.names == NAMES
    assert len(rig) == 6
    for cam, entry in zip(rig.cameras, doc["cameras"]):
        np.testing.assert_array_equal(cam.K, np.array(entry["K"]))
        np.testing.assert_array_equal(cam.lidar2cam, np.array(entry["lidar2cam"]["matrix"]))
        assert (cam.width, cam.height, cam.timestamp_us) == (1600, 900, entry["timestamp_us"])
        R = cam.lidar2cam[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
        assert np.linalg.det(R) > 0
        assert cam.K.dtype == np.float64 and cam.lidar2cam.dtype == np.float64
    np.testing.assert_array_equal(rig.lidar2ego, np.array(doc["lidar"]["sensor2ego"]["matrix"]))
    np.testing.assert_array_equal(rig.ego2global, np.array(doc["lidar"]["ego2global"]["matrix"]))


def test_lidar2img_matches_file(rig: Rig, doc: dict) -> None:
    for cam, entry in zip(rig.cameras, doc["cameras"]):
        np.testing.assert_allclose(cam.projection_matrix, np.array(entry["lidar2img"]["matrix"])[:3], rtol=0, atol=1e-9)


def test_arrays_are_read_only(rig: Rig) -> None:
    with pytest.raises(ValueError):
        rig.cameras[0].K[0, 0] = 1.0


def test_to_dict_round_trip_and_hash(rig: Rig) -> None:
    again = Rig.from_calibration_json(json.loads(json.dumps(rig.to_dict())))
    assert again == rig
    assert again.sha256() == rig.sha256()
    K = rig.cameras[0].K.copy()
    K[1, 1] *= 1.0 + 1e-12  # the hash covers every bit of every number
    bumped = Rig((Camera("CAM_FRONT", K, rig.cameras[0].lidar2cam, 1600, 900),) + rig.cameras[1:], rig.lidar2ego, rig.ego2global)
    assert bumped.sha256() != rig.sha256()
    # the ego pose does not move any voxel's projection, so it does not change the hash
    moved = Rig(rig.cameras, rig.lidar2ego, make_transform(np.eye(3), [1.0, 2.0, 0.0]))
    assert moved.sha256() == rig.sha256()


def test_rig_accessors(rig: Rig) -> None:
    assert rig.camera("CAM_BACK") is rig.cameras[3]
    with pytest.raises(KeyError, match="CAM_FRONT_RIGHT"):
        rig.camera("CAM_NOPE")
    fewer = rig.without(["CAM_BACK"])
    assert fewer.names == tuple(n for n in NAMES if n != "CAM_BACK")
    assert rig.without("CAM_BACK") == fewer
    with pytest.raises(KeyError, match="CAM_NOPE"):
        rig.without(["CAM_NOPE"])
    with pytest.raises(CalibrationError, match="every camera"):
        rig.without(NAMES)
    small = rig.resized(800, 450)
    assert all((c.width, c.height) == (800, 450) for c in small.cameras)


def test_file_errors(tmp_path) -> None:
    with pytest.raises(CalibrationError, match="missing.json: cannot read"):
        Rig.from_calibration_json(tmp_path / "missing.json")
    bad = tmp_path / "calibration.json"
    bad.write_text("{not json")
    with pytest.raises(CalibrationError, match="calibration.json: not valid JSON"):
        Rig.from_calibration_json(bad)
    bad.write_text("[1, 2]")
    with pytest.raises(CalibrationError, match="top level"):
        Rig.from_calibration_json(bad)


def _set(d: dict, path: tuple, value) -> None:
    for key in path[:-1]:
        d = d[key]
    if value is _DELETE:
        del d[path[-1]]
    else:
        d[path[-1]] = value


_DELETE = object()


def _not_orthonormal(doc):
    m = np.array(doc["cameras"][2]["lidar2cam"]["matrix"])
    m[:3, :3] *= 1.01
    return m.tolist()


def _reflection(doc):
    m = np.array(doc["cameras"][4]["lidar2cam"]["matrix"])
    m[:3, 0] *= -1
    return m.tolist()


def _nan_matrix(doc):
    m = np.array(doc["lidar"]["sensor2ego"]["matrix"])
    m[0, 3] = float("nan")
    return m.tolist()


MALFORMED = [
    # (path, value maker, regex that must name the field)
    (("cameras", 2, "lidar2cam", "matrix"), _not_orthonormal, r"cameras\[2\]\.lidar2cam\.matrix: rotation is not orthonormal"),
    (("cameras", 4, "lidar2cam", "matrix"), _reflection, r"cameras\[4\]\.lidar2cam\.matrix: rotation is a reflection"),
    (("cameras", 2, "K"), lambda d: np.hstack([np.array(d["cameras"][2]["K"]), np.zeros((3, 1))]).tolist(),
     r"calibration.json: cameras\[2\]\.K: expected shape \(3, 3\), got \(3, 4\)"),
    (("cameras", 1, "K"), lambda d: [[float("nan"), 0, 800], [0, 1000, 450], [0, 0, 1]], r"cameras\[1\]\.K: contains NaN"),
    (("cameras", 0, "K"), lambda d: [[1000, 0, 800], [0, 1000, 450], [0, 1, 1]], r"cameras\[0\]\.K: expected \[\[fx"),
    (("cameras", 0, "K"), lambda d: [[-1000, 0, 800], [0, 1000, 450], [0, 0, 1]], r"cameras\[0\]\.K: focal lengths"),
    (("cameras", 5, "K"), lambda d: "K", r"cameras\[5\]\.K: expected a numeric array"),
    (("lidar", "sensor2ego", "matrix"), _nan_matrix, r"lidar\.sensor2ego\.matrix: contains NaN"),
    (("cameras", 3, "lidar2cam", "matrix"), lambda d: np.eye(4)[:3].tolist(), r"cameras\[3\]\.lidar2cam\.matrix: expected shape \(4, 4\), got \(3, 4\)"),
    (("cameras", 3, "lidar2cam", "matrix"), lambda d: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.5, 0, 0, 1]],
     r"cameras\[3\]\.lidar2cam\.matrix: bottom row"),
    (("cameras", 3, "width"), lambda d: _DELETE, r"cameras\[3\]\.width: missing field"),
    (("cameras", 0, "K"), lambda d: _DELETE, r"cameras\[0\]\.K: missing field"),
    (("cameras", 1, "name"), lambda d: _DELETE, r"cameras\[1\]\.name: missing field"),
    (("cameras", 1, "lidar2cam"), lambda d: _DELETE, r"cameras\[1\]\.lidar2cam: missing field"),
    (("cameras", 2, "lidar2cam", "matrix"), lambda d: _DELETE, r"cameras\[2\]\.lidar2cam\.matrix: missing field"),
    (("cameras", 2, "height"), lambda d: 0, r"cameras\[2\]\.height: expected a positive integer"),
    (("cameras", 2, "height"), lambda d: 900.5, r"cameras\[2\]\.height: expected a positive integer"),
    (("cameras", 2, "timestamp_us"), lambda d: "soon", r"cameras\[2\]\.timestamp_us"),
    (("cameras", 2, "name"), lambda d: "CAM_FRONT", r"duplicate camera names \['CAM_FRONT'\]"),
    (("cameras",), lambda d: [], r"cameras: expected a non-empty list"),
    (("lidar",), lambda d: _DELETE, r"lidar: missing field"),
    (("lidar", "sensor2ego"), lambda d: _DELETE, r"lidar\.sensor2ego: missing field"),
]


@pytest.mark.parametrize("path, make, pattern", MALFORMED, ids=[m[2][:40] for m in MALFORMED])
def test_malformed_file_names_the_field(doc: dict, tmp_path, path, make, pattern) -> None:
    bad = copy.deepcopy(doc)
    _set(bad, path, make(doc))
    target = tmp_path / "calibration.json"
    target.write_text(json.dumps(bad))
    with pytest.raises(CalibrationError, match=pattern):
        Rig.from_calibration_json(target)
    with pytest.raises(CalibrationError, match=pattern.replace("calibration.json", "calibration")):
        Rig.from_calibration_json(bad)  # the parsed dict reports the same field


def test_calibration_error_is_value_error() -> None:
    assert issubclass(CalibrationError, ValueError)


def test_pose_from_quaternion_when_no_matrix(doc: dict) -> None:
    alt = copy.deepcopy(doc)
    del alt["lidar"]["sensor2ego"]["matrix"]
    rig = Rig.from_calibration_json(alt)
    np.testing.assert_allclose(rig.lidar2ego, np.array(doc["lidar"]["sensor2ego"]["matrix"]), atol=1e-6)
    del alt["lidar"]["ego2global"]  # unknown pose -> identity
    np.testing.assert_array_equal(Rig.from_calibration_json(alt).ego2global, np.eye(4))


# ---- nuScenes records ----------------------------------------------------------------------------

def _records(doc: dict):
    def rec(entry):
        return {"translation": entry["translation"], "rotation": entry["rotation_wxyz"]}

    lidar_sensor = {**rec(doc["lidar"]["sensor2ego"]), "camera_intrinsic": []}
    cams = [
        {
            "name": c["name"],
            "calibrated_sensor": {**rec(c["sensor2ego"]), "camera_intrinsic": c["K"]},
            "ego_pose": rec(c["ego2global"]),
            "width": c["width"],
            "height": c["height"],
            "timestamp_us": c["timestamp_us"],
        }
        for c in doc["cameras"]
    ]
    return lidar_sensor, rec(doc["lidar"]["ego2global"]), cams


def test_nuscenes_records_reproduce_lidar2cam(rig: Rig, doc: dict) -> None:
    from_records = Rig.from_nuscenes_records(*_records(doc))
    assert from_records.names == rig.names
    for a, b in zip(from_records.cameras, rig.cameras):
        np.testing.assert_allclose(a.lidar2cam, b.lidar2cam, rtol=0, atol=1e-6, err_msg=a.name)
        np.testing.assert_array_equal(a.K, b.K)
    np.testing.assert_allclose(from_records.lidar2ego, rig.lidar2ego, atol=1e-6)


def test_nuscenes_records_chain_is_the_devkit_chain(doc: dict) -> None:
    """lidar -> ego(t_lidar) -> global -> ego(t_cam) -> cam, written out with general matrix inverses."""
    lidar_sensor, lidar_pose, cams = _records(doc)
    rig = Rig.from_nuscenes_records(lidar_sensor, lidar_pose, cams)

    def T(rec):
        return make_transform(quaternion_to_matrix(rec["rotation"]), rec["translation"])

    for cam, c in zip(rig.cameras, cams):
        expected = np.linalg.inv(T(c["calibrated_sensor"])) @ np.linalg.inv(T(c["ego_pose"])) @ T(lidar_pose) @ T(lidar_sensor)
        np.testing.assert_allclose(cam.lidar2cam, expected, atol=1e-9)


@pytest.mark.parametrize(
    "mutate, pattern",
    [
        (lambda ls, lp, cs: cs[1]["calibrated_sensor"].__setitem__("rotation", [1.0, 0.5, 0.0, 0.0]), r"cameras\[1\]\.calibrated_sensor\.rotation: quaternion must have unit norm"),
        (lambda ls, lp, cs: cs[2]["calibrated_sensor"].__setitem__("camera_intrinsic", []), r"cameras\[2\]\.calibrated_sensor\.camera_intrinsic: expected shape \(3, 3\)"),
        (lambda ls, lp, cs: cs[0].pop("ego_pose"), r"cameras\[0\]\.ego_pose: missing field"),
        (lambda ls, lp, cs: lp.__setitem__("translation", [0.0, float("nan"), 0.0]), r"lidar_pose\.translation: contains NaN"),
        (lambda ls, lp, cs: ls.pop("rotation"), r"lidar_sensor\.rotation: missing field"),
        (lambda ls, lp, cs: cs[3].__setitem__("width", -5), r"cameras\[3\]\.width"),
    ],
)
def test_nuscenes_records_malformed(doc: dict, mutate, pattern) -> None:
    ls, lp, cs = copy.deepcopy(_records(doc))
    mutate(ls, lp, cs)
    with pytest.raises(CalibrationError, match=pattern):
        Rig.from_nuscenes_records(ls, lp, cs)


# ---- rotations -------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", range(5))
def test_quaternion_to_matrix_matches_hamilton_product(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    R = quaternion_to_matrix(q)
    for p in rng.normal(size=(4, 3)):
        np.testing.assert_allclose(R @ p, _naive_quaternion_rotate(q, p), atol=1e-12)
    back = matrix_to_quaternion(R)
    assert back[0] >= 0
    np.testing.assert_allclose(back, q if q[0] >= 0 else -q, atol=1e-12)


@pytest.mark.parametrize("axis", range(3))
def test_matrix_to_quaternion_half_turns(axis: int) -> None:
    R = -np.eye(3)
    R[axis, axis] = 1.0  # 180 degrees about one axis: the trace branch would divide by ~0
    np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R, atol=1e-12)


def test_rotation_inputs_validated() -> None:
    with pytest.raises(CalibrationError, match="unit norm"):
        quaternion_to_matrix([2.0, 0.0, 0.0, 0.0])
    with pytest.raises(CalibrationError, match=r"expected shape \(4,\)"):
        quaternion_to_matrix([1.0, 0.0, 0.0])
    with pytest.raises(CalibrationError, match="orthonormal"):
        matrix_to_quaternion(np.eye(3) * 2)


# ---- projection, visibility, resize ---------------------------------------------------------------------

def _naive_project(cam: Camera, p) -> tuple[float, float, float]:
    R, t = cam.lidar2cam[:3, :3], cam.lidar2cam[:3, 3]
    pc = [sum(R[i, k] * p[k] for k in range(3)) + t[i] for i in range(3)]
    u = (cam.K[0, 0] * pc[0] + cam.K[0, 1] * pc[1] + cam.K[0, 2] * pc[2]) / pc[2]
    v = (cam.K[1, 1] * pc[1] + cam.K[1, 2] * pc[2]) / pc[2]
    return u, v, pc[2]


@pytest.mark.parametrize("seed", range(3))
def test_project_and_visible_match_naive(rig: Rig, seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-40, 40, size=(300, 5)).astype(np.float32)  # 5 columns like a sweep
    for cam in rig.cameras:
        uv, depth = cam.project(pts)
        vis = cam.visible(pts, min_depth_m=1.0)
        for i in range(0, 300, 7):
            u, v, d = _naive_project(cam, [float(x) for x in pts[i, :3]])
            assert math.isclose(depth[i], d, abs_tol=1e-9)
            np.testing.assert_allclose(uv[i], [u, v], rtol=1e-9, atol=1e-9)
            assert vis[i] == (d > 1.0 and 0 <= u < cam.width and 0 <= v < cam.height)


def test_project_empty_and_malformed(rig: Rig) -> None:
    cam = rig.cameras[0]
    uv, depth = cam.project(np.zeros((0, 3)))
    assert uv.shape == (0, 2) and depth.shape == (0,)
    assert cam.visible(np.zeros((0, 4))).shape == (0,)
    with pytest.raises(ValueError, match=r"points_lidar: expected shape \(N, 3\)"):
        cam.project(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="points_lidar"):
        cam.project(np.zeros(3))


def test_point_at_camera_centre_is_not_visible(rig: Rig) -> None:
    cam = rig.cameras[0]
    assert not cam.visible(cam.center_lidar[None])[0]


@pytest.mark.parametrize("size", [(800, 450), (1200, 675), (1601, 901)])
def test_resized_scales_pixels(rig: Rig, size) -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-30, 30, size=(200, 3))
    for cam in rig.cameras:
        small = cam.resized(*size)
        uv, d = cam.project(pts)
        uv2, d2 = small.project(pts)
        front = d > 0.5
        np.testing.assert_allclose(uv2[front], uv[front] * np.array(size) / [1600, 900], rtol=1e-10, atol=1e-9)
        np.testing.assert_array_equal(d, d2)
    with pytest.raises(CalibrationError, match="width"):
        rig.cameras[0].resized(0, 450)


def test_fov_against_brute_force(rig: Rig) -> None:
    """The azimuth interval of the rays through the image border vs. the visible directions found by scanning."""
    az = np.radians(np.arange(0.0, 360.0, 0.05))
    el = np.radians(np.linspace(-30, 30, 61))
    aa, ee = np.meshgrid(az, el, indexing="ij")
    dirs = np.stack([np.cos(ee) * np.cos(aa), np.cos(ee) * np.sin(aa), np.sin(ee)], -1).reshape(-1, 3)
    for cam in rig.cameras:
        R = cam.lidar2cam[:3, :3]
        # a direction d is seen iff the pixel of R d (no translation: a point at infinity) is inside the image
        pc = dirs @ R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (pc @ cam.K.T)[:, 0] / pc[:, 2]
            v = (pc @ cam.K.T)[:, 1] / pc[:, 2]
        seen = (pc[:, 2] > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        seen_az = np.degrees(np.arctan2(dirs[seen, 1], dirs[seen, 0]))
        lo, hi = cam.fov_azimuth_deg
        assert 0 <= lo < 360 and 55 < hi - lo < 120, (cam.name, lo, hi)
        rel = np.mod(seen_az - lo, 360.0)
        assert rel.max() <= hi - lo + 1e-6, cam.name  # nothing seen outside the interval
        assert rel.min() <= 0.1 and rel.max() >= hi - lo - 0.1, cam.name  # and it is tight at both ends


def test_camera_direct_construction_errors() -> None:
    K = [[1000.0, 0, 800], [0, 1000.0, 450], [0, 0, 1]]
    with pytest.raises(CalibrationError, match=r"Camera 'X'\.lidar2cam: expected shape \(4, 4\)"):
        Camera("X", K, np.eye(3), 1600, 900)
    with pytest.raises(CalibrationError, match="Camera.name"):
        Camera("", K, np.eye(4), 1600, 900)
    with pytest.raises(CalibrationError, match=r"Camera 'X'\.width"):
        Camera("X", K, np.eye(4), True, 900)
    with pytest.raises(CalibrationError, match="at least one camera"):
        Rig((), np.eye(4), np.eye(4))


def test_loads_from_a_traversable(rig: Rig) -> None:
    """A resource that is not a filesystem path (zipped install) is read through read_text()."""

    class Resource:
        name = "calibration.json"

        def read_text(self, encoding: str = "utf-8") -> str:
            return CALIB.read_text(encoding=encoding)

    assert Rig.from_calibration_json(Resource()) == rig


# ---- implausible intrinsics at the other end: a tiny focal length, a huge skew (review 39, L1) ---------------------

def _with_K(K: np.ndarray) -> Camera:
    return Camera("CAM_X", K, np.eye(4), 1600, 900)


def _naive_fov_deg(f: float, side: int) -> float:
    return math.degrees(2 * math.atan(side / (2 * f)))


@pytest.mark.parametrize("fx, fy", [(1e-9, 1e-9), (1.5, 1000.0), (1000.0, 1.599), (0.5, 0.5)])
def test_a_focal_length_under_a_thousandth_of_the_side_is_refused(fx, fy) -> None:
    assert _naive_fov_deg(min(fx, fy), 1600) > 179.77  # what the bound means: no pinhole sees that wide
    with pytest.raises(CalibrationError, match=rf"Camera 'CAM_X'\.K: focal length fx={fx:.6g}, fy={fy:.6g} px is under "
                                               r"0\.001 times the image's 1600 px side"):  # fmt: skip
        _with_K(np.array([[fx, 0, 800], [0, fy, 450], [0, 0, 1.0]]))


@pytest.mark.parametrize("skew", [1e6, -1e6, 1e300, 0.11 * 1000, -0.101 * 1000])
def test_a_skew_over_a_tenth_of_fx_is_refused(skew) -> None:
    with pytest.raises(CalibrationError, match=rf"Camera 'CAM_X'\.K: skew K\[0\]\[1\]={re.escape(f'{skew:.6g}')} is over 0\.1 times "
                                               r"fx=1000 \(pixel axes [\d.e+-]+ degrees apart"):  # fmt: skip
        _with_K(np.array([[1000.0, skew, 800], [0, 1000.0, 450], [0, 0, 1.0]]))


def test_the_bounds_themselves_and_real_cameras_pass(rig: Rig) -> None:
    assert 179.77 < _naive_fov_deg(1.6, 1600) < 179.78  # the focal bound's field of view, documented in camera.py
    assert _with_K(np.array([[1.6, 0, 800], [0, 1.6, 450], [0, 0, 1.0]])).K[0, 0] == 1.6  # exactly side / 1000
    for skew in (100.0, -100.0, 0.5):  # exactly 0.1 fx, and a little skew as some calibration tools report
        assert _with_K(np.array([[1000.0, skew, 800], [0, 1000.0, 450], [0, 0, 1.0]])).K[0, 1] == skew
    for cam in rig.cameras:  # the bundled nuScenes sample: square pixels, focal lengths near 0.8 of the width
        assert cam.K[0, 1] == 0 and cam.K[0, 0] > 1e-3 * max(cam.width, cam.height)


def test_a_calibration_file_with_a_tiny_focal_length_names_file_and_camera(doc: dict, tmp_path) -> None:
    bad = copy.deepcopy(doc)
    bad["cameras"][3]["K"] = [[0.5, 0.0, 800.0], [0.0, 0.5, 450.0], [0.0, 0.0, 1.0]]
    (tmp_path / "calibration.json").write_text(json.dumps(bad))
    with pytest.raises(CalibrationError, match=r"calibration\.json: cameras\[3\]: Camera 'CAM_BACK'\.K: focal length fx=0\.5"):
        Rig.from_calibration_json(tmp_path / "calibration.json")


# ---- camera names go into logs and CLI output: printable only (review 39, L3) ----------------------------------

@pytest.mark.parametrize("name", ["CAM\n\x1b[31mX", "CAM\tFRONT", "CAM\x00", "CAM\u2028X", "\x7f"])
def test_an_unprintable_camera_name_is_refused_quoting_its_repr(doc: dict, tmp_path, name) -> None:
    K = [[1000.0, 0, 800], [0, 1000.0, 450], [0, 0, 1]]
    with pytest.raises(CalibrationError, match=r"Camera\.name: expected a non-empty printable string, got " + re.escape(repr(name))):
        Camera(name, K, np.eye(4), 1600, 900)
    bad = copy.deepcopy(doc)
    bad["cameras"][1]["name"] = name
    (tmp_path / "calibration.json").write_text(json.dumps(bad))
    with pytest.raises(CalibrationError, match=r"calibration\.json: cameras\[1\]\.name: expected a non-empty printable string, got "
                                               + re.escape(repr(name))):  # fmt: skip
        Rig.from_calibration_json(tmp_path / "calibration.json")
    assert name.isprintable() is False  # the rule is str.isprintable


def test_printable_names_pass_including_non_ascii() -> None:
    K = [[1000.0, 0, 800], [0, 1000.0, 450], [0, 0, 1]]
    for name in ("CAM_FRONT", "cam front 2", "Kamera_vorn_ü", "相机"):
        assert Camera(name, K, np.eye(4), 1600, 900).name == name
