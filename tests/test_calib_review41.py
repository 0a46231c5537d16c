"""Review 41 (calib) findings C1-C6 and docs finding D4, each as a regression test.

C1 two streamdet-calib rebuilds of one export take turns (an exclusive lock) and the manifest hashes the bytes
   written; C2 Lut.load names a meta whose camera count / stride disagree with its stored sentinel / feature map;
C3 GridSpec normalises its ranges and voxel sizes and names malformed ones; C4 a camera moved out of sight is
   reported blind only, not "turned around"; C5 / D4 docs/architecture.md matches the LUT format and the folders'
   plotting dependency; C6 build_lut names an argument that is no Rig.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import streamdet.runtime_ort.calib_cli as calib_cli
from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut import Lut, moved_cameras
from streamdet.calibration.lut_build import build_lut
from streamdet.runtime_ort.manifest import ManifestError, read_manifest, sha256_file

ROOT = Path(__file__).resolve().parents[1]
CALIBRATION = ROOT / "data" / "nuscenes_sample" / "calibration.json"
TINY = GridSpec(x_range_m=(-6.4, 6.4), y_range_m=(-6.4, 6.4), z_range_m=(-1.0, 1.0), voxel_xy_m=0.4, voxel_z_m=0.5)
LOCK = ".streamdet-calib.lock"


def _calibration(tmp_path: Path, name: str, edit) -> Path:
    """The bundled calibration.json with camera 0's lidar2cam (R, t) replaced by ``edit(R, t)``."""
    d = json.loads(CALIBRATION.read_text())
    m = np.array(d["cameras"][0]["lidar2cam"]["matrix"], dtype=np.float64)
    R, t = edit(m[:3, :3], m[:3, 3])
    m[:3, :3], m[:3, 3] = R, t
    d["cameras"][0]["lidar2cam"] = {"matrix": m.tolist()}
    path = tmp_path / name
    path.write_text(json.dumps(d))
    return path


def _shifted(tmp_path: Path) -> Path:  # a routine recalibration: camera 0 moved 5 cm
    return _calibration(tmp_path, "shifted.json", lambda R, t: (R, t + np.array([0.05, 0.0, 0.0])))


def _blind(tmp_path: Path) -> Path:  # camera 0 900 m above the LiDAR, looking at the horizon: it sees no voxel
    return _calibration(tmp_path, "blind.json", lambda R, t: (R, t - R @ np.array([0.0, 0.0, 900.0])))


def _turned(tmp_path: Path) -> Path:  # camera 0 turned 180 degrees about its y axis, in place
    flip = np.diag([-1.0, 1.0, -1.0])
    return _calibration(tmp_path, "turned.json", lambda R, t: (flip @ R, flip @ t))


@pytest.fixture
def export_dir(tiny_export_fp32, tmp_path) -> Path:
    out = tmp_path / "export"
    shutil.copytree(tiny_export_fp32, out)
    return out


def _assert_consistent(export_dir: Path, calibration: Path) -> None:
    """The export opens: the manifest's sha256 is the file's, and the LUT is the one the manifest says."""
    manifest = read_manifest(export_dir)  # verifies every file's sha256
    lut = Lut.load(export_dir / "lut.npz")
    assert lut.calibration_sha256 == manifest.lut.calibration_sha256 == Rig.from_calibration_json(calibration).sha256()
    assert not (export_dir / LOCK).exists()  # the lock file is removed by its holder


# ---- C1: rebuilds take turns; the manifest hashes the bytes written ---------------------------------------------
def test_c1_a_second_rebuild_waits_for_the_first_and_the_export_stays_openable(export_dir, tmp_path, monkeypatch):
    calib_a, calib_b = _shifted(tmp_path), CALIBRATION
    real_write = calib_cli.atomic_write
    other: dict[str, object] = {}

    def write_then_race(directory, name, write):
        path = real_write(directory, name, write)
        if name == "lut.npz" and threading.current_thread() is threading.main_thread() and "thread" not in other:
            # run B between A's LUT write and A's manifest write
            other["thread"] = t = threading.Thread(target=lambda: other.setdefault("result", calib_cli.rebuild_lut(calib_b, export_dir)))
            t.start()
            t.join(timeout=1.0)
            other["finished_inside_a"] = not t.is_alive()
        return path

    monkeypatch.setattr(calib_cli, "atomic_write", write_then_race)
    calib_cli.rebuild_lut(calib_a, export_dir)
    other["thread"].join(timeout=60)
    assert "result" in other, "the second rebuild did not finish"
    assert other["finished_inside_a"] is False  # B waited for A's manifest: the two rebuilds did not interleave
    _assert_consistent(export_dir, calib_b)  # the later run's LUT and manifest, paired


