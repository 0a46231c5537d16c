"""A hostile lut.npz is refused from its zip directory and array headers, before any array is read
(calibration/lut_file.py): zip-bomb sizes, pickles, wrong dtype / shape / order, truncated or extra members."""

from __future__ import annotations

import io
import json
import shutil
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut import Lut
from streamdet.calibration.lut_build import build_lut
from streamdet.calibration.lut_file import MAX_LUT_BYTES, MAX_LUT_META_BYTES, LutFileError
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "nuscenes_sample"
TINY = GridSpec(x_range_m=(-6.4, 6.4), y_range_m=(-6.4, 6.4), z_range_m=(-1.0, 1.0), voxel_xy_m=0.4, voxel_z_m=0.5)
OTHER = GridSpec(x_range_m=(-6.4, 6.4), y_range_m=(-6.4, 6.4), z_range_m=(-1.0, 1.0), voxel_xy_m=0.8, voxel_z_m=0.5)


@pytest.fixture(scope="module")
def lut() -> Lut:
    return build_lut(Rig.from_calibration_json(SAMPLE / "calibration.json"), TINY, 4, image_size=(64, 36))


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, allow_pickle=True)
    return buf.getvalue()


def _zip(path: Path, members: dict[str, bytes], compression: int = zipfile.ZIP_STORED) -> Path:
    with zipfile.ZipFile(path, "w", compression) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def _members(lut: Lut, **override: np.ndarray) -> dict[str, bytes]:
    arrays = {"index": lut.index, "weight": lut.weight, "meta": np.array(json.dumps(lut.meta()))}
    arrays.update(override)
    return {f"{k}.npy": _npy(np.asarray(v)) for k, v in arrays.items()}


def _declare_size(path: Path, member: str, size: int) -> None:
    """Patch the central directory so ``member`` declares ``size`` bytes uncompressed (what a bomb's header says)."""
    data = bytearray(path.read_bytes())
    (at,) = struct.unpack_from("<I", data, data.rindex(b"PK\x05\x06") + 16)  # the central directory's start
    while True:
        name_len, extra_len, comment_len = struct.unpack_from("<HHH", data, at + 28)
        if data[at + 46:at + 46 + name_len].decode() == member:
            struct.pack_into("<I", data, at + 24, size)
            break
        at += 46 + name_len + extra_len + comment_len
    path.write_bytes(bytes(data))


def test_a_well_formed_file_loads_with_and_without_the_manifests_expectation(lut, tmp_path):
    path = _zip(tmp_path / "lut.npz", _members(lut))
    for back in (Lut.load(path), Lut.load(path, TINY, lut.num_cameras)):
        assert np.array_equal(back.index, lut.index) and np.array_equal(back.weight, lut.weight)
    compressed = _zip(tmp_path / "c.npz", _members(lut), zipfile.ZIP_DEFLATED)  # np.savez_compressed's form
    assert np.array_equal(Lut.load(compressed, TINY, lut.num_cameras).index, lut.index)


@pytest.mark.parametrize("member, size", [("index.npy", 0xFFFFFFF0), ("meta.npy", MAX_LUT_META_BYTES + 1)])
def test_a_zip_bomb_header_is_refused_before_inflating(lut, tmp_path, member, size):
    path = _zip(tmp_path / "lut.npz", _members(lut), zipfile.ZIP_DEFLATED)
    _declare_size(path, member, size)
    with pytest.raises(LutFileError, match=r"lut\.npz: .*declares \d+ bytes.*over the \d+-byte cap"):
        Lut.load(path)


def test_a_small_file_inflating_to_a_big_table_is_refused_by_its_header(lut, tmp_path):
    # zeros deflate to almost nothing: a bomb is such a table with a K (or grid) no manifest implies
    k = lut.num_cameras + 1
    big = np.zeros((4, k) + lut.index.shape[2:], np.int32)
    path = _zip(tmp_path / "lut.npz", _members(lut, index=big, weight=big.astype(np.float32)), zipfile.ZIP_DEFLATED)
    with pytest.raises(LutFileError, match=rf"Lut.index: K = {k} slots, more than the {lut.num_cameras} its cameras"):
        Lut.load(path, TINY, lut.num_cameras)


@pytest.mark.parametrize("table, dtype", [("index", np.int64), ("index", np.float32), ("weight", np.float16), ("weight", ">f4")])
def test_a_wrong_dtype_is_refused(lut, tmp_path, table, dtype):
    bad = getattr(lut, table).astype(dtype)
    path = _zip(tmp_path / "lut.npz", _members(lut, **{table: bad}))
    with pytest.raises(LutFileError, match=rf"lut\.npz: Lut\.{table}: expected an? (int32|float32) array, got"):
        Lut.load(path, TINY, lut.num_cameras)


def test_a_pickled_object_array_is_refused_unread(lut, tmp_path):
    path = _zip(tmp_path / "lut.npz", _members(lut, index=np.array([{"boom": 1}], dtype=object)))
    with pytest.raises(LutFileError, match=r"index\.npy holds Python objects .*a pickle, never loaded"):
        Lut.load(path)


def test_a_shape_other_than_the_manifests_grid_is_refused(lut, tmp_path):
    path = _zip(tmp_path / "lut.npz", _members(lut))
    vol = f"{OTHER.nz}, {OTHER.quadrant_ny}, {OTHER.quadrant_nx}"
    with pytest.raises(LutFileError, match=rf"Lut.index: expected shape \(4, K >= 1, {vol}\) for the grid"):
        Lut.load(path, OTHER, lut.num_cameras)
    fortran = _zip(tmp_path / "f.npz", _members(lut, index=np.asfortranarray(lut.index)))
    with pytest.raises(LutFileError, match="in Fortran order"):
        Lut.load(fortran, TINY, lut.num_cameras)
    mismatch = _zip(tmp_path / "m.npz", _members(lut, weight=lut.weight[:, :1].copy()))
    with pytest.raises(LutFileError, match="Lut.weight: shape .* differs from index shape"):
        Lut.load(mismatch, TINY, lut.num_cameras)


