"""What a ``lut.npz`` may hold, checked from its zip directory and array headers before any array is read.

An export folder can come from anyone, and an .npz is a zip: a small file can declare (or inflate to) gigabytes,
hold pickled objects, or announce arrays of another dtype or shape than the LUT the export needs. `check_lut_archive`
refuses all of that with a `LutFileError` naming the file and the member, reading only the zip's central directory,
the three ``.npy`` headers and the small ``meta`` string:

- exactly the members ``index.npy``, ``weight.npy``, ``meta.npy``, once each;
- declared uncompressed sizes within `MAX_LUT_BYTES` (all members) and `MAX_LUT_META_BYTES` (meta); the zip
  reader never inflates a member past its declared size, so these bound the memory a load can take;
- ``meta`` one unicode string (shape (), dtype ``<U``n), the JSON object of `Lut.meta`;
- no object (pickled) dtype; ``index`` int32, ``weight`` float32, both C-ordered and of shape (4, K, Z, Yq, Xq),
  with (Z, Yq, Xq) the expected grid's and 1 <= K <= cameras x heights per voxel (the most distinct feature rows one
  voxel can read); the expectation is the caller's (the manifest's grid and camera count) or else the file's meta;
- each member's declared size is exactly its header plus its data: a truncated or padded member is refused.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
import zlib

import numpy as np

from streamdet.calibration.camera import CalibrationError
from streamdet.calibration.grid import GridSpec
from streamdet.core.npz_input import NpyHeader, check_member_size, npy_header
from streamdet.core.sectors import NUM_QUADRANTS

# All members, uncompressed. The largest preset grid (16 x 256 x 256 per quadrant) takes 32 MiB per slot K for both
# tables: 1 GiB allows K = 32, above its 6 cameras x 2 heights per voxel; a bomb declares far more.
MAX_LUT_BYTES = 1 << 30
MAX_LUT_META_BYTES = 1 << 20  # the meta JSON string; a real one is under a kB
MAX_LUT_FILE_BYTES = MAX_LUT_BYTES + MAX_LUT_META_BYTES + (1 << 20)  # the whole .npz: members plus zip headers
MAX_HEIGHTS_PER_VOXEL = 64  # as calibration.lut: bounds K for a given camera count
MEMBERS = ("index", "weight", "meta")
DTYPES = {"index": np.dtype(np.int32), "weight": np.dtype(np.float32)}


class LutFileError(CalibrationError):
    """A lut.npz that cannot be the LUT the export needs: oversized, a zip bomb, pickled, wrong header, truncated."""


def check_lut_archive(path: str | os.PathLike, grid: GridSpec | None = None, num_cameras: int | None = None,
                      data: bytes | None = None) -> None:  # fmt: skip
    """Refuse ``path`` unless its members fit a LUT of ``grid`` and ``num_cameras`` (None: as its meta says).
    ``data``: the file's bytes, already read (then ``path`` only names it)."""
    src = os.path.basename(os.fspath(path))
    try:
        with zipfile.ZipFile(io.BytesIO(data) if data is not None else path) as zf:
            infos = _members(zf, src)
            meta = _read_meta(zf, infos["meta"], src)
            grid = grid if grid is not None else _meta_grid(meta)
            if num_cameras is None and isinstance(meta.get("camera_names"), list):
                num_cameras = len(meta["camera_names"])
            heights = meta.get("heights_per_voxel", 1)
            if isinstance(heights, bool) or not isinstance(heights, int) or not 1 <= heights <= MAX_HEIGHTS_PER_VOXEL:
                heights = MAX_HEIGHTS_PER_VOXEL  # the meta check names the bad value; here it only bounds K
            max_slots = None if num_cameras is None else num_cameras * heights
            shapes = [_check_table(zf, infos[name], name, grid, max_slots, src) for name in DTYPES]
    except LutFileError:
        raise
    except (OSError, EOFError, zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, ValueError, KeyError,
            NotImplementedError, RuntimeError) as e:  # the last two: zip flags zipfile does not support (patched, encrypted)
        raise LutFileError(f"{src}: not a readable LUT .npz: {e}") from None
    if shapes[0] != shapes[1]:
        raise LutFileError(f"{src}: Lut.weight: shape {shapes[1]} differs from index shape {shapes[0]}")


