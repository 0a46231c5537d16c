"""Hostile inputs to the calibration side: lut.npz meta headers and fields, calibration JSON numbers and image sizes,
degenerate or huge grids, and streamdet-calib lut over a broken old LUT or an oversized manifest grid.

Each behaviour is paired with malformed input: the library raises a ValueError subclass naming the file, field and
value (never OverflowError / MemoryError / TypeError), and the CLI exits non-zero with one line.
"""

from __future__ import annotations

import copy
import io
import json
import re
import shutil
import struct
import zipfile
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.calibration import lut as lut_module
from streamdet.calibration.camera import MAX_IMAGE_PX, CalibrationError, Camera, Rig
from streamdet.calibration.grid import MAX_GRID_VOXELS, GridSpec
from streamdet.calibration.lut import Lut, check_rig_fits, lut_nbytes
from streamdet.calibration.lut_build import build_lut
from streamdet.calibration.lut_file import LutFileError
from streamdet.models.presets import get_preset, preset_names

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = files("streamdet.data") / "nuscenes_sample"
CALIBRATION = ROOT / "data" / "nuscenes_sample" / "calibration.json"
TINY = GridSpec(x_range_m=(-6.4, 6.4), y_range_m=(-6.4, 6.4), z_range_m=(-1.0, 1.0), voxel_xy_m=0.4, voxel_z_m=0.5)
HUGE = 10**400  # a JSON integer past float range: float() of it raises OverflowError


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.from_calibration_json(SAMPLE / "calibration.json")


@pytest.fixture(scope="module")
def tiny_lut(rig: Rig) -> Lut:
    return build_lut(rig, TINY, image_size=(800, 450))


# ---- lut.npz writing helpers -------------------------------------------------------------------------------------

