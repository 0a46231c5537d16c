"""The projection look-up table: which feature-map cell of which camera each image-volume voxel reads.

Format (docs/architecture.md, "Projection LUT"): for the four quadrant volumes (Z, Yq, Xq) and J cameras with
stride-s feature maps (Hf, Wf) = (ceil(H / s), ceil(W / s)):

- ``index`` (4, K, Z, Yq, Xq) int32: row ``j * Hf * Wf + v_f * Wf + u_f`` of the flattened feature table
  ``(J * Hf * Wf + 1, C)``; the sentinel ``J * Hf * Wf`` names its all-zero last row.
- ``weight`` (4, K, Z, Yq, Xq) float32: 1 / (number of cameras seeing the voxel) on valid slots, 0 on sentinels.

A voxel centre p is seen by camera j if ``z_c > min_depth_m`` and ``0 <= u < W``, ``0 <= v < H`` with
``(u z_c, v z_c, z_c) = K_j (R_j p + t_j)``; then ``u_f = floor(u / s)``, ``v_f = floor(v / s)``. Valid slots come
first, in camera order. K is the largest number of cameras seeing one voxel (at least 1).

``heights_per_voxel`` H > 1 samples each voxel at H heights, ``z_lo + (i + 1/2) dz / H``, instead of its centre
alone: a tall voxel (the small preset's are 2 m) then also reads the pixels of an object shorter than its centre
height. Every (height, camera) hit is one vote; a voxel's slots are its distinct feature rows (in row order,
which is camera order), each weighted by its share of the voxel's votes, so the lifter averages the heights. K is
then the largest number of distinct rows of one voxel. H is stored in the file's meta (absent = 1, the files
written before it) so whoever rebuilds the LUT for a new calibration builds the same kind.

The LUT is rebuilt in numpy whenever the calibration changes; the ONNX lifter takes it as an input, so a new
calibration never needs a re-export.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import zipfile
import zlib
from dataclasses import dataclass
from typing import BinaryIO, Sequence

import numpy as np

from streamdet.calibration.camera import MAX_IMAGE_PX, CalibrationError, Rig, as_image_px, check_camera_name
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut_file import (  # noqa: F401  (re-exported)
    MAX_HEIGHTS_PER_VOXEL, MAX_LUT_BYTES, MAX_LUT_FILE_BYTES, LutFileError, check_lut_archive,
)
from streamdet.core.file_input import InputFileError, read_regular_file
from streamdet.core.file_output import atomic_write_file
from streamdet.core.json_input import short_repr
from streamdet.core.sectors import NUM_QUADRANTS, check_quadrants

ASPECT_TOLERANCE = 0.005  # relative; 1600x900 -> 800x450 is exact, 1920x1080 -> 800x450 too
LUT_FORMAT = "streamdet-lut"
LUT_VERSION = 1
_META_KEYS = (
    "format", "version", "grid", "feature_stride", "image_width", "image_height", "feature_width",
    "feature_height", "camera_names", "calibration_sha256", "sentinel", "num_slots", "min_depth_m",
)
# What Rig.sha256() writes (hashlib's hexdigest); every lut.npz this project wrote holds one.
_SHA256_HEX = re.compile(r"[0-9a-f]{64}")


class BlindCameraWarning(UserWarning):
    """A camera of the rig sees no voxel of the grid (placed far away, or facing away from it): its images are
    encoded but never reach the BEV. Usually a wrong calibration; accepted, since a rig may carry such a camera."""


def check_rig_fits(rig: Rig, camera_names: Sequence[str], width: int, height: int) -> None:
    """CalibrationError unless ``rig`` names ``camera_names`` in that order and every camera has the aspect ratio of
    ``width`` x ``height`` images (its intrinsics are scaled to that size, as the images are resized: another
    aspect would distort them)."""
    if not isinstance(rig, Rig):
        raise CalibrationError(f"expected a Rig, got {type(rig).__name__}")
    width, height = as_image_px(width, "image width"), as_image_px(height, "image height")  # a huge int overflows the ratio
    if tuple(rig.names) != tuple(camera_names):
        raise CalibrationError(
            f"calibration cameras {list(rig.names)} do not match the export's {list(camera_names)} "
            "(same names in the same order: it is the order of the images fed to image_encoder)"
        )
    want = width / height
    for cam in rig.cameras:
        have = cam.width / cam.height
        if abs(have / want - 1.0) > ASPECT_TOLERANCE:
            raise CalibrationError(
                f"calibration camera {cam.name} is {cam.width}x{cam.height} (aspect {have:.4f}) but the export takes "
                f"{width}x{height} images (aspect {want:.4f}): resizing would distort them"
            )


def blind_cameras(lut: "Lut") -> list[tuple[str, int]]:
    """(name, number of LUT slots that read it) of every camera no voxel reads: each is 0 (BlindCameraWarning)."""
    slots = lut.slots_per_camera()
    return [(name, n) for name, n in slots.items() if n == 0]


class CameraMovedWarning(UserWarning):
    """A recalibrated camera sees another part of the grid than before (turned around, swapped with another, a
    sign error in its extrinsics): accepted, since a camera can be remounted, but almost always a wrong calibration."""


MOVED_CAMERA_IOU = 0.5  # a camera whose seen voxels overlap its previous ones less than this has moved a lot


def moved_cameras(old: "Lut", new: "Lut", min_iou: float = MOVED_CAMERA_IOU) -> list[tuple[str, float]]:
    """(name, IoU) of the cameras whose seen voxels in ``new`` overlap those in ``old`` by less than ``min_iou``.

    A recalibration moves a camera by centimetres and a fraction of a degree; a camera that now sees another part
    of the grid (turned around, swapped with another, a sign error in the extrinsics) is almost always a wrong
    calibration. Empty when the two LUTs do not describe the same cameras on the same grid (nothing to compare).
    A camera that now sees no voxel at all is left out: `blind_cameras` reports it, and it has not turned around.
    """
    if old.camera_names != new.camera_names or old.grid != new.grid:
        return []
    moved = []
    for name, was, now in zip(new.camera_names, old.camera_coverage(), new.camera_coverage()):
        if not now.any():  # blind now (BlindCameraWarning): one cause, one warning
            continue
        union = int(np.count_nonzero(was | now))
        iou = 1.0 if union == 0 else int(np.count_nonzero(was & now)) / union
        if iou < min_iou:
            moved.append((name, iou))
    return moved


@dataclass(frozen=True, eq=False)
class Lut:
    """A validated projection LUT and the metadata that says which rig, grid and image size it was built for."""

    index: np.ndarray  # (4, K, Z, Yq, Xq) int32 rows of the flattened feature table; sentinel = J * Hf * Wf
    weight: np.ndarray  # (4, K, Z, Yq, Xq) float32, 1 / count on valid slots, 0 on sentinel slots
    grid: GridSpec
    feature_stride: int  # image pixels per feature cell (4: ResNet stem + FPN P2)
    image_width: int  # image size the cameras' K refer to
    image_height: int
    camera_names: tuple[str, ...]  # J axis order of the feature table
    calibration_sha256: str  # Rig.sha256() of the rig the LUT was built from (before any resize)
    min_depth_m: float = 0.0  # voxels at camera depth <= this were left out
    heights_per_voxel: int = 1  # H heights sampled per voxel (module doc); 1 = the voxel centre

    def __post_init__(self) -> None:
        object.__setattr__(self, "camera_names", _check_camera_names(self.camera_names))
        check_heights_per_voxel(self.heights_per_voxel)
        object.__setattr__(self, "heights_per_voxel", int(self.heights_per_voxel))
        for name in ("feature_stride", "image_width", "image_height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise CalibrationError(f"Lut.{name}: expected a positive integer, got {short_repr(value)}")
            if name != "feature_stride" and value > MAX_IMAGE_PX:
                raise CalibrationError(f"Lut.{name}: expected at most {MAX_IMAGE_PX} pixels, got {short_repr(value)}")
            object.__setattr__(self, name, int(value))
        object.__setattr__(self, "min_depth_m", check_min_depth(self.min_depth_m))
        if not isinstance(self.calibration_sha256, str):
            raise CalibrationError(f"Lut.calibration_sha256: expected a string, got {short_repr(self.calibration_sha256)}")
        if not isinstance(self.grid, GridSpec):
            raise CalibrationError(f"Lut.grid: expected a GridSpec, got {type(self.grid).__name__}")
        for name in ("index", "weight"):
            value = getattr(self, name)
            if isinstance(value, np.ndarray):  # owned before it is checked: what was validated is what is kept
                object.__setattr__(self, name, _owned_readonly(value))
        _validate_tables(self.index, self.weight, self.grid, self.sentinel, "Lut")

    # ---- derived metadata ------------------------------------------------------------------------
    @property
    def feature_width(self) -> int:
        return math.ceil(self.image_width / self.feature_stride)

    @property
    def feature_height(self) -> int:
        return math.ceil(self.image_height / self.feature_stride)

    @property
    def num_cameras(self) -> int:
        return len(self.camera_names)

    @property
    def num_slots(self) -> int:
        """K: the largest number of cameras that see one voxel."""
        return int(self.index.shape[1])

    @property
    def sentinel(self) -> int:
        """Index of the all-zero row appended to the (J * Hf * Wf, C) feature table."""
        return self.num_cameras * self.feature_height * self.feature_width

    def camera_coverage(self) -> np.ndarray:
        """(J, 4, Z, Yq, Xq) bool: which voxels each camera is seen from."""
        cells = self.feature_height * self.feature_width
        camera = np.where(self.index == self.sentinel, -1, self.index // cells)  # (4, K, Z, Yq, Xq)
        return np.stack([(camera == j).any(axis=1) for j in range(self.num_cameras)])

    def slots_per_camera(self) -> dict[str, int]:
        """Valid LUT slots reading each camera (over all quadrants, voxels and slots), by camera name."""
        cells = self.feature_height * self.feature_width
        rows = self.index[self.index != self.sentinel]
        counts = np.bincount(rows // cells, minlength=self.num_cameras)
        return {name: int(counts[j]) for j, name in enumerate(self.camera_names)}

    def meta(self) -> dict:
        return {
            "format": LUT_FORMAT,
            "version": LUT_VERSION,
            "grid": self.grid.to_dict(),
            "feature_stride": self.feature_stride,
            "image_width": self.image_width,
            "image_height": self.image_height,
            "feature_width": self.feature_width,
            "feature_height": self.feature_height,
            "camera_names": list(self.camera_names),
            "calibration_sha256": self.calibration_sha256,
            "sentinel": self.sentinel,
            "num_slots": self.num_slots,
            "min_depth_m": self.min_depth_m,
            # written only when not the default: a centre-sampled LUT keeps the exact bytes it always had
            **({"heights_per_voxel": self.heights_per_voxel} if self.heights_per_voxel != 1 else {}),
        }

    # ---- slicing ---------------------------------------------------------------------------------
    def for_quadrants(self, quadrants: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """(index, weight), each (Q, K, Z, Yq, Xq) contiguous, for the increasing quadrant list of one slice."""
        sel = list(check_quadrants(quadrants))
        return np.ascontiguousarray(self.index[sel]), np.ascontiguousarray(self.weight[sel])

    # ---- files -----------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write an uncompressed .npz (index, weight, meta as a JSON string) atomically: a hidden temp file beside
        ``path``, then a rename (which replaces a symlink at ``path`` rather than writing through it). The file gets
        the permissions of a plain ``open()`` (0666 minus the umask); a failure leaves no temp file."""
        atomic_write_file(path, self.write_npz)

    def write_npz(self, f: BinaryIO) -> None:
        """The .npz bytes of ``save`` into an open binary file (for writers that make the file themselves)."""
        np.savez(f, index=self.index, weight=self.weight, meta=np.array(json.dumps(self.meta(), sort_keys=True)))

    @classmethod
    def load(cls, path: str | os.PathLike, grid: GridSpec | None = None, num_cameras: int | None = None,
             data: bytes | None = None) -> "Lut":  # fmt: skip
        """Read and validate a LUT written by ``save``; any defect raises CalibrationError naming file and key.

        Before any array is read, the archive's members must fit a LUT of ``grid`` and ``num_cameras`` (the
        manifest's; None: as the file's meta says), else `LutFileError` (`calibration/lut_file.py`). ``data``: the
        file's bytes, already read (and hashed) by the caller; then ``path`` only names it and is not opened, so
        what was checked is what is loaded."""
        src = os.path.basename(os.fspath(path))
        if data is None:  # read once, bounded: a FIFO (it would block) or a device is refused, never opened twice
            try:
                data = read_regular_file(path, MAX_LUT_FILE_BYTES)
            except InputFileError as e:
                raise LutFileError(f"{src}: not a readable LUT .npz: {e.reason}") from None
        check_lut_archive(path, grid, num_cameras, data)
        try:
            with np.load(io.BytesIO(data) if data is not None else path, allow_pickle=False) as z:
                missing = [k for k in ("index", "weight", "meta") if k not in z.files]
                if missing:
                    raise CalibrationError(f"{src}: missing key(s) {missing}; found {sorted(z.files)}")
                index, weight, meta_arr = z["index"], z["weight"], z["meta"]
        except CalibrationError:
            raise
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, KeyError, NotImplementedError, RuntimeError) as e:
            raise LutFileError(f"{src}: not a readable LUT .npz: {e}") from None
        except (AttributeError, TypeError):  # np.load gave a plain array (an .npy file), not an archive
            raise CalibrationError(f"{src}: not a readable LUT .npz: a single array, not an archive") from None
        if meta_arr.shape != () or meta_arr.dtype.kind != "U":
            raise CalibrationError(f"{src}: meta: expected a JSON string, got dtype {meta_arr.dtype} shape {meta_arr.shape}")
        try:
            meta = json.loads(str(meta_arr))
        except RecursionError:
            raise CalibrationError(f"{src}: meta: nests too deeply") from None
        except ValueError as e:  # JSONDecodeError, or an integer literal past Python's 4300-digit limit
            raise CalibrationError(f"{src}: meta: not valid JSON: {e}") from None
        if not isinstance(meta, dict):
            raise CalibrationError(f"{src}: meta: expected a JSON object, got {type(meta).__name__}")
        missing = [k for k in _META_KEYS if k not in meta]
        if missing:
            raise CalibrationError(f"{src}: meta: missing field(s) {missing}")
        version = meta["version"]  # an int: True and 1.0 equal 1 but are no version this project wrote
        if meta["format"] != LUT_FORMAT or type(version) is not int or version != LUT_VERSION:
            raise CalibrationError(
                f"{src}: meta.format/version: expected {LUT_FORMAT!r} v{LUT_VERSION}, got {meta['format']!r} v{meta['version']!r}"
            )
        try:
            grid = GridSpec.from_dict(meta["grid"])
        except (KeyError, TypeError, ValueError) as e:
            raise CalibrationError(f"{src}: meta.grid: {e}") from None
        sha = meta["calibration_sha256"]
        if not (isinstance(sha, str) and _SHA256_HEX.fullmatch(sha)):
            raise CalibrationError(f"{src}: meta.calibration_sha256: expected 64 lowercase hex digits (Rig.sha256()), got {short_repr(sha)}")
        _check_stored_geometry(src, meta)
        try:
            lut = cls(
                index=index,  # np.load's own arrays: __post_init__ takes its read-only copy, the only one
                weight=weight,
                grid=grid,
                feature_stride=meta["feature_stride"],
                image_width=meta["image_width"],
                image_height=meta["image_height"],
                camera_names=meta["camera_names"],  # as stored: __post_init__ refuses a string or a number here
                calibration_sha256=sha,
                min_depth_m=meta["min_depth_m"],
                heights_per_voxel=meta.get("heights_per_voxel", 1),
            )
        except CalibrationError as e:
            raise CalibrationError(f"{src}: {e}") from None
        except (TypeError, ValueError) as e:  # a meta field of the wrong type (camera_names 3, min_depth_m "x")
            raise CalibrationError(f"{src}: meta: a field has the wrong type: {e}") from None
        # Derived numbers are stored for readers without this class; they must agree with the tables.
        for key in ("feature_width", "feature_height", "sentinel", "num_slots"):
            if meta[key] != getattr(lut, key):
                raise CalibrationError(f"{src}: meta.{key}: stored {meta[key]!r}, but the tables imply {getattr(lut, key)!r}")
        return lut


