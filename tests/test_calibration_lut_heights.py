"""Several heights per voxel in the LUT (calibration/lut.py ``heights_per_voxel``) and the coverage measure."""

from __future__ import annotations

import io
import json
import math
from collections import Counter

import numpy as np
import pytest

from streamdet.calibration import Camera, CalibrationError, GridSpec, Lut, Rig, build_lut, make_transform
from streamdet.calibration import lut_build as lut_module
from streamdet.calibration.lut import lut_nbytes
from streamdet.calibration.lut_build import MAX_LUT_BUILD_BYTES, lut_build_nbytes
from streamdet.calibration.lut_coverage import instance_feature_cells, object_coverage

TINY = GridSpec(x_range_m=(-6.4, 6.4), y_range_m=(-6.4, 6.4), z_range_m=(-1.0, 1.0), voxel_xy_m=0.4, voxel_z_m=0.5)
BORDER_EPS = 1e-3


def random_rig(seed: int, num_cameras: int = 3, size=(64, 48)) -> Rig:
    """Cameras on a 1 m circle, looking outwards at random yaws with a little pitch and roll (as test_calibration_lut)."""
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


def _bytes(lut: Lut) -> bytes:
    f = io.BytesIO()
    lut.write_npz(f)
    return f.getvalue()


@pytest.mark.parametrize("seed", range(3))
def test_one_height_is_the_centre_lut_byte_for_byte(seed):
    rig = random_rig(seed)
    assert _bytes(build_lut(rig, TINY, heights_per_voxel=1)) == _bytes(build_lut(rig, TINY))
    assert "heights_per_voxel" not in build_lut(rig, TINY).meta()


def _reference_votes(rig, grid: GridSpec, stride: int, heights: int):
    """Per voxel (4, Z, Yq, Xq) flat: Counter(row -> votes) in float64, and whether any sample is borderline."""
    (width, height), = {(c.width, c.height) for c in rig.cameras}
    fw, fh = math.ceil(width / stride), math.ceil(height / stride)
    offsets = ((np.arange(heights) + 0.5) / heights - 0.5) * grid.voxel_z_m
    votes, border = [], []
    for q in range(4):
        centres = grid.voxel_centers(q).reshape(-1, 3)  # (M, 3)
        vq = [Counter() for _ in range(len(centres))]
        bq = np.zeros(len(centres), bool)
        for dz in offsets:
            pts = centres + [0.0, 0.0, dz]
            for j, cam in enumerate(rig.cameras):
                uv, depth = cam.project(pts)
                seen = cam.visible(pts)
                with np.errstate(invalid="ignore"):
                    near = lambda a: np.abs(a - np.round(a)) < BORDER_EPS  # noqa: E731
                    bq |= (depth > -1e-3) & (near(uv[:, 0] / stride) | near(uv[:, 1] / stride) | (np.abs(depth) < 1e-4))
                rows = j * fw * fh + np.floor(uv[:, 1] / stride) * fw + np.floor(uv[:, 0] / stride)
                for m in np.flatnonzero(seen).tolist():
                    vq[m][int(rows[m])] += 1
        votes += vq
        border.append(bq)
    return votes, np.concatenate(border)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("heights", [2, 3])
@pytest.mark.parametrize("stride", [1, 4])
def test_heights_match_a_naive_vote_count(seed, heights, stride):
    rig = random_rig(seed, size=(66, 50))
    lut = build_lut(rig, TINY, feature_stride=stride, heights_per_voxel=heights)
    assert lut.heights_per_voxel == heights and lut.meta()["heights_per_voxel"] == heights
    votes, border = _reference_votes(rig, TINY, stride, heights)
    index = lut.index.transpose(0, 2, 3, 4, 1).reshape(-1, lut.num_slots)  # (4 * M, K)
    weight = lut.weight.transpose(0, 2, 3, 4, 1).reshape(-1, lut.num_slots)
    checked = 0
    for v, ref in enumerate(votes):
        if border[v]:
            continue
        valid = index[v] != lut.sentinel
        got_rows = index[v][valid].tolist()
        assert got_rows == sorted(ref), v  # distinct rows, row order (= camera order), valid slots first
        total = sum(ref.values())
        np.testing.assert_allclose(weight[v][valid], [ref[r] / total for r in got_rows], rtol=1e-6)
        checked += 1
    assert checked > 0.9 * len(votes)
    assert lut.num_slots >= build_lut(rig, TINY, feature_stride=stride).num_slots