def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def _npy_raw(header: dict, data: bytes) -> bytes:
    """A .npy member whose header says anything, followed by ``data`` (what a hostile file can hold)."""
    text = repr(header).encode("latin1")
    text += b" " * (64 - (10 + len(text) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + data


def _write_lut(path: Path, lut: Lut, meta_member: bytes) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("index.npy", _npy(lut.index))
        zf.writestr("weight.npy", _npy(lut.weight))
        zf.writestr("meta.npy", meta_member)
    return path


def _with_meta(path: Path, lut: Lut, **fields) -> Path:
    meta = {**lut.meta(), **fields}
    return _write_lut(path, lut, _npy(np.array(json.dumps(meta))))


# ---- #4: meta.npy headers are checked before numpy allocates what they declare -----------------------------------

@pytest.mark.parametrize(
    "header, data",
    [
        ({"descr": "<f8", "fortran_order": False, "shape": (1 << 40,)}, b"\0" * 64),  # 8 TiB declared in 128 bytes
        ({"descr": "<U1", "fortran_order": False, "shape": (1 << 40,)}, b"\0" * 64),
        ({"descr": "<U4", "fortran_order": False, "shape": (3,)}, b"\0" * 48),  # a list of strings, not one
        ({"descr": "<f8", "fortran_order": False, "shape": ()}, b"\0" * 8),  # a number
        ({"descr": "<i4", "fortran_order": False, "shape": (2, 2)}, b"\0" * 16),
    ],
    ids=["f8-2**40", "U1-2**40", "U4-list", "f8-scalar", "i4-matrix"],
)
def test_a_meta_header_that_is_not_one_string_is_refused_before_reading(tiny_lut, tmp_path, header, data) -> None:
    path = _write_lut(tmp_path / "lut.npz", tiny_lut, _npy_raw(header, data))
    with pytest.raises(LutFileError, match=r"lut\.npz: meta: expected a JSON string \(a 0-d unicode array\), got dtype"):
        Lut.load(path)


@pytest.mark.parametrize("itemsize, data_bytes", [(1 << 18, 64), (2, 64), (1 << 28, 16)], ids=["short", "padded", "1GiB"])
def test_a_meta_string_whose_size_disagrees_with_its_member_is_refused(tiny_lut, tmp_path, itemsize, data_bytes) -> None:
    """A 0-d <U string whose declared length is not the member's rest (truncated, padded, or 1 GiB in 16 bytes)."""
    header = {"descr": f"<U{itemsize}", "fortran_order": False, "shape": ()}
    path = _write_lut(tmp_path / "lut.npz", tiny_lut, _npy_raw(header, b"\0" * data_bytes))
    with pytest.raises(LutFileError, match=r"lut\.npz: meta\.npy declares \d+ bytes, but its header implies \d+ .*truncated or padded"):
        Lut.load(path)


def test_a_saved_lut_still_loads(tiny_lut, tmp_path) -> None:
    tiny_lut.save(tmp_path / "lut.npz")
    back = Lut.load(tmp_path / "lut.npz")
    assert back.camera_names == tiny_lut.camera_names and back.calibration_sha256 == tiny_lut.calibration_sha256
    assert back.min_depth_m == 0.0 and isinstance(back.min_depth_m, float)


# ---- #5 / #13: meta fields of the wrong kind ----------------------------------------------------------------------

@pytest.mark.parametrize(
    "fields, pattern",
    [
        ({"min_depth_m": HUGE}, r"Lut\.min_depth_m: expected a finite number of metres >= 0, got an integer of 401 digits"),
        ({"min_depth_m": float("nan")}, r"min_depth_m: .* got nan"),
        ({"min_depth_m": float("inf")}, r"min_depth_m: .* got inf"),
        ({"min_depth_m": -5}, r"min_depth_m: .* got -5"),
        ({"min_depth_m": True}, r"min_depth_m: .* got True"),
        ({"min_depth_m": "0.5"}, r"min_depth_m: .* got '0\.5'"),
        ({"min_depth_m": None}, r"min_depth_m: .* got None"),
        ({"min_depth_m": [0.5]}, r"min_depth_m: .* got \[0\.5\]"),
        ({"camera_names": "ABCDEF"}, r"Lut\.camera_names: expected a list of non-empty camera names, got 'ABCDEF'"),
        ({"camera_names": ["A"] * 6}, r"Lut\.camera_names: duplicate camera names \['A'\]"),
        ({"camera_names": ["A", "B", "C", "D", "E", ""]}, r"camera_names: expected a list of non-empty"),
        ({"camera_names": ["A", "B", "C", "D", "E", 6]}, r"camera_names: expected a list of non-empty"),
        ({"camera_names": {"A": 1}}, r"camera_names: expected a list of non-empty"),
        ({"camera_names": []}, r"(camera_names|more than the 0 its cameras can fill)"),
        ({"calibration_sha256": 5}, r"meta\.calibration_sha256: expected 64 lowercase hex digits .*got 5$"),
        ({"calibration_sha256": None}, r"meta\.calibration_sha256: .*got None"),
        ({"calibration_sha256": "x"}, r"meta\.calibration_sha256: .*got 'x'"),
        ({"calibration_sha256": "A" * 64}, r"meta\.calibration_sha256: .*got 'AAAA"),
        ({"calibration_sha256": "a" * 63}, r"meta\.calibration_sha256"),
        ({"calibration_sha256": ["a" * 64]}, r"meta\.calibration_sha256"),
        ({"image_width": HUGE}, r"Lut\.image_width: expected at most 65536 pixels"),
    ],
)
def test_meta_fields_of_the_wrong_kind_are_named(tiny_lut, tmp_path, fields, pattern) -> None:
    path = _with_meta(tmp_path / "lut.npz", tiny_lut, **fields)
    with pytest.raises(CalibrationError, match=r"lut\.npz: " + ".*" + pattern):
        Lut.load(path)


def test_a_meta_integer_past_the_digit_limit_is_not_json(tiny_lut, tmp_path) -> None:
    """json.loads raises a plain ValueError for an integer of more than 4300 digits: still a CalibrationError."""
    text = json.dumps(tiny_lut.meta()).replace('"min_depth_m": 0.0', '"min_depth_m": ' + "9" * 5000)
    path = _write_lut(tmp_path / "lut.npz", tiny_lut, _npy(np.array(text)))
    with pytest.raises(CalibrationError, match=r"lut\.npz: meta: not valid JSON"):
        Lut.load(path)


def test_meta_fields_this_project_writes_are_accepted(tiny_lut, tmp_path) -> None:
    """An integer min_depth_m (hand-written meta) and every sha Rig.sha256() can give load as before."""
    lut = Lut.load(_with_meta(tmp_path / "lut.npz", tiny_lut, min_depth_m=0, calibration_sha256="0" * 64))
    assert lut.min_depth_m == 0.0 and lut.calibration_sha256 == "0" * 64


def test_direct_construction_refuses_the_same_kinds(tiny_lut) -> None:
    base = dict(index=tiny_lut.index, weight=tiny_lut.weight, grid=TINY, feature_stride=4, image_width=800,
                image_height=450, camera_names=tiny_lut.camera_names, calibration_sha256="x")  # fmt: skip
    Lut(**base)  # a test's placeholder sha is a string: accepted (load alone insists on 64 hex digits)
    for bad, pattern in [
        ({"camera_names": "".join(tiny_lut.camera_names)}, "camera_names"),
        ({"min_depth_m": -1.0}, "min_depth_m"),
        ({"calibration_sha256": 5}, "calibration_sha256: expected a string"),
    ]:
        with pytest.raises(CalibrationError, match=pattern):
            Lut(**{**base, **bad})


# ---- #8: calibration JSON numbers past float range, image sizes past MAX_IMAGE_PX --------------------------------

def _calib(edit) -> dict:
    doc = copy.deepcopy(json.loads(CALIBRATION.read_text()))
    edit(doc)
    return doc


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda d: d["cameras"][0]["K"][0].__setitem__(0, HUGE), r"cameras\[0\]\.K"),
        (lambda d: d["cameras"][2]["K"][2].__setitem__(2, -HUGE), r"cameras\[2\]\.K"),
        (lambda d: d["cameras"][1]["lidar2cam"]["matrix"][0].__setitem__(3, HUGE), r"cameras\[1\]\.lidar2cam\.matrix"),
        (lambda d: d["lidar"]["sensor2ego"]["matrix"][1].__setitem__(3, HUGE), r"lidar\.sensor2ego\.matrix"),
        (lambda d: d["lidar"].__setitem__("ego2global", {"rotation_wxyz": [HUGE, 0, 0, 0], "translation": [0, 0, 0]}),
         r"lidar\.ego2global\.rotation_wxyz"),
        (lambda d: d["lidar"].__setitem__("ego2global", {"rotation_wxyz": [1, 0, 0, 0], "translation": [HUGE, 0, 0]}),
         r"lidar\.ego2global\.translation"),
        (lambda d: d["cameras"][0].__setitem__("width", HUGE), r"cameras\[0\]\.width: expected a positive integer pixel count up to 65536, got an integer of 401 digits"),
        (lambda d: d["cameras"][0].__setitem__("height", MAX_IMAGE_PX + 1), r"cameras\[0\]\.height: .*up to 65536, got 65537"),
        (lambda d: [c.update(width=16 * 10**300, height=9 * 10**300) for c in d["cameras"]], r"cameras\[0\]\.width"),
    ],
    ids=["K", "K-negative", "lidar2cam", "sensor2ego", "quaternion", "translation", "width-huge", "height-65537", "1.6e304-px"],
)
def test_calibration_numbers_past_range_are_named(tmp_path, edit, field) -> None:
    doc = _calib(edit)
    with pytest.raises(CalibrationError, match=r"^calibration: " + field):
        Rig.from_calibration_json(doc)
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match=r"^" + re.escape(str(path)) + ": " + field):  # the path as given
        Rig.from_calibration_json(path)