def _check_stored_geometry(src: str, meta: dict) -> None:
    """CalibrationError when the meta's stored feature map or sentinel disagree with its camera_names, feature_stride
    and image size. Checked before the tables are: they are validated against the sentinel those fields imply, so
    a meta naming another camera count or stride would otherwise be reported as a symptom (old sentinel slots read
    as valid slots of weight 0). Fields of the wrong type are left to Lut's own checks, which name them."""
    names, stride = meta["camera_names"], meta["feature_stride"]
    width, height = meta["image_width"], meta["image_height"]
    if not isinstance(names, list) or not all(_is_pixel_count(v) for v in (stride, width, height)):
        return
    feat_w, feat_h = -(-width // stride), -(-height // stride)  # ceil, in integers
    implied = {"feature_width": feat_w, "feature_height": feat_h, "sentinel": len(names) * feat_w * feat_h}
    for key, value in implied.items():
        stored = meta[key]
        if isinstance(stored, bool) or not isinstance(stored, int) or stored != value:
            raise CalibrationError(
                f"{src}: meta.{key}: stored {short_repr(stored)}, but camera_names ({len(names)} cameras), "
                f"feature_stride {stride} and image size {width}x{height} imply {value}"
            )  # fmt: skip


def _is_pixel_count(value: object) -> bool:
    return not isinstance(value, bool) and isinstance(value, int) and 0 < value <= MAX_IMAGE_PX


def _owned_readonly(arr: np.ndarray) -> np.ndarray:
    """``arr`` as a read-only array no one else can write through: kept when it already is one (it owns its memory
    and is read-only; only a deliberate ``setflags(write=True)`` by its owner would undo that), else a read-only
    copy. A read-only view is not enough: the caller could still write the validated tables through its own array,
    and the LUT in use (and the views cached per Lut, runtime_ort/lut_views.py) would change unchecked. The copy
    leaves the caller's array as it was, writable included."""
    if arr.base is None and not arr.flags.writeable:
        return arr
    arr = np.array(arr, copy=True)
    arr.setflags(write=False)
    return arr


def _check_camera_names(names: object) -> tuple[str, ...]:
    """A list or tuple of distinct non-empty printable strings (Camera's rule), as a tuple (a bare string would
    split into letters)."""
    if not isinstance(names, (list, tuple)) or not names or not all(isinstance(n, str) and n for n in names):
        raise CalibrationError(f"Lut.camera_names: expected a list of non-empty camera names, got {short_repr(names)}")
    for i, name in enumerate(names):
        check_camera_name(name, f"Lut.camera_names[{i}]")  # a lut.npz's meta names them too
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise CalibrationError(f"Lut.camera_names: duplicate camera names {dupes} (each names one feature map)")
    return tuple(names)


def check_min_depth(value: object) -> float:
    """A finite number >= 0 as a float; the OverflowError of a huge JSON integer becomes the CalibrationError."""
    try:
        ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
        depth = float(value) if ok else math.nan  # type: ignore[arg-type]
    except OverflowError:
        depth = math.nan
    if not (math.isfinite(depth) and depth >= 0):
        raise CalibrationError(f"Lut.min_depth_m: expected a finite number of metres >= 0, got {short_repr(value)}")
    return depth


def check_heights_per_voxel(h: object) -> None:
    if isinstance(h, bool) or not isinstance(h, (int, np.integer)) or not 1 <= h <= MAX_HEIGHTS_PER_VOXEL:
        raise CalibrationError(f"heights_per_voxel must be an integer in 1..{MAX_HEIGHTS_PER_VOXEL}, got {h!r}")


def _validate_tables(index: np.ndarray, weight: np.ndarray, grid: GridSpec, sentinel: int, where: str) -> None:
    if not isinstance(index, np.ndarray) or index.dtype != np.int32:
        raise CalibrationError(f"{where}.index: expected an int32 array, got {getattr(index, 'dtype', type(index).__name__)}")
    if not isinstance(weight, np.ndarray) or weight.dtype != np.float32:
        raise CalibrationError(f"{where}.weight: expected a float32 array, got {getattr(weight, 'dtype', type(weight).__name__)}")
    vol = (grid.nz, grid.quadrant_ny, grid.quadrant_nx)
    if index.ndim != 5 or index.shape[0] != NUM_QUADRANTS or index.shape[1] < 1 or index.shape[2:] != vol:
        raise CalibrationError(f"{where}.index: expected shape (4, K >= 1, {', '.join(map(str, vol))}) for the grid, got {index.shape}")
    if weight.shape != index.shape:
        raise CalibrationError(f"{where}.weight: shape {weight.shape} differs from index shape {index.shape}")
    lo, hi = int(index.min()), int(index.max())
    if lo < 0 or hi > sentinel:
        raise CalibrationError(f"{where}.index: entries must lie in [0, sentinel={sentinel}], found [{lo}, {hi}]")
    is_sentinel = index == sentinel
    if not np.all(np.isfinite(weight)) or np.any(weight[is_sentinel] != 0) or np.any(weight[~is_sentinel] <= 0):
        raise CalibrationError(f"{where}.weight: must be > 0 exactly on valid slots and 0 on sentinel slots")
    # Valid slots first: once a slot is a sentinel, every later slot of that voxel is one too.
    if index.shape[1] > 1 and np.any(is_sentinel[:, :-1] & ~is_sentinel[:, 1:]):
        raise CalibrationError(f"{where}.index: a valid slot follows a sentinel slot (valid slots must come first)")
    total = weight.sum(axis=1, dtype=np.float64)  # (4, Z, Yq, Xq)
    if np.any((np.abs(total - 1.0) > 1e-5) & (total != 0)):
        raise CalibrationError(f"{where}.weight: per-voxel weights must sum to 1 (seen) or 0 (unseen)")


def lut_nbytes(grid: GridSpec, num_slots: int) -> int:
    """Bytes of a LUT's two tables, int32 ``index`` + float32 ``weight`` of shape (4, K, Z, Yq, Xq)."""
    return 8 * int(num_slots) * grid.nz * grid.ny * grid.nx


def check_lut_bytes(grid: GridSpec, num_slots: int) -> None:
    """ValueError (naming the grid, K and the size) when the LUT's tables would exceed `MAX_LUT_BYTES`."""
    nbytes = lut_nbytes(grid, num_slots)
    if nbytes > MAX_LUT_BYTES:
        raise ValueError(
            f"a LUT for the {grid.nx} x {grid.ny} x {grid.nz} grid with K = {num_slots} slots would take {nbytes} "
            f"bytes, over the {MAX_LUT_BYTES}-byte cap of a lut.npz (MAX_LUT_BYTES)"
        )  # fmt: skip
