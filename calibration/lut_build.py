"""Building the projection LUT (``calibration/lut.py`` defines it and its format) from a camera rig: every voxel
centre, or ``heights_per_voxel`` heights of it, projected into every camera, camera by camera, with the memory of
each step bounded before it is allocated.
"""

from __future__ import annotations

import math

import numpy as np

from streamdet.calibration.camera import MAX_IMAGE_PX, CalibrationError, Rig, as_image_px
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut import Lut, check_heights_per_voxel, check_min_depth, check_lut_bytes
from streamdet.core.json_input import short_repr
from streamdet.core.sectors import NUM_QUADRANTS


# At most this many cameras in one LUT build: the centre-sampled build counts the cameras seeing a voxel in a uint8.
MAX_LUT_CAMERAS = 255
# What a build with heights_per_voxel > 1 may take for one camera's vote table (`lut_build_nbytes`): an int32 row per
# (voxel, height) and the masks found from it. Refused over this before anything is projected, so a manifest's grid
# and heights cannot drive a build into gigabytes before the tables' own cap (MAX_LUT_BYTES) refuses it. The paper
# grid (16 x 512 x 512 voxels) fits 32 heights per voxel. It bounds the vote table only: the arrays of distinct
# (voxel, feature row) runs built from it take up to 6 int64 a run, and there are as many runs as distinct pairs
# (one a voxel where its heights meet one feature cell, the usual case; one a vote at worst).
MAX_LUT_BUILD_BYTES = 1 << 30
_LUT_BUILD_BYTES_PER_VOTE = 8  # the int32 row, its hit / run-start masks and the comparison between them


def build_lut(
    rig: Rig,
    grid: GridSpec = GridSpec(),
    feature_stride: int = 4,
    image_size: tuple[int, int] | None = None,
    min_depth_m: float = 0.0,
    heights_per_voxel: int = 1,
) -> Lut:
    """Project every voxel centre of the four quadrant volumes into every camera of ``rig``.

    ``image_size`` (W, H) is the size of the images fed to the encoder, in whole pixels; the rig's K are rescaled
    to it. Without it, every camera must share one size. Math is float32 and separable in x, y, z, camera by camera.
    ``heights_per_voxel`` > 1 samples each voxel at that many heights (module doc). Refused up front with a
    ValueError: a ``rig`` that is no Rig, more than `MAX_LUT_CAMERAS` cameras, a feature table with rows past int32,
    and, with heights, votes of one camera over `MAX_LUT_BUILD_BYTES` (`lut_build_nbytes`). A LUT whose tables would
    exceed `MAX_LUT_BYTES` (what a lut.npz may declare, so no reader would load it) is refused before they are
    allocated, as soon as the cameras projected so far need more slots than fit: ValueError.
    """
    try:
        check_heights_per_voxel(heights_per_voxel)
    except CalibrationError as e:
        raise ValueError(str(e)) from None
    if not isinstance(rig, Rig):  # a parsed calibration.json dict is the likely mistake
        raise ValueError(f"rig must be a Rig (Rig.from_calibration_json for a dict or file), got {type(rig).__name__}")
    if not isinstance(grid, GridSpec):
        raise ValueError(f"grid must be a GridSpec, got {type(grid).__name__}")
    check_lut_bytes(grid, 1)  # K >= 1: refuse a grid too big for any LUT before projecting anything
    if heights_per_voxel > 1:
        check_lut_build_bytes(grid, int(heights_per_voxel))
        return _build_lut_heights(rig, grid, feature_stride, image_size, min_depth_m, int(heights_per_voxel))
    width, height, cams_rig = _image_geometry(rig, feature_stride, image_size, min_depth_m)
    feat_w = math.ceil(width / feature_stride)
    feat_h = math.ceil(height / feature_stride)
    cells = feat_w * feat_h
    sentinel = len(rig.cameras) * cells

    xs, ys, zs = _quadrant_axes(grid)
    per_quadrant = grid.nz * grid.quadrant_ny * grid.quadrant_nx  # M voxels in one quadrant volume
    num_voxels = NUM_QUADRANTS * per_quadrant

    seen_voxels: list[np.ndarray] = []  # per camera: flat voxel index into (4, Z, Yq, Xq)
    seen_rows: list[np.ndarray] = []  # per camera: feature-table row of each of those voxels
    counts = np.zeros(num_voxels, dtype=np.uint8)  # at most MAX_LUT_CAMERAS (_image_geometry)
    num_slots = 1
    for j, cam in enumerate(cams_rig.cameras):
        voxels, rows = _project_camera(cam.K @ cam.lidar2cam[:3], xs, ys, zs, width, height, feature_stride,
                                       feat_w, float(min_depth_m))
        counts[voxels] += 1  # voxels are unique within one camera
        if len(voxels):  # K so far: refused here, not after every camera's hits are held
            num_slots = max(num_slots, int(counts[voxels].max()))
            check_lut_bytes(grid, num_slots)
        seen_voxels.append(voxels)
        seen_rows.append(rows + np.int32(j * cells))

    check_lut_bytes(grid, num_slots)
    shape = (NUM_QUADRANTS, num_slots, grid.nz, grid.quadrant_ny, grid.quadrant_nx)  # (4, K, Z, Yq, Xq)
    index = np.full(shape, sentinel, dtype=np.int32)
    flat = index.reshape(-1)  # (4, K, M), a view: writes land in index
    slot = np.zeros(num_voxels, dtype=np.int64)
    for voxels, rows in zip(seen_voxels, seen_rows):
        # flat voxel v = q * M + r lands at (q, slot, r) of (4, K, M): v + (q * (K - 1) + slot) * M
        q = voxels // per_quadrant
        flat[voxels + (q * (num_slots - 1) + slot[voxels]) * per_quadrant] = rows
        slot[voxels] += 1
    del flat

    counts = counts.reshape(NUM_QUADRANTS, 1, grid.nz, grid.quadrant_ny, grid.quadrant_nx)  # (4, 1, Z, Yq, Xq)
    with np.errstate(divide="ignore"):
        inv = np.where(counts > 0, np.float32(1.0) / counts.astype(np.float32), np.float32(0.0))
    slots = np.arange(num_slots, dtype=np.uint8).reshape(1, num_slots, 1, 1, 1)
    weight = np.where(slots < counts, inv, np.float32(0.0)).astype(np.float32)  # (4, K, Z, Yq, Xq)

    return Lut(
        index=_sealed(index),
        weight=_sealed(weight),
        grid=grid,
        feature_stride=int(feature_stride),
        image_width=width,
        image_height=height,
        camera_names=rig.names,
        calibration_sha256=rig.sha256(),
        min_depth_m=float(min_depth_m),
    )