def test_a_calibration_integer_past_the_digit_limit_is_not_json(tmp_path) -> None:
    path = tmp_path / "calibration.json"
    path.write_text(CALIBRATION.read_text().replace('"width": 1600', '"width": ' + "9" * 5000, 1))
    with pytest.raises(CalibrationError, match=r"calibration\.json: not valid JSON"):
        Rig.from_calibration_json(path)


def test_image_sizes_up_to_the_cap_are_cameras(rig: Rig) -> None:
    cam = rig.cameras[0]
    assert cam.resized(MAX_IMAGE_PX, MAX_IMAGE_PX).width == MAX_IMAGE_PX
    for bad in (MAX_IMAGE_PX + 1, HUGE, 0, -1, 2.0, True):
        with pytest.raises(CalibrationError, match="width"):
            Camera(cam.name, cam.K, cam.lidar2cam, bad, 900)


def test_max_image_px_is_the_manifests_maximum() -> None:
    """One number: calibration sizes are bounded as the manifest schema bounds the export's image size."""
    schema = json.loads((ROOT / "runtime_ort" / "manifest.schema.json").read_text())
    found = []

    def walk(node):
        if isinstance(node, dict):
            for key in ("width", "height"):
                if isinstance(node.get(key), dict) and "maximum" in node[key]:
                    found.append(node[key]["maximum"])
            for v in node.values():
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(schema)
    assert found and set(found) == {MAX_IMAGE_PX}


