"""Review 41 of the exporter: the slice graph's parity compares the K-th detection (F1), int8 calibration records
that say what the calibration used (F2-F4), the folder beside --out (F5), a clamped --top-k (F6), non-finite
outputs (F7), empty path options (F8), the parity seed (F9) and the manifest's doc (F10)."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from streamdet.export import int8 as q8
from streamdet.export.cli import main as export_main
from streamdet.export.exporter import ExportError, ExportOptions, ExportUsageError, _check_options, _resolve_preset
from streamdet.export.graph_steps import reference_decode
from streamdet.export.int8_steps import parity_samples
from streamdet.export.parity import (
    FP16_SCALE_FLOOR,
    FP16_TOL_REL,
    NON_FINITE,
    NOT_COMPARED,
    TORCH_SCALE_FLOOR,
    TORCH_TOL_REL,
    compare_detections,
    match_detections,
    peak_margins,
)
from streamdet.export.record import format_parity
from streamdet.export.staging import check_parity_failed_dir, commit_target
from streamdet.models.decode import decode_head_maps
from streamdet.models.heads import REGRESSION_OUTPUTS
from streamdet.models.presets import get_preset
from streamdet.runtime_ort.manifest import LutEntry, read_manifest

TINY_CELLS = 2560  # classes x cells of a tiny head map (the clamp of --top-k)


def _export(args: list[str]):
    return CliRunner().invoke(export_main, args)


def _car(q: int = 1, k: int = 1, score: float = 0.9) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K confident cars per quadrant, 4 m apart, scores falling from ``score``."""
    boxes = np.zeros((q, k, 9), np.float32)
    boxes[..., 0] = 10.0 + 4.0 * np.arange(k)
    boxes[..., 1] = 20.0
    boxes[..., 2] = 0.5
    boxes[..., 3:6] = (2.0, 4.5, 1.6)
    scores = np.broadcast_to(score - 0.05 * np.arange(k, dtype=np.float32), (q, k)).astype(np.float32).copy()
    return boxes, scores, np.zeros((q, k), np.int64)


def _wrong(ref, what: str):
    got = [a.copy() for a in ref]
    if what == "moved":
        got[0][..., :3] += 25.0
    elif what == "relabelled":
        got[2][...] = 7
    elif what == "score":
        got[1][...] = 0.2
    elif what == "all":
        got[0][..., :3] += 25.0
        got[1][...] = 0.2
        got[2][...] = 7
    return tuple(got)


# ---- F1: the K-th detection is compared; nothing compared is no 0 -------------------------------------------


@pytest.mark.parametrize("what", ["moved", "relabelled", "score", "all"])
@pytest.mark.parametrize("k", [1, 3])
def test_a_wrong_top_k_detection_fails_with_the_first_score_left_out(what, k):
    """With --top-k 1 the one detection was 'at the top-K boundary' (its own score + tol), so a wrong graph passed."""
    ref = _car(q=2, k=k)
    left_out = np.full(2, 0.3)  # the (K+1)-th reference score: well below the K-th
    records = compare_detections("slice_head", "fp32", "torch", _wrong(ref, what), ref, TORCH_TOL_REL, None,
                                 TORCH_SCALE_FLOOR, first_left_out=left_out)  # fmt: skip
    assert not all(r.passed for r in records)
    same = compare_detections("slice_head", "fp32", "torch", ref, ref, TORCH_TOL_REL, None, TORCH_SCALE_FLOOR,
                              first_left_out=left_out)  # fmt: skip
    assert all(r.passed for r in same) and all(not math.isnan(r.max_abs_diff) for r in same)
    m = match_detections(ref, ref, 1e-3, 1e-3, first_left_out=left_out)
    assert m.compared == 2 * k and m.boundary == 0


def test_a_k_th_detection_tied_with_the_first_left_out_is_at_the_boundary():
    ref = _car(q=1, k=2)
    m = match_detections(ref, ref, 1e-3, 1e-3, first_left_out=np.array([ref[1][0, 1] - 1e-4]))
    assert (m.compared, m.boundary) == (1, 1)
    m = match_detections(ref, ref, 1e-3, 1e-3, first_left_out=np.array([-np.inf]))  # nothing left out
    assert (m.compared, m.boundary) == (2, 0)


@pytest.mark.parametrize("bad", [np.zeros(3), np.zeros((2, 1)), np.array([np.nan, 0.1]), np.array([np.inf, 0.1]),
                                 np.array([True, False]), np.array(["a", "b"])])  # fmt: skip
def test_malformed_first_left_out_is_refused(bad):
    ref = _car(q=2, k=2)
    with pytest.raises(ValueError, match="first_left_out"):
        match_detections(ref, ref, 1e-3, 1e-3, first_left_out=bad)