def _members(zf: zipfile.ZipFile, src: str) -> dict[str, zipfile.ZipInfo]:
    names = [i.filename for i in zf.infolist()]
    missing = [k for k in MEMBERS if f"{k}.npy" not in names]
    if missing:
        raise LutFileError(f"{src}: missing key(s) {missing}; found {sorted(n.removesuffix('.npy') for n in names)}")
    extra = sorted(set(names) - {f"{k}.npy" for k in MEMBERS}) + sorted({n for n in names if names.count(n) > 1})
    if extra:
        raise LutFileError(f"{src}: unexpected or repeated member(s) {extra}; a LUT holds exactly {[f'{k}.npy' for k in MEMBERS]}")
    infos = {i.filename.removesuffix(".npy"): i for i in zf.infolist()}
    total = sum(i.file_size for i in infos.values())
    if total > MAX_LUT_BYTES:
        raise LutFileError(f"{src}: declares {total} bytes uncompressed, over the {MAX_LUT_BYTES}-byte cap (MAX_LUT_BYTES)")
    if infos["meta"].file_size > MAX_LUT_META_BYTES:
        raise LutFileError(
            f"{src}: meta.npy declares {infos['meta'].file_size} bytes, over the {MAX_LUT_META_BYTES}-byte cap (MAX_LUT_META_BYTES)"
        )  # fmt: skip
    return infos


def _header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, src: str) -> NpyHeader:
    """``core.npz_input.npy_header`` as a LutFileError naming the file."""
    try:
        return npy_header(zf, info)
    except ValueError as e:
        raise LutFileError(f"{src}: {e}") from None


def _check_size(info: zipfile.ZipInfo, header: NpyHeader, src: str) -> None:
    """``core.npz_input.check_member_size`` as a LutFileError naming the file."""
    try:
        check_member_size(info, header)
    except ValueError as e:
        raise LutFileError(f"{src}: {e}") from None


def _read_meta(zf: zipfile.ZipFile, info: zipfile.ZipInfo, src: str) -> dict:
    """The meta object when it is a JSON object string, else {} (Lut.load names what is wrong with it).

    The header must declare one unicode string whose bytes are exactly the member's rest: numpy allocates the
    declared shape before it reads a non-file stream, so a 128-byte member announcing 2**40 float64 would
    otherwise ask for 8 TiB (MAX_LUT_META_BYTES caps the member, not what its header claims)."""
    h = _header(zf, info, src)
    if h.shape != () or h.dtype.kind != "U":
        raise LutFileError(f"{src}: meta: expected a JSON string (a 0-d unicode array), got dtype {h.dtype.str} shape {h.shape}")
    _check_size(info, h, src)  # exactly its header plus one string
    with zf.open(info) as f:
        arr = np.lib.format.read_array(f, allow_pickle=False)  # bounded: one string of the member's capped size
    try:
        meta = json.loads(str(arr))
    except (ValueError, RecursionError):
        return {}
    return meta if isinstance(meta, dict) else {}


def _meta_grid(meta: dict) -> GridSpec | None:
    try:
        return GridSpec.from_dict(meta["grid"])
    except (KeyError, TypeError, ValueError, OverflowError):
        return None  # Lut.load names the bad grid; the tables are then bounded by MAX_LUT_BYTES alone


def _check_table(zf: zipfile.ZipFile, info: zipfile.ZipInfo, name: str, grid: GridSpec | None, max_slots: int | None,
                 src: str) -> tuple[int, ...]:  # fmt: skip
    h = _header(zf, info, src)
    shape, fortran_order, dtype = h.shape, h.fortran_order, h.dtype
    if dtype != DTYPES[name]:
        article = "an" if name == "index" else "a"
        raise LutFileError(f"{src}: Lut.{name}: expected {article} {DTYPES[name]} array, got {dtype}")
    vol = None if grid is None else (grid.nz, grid.quadrant_ny, grid.quadrant_nx)
    ok = len(shape) == 5 and shape[0] == NUM_QUADRANTS and shape[1] >= 1 and (vol is None or shape[2:] == vol)
    if not ok or fortran_order:
        want = "(4, K >= 1, Z, Yq, Xq)" if vol is None else f"(4, K >= 1, {', '.join(map(str, vol))})"
        order = " in Fortran order" if fortran_order else ""
        raise LutFileError(f"{src}: Lut.{name}: expected shape {want} for the grid, got {shape}{order}")
    if max_slots is not None and shape[1] > max_slots:
        raise LutFileError(f"{src}: Lut.{name}: K = {shape[1]} slots, more than the {max_slots} its cameras can fill")
    _check_size(info, h, src)
    return shape
