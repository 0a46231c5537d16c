"""Projection LUT (calibration/lut.py) against direct float64 projection, on the real rig and on random rigs."""

from __future__ import annotations

import io
import json
import math
from importlib.resources import files

import numpy as np
import pytest

from streamdet.calibration import CalibrationError, Camera, GridSpec, Lut, Rig, build_lut, make_transform

SAMPLE = files("streamdet.data") / "nuscenes_sample"
COARSE = GridSpec(voxel_xy_m=0.8)  # 128 x 128 x 16: the real extent, 16x fewer voxels
TINY = GridSpec(x_range_m=(-6.4, 6.4), y_range_m=(-6.4, 6.4), z_range_m=(-1.0, 1.0), voxel_xy_m=0.4, voxel_z_m=0.5)
BORDER_EPS = 1e-3  # float32 build vs float64 reference may disagree this close to a cell or image edge


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.from_calibration_json(SAMPLE / "calibration.json")


@pytest.fixture(scope="module")
def coarse_lut(rig: Rig) -> Lut:
    return build_lut(rig, COARSE)


def reference_rows(rig: Rig, grid: GridSpec, stride: int, min_depth_m: float = 0.0):
    """Per quadrant and camera, the feature row each voxel centre projects to (-1: unseen), float64.

    Returns rows (4, J, M), borderline (4, J, M) bool where the float32 build may legitimately differ, and the
    feature-map size. M = Z * Yq * Xq in (Z, Yq, Xq) order.
    """
    (width, height), = {(c.width, c.height) for c in rig.cameras}
    fw, fh = math.ceil(width / stride), math.ceil(height / stride)
    rows, border = [], []
    for q in range(4):
        centres = grid.voxel_centers(q).reshape(-1, 3)  # (M, 3)
        rq, bq = [], []
        for j, cam in enumerate(rig.cameras):
            uv, depth = cam.project(centres)
            seen = cam.visible(centres, min_depth_m)
            uf, vf = np.floor(uv[:, 0] / stride), np.floor(uv[:, 1] / stride)
            rq.append(np.where(seen, j * fw * fh + vf * fw + uf, -1).astype(np.int64))
            with np.errstate(invalid="ignore"):
                near = lambda a: np.abs(a - np.round(a)) < BORDER_EPS  # noqa: E731
                in_reach = ((depth > min_depth_m - 1e-3) & (uv[:, 0] > -1) & (uv[:, 0] < width + 1)
                            & (uv[:, 1] > -1) & (uv[:, 1] < height + 1))
                bq.append(in_reach & (near(uv[:, 0] / stride) | near(uv[:, 1] / stride) | (np.abs(depth - min_depth_m) < 1e-4)))
        rows.append(np.stack(rq))
        border.append(np.stack(bq))
    return np.stack(rows), np.stack(border), (fw, fh)


def expected_tables(rows: np.ndarray, sentinel: int):
    """Valid rows first in camera order, then sentinels; weights 1 / count: the contract, computed by sorting."""
    valid = rows >= 0  # (4, J, M)
    order = np.argsort(~valid, axis=1, kind="stable")
    packed = np.take_along_axis(np.where(valid, rows, sentinel), order, axis=1)  # (4, J, M)
    count = valid.sum(axis=1)  # (4, M)
    k = max(1, int(count.max()))
    weight = np.where(np.arange(k)[None, :, None] < count[:, None, :], 1.0 / np.maximum(count, 1)[:, None, :], 0.0)
    return packed[:, :k], weight, count


def compare(lut: Lut, rig: Rig, grid: GridSpec, stride: int, min_depth_m: float = 0.0) -> np.ndarray:
    rows, border, (fw, fh) = reference_rows(rig, grid, stride, min_depth_m)
    assert (lut.feature_width, lut.feature_height) == (fw, fh)
    index_ref, weight_ref, count = expected_tables(rows, lut.sentinel)
    shaky = border.any(axis=1)  # (4, M) voxels whose fate hinges on float rounding
    assert shaky.mean() < 1e-2  # ~2 * BORDER_EPS per axis per seeing camera
    assert lut.num_slots == max(1, int(count[~shaky].max()))
    index = lut.index.reshape(4, lut.num_slots, -1)  # (4, K, M)
    weight = lut.weight.reshape(4, lut.num_slots, -1)
    np.testing.assert_array_equal(np.moveaxis(index, 1, 2)[~shaky], np.moveaxis(index_ref, 1, 2)[~shaky])
    np.testing.assert_allclose(np.moveaxis(weight, 1, 2)[~shaky], np.moveaxis(weight_ref, 1, 2)[~shaky], rtol=1e-6)
    return count