def test_a_record_that_compared_nothing_holds_nan_and_does_not_print_ok():
    """The old rule (no first_left_out: the K-th score stands in) compares nothing at K = 1: said, not a diff of 0."""
    ref = _car()
    records = compare_detections("slice_head", "fp32", "torch", _wrong(ref, "all"), ref, TORCH_TOL_REL, None,
                                 TORCH_SCALE_FLOOR)  # fmt: skip
    for r in records:
        assert math.isnan(r.max_abs_diff) and r.note.startswith(NOT_COMPARED), r
        line = format_parity(r)
        assert "nothing compared" in line and "max |diff|" not in line and not line.endswith("ok"), line
    # a check that compared its detections but no box above the threshold: the box records compared nothing
    low = _car(k=3, score=0.05)
    records = compare_detections("slice_head", "fp16", "onnx-fp32", low, low, FP16_TOL_REL, None, FP16_SCALE_FLOOR,
                                 first_left_out=np.array([0.0]))  # fmt: skip
    assert all(math.isnan(r.max_abs_diff) for r in records[:5]) and records[5].max_abs_diff == 0.0
    assert records[6].max_abs_diff == 0.0 and all(r.passed for r in records)


def _tiny_top_k(k: int):
    tiny = get_preset("tiny")
    return dataclasses.replace(tiny, post=dataclasses.replace(tiny.post, top_k=k))


def _maps(q: int, classes: int, hh: int, wh: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(q, classes, hh, wh, generator=g),
            *(torch.randn(q, c, hh, wh, generator=g) * 0.1 for _, c in REGRESSION_OUTPUTS))  # fmt: skip


@pytest.mark.parametrize("k", [1, 2, 7])
def test_reference_decode_gives_the_top_k_and_the_first_score_left_out(k):
    preset = _tiny_top_k(k)
    maps = _maps(3, 10, 8, 8)
    ref = reference_decode(maps, preset)
    want = [t.numpy() for t in decode_head_maps(maps, preset.head_cell_m, k)]
    np.testing.assert_array_equal(ref.dets[1], want[1])
    assert [a.shape[1] for a in ref.dets] == [k, k, k]
    more = decode_head_maps(maps, preset.head_cell_m, k + 1)[1].numpy()
    np.testing.assert_array_equal(ref.first_left_out, more[:, k].astype(np.float64))
    assert ref(ref.dets).shape == (3, k)  # the near-tie margins of decoded detections


def test_reference_decode_of_every_cell_leaves_nothing_out():
    maps = _maps(2, 2, 2, 2)
    preset = _tiny_top_k(8)  # classes x cells of these maps
    ref = reference_decode(maps, preset)
    assert ref.dets[1].shape == (2, 8) and np.all(ref.first_left_out == -np.inf)


