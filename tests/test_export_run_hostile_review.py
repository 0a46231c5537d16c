"""Fixes of the hostile-input review of streamdet-export / -run / -bench (review37 train_export: H1, M3, M4, M6 and M7
export parts, L4, L5, L6, L7, L9, and the staging clean-up suspicion): each bad input is a one-line error naming
what is wrong, before any work, with nothing written."""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from streamdet.models.detector import build_detector
from streamdet.models.presets import Preset, get_preset
from streamdet.models.torch_files import check_dense, check_fits, check_state_dict

TINY = get_preset("tiny")
REPO = Path(__file__).resolve().parents[1]


def _one_line_error(result, code: int, *needles: str) -> str:
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    errors = [line for line in result.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, result.output
    for needle in needles:
        assert needle in errors[0], errors[0]
    return errors[0]




@pytest.fixture(scope="module")
def lidar_weights(tmp_path_factory) -> Path:
    from streamdet.training.checkpoint import save_weights

    preset = dataclasses.replace(TINY, use_image=False)
    path = tmp_path_factory.mktemp("lo") / "lidar.pt"
    save_weights(path, preset, build_detector(preset))
    return path


def _export(args: list[str]):
    from streamdet.export.cli import main

    return CliRunner().invoke(main, args)


def _run(args: list[str]):
    from streamdet.evaluation.run_cli import main

    return CliRunner().invoke(main, args)


# ---- H1: streamdet-run's bev.png and results_nusc.json ---------------------------------------------------------


@pytest.mark.parametrize("name", ["bev.png", "results_nusc.json"])
def test_run_refuses_a_fifo_at_an_output_before_any_work(tiny_export, tmp_path, name):
    out = tmp_path / "out"
    out.mkdir()
    os.mkfifo(out / name)
    _one_line_error(_run(["--export-dir", str(tiny_export), "--out", str(out)]), 2, "--out", name, "not a regular file")
    assert sorted(p.name for p in out.iterdir()) == [name]  # the other file was not written


def test_run_refuses_a_link_into_the_export_and_leaves_the_export_alone(tiny_export, tmp_path):
    export = tmp_path / "exp"
    shutil.copytree(tiny_export, export)
    before = (export / "lut.npz").read_bytes()
    out = tmp_path / "out"
    out.mkdir()
    (out / "bev.png").symlink_to(export / "lut.npz")
    _one_line_error(_run(["--export-dir", str(export), "--out", str(out)]), 2, "bev.png", "lies inside the input --export-dir")
    assert (export / "lut.npz").read_bytes() == before and not (out / "results_nusc.json").exists()


def test_run_replaces_a_link_at_bev_png_instead_of_writing_through_it(tiny_export, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    out = tmp_path / "out"
    out.mkdir()
    (out / "bev.png").symlink_to(victim)
    result = _run(["--export-dir", str(tiny_export), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert victim.read_text() == "keep me"
    png = out / "bev.png"
    assert not png.is_symlink() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in out.iterdir()) == ["bev.png", "results_nusc.json"]  # no temp file left


def test_run_refuses_an_out_that_is_a_file_or_under_one(tiny_export, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _one_line_error(_run(["--export-dir", str(tiny_export), "--out", str(blocker)]), 2, "--out")
    _one_line_error(_run(["--export-dir", str(tiny_export), "--out", str(blocker / "sub")]), 2, "--out", "not a folder")


# ---- L5: --slices 6 is a usage error ------------------------------------------------------------------------


@pytest.mark.parametrize("value", ["6", "0", "-8"])
def test_run_slices_not_a_slice_count_is_a_usage_error(tiny_export, tmp_path, value):
    _one_line_error(_run(["--export-dir", str(tiny_export), "--out", str(tmp_path / "o"), "--slices", value]), 2, "--slices")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("value", ["6", "3"])
def test_export_slices_not_a_slice_count_is_a_usage_error(tmp_path, value):
    _one_line_error(_export(["--preset", "tiny", "--out", str(tmp_path / "exp"), "--slices", value]), 2, "--slices")
    assert not (tmp_path / "exp").exists()


# ---- M3: sparse / meta / quantized tensors in a checkpoint -------------------------------------------------------


def _hostile(kind: str, shape: tuple[int, ...] = (4,)) -> torch.Tensor:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # quantized tensors are deprecated
        if kind == "sparse":
            return torch.zeros(shape).to_sparse()
        if kind == "meta":
            return torch.empty(shape, device="meta")
        return torch.quantize_per_tensor(torch.zeros(shape), 1.0, 0, torch.qint8)


@pytest.mark.parametrize("kind", ["sparse", "meta", "quantized"])
def test_check_state_dict_and_check_fits_refuse_a_tensor_that_is_no_dense_weight(kind):
    tensor = _hostile(kind)
    with pytest.raises(ValueError, match=rf"^checkpoint f\.pt: w is a {kind} tensor .*not a dense weight$"):
        check_dense(tensor, "w", "f.pt")
    with pytest.raises(ValueError, match=rf"checkpoint f\.pt: w is a {kind} tensor"):
        check_state_dict({"w": tensor}, "f.pt")
    with pytest.raises(ValueError, match=rf"checkpoint f\.pt: w is a {kind} tensor"):
        check_fits({"w": torch.zeros(4)}, {"w": tensor}, "f.pt")
    check_fits({"w": torch.zeros(4)}, {"w": torch.zeros(4)}, "f.pt")  # a dense one still fits


@pytest.mark.parametrize("kind", ["sparse", "meta"])
def test_export_of_a_checkpoint_with_a_sparse_or_meta_tensor_is_one_line(tiny_weights, tmp_path, kind):
    obj = torch.load(tiny_weights, weights_only=True)
    key = next(k for k, v in obj["model"].items() if v.is_floating_point() and v.dim() == 1)
    obj["model"] = {**obj["model"], key: _hostile(kind, tuple(obj["model"][key].shape))}
    path = tmp_path / f"{kind}.pt"
    torch.save(obj, path)
    _one_line_error(_export(["--checkpoint", str(path), "--out", str(tmp_path / "exp")]), 1, str(path), key, f"{kind} tensor")
    assert not (tmp_path / "exp").exists()
    from streamdet.training.checkpoint import load_weights

    with pytest.raises(ValueError, match=rf"{key} is a {kind} tensor"):
        load_weights(path)


# ---- M4, L7: a malformed preset dict --------------------------------------------------------------------------

MALFORMED = {
    "bev_list": (lambda d: d.__setitem__("bev", [1, 2]), "bev must be a mapping"),
    "channels_inf": (lambda d: d.__setitem__("channels", float("inf")), "channels must be an integer, got float inf"),
    "channels_float": (lambda d: d.__setitem__("channels", 8.9), "channels must be an integer, got float 8.9"),
    "channels_whole_float": (lambda d: d.__setitem__("channels", 8.0), "channels must be an integer, got float 8.0"),
    "channels_str": (lambda d: d.__setitem__("channels", "8"), "channels must be an integer, got str '8'"),
    "channels_bool": (lambda d: d.__setitem__("channels", True), "channels must be an integer, got bool True"),
    "channels_huge": (lambda d: d.__setitem__("channels", 10**5000), "channels must be an integer below 2\\*\\*63"),
    "use_image_str": (lambda d: d.__setitem__("use_image", "no"), "use_image must be true or false, got str 'no'"),
    "use_image_int": (lambda d: d.__setitem__("use_image", 1), "use_image must be true or false"),
    "slice_crop_int": (lambda d: d.__setitem__("slice_crop", 0), "slice_crop must be true or false"),
    "norm_flag_str": (lambda d: d.__setitem__("image_bev_norm", "false"), "image_bev_norm must be true or false"),
    "name_int": (lambda d: d.__setitem__("name", 5), "name must be a string"),
    "not_a_dict": (None, "expected a mapping of fields"),
    "grid_list": (lambda d: d.__setitem__("grid", [0.4]), "grid must be a mapping"),
    "grid_str_voxel": (lambda d: d["grid"].__setitem__("voxel_xy_m", "0.4"), "grid.voxel_xy_m must be a finite number"),
    "grid_nan": (lambda d: d["grid"].__setitem__("voxel_z_m", float("nan")), "grid.voxel_z_m must be a finite number"),
    "grid_range_len": (lambda d: d["grid"].__setitem__("x_range_m", [1, 2, 3]), "grid.x_range_m must hold 2 entries"),
    "grid_range_bool": (lambda d: d["grid"].__setitem__("x_range_m", [True, 2]), r"grid.x_range_m\[0\] must be a finite number"),
    "grid_missing": (lambda d: d["grid"].pop("voxel_xy_m"), "lacks the field 'grid.voxel_xy_m'"),
    "grid_unknown": (lambda d: d["grid"].__setitem__("tilt", 1), "grid.tilt is not a field of GridSpec"),
    "image_float": (lambda d: d["image"].__setitem__("width_px", 128.0), "image.width_px must be an integer"),
    "image_unknown": (lambda d: d["image"].__setitem__("colour", "rgb"), "image.colour is not a field of ImageConfig"),
    "lifter_list": (lambda d: d["lifter"].__setitem__("form", ["flat"]), "lifter.form must be a string"),
    "bev_str": (lambda d: d["bev"].__setitem__("upsample_strides", "ab"), "bev.upsample_strides must be a list"),
    "bev_float_int": (lambda d: d["bev"].__setitem__("layer_nums", [1.0, 1]), r"bev.layer_nums\[0\] must be an integer"),
    "bev_inf": (lambda d: d["bev"].__setitem__("upsample_strides", [0.5, float("inf")]), r"bev.upsample_strides\[1\] must be a finite"),
    "head_tasks_str": (lambda d: d["head"].__setitem__("tasks", "car"), "head.tasks must be a list"),
    "head_tasks_int": (lambda d: d["head"].__setitem__("tasks", [[1]]), r"head.tasks\[0\]\[0\] must be a string"),
    "head_multi_str": (lambda d: d["head"].__setitem__("multi_head", "false"), "head.multi_head must be true or false"),
    "head_bias_inf": (lambda d: d["head"].__setitem__("heatmap_bias_init", float("-inf")), "head.heatmap_bias_init must be a finite"),
    "post_nms_dict": (lambda d: d["post"].__setitem__("nms_iou_threshold", {"a": 1}), "post.nms_iou_threshold must be a list"),
    "post_topk_float": (lambda d: d["post"].__setitem__("top_k", 50.5), "post.top_k must be an integer"),
    "pillars_none": (lambda d: d.__setitem__("pillars", None), "pillars must be a mapping"),
}


@pytest.mark.parametrize("name", list(MALFORMED))
def test_from_dict_refuses_a_malformed_preset_naming_the_field(name):
    edit, match = MALFORMED[name]
    d = copy.deepcopy(TINY.to_dict())
    if edit is None:
        d = [d]
    else:
        edit(d)
    with pytest.raises(ValueError, match=match) as info:
        Preset.from_dict(d)
    assert "\n" not in str(info.value) and len(str(info.value)) < 300


def test_from_dict_still_reads_every_preset_and_its_json_round_trip():
    from streamdet.models.presets import preset_names

    for name in preset_names():
        p = get_preset(name)
        assert Preset.from_dict(p.to_dict()) == p
        assert Preset.from_dict(json.loads(json.dumps(p.to_dict()))) == p
    d = json.loads(json.dumps(TINY.to_dict()))
    d["bev"]["upsample_strides"] = [0.5, 1]  # an int where a float is: a number, read as it is
    assert Preset.from_dict(d) == TINY


def test_every_shipped_and_documented_checkpoint_preset_still_reads():
    """Every checkpoint under models/weights (sub-folders too) and docs/ that saves a preset reads under the strict
    reader: none stored a coerced value."""
    files = sorted((REPO / "models" / "weights").rglob("*.pt")) + sorted((REPO / "docs").rglob("*.pt"))
    read = 0
    for path in files:
        obj = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        if isinstance(obj, dict) and isinstance(obj.get("preset"), dict):
            Preset.from_dict(obj["preset"])
            read += 1
    assert read >= 5


@pytest.mark.parametrize("name", ["bev_list", "channels_inf", "channels_float", "use_image_str"])
def test_export_of_a_checkpoint_with_a_malformed_preset_is_one_line(tiny_weights, tmp_path, name):
    edit, match = MALFORMED[name]
    obj = torch.load(tiny_weights, weights_only=True)
    edit(obj["preset"])
    path = tmp_path / f"{name}.pt"
    torch.save(obj, path)
    line = _one_line_error(_export(["--checkpoint", str(path), "--preset", "tiny", "--out", str(tmp_path / "exp")]), 1,
                           str(path), "unreadable preset")  # fmt: skip
    assert "malformed" in line
    assert not (tmp_path / "exp").exists()


# ---- M6: an export into a dataset's linked table folder -----------------------------------------------------------


def test_export_out_inside_the_calibration_datasets_linked_table_folder_is_refused(tmp_path):
    tables = tmp_path / "tables"
    tables.mkdir()
    (tables / "sample.json").write_text("[]")
    data = tmp_path / "data"
    data.mkdir()
    (data / "v1.0-synth").symlink_to(tables, target_is_directory=True)
    _one_line_error(_export(["--preset", "tiny", "--int8", "--calibration-data", str(data), "--out", str(tables / "exp")]),
                    2, "--out", "--calibration-data's v1.0-synth")  # fmt: skip
    assert sorted(p.name for p in tables.iterdir()) == ["sample.json"]


# ---- M7: options this export would ignore ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "args, named",
    [
        (["--image-layout", "image_half"], "--image-layout"),
        (["--image-layout", "image_bev"], "--image-layout"),  # the default, typed: still an option it ignores
        (["--lut-layout", "slots"], "--lut-layout"),
        (["--resolution", "800x450"], "--resolution"),
        (["--calibration", str(REPO / "data" / "nuscenes_sample" / "calibration.json")], "--calibration"),
        (["--seed", "5"], "--seed"),
    ],
)
def test_a_lidar_only_export_refuses_the_image_options(lidar_weights, tmp_path, args, named):
    line = _one_line_error(_export(["--checkpoint", str(lidar_weights), *args, "--out", str(tmp_path / "exp")]), 2, named)
    if named != "--seed":
        assert "LiDAR-only" in line
    assert not (tmp_path / "exp").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_calibration_samples_without_int8_is_refused(tmp_path):
    _one_line_error(_export(["--preset", "tiny", "--calibration-samples", "5", "--out", str(tmp_path / "exp")]), 2,
                    "--calibration-samples", "--int8")  # fmt: skip
    assert not (tmp_path / "exp").exists()


def test_seed_with_a_checkpoint_of_the_bundled_cameras_is_refused(tiny_weights, tmp_path):
    _one_line_error(_export(["--checkpoint", str(tiny_weights), "--seed", "5", "--out", str(tmp_path / "exp")]), 2,
                    "--seed 5 would be ignored", str(tiny_weights))  # fmt: skip
    assert not (tmp_path / "exp").exists()


def test_seed_with_the_bundled_checkpoint_of_a_preset_is_refused():
    from streamdet.export.exporter import ExportOptions, ExportUsageError, _check_options, _resolve_preset
    from streamdet.export.weights import bundled_checkpoint

    if bundled_checkpoint("small_v3") is None:
        pytest.skip("no bundled small_v3 checkpoint in this checkout")
    opts = ExportOptions(preset="small_v3", seed=3)
    with pytest.raises(ExportUsageError, match="--seed 3 would be ignored: .*the bundled checkpoint"):
        _check_options(opts, _resolve_preset(opts)[0])


def test_seed_is_kept_where_it_still_draws_something(tiny_weights, tmp_path):
    """Without a checkpoint it draws the weights; with one and a calibration of other cameras it draws the parity
    check's noise images (export/parity_inputs.py): both are accepted. The int8 calibration draws no random sample."""
    from streamdet.export.exporter import ExportOptions, _check_options, _resolve_preset
    from test_export_cli import two_camera_calibration

    calib = two_camera_calibration(tmp_path)
    for opts in (ExportOptions(preset="tiny", seed=5), ExportOptions(checkpoint=str(tiny_weights), calibration=str(calib), seed=5)):
        _check_options(opts, _resolve_preset(opts)[0])


def test_options_not_given_are_not_refused(lidar_weights, tmp_path):
    """The refusals look at what was typed: a plain LiDAR-only export and a plain export with a checkpoint pass the
    checks (their defaults: image layout, LUT layout, seed, calibration samples)."""
    from streamdet.export.exporter import ExportOptions, _check_options, _resolve_preset

    # (--calibration-samples with --int8 needs --calibration-data since review 41 F4: the bundled sample is one sample)
    for opts in (ExportOptions(checkpoint=str(lidar_weights)), ExportOptions(preset="tiny", int8=True)):
        _check_options(opts, _resolve_preset(opts)[0])
    result = _export(["--checkpoint", str(lidar_weights), "--seed", "0", "--out", str(tmp_path / "exp")])
    _one_line_error(result, 2, "--seed 0 would be ignored")  # typed, even at its default value


# ---- L4: --out '.', '' and '/' --------------------------------------------------------------------------------


@pytest.mark.parametrize("out, needle", [(".", "is the current folder"), ("./", "is the current folder"), ("", "is empty"),
                                         ("/", "is the root folder"), ("..", "ends in '..'")])  # fmt: skip
def test_export_out_that_names_no_folder_of_its_own_is_one_line(tmp_path, monkeypatch, out, needle):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    _one_line_error(_export(["--preset", "tiny", "--out", out]), 1, f"--out {out!r}", needle)
    assert list(work.iterdir()) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["work"]


def test_export_out_spelled_as_the_current_folder_another_way_is_refused(tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    (tmp_path / "link").symlink_to(work, target_is_directory=True)
    monkeypatch.chdir(work)
    for out in ("../work", str(work), str(tmp_path / "link")):
        _one_line_error(_export(["--preset", "tiny", "--out", out]), 1, "is the current folder")
    assert list(work.iterdir()) == []


# ---- L6: the aspect-mismatch error names the sample's own folder ------------------------------------------------


def test_sample_folder_of_both_layouts(tmp_path):
    from streamdet.runtime_ort.pipeline import sample_folder

    bundled = tmp_path / "mysample"
    bundled.mkdir()
    (bundled / "calibration.json").write_text("{}")
    assert sample_folder(bundled / "CAM_FRONT.jpg") == bundled
    named_samples = tmp_path / "samples"  # a sample folder that happens to be called "samples"
    named_samples.mkdir()
    (named_samples / "calibration.json").write_text("{}")
    assert sample_folder(named_samples / "cam.jpg") == named_samples
    assert sample_folder(bundled / "imgs" / "cam.jpg") == bundled  # files in a sub-folder of the sample
    data = tmp_path / "DATA"
    assert sample_folder(data / "samples" / "CAM_FRONT" / "x.jpg") == data
    assert sample_folder(Path("DATA/samples/CAM_FRONT/x.jpg")) == Path("DATA")


def test_a_sample_folder_of_another_aspect_is_named_itself(tiny_export, tmp_path, monkeypatch):
    from streamdet.calibration.camera import CalibrationError
    from streamdet.data.sample import bundled_sample_dir, load_bundled_sample
    from streamdet.runtime_ort.detector import StreamingDetector
    from streamdet.runtime_ort.pipeline import feed_images

    copy_dir = tmp_path / "l6s"
    shutil.copytree(bundled_sample_dir(), copy_dir)
    doc = json.loads((copy_dir / "calibration.json").read_text())
    for cam in doc["cameras"]:
        cam.update(width=1600, height=1200)
    (copy_dir / "calibration.json").write_text(json.dumps(doc))
    monkeypatch.chdir(tmp_path)
    sample = load_bundled_sample("l6s")
    det = StreamingDetector(tiny_export)
    try:
        with pytest.raises(CalibrationError, match=rf"^sample {sample.token} \(l6s\): calibration camera"):
            feed_images(det, sample)
    finally:
        det.close()


# ---- L9: streamdet-bench opens the export before timing -----------------------------------------------------------


def test_bench_refuses_a_swapped_graph_before_any_timing(tiny_export, tmp_path, monkeypatch):
    import streamdet.benchmarks.run as bench_run
    from streamdet.benchmarks.cli import main as bench_main

    export = tmp_path / "l9"
    shutil.copytree(tiny_export, export)
    shutil.copy(export / "volumetric_lifter.onnx", export / "slice_head.onnx")
    manifest = json.loads((export / "manifest.json").read_text())
    for g in manifest["graphs"]:
        if g["file"] == "slice_head.onnx":
            g["sha256"] = hashlib.sha256((export / "slice_head.onnx").read_bytes()).hexdigest()
    (export / "manifest.json").write_text(json.dumps(manifest))

    def timed(*args, **kwargs):
        raise AssertionError("rows timed before the export was checked")

    monkeypatch.setattr(bench_run, "run_benchmark", timed)
    result = CliRunner().invoke(bench_main, ["--preset", "tiny", "--quick", "--no-int8", "--no-fp16", "--repeat", "1",
                                             "--export-dir", str(export)])  # fmt: skip
    _one_line_error(result, 2, "--export-dir", "slice_head.onnx")


# ---- the export's stale-staging clean-up removes only its own folders ---------------------------------------------


def _dead_pid() -> int:
    out = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True)
    return int(out.stdout)


def test_stale_staging_clean_up_keeps_a_folder_that_merely_has_the_name(tmp_path):
    from streamdet.export.staging import STAGING_MARKER, STAGING_MARKER_TEXT, clean_stale_staging

    out = tmp_path / "exp"
    pid = _dead_pid()
    foreign = tmp_path / f".exp.partial-{pid}-mine"  # a user's folder of that name: no marker
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    other_pid = tmp_path / f".exp.old-{pid}-x"  # a marker naming another pid than the folder's
    other_pid.mkdir()
    (other_pid / STAGING_MARKER).write_text(f"{STAGING_MARKER_TEXT} {pid + 1}\n")
    linked = tmp_path / f".exp.partial-{pid}-y"  # a marker that is a link
    linked.mkdir()
    (tmp_path / "target").write_text(f"{STAGING_MARKER_TEXT} {pid}\n")
    (linked / STAGING_MARKER).symlink_to(tmp_path / "target")
    folder_link = tmp_path / f".exp.partial-{pid}-z"  # a link to a marked folder
    marked_elsewhere = tmp_path / "elsewhere"
    marked_elsewhere.mkdir()
    (marked_elsewhere / STAGING_MARKER).write_text(f"{STAGING_MARKER_TEXT} {pid}\n")
    folder_link.symlink_to(marked_elsewhere, target_is_directory=True)
    ours = tmp_path / f".exp.partial-{pid}-ours"  # what a killed export left: marked with its pid
    ours.mkdir()
    (ours / STAGING_MARKER).write_text(f"{STAGING_MARKER_TEXT} {pid}\n")
    clean_stale_staging(out)
    assert (foreign / "notes.txt").read_text() == "keep me"
    assert other_pid.is_dir() and linked.is_dir() and folder_link.is_symlink() and (marked_elsewhere / STAGING_MARKER).is_file()
    assert not ours.exists()


def test_an_export_carries_no_staging_marker(tiny_export):
    from streamdet.export.staging import STAGING_MARKER

    assert not (tiny_export / STAGING_MARKER).exists()
    assert (tiny_export / "manifest.json").is_file()


def test_staging_folders_carry_the_marker_and_a_failed_export_leaves_nothing(tmp_path):
    from streamdet.export.staging import STAGING_MARKER, commit_staging_dir, make_staging_dir

    out = tmp_path / "exp"
    tmp = make_staging_dir(out)
    assert (tmp / STAGING_MARKER).is_file()
    (tmp / "manifest.json").write_text("{}")
    commit_staging_dir(tmp, out)
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp"]