# ---- the real rig ------------------------------------------------------------------------------------

def test_real_rig_coarse_grid_matches_direct_projection(rig: Rig, coarse_lut: Lut) -> None:
    lut = coarse_lut
    assert lut.index.shape == (4, lut.num_slots, 16, 64, 64) and lut.index.dtype == np.int32
    assert lut.weight.dtype == np.float32
    assert (lut.feature_width, lut.feature_height) == (400, 225)
    assert lut.sentinel == 6 * 400 * 225
    count = compare(lut, rig, COARSE, 4)
    # voxels nobody sees exist (e.g. low and right beside the car) and hold only the sentinel with weight 0
    unseen = count == 0
    assert unseen.any()
    index = lut.index.reshape(4, lut.num_slots, -1)
    weight = lut.weight.reshape(4, lut.num_slots, -1)
    assert np.all(np.moveaxis(index, 1, 2)[unseen] == lut.sentinel)
    assert np.all(np.moveaxis(weight, 1, 2)[unseen] == 0)
    # two cameras' overlaps exist: both rows present, from two different cameras in rig order, weight 1/2 each
    both = np.argwhere(count == 2)
    assert len(both) > 1000
    q, m = both[len(both) // 2]
    cams = index[q, :2, m] // (lut.feature_width * lut.feature_height)
    assert cams[0] < cams[1]
    np.testing.assert_array_equal(weight[q, :2, m], [0.5, 0.5])


def test_real_rig_overlap_is_front_and_front_right(rig: Rig, coarse_lut: Lut) -> None:
    """A voxel 20 m out at azimuth 61 deg lies where CAM_FRONT ([58, 123]) and CAM_FRONT_RIGHT ([1, 66]) overlap."""
    x, y, z = 20 * math.cos(math.radians(61)), 20 * math.sin(math.radians(61)), 0.25
    g = COARSE
    col = int((x - g.quadrant_origin_m(0)[0]) // g.voxel_xy_m)
    row = int((y - g.quadrant_origin_m(0)[1]) // g.voxel_xy_m)
    zi = int((z - g.z_range_m[0]) // g.voxel_z_m)
    entries = coarse_lut.index[0, :, zi, row, col]
    cells = coarse_lut.feature_width * coarse_lut.feature_height
    assert [rig.names[e // cells] for e in entries if e != coarse_lut.sentinel] == ["CAM_FRONT", "CAM_FRONT_RIGHT"]
    centre = g.voxel_centers(0)[zi, row, col]
    for e in entries:
        cam = rig.cameras[e // cells]
        (u, v), = cam.project(centre[None])[0]
        assert (e % cells) == int(v // 4) * coarse_lut.feature_width + int(u // 4)


def test_real_rig_default_grid_on_random_voxels(rig: Rig) -> None:
    """The paper grid (4 x 16 x 256 x 256, stride 4, 1600 x 900) against a pure-Python check of 3,000 voxels.

    How long the build takes is a benchmark's question, not a test's (timings on a shared machine vary too much to
    assert on)."""
    grid = GridSpec()
    lut = build_lut(rig, grid)
    assert lut.index.shape == (4, 2, 16, 256, 256)  # nuScenes: at most two cameras see one voxel
    rng = np.random.default_rng(0)
    fw, fh = lut.feature_width, lut.feature_height
    checked = 0
    for _ in range(3000):
        q, z, y, x = (int(rng.integers(n)) for n in (4, grid.nz, grid.quadrant_ny, grid.quadrant_nx))
        px, py = (o + (i + 0.5) * grid.voxel_xy_m for o, i in zip(grid.quadrant_origin_m(q), (x, y)))
        pz = grid.z_range_m[0] + (z + 0.5) * grid.voxel_z_m
        expected, shaky = [], False
        for j, cam in enumerate(rig.cameras):
            R, t, K = cam.lidar2cam[:3, :3], cam.lidar2cam[:3, 3], cam.K
            c = [R[i, 0] * px + R[i, 1] * py + R[i, 2] * pz + t[i] for i in range(3)]
            if c[2] <= 0:
                continue
            u = (K[0, 0] * c[0] + K[0, 1] * c[1] + K[0, 2] * c[2]) / c[2]
            v = (K[1, 1] * c[1] + K[1, 2] * c[2]) / c[2]
            shaky |= any(abs(a / 4 - round(a / 4)) < BORDER_EPS for a in (u, v))
            if 0 <= u < cam.width and 0 <= v < cam.height:
                expected.append(j * fw * fh + int(v // 4) * fw + int(u // 4))
        if shaky:
            continue
        checked += 1
        got = lut.index[q, :, z, y, x].tolist()
        assert got == expected + [lut.sentinel] * (2 - len(expected)), (q, z, y, x)
        w = lut.weight[q, :, z, y, x]
        assert w.tolist() == [1.0 / len(expected) if k < len(expected) else 0.0 for k in range(2)] or not expected and not w.any()
    assert checked > 2900


def test_image_size_rescales_intrinsics(rig: Rig) -> None:
    small = build_lut(rig, COARSE, image_size=(800, 450))
    direct = build_lut(rig.resized(800, 450), COARSE)
    np.testing.assert_array_equal(small.index, direct.index)
    assert (small.image_width, small.image_height, small.feature_width, small.feature_height) == (800, 450, 200, 113)
    assert small.calibration_sha256 == rig.sha256()  # the rig it came from, not the resized one


def test_min_depth_drops_near_voxels(rig: Rig) -> None:
    lut = build_lut(rig, COARSE, min_depth_m=5.0)
    compare(lut, rig, COARSE, 4, min_depth_m=5.0)


# ---- random rigs ---------------------------------------------------------------------------------------

def random_rig(seed: int, num_cameras: int = 3, size=(64, 48)) -> Rig:
    """Cameras on a 1 m circle, looking outwards at random yaws with a little pitch and roll."""
    rng = np.random.default_rng(seed)
    cams = []
    for j in range(num_cameras):
        yaw = rng.uniform(0, 2 * np.pi)
        fwd = np.array([np.cos(yaw), np.sin(yaw), rng.uniform(-0.2, 0.2)])
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        cam2lidar = make_transform(np.stack([right, down, fwd], axis=1), [np.cos(yaw), np.sin(yaw), rng.uniform(0, 1)])
        f = rng.uniform(20, 60)
        K = [[f, 0, size[0] / 2 + rng.uniform(-3, 3)], [0, f, size[1] / 2 + rng.uniform(-3, 3)], [0, 0, 1]]
        cams.append(Camera(f"CAM_{j}", K, np.linalg.inv(cam2lidar), size[0], size[1]))
    return Rig(tuple(cams), np.eye(4), np.eye(4))


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("stride", [1, 4, 8])
def test_random_rigs_match_direct_projection(seed: int, stride: int) -> None:
    rig = random_rig(seed, num_cameras=2 + seed % 3, size=(66, 50))  # sizes not divisible by the stride
    lut = build_lut(rig, TINY, feature_stride=stride)
    assert (lut.feature_width, lut.feature_height) == (math.ceil(66 / stride), math.ceil(50 / stride))
    compare(lut, rig, TINY, stride)


def test_no_voxel_seen_gives_one_sentinel_slot() -> None:
    K = [[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]
    up = make_transform(np.eye(3), [0, 0, 10.0])  # 10 m up, optical axis along +z: every voxel is behind it
    rig = Rig((Camera("SKY", K, np.linalg.inv(up), 64, 48),), np.eye(4), np.eye(4))
    lut = build_lut(rig, TINY)
    assert lut.index.shape == (4, 1, 4, 16, 16)
    assert np.all(lut.index == lut.sentinel) and not lut.weight.any()


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        ({"feature_stride": 0}, "feature_stride"),
        ({"feature_stride": 2.5}, "feature_stride"),
        ({"feature_stride": True}, "feature_stride"),
        ({"min_depth_m": -1.0}, "min_depth_m"),
        ({"min_depth_m": float("nan")}, "min_depth_m"),
        ({"image_size": (800,)}, "image_size"),
        ({"image_size": (0, 450)}, "width"),
    ],
)
def test_build_rejects_bad_arguments(rig: Rig, kwargs, pattern) -> None:
    with pytest.raises(ValueError, match=pattern):
        build_lut(rig, TINY, **kwargs)


def test_mixed_image_sizes_need_image_size(rig: Rig) -> None:
    mixed = Rig((rig.cameras[0], rig.cameras[1].resized(800, 450)), rig.lidar2ego, rig.ego2global)
    with pytest.raises(ValueError, match="different image sizes"):
        build_lut(mixed, TINY)
    assert build_lut(mixed, TINY, image_size=(1600, 900)).image_width == 1600


# ---- slicing, files ------------------------------------------------------------------------------------

def test_for_quadrants(coarse_lut: Lut) -> None:
    for qs in ([0], [3], [1, 2], [0, 1, 2, 3]):
        index, weight = coarse_lut.for_quadrants(qs)
        assert index.shape == (len(qs),) + coarse_lut.index.shape[1:]
        assert index.flags.c_contiguous and weight.flags.c_contiguous
        np.testing.assert_array_equal(index, coarse_lut.index[qs])
        np.testing.assert_array_equal(weight, coarse_lut.weight[qs])
    for bad in ([], [1, 0], [0, 0], [4], [-1], [True]):
        with pytest.raises(ValueError, match="quadrants"):
            coarse_lut.for_quadrants(bad)


def test_tables_are_read_only(coarse_lut: Lut) -> None:
    with pytest.raises(ValueError):
        coarse_lut.index[0, 0, 0, 0, 0] = 0


def test_save_load_round_trip(coarse_lut: Lut, rig: Rig, tmp_path) -> None:
    path = tmp_path / "lut.npz"
    coarse_lut.save(path)
    back = Lut.load(path)
    np.testing.assert_array_equal(back.index, coarse_lut.index)
    np.testing.assert_array_equal(back.weight, coarse_lut.weight)
    assert back.meta() == coarse_lut.meta()
    assert back.grid == COARSE and back.camera_names == rig.names and back.calibration_sha256 == rig.sha256()
    with np.load(path) as z:
        assert set(z.files) == {"index", "weight", "meta"}
        meta = json.loads(str(z["meta"]))
    assert meta["grid"] == COARSE.to_dict()
    assert (meta["feature_stride"], meta["image_width"], meta["image_height"]) == (4, 1600, 900)
    assert (meta["feature_width"], meta["feature_height"], meta["sentinel"]) == (400, 225, 540000)
    assert meta["camera_names"] == list(rig.names) and meta["num_slots"] == coarse_lut.num_slots


def _write(path, **arrays) -> None:
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def _tables(lut: Lut):
    return lut.index.copy(), lut.weight.copy(), json.dumps(lut.meta())


@pytest.fixture(scope="module")
def tiny_lut() -> Lut:
    return build_lut(random_rig(0), TINY)


def _corrupt_cases():
    def index_float(i, w, m):
        return {"index": i.astype(np.float32), "weight": w, "meta": np.array(m)}

    def weight_f64(i, w, m):
        return {"index": i, "weight": w.astype(np.float64), "meta": np.array(m)}

    def wrong_shape(i, w, m):
        return {"index": i[:, :, :2], "weight": w[:, :, :2], "meta": np.array(m)}

    def missing_weight(i, w, m):
        return {"index": i, "meta": np.array(m)}

    def bad_json(i, w, m):
        return {"index": i, "weight": w, "meta": np.array("{oops")}

    def meta_not_string(i, w, m):
        return {"index": i, "weight": w, "meta": np.zeros(3)}

    def meta_missing_field(i, w, m):
        d = json.loads(m)
        del d["feature_stride"]
        return {"index": i, "weight": w, "meta": np.array(json.dumps(d))}

    def meta_sentinel_lies(i, w, m):
        d = json.loads(m)
        d["sentinel"] += 1
        return {"index": i, "weight": w, "meta": np.array(json.dumps(d))}

    def meta_bad_grid(i, w, m):
        d = json.loads(m)
        d["grid"]["voxel_xy_m"] = -1
        return {"index": i, "weight": w, "meta": np.array(json.dumps(d))}

    def index_out_of_range(i, w, m):
        i = i.copy()
        i.flat[0] = -5
        return {"index": i, "weight": w, "meta": np.array(m)}

    def weight_on_sentinel(i, w, m):
        w = w.copy()
        w[i == i.max()] = 0.25
        return {"index": i, "weight": w, "meta": np.array(m)}

    def valid_after_sentinel(i, w, m):
        i, w = i[:, ::-1].copy(), w[:, ::-1].copy()  # sentinels first
        return {"index": i, "weight": w, "meta": np.array(m)}

    return [
        (index_float, r"lut.npz: Lut.index: expected an int32 array"),
        (weight_f64, r"Lut.weight: expected a float32 array"),
        (wrong_shape, r"Lut.index: expected shape \(4, K >= 1, 4, 16, 16\)"),
        (missing_weight, r"lut.npz: missing key\(s\) \['weight'\]"),
        (bad_json, r"lut.npz: meta: not valid JSON"),
        (meta_not_string, r"lut.npz: meta: expected a JSON string"),
        (meta_missing_field, r"meta: missing field\(s\) \['feature_stride'\]"),
        (meta_sentinel_lies, r"meta.sentinel: stored"),
        (meta_bad_grid, r"meta.grid"),
        (index_out_of_range, r"Lut.index: entries must lie in"),
        (weight_on_sentinel, r"Lut.weight: must be > 0 exactly on valid slots"),
        (valid_after_sentinel, r"valid slot follows a sentinel"),
    ]


@pytest.mark.parametrize("make, pattern", _corrupt_cases(), ids=[c[0].__name__ for c in _corrupt_cases()])
def test_load_rejects_corrupted_file(tiny_lut: Lut, tmp_path, make, pattern) -> None:
    assert tiny_lut.num_slots >= 2  # the reversal case needs a voxel with a sentinel after a valid slot
    path = tmp_path / "lut.npz"
    _write(path, **make(*_tables(tiny_lut)))
    with pytest.raises(CalibrationError, match=pattern):
        Lut.load(path)


def test_load_rejects_unreadable_files(tiny_lut: Lut, tmp_path) -> None:
    good = tmp_path / "good.npz"
    tiny_lut.save(good)
    data = good.read_bytes()
    cases = {"garbage.npz": b"not a zip file at all", "truncated.npz": data[: len(data) // 2], "empty.npz": b""}
    for name, blob in cases.items():
        (tmp_path / name).write_bytes(blob)
        with pytest.raises(CalibrationError, match=name.replace(".", r"\.")):
            Lut.load(tmp_path / name)
    with pytest.raises(CalibrationError, match="missing.npz"):
        Lut.load(tmp_path / "missing.npz")
    buf = io.BytesIO()  # a pickled object array must not be executed
    np.savez(buf, index=np.array([object()], dtype=object), weight=tiny_lut.weight, meta=np.array("{}"))
    (tmp_path / "pickle.npz").write_bytes(buf.getvalue())
    with pytest.raises(CalibrationError, match="pickle.npz"):
        Lut.load(tmp_path / "pickle.npz")


def test_construction_leaves_caller_arrays_writable(tiny_lut: Lut) -> None:
    index, weight = tiny_lut.index.copy(), tiny_lut.weight.copy()
    lut = Lut(index, weight, TINY, 4, tiny_lut.image_width, tiny_lut.image_height, tiny_lut.camera_names,
              tiny_lut.calibration_sha256)
    assert index.flags.writeable and not lut.index.flags.writeable


def test_the_caller_cannot_change_a_lut_through_its_own_arrays(tiny_lut: Lut) -> None:
    index, weight = tiny_lut.index.copy(), tiny_lut.weight.copy()
    lut = Lut(index, weight, TINY, 4, tiny_lut.image_width, tiny_lut.image_height, tiny_lut.camera_names,
              tiny_lut.calibration_sha256)
    assert not np.shares_memory(lut.index, index) and not np.shares_memory(lut.weight, weight)
    index[...] = lut.sentinel  # what a caller reusing its buffers for the next LUT does
    weight[...] = 0.0
    index.flat[0] = 10**9  # past the sentinel: never validated, it would reach the lifter's Gather
    assert np.array_equal(lut.index, tiny_lut.index) and np.array_equal(lut.weight, tiny_lut.weight)
    assert not lut.index.flags.writeable and not lut.weight.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        lut.index[0, 0, 0, 0, 0] = 0
    # a writable view of another array is copied too: writes through its base must not reach the LUT
    base = tiny_lut.index.copy()
    view = Lut(base[:], tiny_lut.weight.copy(), TINY, 4, tiny_lut.image_width, tiny_lut.image_height,
               tiny_lut.camera_names, tiny_lut.calibration_sha256)
    base[...] = 0
    assert np.array_equal(view.index, tiny_lut.index)


def test_an_owned_read_only_table_is_kept_without_a_copy(tiny_lut: Lut, tmp_path) -> None:
    assert tiny_lut.index.base is None and tiny_lut.weight.base is None  # build_lut hands Lut its own tables
    again = Lut(tiny_lut.index, tiny_lut.weight, TINY, 4, tiny_lut.image_width, tiny_lut.image_height,
                tiny_lut.camera_names, tiny_lut.calibration_sha256)
    assert again.index is tiny_lut.index and again.weight is tiny_lut.weight  # nobody can write them: shared
    ro_view = tiny_lut.index.view()  # read-only, but a view: its base might be writable elsewhere, so copied
    ro_view.setflags(write=False)
    copied = Lut(ro_view, tiny_lut.weight, TINY, 4, tiny_lut.image_width, tiny_lut.image_height,
                 tiny_lut.camera_names, tiny_lut.calibration_sha256)
    assert copied.index is not ro_view and copied.index.base is None and np.array_equal(copied.index, tiny_lut.index)
    tiny_lut.save(tmp_path / "lut.npz")
    loaded = Lut.load(tmp_path / "lut.npz")  # np.load's arrays: one copy, owned and read-only
    assert loaded.index.base is None and not loaded.index.flags.writeable and np.array_equal(loaded.index, tiny_lut.index)