@pytest.mark.parametrize("width, height", [(HUGE, 450), (800, HUGE), (0, 450), (800, -1), (800.0, 450), ("800", 450)])
def test_check_rig_fits_names_a_bad_export_size(rig: Rig, width, height) -> None:
    with pytest.raises(CalibrationError, match="image (width|height)"):
        check_rig_fits(rig, rig.names, width, height)


@pytest.mark.parametrize("image_size", [(float("inf"), 450), ("x", 450), (None, 450), "800x450", 800, (800, 450, 3)])
def test_build_lut_names_a_bad_image_size(rig: Rig, image_size) -> None:
    with pytest.raises(ValueError, match="image_size"):
        build_lut(rig, TINY, image_size=image_size)


# ---- #14: grids with no cell, astronomically many, or a LUT over the cap ------------------------------------------

@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        ({"x_range_m": (-1e-8, 1e-8), "y_range_m": (-1e-8, 1e-8), "voxel_xy_m": 1.0}, r"x_range_m extent 2e-08 m holds 0 voxels"),
        ({"z_range_m": (0.0, 1e-9), "voxel_z_m": 1.0}, r"z_range_m extent 1e-09 m holds 0 voxels"),
        ({"voxel_xy_m": 1e-300}, r"x_range_m extent 102\.4 m holds 1\.02e\+302 voxels of 1e-300 m, over the \d+-voxel cap"),
        ({"voxel_z_m": 1e-300}, r"z_range_m .* over the \d+-voxel cap"),
        ({"x_range_m": (-3000.0, 3000.0), "y_range_m": (-3000.0, 3000.0)}, r"grid 30000 x 30000 x 16 = 14400000000 voxels .*MAX_GRID_VOXELS"),
        ({"x_range_m": (-1e308, 1e308)}, r"x_range_m extent inf m"),
        ({"x_range_m": (-HUGE, HUGE)}, r"x_range_m must be a finite \(min, max\)"),
        ({"voxel_xy_m": HUGE}, r"voxel sizes must be finite and > 0"),
        ({"voxel_z_m": float("inf")}, r"voxel sizes must be finite and > 0"),
    ],
)
def test_degenerate_or_huge_grids_are_named(kwargs, pattern) -> None:
    with pytest.raises(ValueError, match=pattern):
        GridSpec(**kwargs)


def test_grid_from_dict_names_a_huge_voxel() -> None:
    with pytest.raises(ValueError, match=r"GridSpec\.voxel_xy_m must be a finite number"):
        GridSpec.from_dict({**GridSpec().to_dict(), "voxel_xy_m": HUGE})


def test_the_grid_cap_is_well_above_every_preset_and_exact() -> None:
    for name in preset_names():
        g = get_preset(name).grid
        assert 16 * g.nx * g.ny * g.nz <= MAX_GRID_VOXELS, name
    side = 2048  # 2048 x 2048 x 16 = MAX_GRID_VOXELS exactly: accepted (nothing is allocated)
    assert side * side * 16 == MAX_GRID_VOXELS
    GridSpec(x_range_m=(-204.8, 204.8), y_range_m=(-204.8, 204.8))
    with pytest.raises(ValueError, match="MAX_GRID_VOXELS"):
        GridSpec(x_range_m=(-205.2, 205.2), y_range_m=(-204.8, 204.8))


def test_lut_nbytes_is_the_tables_size(tiny_lut) -> None:
    assert lut_nbytes(TINY, tiny_lut.num_slots) == tiny_lut.index.nbytes + tiny_lut.weight.nbytes


@pytest.mark.parametrize("heights", [1, 2])
def test_build_lut_refuses_a_lut_over_the_cap_before_allocating_it(rig: Rig, monkeypatch, heights) -> None:
    monkeypatch.setattr(lut_module, "MAX_LUT_BYTES", lut_nbytes(TINY, 1) - 1)  # no K fits: refused up front
    with pytest.raises(ValueError, match=r"a LUT for the 32 x 32 x 4 grid with K = 1 slots would take \d+ bytes, over .*MAX_LUT_BYTES"):
        build_lut(rig, TINY, image_size=(800, 450), heights_per_voxel=heights)
    monkeypatch.setattr(lut_module, "MAX_LUT_BYTES", lut_nbytes(TINY, 1))  # K = 1 fits, the real K does not
    with pytest.raises(ValueError, match=r"with K = [2-9]\d* slots would take"):
        build_lut(rig, TINY, image_size=(800, 450), heights_per_voxel=heights)


