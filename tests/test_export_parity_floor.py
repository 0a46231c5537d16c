"""The parity tolerance's floor, and what an export that fails its parity check does to the export it would replace.

A nearly untrained head's scores (or the few of a small ``--top-k``) span a band far narrower than their size: 1e-4 x
range fell to a float32 ulp, and rounding alone failed 7 of 9 fresh smoke-trained checkpoints' exports (then every
runtime tool refused them). The tolerance's scale is now the range floored at a fraction of the magnitude. An
export that does fail no longer replaces a working one in its ``--out``."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.export import graph_steps
from streamdet.export.cli import main as export_main
from streamdet.export.parity import (
    FP16_SCALE_FLOOR,
    FP16_TOL_REL,
    TORCH_SCALE_FLOOR,
    TORCH_TOL_REL,
    compare_dense,
    compare_detections,
    value_range,
    value_scale,
)
from streamdet.export.record import format_parity
from streamdet.export.staging import PARITY_FAILED_SUFFIX
from streamdet.runtime_ort.manifest import read_manifest
from streamdet.runtime_ort.manifest_records import ParityRecord

SEEDS = [0, 1, 2]


def _flat_detections(rng: np.random.Generator, centre: float = 0.3, band: float = 5e-4, q: int = 1, k: int = 10):
    """Top-K outputs of a head whose scores lie in a narrow band around ``centre`` (untrained, or a small top-K)."""
    boxes = np.zeros((q, k, 9), np.float32)
    boxes[..., 0] = np.arange(k) * 2.0  # distinct centres, 2 m apart
    boxes[..., 3:6] = 1.0
    scores = (centre + band * np.linspace(1.0, 0.0, k))[None].repeat(q, 0).astype(np.float32)
    labels = rng.integers(0, 3, (q, k)).astype(np.int64)
    return boxes, scores, labels


def _nudged(dets, score_diff: float):
    boxes, scores, labels = dets
    return boxes.copy(), (scores.astype(np.float64) + score_diff).astype(np.float32), labels.copy()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("seed", SEEDS)
def test_value_scale_is_the_range_floored_at_a_fraction_of_the_magnitude(seed, dtype):
    x = np.random.default_rng(seed).normal(0.3, 1e-4, size=50).astype(dtype)
    naive_range = float(max(x)) - float(min(x))
    naive_mag = max(abs(float(v)) for v in x)
    assert value_range(x) == pytest.approx(naive_range)
    assert value_scale(x) == pytest.approx(naive_range)
    assert value_scale(x, 0.1) == pytest.approx(max(naive_range, 0.1 * naive_mag))
    assert value_scale(np.zeros(0, dtype), 0.1) == 0.0


@pytest.mark.parametrize("seed", SEEDS)
def test_rounding_of_flat_scores_passes_with_the_floor(seed):
    ref = _flat_detections(np.random.default_rng(seed))
    got = _nudged(ref, 9e-8)  # float32 rounding of scores near 0.3 (what the audit saw: 5e-8 to 1e-7)
    without = {r.output: r for r in compare_detections("slice_head", "fp32", "torch", got, ref, TORCH_TOL_REL)}
    assert not without["det_scores"].passed  # the false failure the floor removes
    records = compare_detections("slice_head", "fp32", "torch", got, ref, TORCH_TOL_REL, scale_floor=TORCH_SCALE_FLOOR)
    assert all(r.passed for r in records), [format_parity(r) for r in records]
    scores = next(r for r in records if r.output == "det_scores")
    assert scores.output_range == pytest.approx(value_range(ref[1])) and scores.output_scale > scores.output_range


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("tol_rel, floor, band, error", [(TORCH_TOL_REL, TORCH_SCALE_FLOOR, 5e-4, 1e-4),
                                                         (FP16_TOL_REL, FP16_SCALE_FLOOR, 5e-2, 2e-2)])  # fmt: skip
def test_a_real_difference_in_flat_scores_still_fails(seed, tol_rel, floor, band, error):
    """(Scores closer than the tolerance to the K-th are not compared: they may swap ranks. fp16 cannot order a band
    of 5e-4 at 0.3, so its case takes a wider one.)"""
    ref = _flat_detections(np.random.default_rng(seed), band=band)
    records = compare_detections("slice_head", "fp32", "torch", _nudged(ref, error), ref, tol_rel, scale_floor=floor)
    scores = next(r for r in records if r.output == "det_scores")
    assert not scores.passed and scores.max_abs_diff == pytest.approx(error, rel=1e-3)


@pytest.mark.parametrize("seed", SEEDS)
def test_dense_outputs_take_the_floor_too(seed):
    rng = np.random.default_rng(seed)
    ref = (5.0 + rng.normal(scale=1e-5, size=(2, 4, 8))).astype(np.float32)  # nearly constant, large
    got = np.nextafter(ref, np.float32(np.inf))  # one ulp off everywhere
    assert not compare_dense("g", "fp32", "torch", "o", got, ref, TORCH_TOL_REL).passed
    rec = compare_dense("g", "fp32", "torch", "o", got, ref, TORCH_TOL_REL, TORCH_SCALE_FLOOR)
    assert rec.passed and rec.output_scale == pytest.approx(0.1 * float(np.abs(ref).max()))
    assert not compare_dense("g", "fp32", "torch", "o", ref + 1e-3, ref, TORCH_TOL_REL, TORCH_SCALE_FLOOR).passed


def test_a_record_without_a_scale_reads_as_its_range():
    old = {"graph": "g", "precision": "fp32", "reference": "torch", "output": "o", "max_abs_diff": 1e-6,
           "output_range": 0.5, "tolerance_rel": 1e-4, "passed": True}  # fmt: skip
    rec = ParityRecord.from_dict(old)
    assert rec.output_scale is None
    assert format_parity(rec).endswith("vs 0.0001 x range 0.5 = 5e-05: ok")


# ---- an export that fails its parity check ------------------------------------------------------------------------


def _digest(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


def _export(out: Path, *args: str):
    return CliRunner().invoke(export_main, ["--preset", "tiny", "--slices", "8", *args, "--out", str(out)])


@pytest.fixture(scope="module")
def working_export(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("parity_floor") / "exp"
    result = _export(out)
    assert result.exit_code == 0, result.output
    return out


def test_a_failing_export_leaves_the_working_one_in_place(working_export, monkeypatch):
    before = _digest(working_export)
    monkeypatch.setattr(graph_steps, "TORCH_TOL_REL", -1.0)  # every fp32 check fails
    result = _export(working_export)
    assert result.exit_code == 2, result.output
    failed = working_export.with_name(working_export.name + PARITY_FAILED_SUFFIX)
    assert _digest(working_export) == before  # untouched
    assert f"{working_export} keeps the export it held; the one that failed is in {failed}" in result.output
    assert not all(p.passed for p in read_manifest(failed).parity)
    again = _export(working_export)  # a second failure replaces the first failed one, still not the working export
    assert again.exit_code == 2 and _digest(working_export) == before and failed.is_dir()


def test_a_failing_export_into_a_new_folder_is_written_there(tmp_path, monkeypatch):
    monkeypatch.setattr(graph_steps, "TORCH_TOL_REL", -1.0)
    result = _export(tmp_path / "new")
    assert result.exit_code == 2 and "keeps the export" not in result.output
    assert (tmp_path / "new" / "manifest.json").is_file() and not (tmp_path / f"new{PARITY_FAILED_SUFFIX}").exists()


def test_fp16_after_a_failed_fp32_check_records_the_failure_instead_of_crashing(tmp_path, monkeypatch):
    monkeypatch.setattr(graph_steps, "TORCH_TOL_REL", -1.0)
    result = _export(tmp_path / "e16", "--fp16")
    assert result.exit_code == 2, result.output  # exit 1 with the runtime's refusal before
    assert "fp16 pipeline check not run: the fp32 graphs failed their check against PyTorch" in result.output
    assert read_manifest(tmp_path / "e16").pipeline_parity is None


def test_int8_after_a_failed_fp32_check_says_why_it_cannot_run(tmp_path, monkeypatch):
    monkeypatch.setattr(graph_steps, "TORCH_TOL_REL", -1.0)
    result = _export(tmp_path / "e8", "--int8")
    assert result.exit_code != 0 and "Traceback" not in result.output
    assert "the fp32 graphs failed their parity check against PyTorch" in result.output
    assert "int8 calibration runs the pipeline through them, so no int8 graph can be made" in result.output
    assert not (tmp_path / "e8").exists()