def _all_cameras_at_once(rig, grid: GridSpec, stride: int, size, min_depth_m: float, heights: int):
    """(index, weight) as build_lut made them before it went camera by camera: every (height, camera) hit of every
    camera as one int64 key voxel * (sentinel + 1) + row, one np.unique over all of them, slots ranked by
    searchsorted. The same projection (lut_module._project_camera); only the vote counting differs."""
    width, height = size
    cams = rig.resized(width, height).cameras
    feat_w = math.ceil(width / stride)
    cells = feat_w * math.ceil(height / stride)
    sentinel = len(cams) * cells
    axes = [grid.voxel_center_axes(q) for q in range(4)]
    xs = np.stack([a[0] for a in axes]).astype(np.float32)
    ys = np.stack([a[1] for a in axes]).astype(np.float32)
    per_quadrant = grid.nz * grid.quadrant_ny * grid.quadrant_nx
    keys = []
    for dz in ((np.arange(heights) + 0.5) / heights - 0.5) * grid.voxel_z_m:
        zs = (axes[0][2] + dz).astype(np.float32)
        for j, cam in enumerate(cams):
            voxels, rows = lut_module._project_camera(cam.K @ cam.lidar2cam[:3], xs, ys, zs, width, height, stride,
                                                      feat_w, min_depth_m)  # fmt: skip
            keys.append(voxels.astype(np.int64) * (sentinel + 1) + rows + j * cells)
    key, votes = np.unique(np.concatenate(keys), return_counts=True)
    voxel, row = key // (sentinel + 1), (key % (sentinel + 1)).astype(np.int32)
    total = np.bincount(voxel, weights=votes, minlength=4 * per_quadrant)
    slot = np.arange(len(voxel)) - np.searchsorted(voxel, voxel, side="left")
    k = max(1, int(slot.max()) + 1) if len(slot) else 1
    flat = ((voxel // per_quadrant) * k + slot) * per_quadrant + voxel % per_quadrant
    index = np.full(4 * k * per_quadrant, sentinel, np.int32)
    weight = np.zeros(4 * k * per_quadrant, np.float32)
    index[flat] = row
    weight[flat] = (votes / total[voxel]).astype(np.float32)
    shape = (4, k, grid.nz, grid.quadrant_ny, grid.quadrant_nx)
    return index.reshape(shape), weight.reshape(shape)


@pytest.mark.parametrize("seed, num_cameras", [(0, 1), (1, 3), (2, 6), (5, 9)])
@pytest.mark.parametrize("heights", [2, 3, 5])
@pytest.mark.parametrize("stride, min_depth_m", [(4, 0.0), (1, 1.5), (8, 0.0)])
def test_camera_by_camera_votes_are_the_all_at_once_count_bit_for_bit(seed, num_cameras, heights, stride, min_depth_m):
    rig = random_rig(seed, num_cameras, size=(66, 50))  # 9 cameras on a 1 m circle overlap: K well above 1
    lut = build_lut(rig, TINY, stride, (66, 50), min_depth_m=min_depth_m, heights_per_voxel=heights)
    index, weight = _all_cameras_at_once(rig, TINY, stride, (66, 50), min_depth_m, heights)
    assert lut.index.shape == index.shape and lut.index.tobytes() == index.tobytes()
    assert lut.weight.tobytes() == weight.tobytes()



def test_a_blind_camera_between_seeing_ones_is_counted_bit_for_bit():
    seeing = random_rig(3, 2, size=(66, 50)).cameras
    up = make_transform(np.eye(3), [0, 0, 10.0])  # 10 m up, looking up: sees no voxel at any height
    sky = Camera("SKY", [[30, 0, 33], [0, 30, 25], [0, 0, 1]], np.linalg.inv(up), 66, 50)
    rig = Rig((seeing[0], sky, seeing[1]), np.eye(4), np.eye(4))
    lut = build_lut(rig, TINY, 4, (66, 50), heights_per_voxel=3)
    index, weight = _all_cameras_at_once(rig, TINY, 4, (66, 50), 0.0, 3)
    assert lut.index.tobytes() == index.tobytes() and lut.weight.tobytes() == weight.tobytes()
    assert lut.slots_per_camera()["SKY"] == 0 and lut.num_slots > 1
    alone = build_lut(Rig((sky,), np.eye(4), np.eye(4)), TINY, 4, (66, 50), heights_per_voxel=3)
    assert alone.num_slots == 1 and np.all(alone.index == alone.sentinel) and not alone.weight.any()

def _count_projections(monkeypatch) -> list[int]:
    calls = []
    project = lut_module._project_camera

    def counted(*args, **kwargs):
        calls.append(1)
        return project(*args, **kwargs)

    monkeypatch.setattr(lut_module, "_project_camera", counted)
    return calls


def test_a_build_whose_votes_pass_the_cap_is_refused_before_projecting(monkeypatch):
    rig = random_rig(0)
    calls = _count_projections(monkeypatch)
    assert lut_build_nbytes(TINY, 4) == 8 * 4 * TINY.nx * TINY.ny * TINY.nz
    monkeypatch.setattr(lut_module, "MAX_LUT_BUILD_BYTES", lut_build_nbytes(TINY, 4))
    assert build_lut(rig, TINY, heights_per_voxel=4).heights_per_voxel == 4  # at the cap: built
    calls.clear()
    with pytest.raises(ValueError, match=rf"a LUT build for the 32 x 32 x 4 grid at 5 heights per voxel would hold "
                                         rf"{lut_build_nbytes(TINY, 5)} bytes of votes per camera, over the "
                                         rf"{lut_build_nbytes(TINY, 4)}-byte cap \(MAX_LUT_BUILD_BYTES\)"):  # fmt: skip
        build_lut(rig, TINY, heights_per_voxel=5)
    assert not calls  # refused up front
    # the paper grid's documented reach with the real cap: 32 heights fit, 33 do not
    assert lut_build_nbytes(GridSpec(), 32) <= MAX_LUT_BUILD_BYTES < lut_build_nbytes(GridSpec(), 33)


def test_k_over_the_table_cap_is_refused_after_the_camera_that_needs_it(monkeypatch):
    rig = random_rig(2, 6, size=(66, 50))
    full = build_lut(rig, TINY, heights_per_voxel=3)
    assert full.num_slots > 2
    calls = _count_projections(monkeypatch)
    monkeypatch.setattr("streamdet.calibration.lut.MAX_LUT_BYTES", lut_nbytes(TINY, 1))  # the first camera that needs K >= 2 stops it
    with pytest.raises(ValueError, match=r"with K = [2-9]\d* slots would take"):
        build_lut(rig, TINY, heights_per_voxel=3)
    assert 0 < len(calls) < 3 * len(rig) and len(calls) % 3 == 0  # whole cameras, not every camera, were projected


def test_heights_round_trip_and_bad_values(tmp_path):
    rig = random_rig(1)
    lut = build_lut(rig, TINY, heights_per_voxel=4)
    lut.save(tmp_path / "lut.npz")
    back = Lut.load(tmp_path / "lut.npz")
    assert back.heights_per_voxel == 4 and np.array_equal(back.index, lut.index)
    for bad in (0, -1, 2.5, True, 65):
        with pytest.raises(ValueError, match="heights_per_voxel"):
            build_lut(rig, TINY, heights_per_voxel=bad)
    meta = lut.meta() | {"heights_per_voxel": "4"}
    with open(tmp_path / "bad.npz", "wb") as f:
        np.savez(f, index=lut.index, weight=lut.weight, meta=np.array(json.dumps(meta)))
    with pytest.raises(CalibrationError, match="heights_per_voxel"):
        Lut.load(tmp_path / "bad.npz")


def test_instance_feature_cells_pads_and_blocks():
    inst = np.arange(1, 16, dtype=np.uint16).reshape(3, 5)
    cells = instance_feature_cells(inst, 2, (2, 3))  # (2, 3, 4)
    assert cells.shape == (2, 3, 4)
    assert sorted(cells[0, 0].tolist()) == [1, 2, 6, 7]
    assert sorted(cells[1, 2].tolist()) == [0, 0, 0, 15]


def _hand_lut(rows_for_column: list[int]) -> Lut:
    """One camera of 4 x 4 pixels at stride 2 (2 x 2 feature cells), a 2-voxel-wide grid; column (q 0, 0, 0) reads
    ``rows_for_column``, every other voxel nothing."""
    grid = GridSpec(x_range_m=(-0.8, 0.8), y_range_m=(-0.8, 0.8), z_range_m=(0.0, 1.0), voxel_xy_m=0.4, voxel_z_m=1.0)
    k = max(1, len(rows_for_column))
    sentinel = 4
    index = np.full((4, k, 1, 2, 2), sentinel, np.int32)
    weight = np.zeros((4, k, 1, 2, 2), np.float32)
    for s, r in enumerate(rows_for_column):
        index[0, s, 0, 0, 0] = r
        weight[0, s, 0, 0, 0] = 1.0 / len(rows_for_column)
    return Lut(index=index, weight=weight, grid=grid, feature_stride=2, image_width=4, image_height=4,
               camera_names=("CAM",), calibration_sha256="x")  # fmt: skip


@pytest.mark.parametrize("rows,expect", [([3], True), ([0, 1], False), ([], False)])
def test_object_coverage_reads_the_own_column(rows, expect):
    mask = np.zeros((4, 4), np.uint16)
    mask[3, 3] = 7  # object 7 in feature cell (1, 1) = row 3
    mask[0, 0] = 9  # object 9 elsewhere, hidden from no one
    lut = _hand_lut(rows)
    cov = object_coverage(lut, [mask], np.array([[0.1, 0.1], [0.1, 0.1], [100.0, 0.0]]), np.array([7, 5, 9]))
    assert cov.covered.tolist() == [expect, False, False]
    assert cov.visible.tolist() == [True, False, False]  # 5 has no pixel; the third lies outside the grid
    with pytest.raises(ValueError, match="instance masks"):
        object_coverage(lut, [], np.zeros((0, 2)), np.zeros(0))
    empty = object_coverage(lut, [mask], np.zeros((0, 2)), np.zeros(0, np.int64))
    assert empty.covered.shape == (0,)