@pytest.mark.parametrize("cut", [1, 100])
def test_a_truncated_member_is_refused(lut, tmp_path, cut):
    members = _members(lut)
    members["index.npy"] = members["index.npy"][:-cut]
    path = _zip(tmp_path / "lut.npz", members)
    with pytest.raises(LutFileError, match=r"index\.npy declares \d+ bytes, but its header implies \d+ .*truncated"):
        Lut.load(path, TINY, lut.num_cameras)


def test_extra_or_repeated_members_are_refused(lut, tmp_path):
    extra = _zip(tmp_path / "extra.npz", {**_members(lut), "payload.npy": _npy(np.zeros(3))})
    with pytest.raises(LutFileError, match=r"unexpected or repeated member\(s\) \['payload.npy'\]"):
        Lut.load(extra)
    with pytest.warns(UserWarning, match="Duplicate name"):
        twice = _zip(tmp_path / "twice.npz", _members(lut))
        with zipfile.ZipFile(twice, "a") as zf:
            zf.writestr("index.npy", _npy(lut.index))
    with pytest.raises(LutFileError, match=r"repeated member\(s\) \['index.npy'\]"):
        Lut.load(twice)


def test_the_error_is_a_calibration_error_and_the_caps_are_sane():
    assert issubclass(LutFileError, CalibrationError) and issubclass(LutFileError, ValueError)
    assert MAX_LUT_META_BYTES < MAX_LUT_BYTES


def test_the_detector_refuses_a_hostile_lut_before_reading_it(tiny_export, tmp_path, lut):
    export = tmp_path / "export"
    shutil.copytree(tiny_export, export)
    good = Lut.load(export / "lut.npz")
    path = _zip(export / "lut.npz", _members(good), zipfile.ZIP_DEFLATED)
    _declare_size(path, "weight.npy", 0xFFFFFFF0)
    with pytest.raises(LutFileError, match=r"lut\.npz: declares \d+ bytes uncompressed, over the"):
        StreamingDetector(export, DetectorConfig(verify_sha256=False))


# ---- damage that numpy and zipfile report with other exceptions than ValueError (review 39, M1) ------------------

def _header_byte_damaged(data: bytes) -> bytes:
    """The first .npy header's shape tuple loses its closing parenthesis (one byte): numpy's header parser, Python's
    tokenizer, raises tokenize.TokenError."""
    at = data.index(b")", data.index(b"'shape': ("))
    return data[:at] + b" " + data[at + 1:]


def _patched_flag_set(data: bytes) -> bytes:
    """General-purpose flag bit 5 ("compressed patched data") set in the first central-directory entry: zipfile
    raises NotImplementedError when that member is opened."""
    out = bytearray(data)
    out[data.index(b"PK\x01\x02") + 8] |= 0x20
    return bytes(out)


DAMAGE = [(_header_byte_damaged, r"TokenError"), (_patched_flag_set, r"NotImplementedError: compressed patched data")]


@pytest.mark.parametrize("damage, cause", DAMAGE, ids=["npy_header_byte", "zip_flag_bit_5"])
def test_a_damaged_file_is_a_lut_file_error_naming_it(lut, tmp_path, damage, cause):
    good = tmp_path / "good.npz"
    lut.save(good)
    bad = tmp_path / "broken_lut.npz"
    bad.write_bytes(damage(good.read_bytes()))
    for load in (lambda: Lut.load(bad), lambda: Lut.load(bad, TINY, lut.num_cameras), lambda: Lut.load(bad, data=bad.read_bytes())):
        with pytest.raises(LutFileError, match=rf"broken_lut\.npz: index\.npy: cannot read its \.npy header: {cause}"):
            load()


@pytest.mark.parametrize("damage, cause", DAMAGE, ids=["npy_header_byte", "zip_flag_bit_5"])
def test_the_detector_and_streamdet_calib_handle_a_damaged_lut(tiny_export, tmp_path, damage, cause):
    from click.testing import CliRunner

    from streamdet.runtime_ort.calib_cli import main as calib_main

    export = tmp_path / "export"
    shutil.copytree(tiny_export, export)
    good = (export / "lut.npz").read_bytes()
    (export / "lut.npz").write_bytes(damage(good))
    with pytest.raises(LutFileError, match=rf"lut\.npz: .*{cause}"):  # unhashed: the header check is what stops it
        StreamingDetector(export, DetectorConfig(verify_sha256=False))
    det = StreamingDetector(tiny_export, DetectorConfig())
    in_use = det.lut
    with pytest.raises(LutFileError, match=rf"lut\.npz: .*{cause}"):  # a CalibrationError, as callers catch
        det.set_calibration(export / "lut.npz")
    assert det.lut is in_use
    det.close()
    # a rebuild is how a broken LUT is repaired: the old one is noted and replaced, not a traceback
    result = CliRunner().invoke(calib_main, ["lut", "--calibration", str(SAMPLE / "calibration.json"), "--export-dir", str(export)])
    assert result.exit_code == 0, result.output
    assert "the previous lut.npz is unreadable, so it is replaced without comparing cameras" in result.output
    assert (export / "lut.npz").read_bytes() == good  # the same calibration: the same file again
    StreamingDetector(export, DetectorConfig())  # and its manifest's hash matches it