@pytest.fixture(scope="module")
def top_k_1_export(tmp_path_factory):
    out = tmp_path_factory.mktemp("review41_topk1") / "e"
    result = _export(["--preset", "tiny", "--top-k", "1", "--fp16", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out, result.output


def test_top_k_1_export_compares_its_detection(top_k_1_export):
    out, output = top_k_1_export
    m = read_manifest(out)  # NaN records read back
    fp32 = {p.output: p for p in m.parity if p.graph == "slice_head" and p.precision == "fp32"}
    assert not math.isnan(fp32["det_scores"].max_abs_diff) and "1 of " in fp32["det_scores"].note
    for p in m.parity:  # the fp16 check may leave the untrained head's one detection out as a near-tie: said so
        line = f"{p.graph} {p.precision} {p.output}: " + ("nothing compared" if math.isnan(p.max_abs_diff) else "max |diff| ")
        assert line in output
        assert p.note.startswith(NOT_COMPARED) == math.isnan(p.max_abs_diff) or p.graph != "slice_head"


# ---- F2: a broken splits.json is refused, not read as "every sample" ------------------------------------------


@pytest.fixture(scope="module")
def dataset(tiny_train_data):
    return tiny_train_data  # read-only (conftest): copied before a change


@pytest.mark.parametrize("text, needle", [
    ('{"val": ["scene-x"]}', "no split 'train'"),
    ('{"trian": ["x"], "val": ["y"]}', "no split 'train'"),
    ('{"train": ["a"], "val": [', "not valid JSON"),
    ("[]", "got a JSON list"),
    ('{"train": "scene-0"}', "must be a list"),
    ('{"train": [1]}', "scene names"),
    ("", "not valid JSON"),
])  # fmt: skip
def test_a_broken_splits_file_is_refused(dataset, tmp_path, text, needle):
    copy = tmp_path / "data"
    shutil.copytree(dataset, copy)
    (copy / "splits.json").write_text(text)
    with pytest.raises(q8.Int8CalibrationDataError, match=needle) as e:
        q8.load_calibration_samples(copy, 8, ())
    assert "splits.json" in str(e.value)
    with pytest.raises(ExportError, match=needle):  # before any work
        _check_options(ExportOptions(preset="tiny", int8=True, calibration_data=str(copy)), get_preset("tiny"))


def test_a_splits_folder_is_refused_and_no_file_means_every_sample(dataset, tmp_path):
    copy = tmp_path / "data"
    shutil.copytree(dataset, copy)
    (copy / "splits.json").unlink()
    assert q8.load_calibration_samples(copy, 100, ()).split == "all"
    (copy / "splits.json").mkdir()
    with pytest.raises(q8.Int8CalibrationDataError, match="not a regular file"):
        q8.load_calibration_samples(copy, 8, ())


# ---- F3: held out only when the calibration did not draw the bundled sample -----------------------------------


def _cal(tokens, source="data/mini"):
    return q8.CalibrationSamples(tuple(SimpleNamespace(token=t) for t in tokens), source, "v1.0-mini", "train")


BUNDLED = SimpleNamespace(token="ca9a282c9e77460f8360f564131a8af5", image_paths={"CAM_FRONT": "a", "CAM_BACK": "b"})


@pytest.mark.parametrize("tokens, source, held_out, reads_bundled, said", [
    (("t1", "t2"), "data/mini", True, True, "bundled nuScenes sample, held out"),
    (("t1", BUNDLED.token), "data/mini", False, True, "not held out: a calibration sample too (drawn from data/mini)"),
    ((BUNDLED.token,), q8.BUNDLED_SOURCE, False, False, "the calibration sample itself"),  # its own inputs serve
])  # fmt: skip
def test_parity_held_out_follows_the_tokens(tokens, source, held_out, reads_bundled, said):
    chosen, got_held_out, note = parity_samples(_cal(tokens, source), BUNDLED, ("CAM_FRONT",))
    assert got_held_out is held_out and (chosen == (BUNDLED,)) is reads_bundled and said in note


def test_a_foreign_rig_runs_the_parity_on_the_calibration_samples():
    chosen, held_out, note = parity_samples(_cal(("t1",)), BUNDLED, ("CAM_X",))
    assert chosen is None and not held_out and "lacks this rig's cameras" in note


# ---- F4: --calibration-samples without --calibration-data -----------------------------------------------------


@pytest.mark.parametrize("n", [1, 2, 50])
def test_calibration_samples_without_data_is_refused(n):
    opts = ExportOptions(preset="tiny", int8=True, calibration_samples=n)
    with pytest.raises(ExportUsageError, match=f"--calibration-samples {n} draws from --calibration-data"):
        _check_options(opts, _resolve_preset(opts)[0])


def test_calibration_samples_without_data_exits_2(tmp_path, dataset):
    result = _export(["--preset", "tiny", "--int8", "--calibration-samples", "50", "--out", str(tmp_path / "e")])
    assert result.exit_code == 2 and "the bundled sample, which is one sample" in result.output
    assert not (tmp_path / "e").exists()
    opts = ExportOptions(preset="tiny", int8=True, calibration_samples=2, calibration_data=str(dataset))
    _check_options(opts, _resolve_preset(opts)[0])  # with a dataset it sizes the draw


# ---- F5: the folder beside --out --------------------------------------------------------------------------------


def _export_like(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text(json.dumps({"graphs": [], "preset": {}}))
    return folder


def test_a_foreign_parity_failed_folder_blocks_no_fresh_export(tmp_path):
    out = tmp_path / "e5"
    failed = tmp_path / "e5.parity-failed"
    failed.mkdir()
    (failed / "notes.txt").write_text("mine")
    result = _export(["--preset", "tiny", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert (out / "manifest.json").is_file() and (failed / "notes.txt").read_text() == "mine"
    # with an export in --out, a failed one would go there: refused, named as the folder beside --out
    result = _export(["--preset", "tiny", "--out", str(out)])
    assert result.exit_code == 1 and f"beside --out {out}" in result.output
    assert f"Error: --out {failed}" not in result.output and (failed / "notes.txt").is_file()


@pytest.mark.parametrize("kind", ["foreign", "file", "export", "empty", "absent"])
def test_check_parity_failed_dir(tmp_path, kind):
    out = _export_like(tmp_path / "exp")
    failed = tmp_path / "exp.parity-failed"
    if kind == "foreign":
        failed.mkdir()
        (failed / "x").write_text("")
    elif kind == "file":
        failed.write_text("")
    elif kind == "export":
        _export_like(failed)
    elif kind == "empty":
        failed.mkdir()
    if kind in ("foreign", "file"):
        for call in (lambda: check_parity_failed_dir(out), lambda: commit_target(out, parity_passed=False)):
            with pytest.raises(ExportError, match=f"beside --out {out}"):
                call()
    else:
        assert check_parity_failed_dir(out) == failed == commit_target(out, parity_passed=False)
    assert commit_target(out, parity_passed=True) == out


# ---- F6: --top-k beyond classes x cells ---------------------------------------------------------------------


def test_a_clamped_top_k_is_noted_and_recorded_as_decoded(tmp_path):
    notes: list[str] = []
    preset, _, _ = _resolve_preset(ExportOptions(preset="tiny", top_k=100_000), notes.append)
    assert preset.top_k == TINY_CELLS and len(notes) == 1 and f"the graph decodes {TINY_CELLS}" in notes[0]
    notes.clear()
    _resolve_preset(ExportOptions(preset="tiny", top_k=TINY_CELLS), notes.append)
    assert notes == []
    out = tmp_path / "e"
    result = _export(["--preset", "tiny", "--top-k", "100000", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"--top-k 100000 exceeds the {TINY_CELLS}" in result.output
    m = read_manifest(out)
    assert m.post["top_k"] == m.post["top_k_per_quadrant"] == TINY_CELLS
    assert all(p.passed for p in m.parity)


# ---- F7: non-finite outputs ---------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("where", [0, 1])
def test_non_finite_outputs_fail_with_their_reason(bad, where):
    ref = _car(k=3)
    got = [a.copy() for a in ref]
    got[where][0, 0, ...] = bad
    records = compare_detections("slice_head", "fp32", "torch", tuple(got), ref, TORCH_TOL_REL, None,
                                 TORCH_SCALE_FLOOR, first_left_out=np.array([0.1]))  # fmt: skip
    assert not any(r.passed for r in records)
    assert all(r.note.startswith(NON_FINITE) for r in records)
    assert all(NON_FINITE in format_parity(r) for r in records)


def test_peak_margins_of_huge_logits_warn_nothing():
    logits = np.array([[[[-1e4, 3.0], [1e4, -800.0]]]], np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        margins = peak_margins(logits)
    assert np.isfinite(margins).all()


# ---- F8: empty path options ---------------------------------------------------------------------------------


@pytest.mark.parametrize("option", ["--checkpoint", "--calibration", "--calibration-data"])
def test_an_empty_path_option_is_refused(tmp_path, option):
    extra = ["--int8"] if option == "--calibration-data" else []
    result = _export(["--preset", "tiny", *extra, option, "", "--out", str(tmp_path / "e")])
    assert result.exit_code == 2 and f"'{option}': '' is empty" in result.output, result.output
    assert "current folder" not in result.output and not (tmp_path / "e").exists()


# ---- F9: the parity seed --------------------------------------------------------------------------------------


def test_the_parity_seed_of_noise_images_is_recorded(tiny_weights, tmp_path, top_k_1_export):
    from test_export_cli import two_camera_calibration

    out = tmp_path / "e"
    calib = two_camera_calibration(tmp_path)
    result = _export(["--checkpoint", str(tiny_weights), "--calibration", str(calib), "--seed", "5", "--out", str(out)])
    assert result.exit_code == 0, result.output
    source = read_manifest(out).source
    assert source["seed"] is None and source["parity_seed"] == 5 and "noise" in source["parity_input"]
    assert read_manifest(top_k_1_export[0]).source["parity_seed"] is None  # real images: no seed drew them


# ---- F10: the manifest's doc and the --calibration-data message -------------------------------------------------


def test_the_manifest_doc_names_the_lut_fields_written():
    import streamdet.runtime_ort.manifest as manifest_module

    doc = manifest_module.__doc__
    lut = doc[doc.index("    lut "):doc.index("    parity ")]
    for f in dataclasses.fields(LutEntry):
        assert f.name in lut
    for stale in ("camera_names", "image_width", "image_height"):
        assert f"{stale}," not in lut and f"{stale}}}" not in lut
    source = doc[doc.index("    source "):doc.index("    int8 ")]
    assert "parity_input" in source and "parity_seed" in source


def test_calibration_data_without_int8_quotes_its_value():
    opts = ExportOptions(preset="tiny", calibration_data="some/dir")
    with pytest.raises(ExportUsageError, match="--calibration-data some/dir is the int8 calibration set"):
        _check_options(opts, get_preset("tiny"))