def test_c1_the_manifest_records_the_bytes_written_not_a_re_read(export_dir, tmp_path, monkeypatch):
    monkeypatch.setattr(calib_cli, "sha256_file", lambda path: "0" * 64)  # a re-read would put this in the manifest
    calib_cli.rebuild_lut(_shifted(tmp_path), export_dir)
    monkeypatch.undo()
    assert read_manifest(export_dir).lut.sha256 == sha256_file(export_dir / "lut.npz")


def test_c1_a_held_lock_makes_the_rebuild_give_up_writing_nothing(export_dir, tmp_path):
    before = {p.name: p.read_bytes() for p in export_dir.iterdir()}
    fd = os.open(export_dir / LOCK, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with pytest.raises(calib_cli.ExportBusy, match=r"another streamdet-calib run holds .*\.streamdet-calib\.lock"):
            calib_cli.rebuild_lut(_shifted(tmp_path), export_dir, lock_wait_s=0.2)
        assert {p.name: p.read_bytes() for p in export_dir.iterdir() if p.name != LOCK} == before
    finally:
        os.close(fd)
        (export_dir / LOCK).unlink()


def test_c1_the_cli_reports_a_busy_export_in_one_line(export_dir, tmp_path, monkeypatch):
    monkeypatch.setattr(calib_cli, "LOCK_WAIT_S", 0.2)
    fd = os.open(export_dir / LOCK, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        result = CliRunner().invoke(calib_cli.main, ["lut", "--calibration", str(CALIBRATION), "--export-dir", str(export_dir)])
    finally:
        os.close(fd)
    assert result.exit_code == 1 and "another streamdet-calib run holds" in result.output
    assert "Traceback" not in result.output


def test_c1_a_rebuild_leaves_only_lut_and_manifest_changed(export_dir, tmp_path):
    before = {p.name: p.read_bytes() for p in export_dir.iterdir()}
    calib_cli.rebuild_lut(_shifted(tmp_path), export_dir)
    after = {p.name: p.read_bytes() for p in export_dir.iterdir()}
    assert set(after) == set(before)  # no lock file (nor temp file) left behind
    assert {n for n in after if after[n] != before[n]} == {"lut.npz", "manifest.json"}
    _assert_consistent(export_dir, tmp_path / "shifted.json")


def test_c1_a_stale_lock_file_is_taken_over_and_removed(export_dir, tmp_path):
    (export_dir / LOCK).write_bytes(b"")  # left by a run that was killed: flock died with it
    calib_cli.rebuild_lut(_shifted(tmp_path), export_dir)
    _assert_consistent(export_dir, tmp_path / "shifted.json")


@pytest.mark.parametrize("kind", ["symlink", "directory", "fifo"])
def test_c1_a_lock_path_that_is_no_regular_file_is_refused_untouched(export_dir, tmp_path, kind):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    lock = export_dir / LOCK
    {"symlink": lambda: lock.symlink_to(victim), "directory": lock.mkdir, "fifo": lambda: os.mkfifo(lock)}[kind]()
    before = {p.name: p.read_bytes() for p in export_dir.iterdir() if p.is_file() and p.name != LOCK}
    with pytest.raises(ManifestError, match=r"\.streamdet-calib\.lock: the rebuild lock is"):
        calib_cli.rebuild_lut(_shifted(tmp_path), export_dir, lock_wait_s=0.2)
    assert victim.read_text() == "precious" and (lock.is_symlink() or lock.exists())
    assert {p.name: p.read_bytes() for p in export_dir.iterdir() if p.is_file() and p.name != LOCK} == before


def test_c1_a_manifest_changed_during_the_build_is_not_overwritten(export_dir, tmp_path, monkeypatch):
    real_build = calib_cli.build_lut

    def build_while_reexported(*args, **kwargs):
        d = json.loads((export_dir / "manifest.json").read_text())
        d["num_slices"] = 4 if d["num_slices"] != 4 else 8  # another tool rewrote the export meanwhile
        (export_dir / "manifest.json").write_text(json.dumps(d))
        return real_build(*args, **kwargs)

    monkeypatch.setattr(calib_cli, "build_lut", build_while_reexported)
    lut_before = (export_dir / "lut.npz").read_bytes()
    with pytest.raises(ManifestError, match="changed while the LUT was built"):
        calib_cli.rebuild_lut(_shifted(tmp_path), export_dir)
    assert (export_dir / "lut.npz").read_bytes() == lut_before


def test_c1_calib_cli_stays_torch_free() -> None:
    import subprocess
    import sys

    code = ("import sys, streamdet.runtime_ort.calib_cli, streamdet.calibration.grid, streamdet.calibration.lut_build; "
            "bad = [m for m in ('torch', 'streamdet.models', 'streamdet.export') if m in sys.modules]; "
            "sys.exit(f'imported {bad}' if bad else 0)")  # fmt: skip
    subprocess.run([sys.executable, "-c", code], check=True)


# ---- C2: a meta that disagrees with its own sentinel / feature map is named ---------------------------------------
@pytest.fixture(scope="module")
def tiny_lut() -> Lut:
    return build_lut(Rig.from_calibration_json(CALIBRATION), TINY, 4, image_size=(64, 36))


def _with_meta(lut: Lut, path: Path, **changes) -> Path:
    meta = {**lut.meta(), **changes}
    np.savez(path, index=lut.index, weight=lut.weight, meta=np.array(json.dumps(meta, sort_keys=True)))
    return path


@pytest.mark.parametrize(
    "changes, pattern",
    [
        ({"camera_names": ["A", "B", "C"]}, r"meta\.sentinel: stored 864, but camera_names \(3 cameras\), feature_stride 4 and image size 64x36 imply 432"),
        ({"camera_names": [f"C{i}" for i in range(7)]}, r"meta\.sentinel: stored 864, but .* imply 1008"),
        ({"feature_stride": 1}, r"meta\.feature_width: stored 16, but .*feature_stride 1 and image size 64x36 imply 64"),
        ({"feature_stride": 8}, r"meta\.feature_width: stored 16, .* imply 8"),
        ({"image_height": 72}, r"meta\.feature_height: stored 9, .* imply 18"),
        ({"sentinel": 865}, r"meta\.sentinel: stored 865, .* imply 864"),
        ({"sentinel": 864.0}, r"meta\.sentinel: stored 864\.0"),
        ({"feature_width": True}, r"meta\.feature_width: stored True"),
    ],
)
def test_c2_a_meta_disagreeing_with_its_sentinel_is_named(tiny_lut, tmp_path, changes, pattern):
    with pytest.raises(CalibrationError, match=pattern):
        Lut.load(_with_meta(tiny_lut, tmp_path / "lut.npz", **changes))


@pytest.mark.parametrize("version", [True, 1.0, "1", None, 2])
def test_c2_only_the_integer_version_1_is_read(tiny_lut, tmp_path, version):
    with pytest.raises(CalibrationError, match=r"meta\.format/version: expected 'streamdet-lut' v1"):
        Lut.load(_with_meta(tiny_lut, tmp_path / "lut.npz", version=version))


@pytest.mark.parametrize("changes", [{"feature_stride": "4"}, {"image_width": -64}, {"camera_names": "AB"}])
def test_c2_a_field_of_the_wrong_type_is_still_named_by_lut(tiny_lut, tmp_path, changes):
    (key,) = changes
    with pytest.raises(CalibrationError, match=key):
        Lut.load(_with_meta(tiny_lut, tmp_path / "lut.npz", **changes))


def test_c2_a_saved_lut_still_loads(tiny_lut, tmp_path):
    tiny_lut.save(tmp_path / "lut.npz")
    loaded = Lut.load(tmp_path / "lut.npz")
    assert loaded.meta() == tiny_lut.meta()


# ---- C3: GridSpec normalises its ranges and voxel sizes -----------------------------------------------------------
RANGES = {
    "tuple": (-4.0, 4.0),
    "list": [-4.0, 4.0],
    "ints": (-4, 4),
    "numpy ints": (np.int64(-4), np.int64(4)),
    "numpy floats": (np.float32(-4.0), np.float64(4.0)),
    "array": np.array([-4.0, 4.0]),
}


@pytest.mark.parametrize("kind", list(RANGES))
def test_c3_ranges_become_tuples_of_floats(kind):
    r = RANGES[kind]
    g = GridSpec(r, r, (-1, 1), np.int64(1), 1)
    ref = GridSpec((-4.0, 4.0), (-4.0, 4.0), (-1.0, 1.0), 1.0, 1.0)
    assert g == ref and hash(g) == hash(ref) and repr(g) == repr(ref)
    for name in ("x_range_m", "y_range_m", "z_range_m"):
        value = getattr(g, name)
        assert type(value) is tuple and all(type(v) is float for v in value), (name, value)
    assert type(g.voxel_xy_m) is float and type(g.voxel_z_m) is float
    json.dumps(g.to_dict())  # no numpy scalar left: a LUT's meta and a manifest can be written


def test_c3_a_list_ranged_grid_works_with_the_cached_slice_maps_and_saves(tmp_path):
    from streamdet.calibration.slice_maps import slice_maps

    g = GridSpec([-6.4, 6.4], [-6.4, 6.4], [np.int64(-1), 1], 0.4, 0.5)
    assert g == TINY
    slice_maps(g, (0,))  # its lru_cache hashed the grid
    lut = build_lut(Rig.from_calibration_json(CALIBRATION), g, 4, image_size=(64, 36))
    lut.save(tmp_path / "lut.npz")
    assert Lut.load(tmp_path / "lut.npz", grid=TINY).grid == TINY


BAD_RANGES = [(-4, 4, 1), (4.0,), (), ("a", "b"), "ab", "-4,4", 4.0, None, (True, 2), (-4.0, np.bool_(True)),
              {"lo": -4, "hi": 4}, {-4.0, 4.0}, np.array([[-4.0, 4.0]]), (-4.0, "4"), (-4.0, [4.0])]  # fmt: skip


@pytest.mark.parametrize("value", BAD_RANGES, ids=repr)
@pytest.mark.parametrize("name", ["x_range_m", "z_range_m"])
def test_c3_a_malformed_range_is_named_with_its_value(name, value):
    with pytest.raises(ValueError, match=rf"GridSpec\.{name} must be a \(min, max\) pair of numbers, got "):
        GridSpec(**{name: value})


@pytest.mark.parametrize("value", [True, False, np.bool_(True), "1", " 1 ", None, [1.0], (1.0,), np.array([1.0]), 0, -1.0,
                                   float("nan"), float("inf"), 10**400])  # fmt: skip
@pytest.mark.parametrize("name", ["voxel_xy_m", "voxel_z_m"])
def test_c3_a_bad_voxel_size_is_named_with_its_value(name, value):
    with pytest.raises(ValueError, match=rf"GridSpec\.{name} must be a finite number > 0 .*, got "):
        GridSpec(**{name: value})


@pytest.mark.parametrize(
    "field, value",
    [("voxel_xy_m", " 1 "), ("voxel_z_m", "0.5"), ("voxel_xy_m", True), ("x_range_m", "ab"), ("x_range_m", [-4, 4, 1]),
     ("z_range_m", ["-1", "1"]), ("y_range_m", {"a": 1, "b": 2})],
)  # fmt: skip
def test_c3_from_dict_reads_no_string_or_bool_as_a_number(field, value):
    d = {**GridSpec(x_range_m=(-4.0, 4.0), y_range_m=(-4.0, 4.0), voxel_xy_m=1.0).to_dict(), field: value}
    with pytest.raises(ValueError, match=rf"GridSpec\.{field} must be"):
        GridSpec.from_dict(d)


def test_c3_from_dict_round_trips_saved_grids():
    for g in (GridSpec(), TINY, GridSpec(x_range_m=(-4, 4), y_range_m=(-4, 4), voxel_xy_m=1)):
        assert GridSpec.from_dict(json.loads(json.dumps(g.to_dict()))) == g
    # a grid written with integer numbers (JSON 1, not 1.0) reads as the float one
    assert GridSpec.from_dict({"x_range_m": [-4, 4], "y_range_m": [-4, 4], "z_range_m": [-1, 1], "voxel_xy_m": 1,
                               "voxel_z_m": 1}) == GridSpec((-4.0, 4.0), (-4.0, 4.0), (-1.0, 1.0), 1.0, 1.0)  # fmt: skip


def test_c3_a_lut_meta_with_a_malformed_grid_names_the_field(tiny_lut, tmp_path):
    grid = {**TINY.to_dict(), "x_range_m": [-6.4, 6.4, 1]}
    with pytest.raises(CalibrationError, match=r"meta\.grid: GridSpec\.x_range_m must be a \(min, max\) pair of numbers, got \[-6\.4, 6\.4, 1\]"):
        Lut.load(_with_meta(tiny_lut, tmp_path / "lut.npz", grid=grid))


# ---- C4: a camera moved out of sight is blind, not "turned around" -------------------------------------------------
@pytest.fixture(scope="module")
def luts(tmp_path_factory) -> dict[str, Lut]:
    tmp = tmp_path_factory.mktemp("c4")
    rigs = {"base": CALIBRATION, "blind": _blind(tmp), "turned": _turned(tmp)}
    return {k: build_lut(Rig.from_calibration_json(v), TINY, 4, image_size=(64, 36)) for k, v in rigs.items()}


def test_c4_a_blind_camera_is_not_reported_as_moved(luts):
    assert luts["blind"].slots_per_camera()["CAM_FRONT"] == 0
    assert moved_cameras(luts["base"], luts["blind"]) == []


def test_c4_a_turned_camera_is_still_reported(luts):
    moved = moved_cameras(luts["base"], luts["turned"])
    assert [name for name, _ in moved] == ["CAM_FRONT"] and moved[0][1] < 0.5


def test_c4_the_cli_warns_once_for_a_blind_camera(export_dir, tmp_path):
    result = CliRunner().invoke(calib_cli.main, ["lut", "--calibration", str(_blind(tmp_path)), "--export-dir", str(export_dir)])
    assert result.exit_code == 0, result.output
    assert "camera CAM_FRONT sees no voxel" in result.output
    assert "turned around" not in result.output


# ---- C5 / D4: docs/architecture.md ------------------------------------------------------------------------------
ARCH = (ROOT / "docs" / "architecture.md").read_text()


def test_c5_the_lut_format_doc_names_every_meta_field_and_one_json_member(tiny_lut):
    para = ARCH[ARCH.index("Metadata is stored beside"):]
    para = para[: para.index("\n\n")]
    assert "0-d / 1-d arrays" not in ARCH
    fields = set(tiny_lut.meta()) | {"heights_per_voxel"}
    missing = [k for k in sorted(fields) if f"`{k}`" not in para]
    assert not missing, missing


def test_d4_every_folder_that_plots_lists_matplotlib():
    for folder in ("data", "studies", "replay"):
        plots = any(re.search(r"^\s*import matplotlib", p.read_text(), re.M) for p in (ROOT / folder).rglob("*.py"))
        (row,) = [line for line in ARCH.splitlines() if line.startswith(f"| `{folder}/` |")]
        needs = row.split("|")[3]
        assert plots and "matplotlib" in needs, (folder, needs)


# ---- C6: build_lut names an argument that is no Rig -------------------------------------------------------------
@pytest.mark.parametrize("rig", [{"cameras": []}, None, [], "calibration.json", CALIBRATION], ids=repr)
def test_c6_build_lut_names_a_rig_that_is_no_rig(rig):
    with pytest.raises(ValueError, match=r"rig must be a Rig \(Rig\.from_calibration_json for a dict or file\), got "):
        build_lut(rig, TINY, 4, image_size=(64, 36))


def test_c6_build_lut_with_heights_names_it_too():
    with pytest.raises(ValueError, match=r"rig must be a Rig .*got dict"):
        build_lut({"cameras": []}, TINY, 4, image_size=(64, 36), heights_per_voxel=2)