@pytest.mark.parametrize("kwargs, pattern", [
    ({"min_depth_m": HUGE}, "min_depth_m must be a finite number >= 0, got an integer of 401 digits"),
    ({"min_depth_m": True}, "min_depth_m"),
    ({"feature_stride": HUGE}, "feature_stride must be a positive integer up to 65536"),
])  # fmt: skip
def test_build_lut_names_huge_arguments(rig: Rig, kwargs, pattern) -> None:
    with pytest.raises(ValueError, match=pattern):
        build_lut(rig, TINY, image_size=(800, 450), **kwargs)


def test_build_lut_names_a_grid_that_is_not_one(rig: Rig) -> None:
    with pytest.raises(ValueError, match="grid must be a GridSpec, got dict"):
        build_lut(rig, TINY.to_dict())


# ---- streamdet-calib lut -----------------------------------------------------------------------------------------

@pytest.fixture
def export_copy(tiny_export, tmp_path) -> Path:
    out = tmp_path / "exp"
    shutil.copytree(tiny_export, out)
    return out


def _calib_lut(export_dir: Path, calibration: Path = CALIBRATION):
    return CliRunner().invoke(__import__("streamdet.runtime_ort.calib_cli", fromlist=["main"]).main,
                              ["lut", "--calibration", str(calibration), "--export-dir", str(export_dir)])


def _one_line_error(result) -> str:
    assert result.exit_code != 0, result.output
    assert isinstance(result.exception, SystemExit), repr(result.exception)  # no traceback
    lines = [ln for ln in result.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.output
    return lines[0]


def _edit_manifest(export_dir: Path, edit) -> None:
    path = export_dir / "manifest.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


def _break_header(d: Path) -> None:
    with zipfile.ZipFile(d / "lut.npz") as zf:
        index, weight = zf.read("index.npy"), zf.read("weight.npy")
    (d / "lut.npz").unlink()
    with zipfile.ZipFile(d / "lut.npz", "w") as zf:
        zf.writestr("index.npy", index)
        zf.writestr("weight.npy", weight)
        zf.writestr("meta.npy", _npy_raw({"descr": "<f8", "fortran_order": False, "shape": (1 << 40,)}, b"\0" * 64))


def _break_meta(d: Path, **fields) -> None:
    with np.load(d / "lut.npz") as z:
        index, weight, meta = z["index"], z["weight"], json.loads(str(z["meta"]))
    meta.update(fields)
    (d / "lut.npz").unlink()
    with zipfile.ZipFile(d / "lut.npz", "w") as zf:
        zf.writestr("index.npy", _npy(index))
        zf.writestr("weight.npy", _npy(weight))
        zf.writestr("meta.npy", _npy(np.array(json.dumps(meta))))


@pytest.mark.parametrize(
    "breakit, said",
    [
        (_break_header, "meta: expected a JSON string"),
        (lambda d: _break_meta(d, min_depth_m=HUGE), "min_depth_m"),
        (lambda d: _break_meta(d, camera_names="ABCDEF"), "camera_names"),
        (lambda d: (d / "lut.npz").write_bytes(b"not a zip"), "not a readable LUT"),
    ],
    ids=["huge-meta-header", "huge-min-depth", "names-string", "garbage"],
)
def test_a_broken_old_lut_never_stops_its_own_rebuild(export_copy, breakit, said) -> None:
    breakit(export_copy)
    result = _calib_lut(export_copy)
    assert result.exit_code == 0, result.output
    assert "note: the previous lut.npz is unreadable" in result.output and said in result.output
    assert "rebuilt" in result.output
    Lut.load(export_copy / "lut.npz")  # the rebuilt one is sound


@pytest.mark.parametrize(
    "grid, said",
    [
        ({"x_range_m": [-1e-8, 1e-8], "y_range_m": [-1e-8, 1e-8], "voxel_xy_m": 1.0}, "holds 0 voxels"),
        ({"voxel_xy_m": 1e-300}, "voxels of 1e-300 m, over the"),
        ({"x_range_m": [-3000, 3000], "y_range_m": [-3000, 3000]}, "MAX_GRID_VOXELS"),
    ],
    ids=["zero-cells", "voxel-1e-300", "3000m"],
)
def test_calib_lut_names_a_bad_manifest_grid(export_copy, grid, said) -> None:
    _edit_manifest(export_copy, lambda m: m["grid"].update(grid))
    line = _one_line_error(_calib_lut(export_copy))
    assert "manifest.json: grid: " in line and said in line


def test_calib_lut_names_a_lut_over_the_cap(export_copy, monkeypatch) -> None:
    monkeypatch.setattr(lut_module, "MAX_LUT_BYTES", 1024)
    line = _one_line_error(_calib_lut(export_copy))
    assert "manifest.json: a LUT for the" in line and "MAX_LUT_BYTES" in line


@pytest.mark.parametrize("lifter", [[], "fat", 3])
def test_calib_lut_names_a_lifter_that_is_not_an_object(export_copy, lifter) -> None:
    _edit_manifest(export_copy, lambda m: m["preset"].__setitem__("lifter", lifter))
    result = _calib_lut(export_copy)
    assert result.exit_code != 0 and isinstance(result.exception, SystemExit), result.output
    assert "lifter" in result.output


@pytest.mark.parametrize(
    "edit, said",
    [
        (lambda d: d["cameras"][0]["K"][0].__setitem__(0, HUGE), "cameras[0].K"),
        (lambda d: d["cameras"][0].__setitem__("width", HUGE), "cameras[0].width"),
        (lambda d: [c.update(width=16 * 10**300, height=9 * 10**300) for c in d["cameras"]], "up to 65536"),
    ],
    ids=["K", "width", "1.6e304-px"],
)
def test_calib_lut_names_a_calibration_number_past_range(export_copy, tmp_path, edit, said) -> None:
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(_calib(edit)))
    before = (export_copy / "lut.npz").read_bytes()
    assert said in _one_line_error(_calib_lut(export_copy, path))
    assert (export_copy / "lut.npz").read_bytes() == before  # nothing written