def lut_build_nbytes(grid: GridSpec, heights_per_voxel: int) -> int:
    """Bytes a build with ``heights_per_voxel`` holds for one camera's votes: every voxel at every height."""
    return _LUT_BUILD_BYTES_PER_VOTE * int(heights_per_voxel) * grid.nz * grid.ny * grid.nx


def check_lut_build_bytes(grid: GridSpec, heights_per_voxel: int) -> None:
    """ValueError (naming the grid, the heights and the size) when a build's votes would exceed `MAX_LUT_BUILD_BYTES`."""
    nbytes = lut_build_nbytes(grid, heights_per_voxel)
    if nbytes > MAX_LUT_BUILD_BYTES:
        raise ValueError(
            f"a LUT build for the {grid.nx} x {grid.ny} x {grid.nz} grid at {heights_per_voxel} heights per voxel "
            f"would hold {nbytes} bytes of votes per camera, over the {MAX_LUT_BUILD_BYTES}-byte cap "
            "(MAX_LUT_BUILD_BYTES): fewer heights per voxel or a coarser grid"
        )  # fmt: skip


def _sealed(arr: np.ndarray) -> np.ndarray:
    """``arr`` (a table this module just allocated, which it owns) made read-only, so Lut keeps it uncopied."""
    arr.setflags(write=False)
    return arr