def _moved(T: np.ndarray, offset_m: float) -> np.ndarray:
    """``T`` with its camera centre moved ``offset_m`` along the LiDAR's x axis."""
    out = T.copy()
    centre = -T[:3, :3].T @ T[:3, 3] + np.array([offset_m, 0.0, 0.0])
    out[:3, 3] = -T[:3, :3] @ centre
    return out


@pytest.mark.parametrize(
    "change, pattern",
    [
        (lambda K, T: (K * np.diag([1e300, 1e300, 1]) , T), r"K: focal length fx=.* is over 1000 times the image's 1600 px side"),
        (lambda K, T: (K * np.diag([1601e3 / K[0, 0], 1, 1]), T), r"K: focal length"),
        (lambda K, T: (K + np.array([[0, 0, 1e7], [0, 0, 0], [0, 0, 0]]), T), r"K: principal point .* over 100 image sides"),
        (lambda K, T: (K - np.array([[0, 0, 0], [0, 0, 1e6], [0, 0, 0]]), T), r"K: principal point"),
        (lambda K, T: (K, _moved(T, 1e308 / 2)), r"lidar2cam: the camera is .* m from the LiDAR, over 1000 m"),
        (lambda K, T: (K, _moved(T, 1001.0)), r"lidar2cam: the camera is 100\d\.\d* m from the LiDAR"),
    ],
    ids=["fx-1e300", "fx-just-over", "cx-far", "cy-far", "offset-1e308", "offset-1km"],
)
def test_implausible_cameras_are_refused_not_blind(rig: Rig, change, pattern) -> None:
    """Numbers that no camera on a vehicle has: a CalibrationError naming the camera, not a LUT that sees nothing."""
    cam = rig.cameras[0]
    K, T = change(cam.K.copy(), cam.lidar2cam.copy())
    with pytest.raises(CalibrationError, match=rf"Camera '{cam.name}'\.{pattern}"):
        Camera(cam.name, K, T, cam.width, cam.height)
    doc = _calib(lambda d: d["cameras"][0].update(K=K.tolist(), lidar2cam={"matrix": T.tolist()}))
    with pytest.raises(CalibrationError, match=r"^calibration: cameras\[0\]"):
        Rig.from_calibration_json(doc)


def test_plausible_extremes_are_still_cameras(rig: Rig) -> None:
    cam = rig.cameras[0]
    tele = cam.K * np.diag([999.0 * 1600 / cam.K[0, 0], 999.0 * 1600 / cam.K[1, 1], 1])
    off_image = cam.K + np.array([[0, 0, 99.0 * 1600 - cam.K[0, 2]], [0, 0, 0], [0, 0, 0]])
    for K, T in ((tele, cam.lidar2cam), (off_image, cam.lidar2cam), (cam.K, _moved(cam.lidar2cam, 999.0))):
        assert Camera(cam.name, K, T, cam.width, cam.height).width == cam.width
    assert cam.resized(16, 9).K[0, 0] > 0  # resizing keeps the ratios, so never crosses a bound