def _quadrant_axes(grid: GridSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """float32 voxel-centre axes: xs (4, Xq), ys (4, Yq), zs (Z,) (the same in every quadrant)."""
    axes = [grid.voxel_center_axes(q) for q in range(NUM_QUADRANTS)]
    xs = np.stack([a[0] for a in axes]).astype(np.float32)
    ys = np.stack([a[1] for a in axes]).astype(np.float32)
    return xs, ys, axes[0][2].astype(np.float32)


def _image_geometry(rig: Rig, feature_stride: int, image_size: tuple[int, int] | None, min_depth_m: float) -> tuple[int, int, Rig]:
    """(width, height, the rig at that image size) of a LUT build, its arguments checked (ValueError quotes them)."""
    stride_ok = isinstance(feature_stride, (int, np.integer)) and not isinstance(feature_stride, bool)
    if not (stride_ok and 0 < feature_stride <= MAX_IMAGE_PX):  # a stride past any image side is no feature map
        raise ValueError(f"feature_stride must be a positive integer up to {MAX_IMAGE_PX}, got {short_repr(feature_stride)}")
    try:
        check_min_depth(min_depth_m)  # not math.isfinite alone: it raises OverflowError for a huge int
    except CalibrationError:
        raise ValueError(f"min_depth_m must be a finite number >= 0, got {short_repr(min_depth_m)}") from None
    if len(rig.cameras) > MAX_LUT_CAMERAS:  # before the uint8 count of cameras per voxel could wrap
        raise ValueError(f"a LUT takes at most {MAX_LUT_CAMERAS} cameras (MAX_LUT_CAMERAS), the rig has {len(rig.cameras)}")
    if image_size is None:
        sizes = {(c.width, c.height) for c in rig.cameras}
        if len(sizes) != 1:
            raise ValueError(f"cameras have different image sizes {sorted(sizes)}; pass image_size=(W, H)")
        (width, height), cams_rig = sizes.pop(), rig
    else:
        try:
            if isinstance(image_size, (str, bytes)) or len(image_size) != 2:
                raise ValueError
        except (TypeError, ValueError):  # not a pair
            raise ValueError(f"image_size must be (W, H), got {short_repr(image_size)}") from None
        try:  # whole pixels only: int() would quietly build an 800.9 x 450.9 request for 800 x 450 images
            width, height = as_image_px(image_size[0], "image_size width"), as_image_px(image_size[1], "image_size height")
        except CalibrationError as e:
            raise ValueError(str(e)) from None
        cams_rig = rig.resized(width, height)
    # the feature table's rows, its sentinel last, are int32 (the lifter's Gather indices)
    rows = len(rig.cameras) * math.ceil(width / feature_stride) * math.ceil(height / feature_stride)
    if rows > np.iinfo(np.int32).max:
        raise ValueError(
            f"{len(rig.cameras)} cameras of {width}x{height} images at feature stride {feature_stride} make a feature "
            f"table of {rows} rows, past the int32 row indices of a LUT ({np.iinfo(np.int32).max})"
        )  # fmt: skip
    return width, height, cams_rig


def _build_lut_heights(rig: Rig, grid: GridSpec, feature_stride: int, image_size: tuple[int, int] | None,
                       min_depth_m: float, heights: int) -> Lut:  # fmt: skip
    """``build_lut`` with ``heights`` samples per voxel: every (height, camera) hit votes for its feature row.

    One camera at a time: its row at every height of every voxel goes into a (voxels, heights) table (the sentinel
    where the height is not seen, which sorts after every row), sorted along the heights, so a voxel's distinct rows
    are the runs of equal entries and their votes the runs' lengths. Camera j's rows all lie below camera j + 1's, so
    a voxel's slots taken camera after camera are in row order, as the module doc says. This holds one camera's
    votes at a time (`lut_build_nbytes`), not every camera's, and K is checked after each camera."""
    width, height, cams_rig = _image_geometry(rig, feature_stride, image_size, min_depth_m)
    feat_w = math.ceil(width / feature_stride)
    cells = feat_w * math.ceil(height / feature_stride)
    sentinel = len(rig.cameras) * cells
    xs, ys, _ = _quadrant_axes(grid)
    centres = grid.voxel_center_axes(0)[2]  # (Z,) float64, the same in every quadrant
    offsets = ((np.arange(heights) + 0.5) / heights - 0.5) * grid.voxel_z_m  # (H,) from the voxel centre, m
    per_quadrant = grid.nz * grid.quadrant_ny * grid.quadrant_nx
    num_voxels = NUM_QUADRANTS * per_quadrant
    taken = np.zeros(num_voxels, dtype=np.int32)  # distinct rows of the cameras so far: the next camera's first slot
    total = np.zeros(num_voxels, dtype=np.int64)  # votes per voxel, every camera
    num_slots = 1
    runs = []  # per camera: (voxel, slot, row, votes) of each distinct row of a voxel
    for j, cam in enumerate(cams_rig.cameras):
        P = cam.K @ cam.lidar2cam[:3]
        table = np.full((num_voxels, heights), sentinel, dtype=np.int32)
        for h, dz in enumerate(offsets):
            voxels, rows = _project_camera(P, xs, ys, (centres + dz).astype(np.float32), width, height, feature_stride,
                                           feat_w, float(min_depth_m))  # fmt: skip
            table[voxels, h] = rows + np.int32(j * cells)
        table.sort(axis=1)
        hit = table != sentinel
        start = hit.copy()  # the first entry of each run of equal rows
        start[:, 1:] &= table[:, 1:] != table[:, :-1]
        count = start.sum(axis=1, dtype=np.int32)  # this camera's distinct rows per voxel
        hits = hit.sum(axis=1, dtype=np.int32)  # and its votes
        del hit
        num_slots = max(num_slots, int((taken + count).max()))
        check_lut_bytes(grid, num_slots)  # before this camera's runs are taken out
        pos = np.flatnonzero(start)  # flat (voxel, height) of each run's first entry, by voxel then row
        del start
        voxel, at = np.divmod(pos, heights)
        row = table.reshape(-1)[pos]
        del table, pos
        n = len(voxel)
        # a run ends where the voxel's next run starts, else at the voxel's last vote (its sentinels sort after it)
        same = np.zeros(n, dtype=bool)
        same[:-1] = voxel[1:] == voxel[:-1]
        votes = np.where(same, np.append(at[1:], 0), hits[voxel]) - at
        first = np.maximum.accumulate(np.where(at == 0, np.arange(n), 0))  # the voxel's first run (its height 0)
        slot = taken[voxel] + (np.arange(n) - first)
        taken += count
        total += hits
        runs.append((voxel.astype(np.int32), slot.astype(np.int32), row, votes.astype(np.uint8)))  # votes <= 64

    check_lut_bytes(grid, num_slots)
    shape = (NUM_QUADRANTS, num_slots, grid.nz, grid.quadrant_ny, grid.quadrant_nx)  # (4, K, Z, Yq, Xq)
    index = np.full(shape, sentinel, dtype=np.int32)
    weight = np.zeros(shape, dtype=np.float32)
    index_flat, weight_flat = index.reshape(-1), weight.reshape(-1)  # (4, K, M) views: writes land in the tables
    while runs:  # a camera's runs are freed once written
        voxel, slot, row, votes = runs.pop(0)
        q, r = np.divmod(voxel.astype(np.int64), per_quadrant)
        flat = (q * num_slots + slot) * per_quadrant + r  # into (4, K, M)
        index_flat[flat] = row
        weight_flat[flat] = (votes / total[voxel]).astype(np.float32)  # the float64 share of the votes, as float32
    del index_flat, weight_flat
    return Lut(index=_sealed(index), weight=_sealed(weight), grid=grid, feature_stride=int(feature_stride),
               image_width=width, image_height=height, camera_names=rig.names, calibration_sha256=rig.sha256(),
               min_depth_m=float(min_depth_m), heights_per_voxel=heights)  # fmt: skip


def _project_camera(
    P: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    zs: np.ndarray,
    width: int,
    height: int,
    stride: int,
    feat_w: int,
    min_depth_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Flat voxel indices (into (4, Z, Yq, Xq)) seen by one camera, and their in-camera feature rows (int32).

    ``P`` (3, 4) = K [R | t]. Homogeneous pixels are separable: h = P_x x + P_y y + (P_z z + P_1), so the
    (4, Z, Yq, Xq) volume is one broadcast add of a (4, 1, Yq, Xq) plane and a (Z,) column per component.
    """
    P = P.astype(np.float32)
    zcol = (P[:, 2:3] * zs[None, :] + P[:, 3:4])  # (3, Z)

    def component(c: int) -> np.ndarray:
        plane = P[c, 0] * xs[:, None, :] + P[c, 1] * ys[:, :, None]  # (4, Yq, Xq)
        return plane[:, None, :, :] + zcol[c][None, :, None, None]  # (4, Z, Yq, Xq)

    depth = component(2)
    hu = component(0)
    # Cheap candidate test without division (depth > 0 there, so the inequalities keep their direction);
    # the slack lets the exact float32 test below decide the borderline voxels.
    cand = depth > np.float32(min_depth_m)
    cand &= hu >= -1e-3 * depth
    cand &= hu <= np.float32(width + 1e-3) * depth
    idx = np.flatnonzero(cand)
    del cand
    hv = component(1).ravel()[idx]
    d = depth.ravel()[idx]
    u = hu.ravel()[idx] / d
    v = hv / d
    ok = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    idx, u, v = idx[ok], u[ok], v[ok]
    uf = np.floor(u / np.float32(stride)).astype(np.int32)
    vf = np.floor(v / np.float32(stride)).astype(np.int32)
    return idx, vf * np.int32(feat_w) + uf
