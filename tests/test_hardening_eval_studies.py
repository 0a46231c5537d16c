"""Hardening of streamdet-eval --compare, streamdet-study, streamdet-run and the sweep NMS (audit of the evaluation /
studies / run side): each refusal beside the valid input it must keep accepting."""

from __future__ import annotations

import json
import math
import shutil
import tracemalloc
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.cli_utils import refuse_output_over_inputs, split_list
from streamdet.core.boxes import BOX_DIM, L, W, bev_extent, paired_bev_iou
from streamdet.evaluation.cli import MAX_DRAWS
from streamdet.evaluation.cli import main as eval_main
from streamdet.evaluation.compare import MAX_SLICE_SUBSETS, compare_runs, ground_truth_difference, load_run, write_sample_info
from streamdet.evaluation.results import write_results_json
from streamdet.runtime_ort import nms as nms_module
from streamdet.runtime_ort.nms import NmsConfig, NmsKind, nms, overlapping_pairs
from streamdet.studies.cli import MAX_SEEDS
from streamdet.studies.cli import main as study_main

from result_entries import result_entry as _entry

META = {"use_camera": False, "use_lidar": True}
CLASSES = ("car", "pedestrian", "traffic_cone")


# ---- saved runs -------------------------------------------------------------------------------------------------


def _world(seed: int = 0, num_samples: int = 6):
    rng = np.random.default_rng(seed)
    gt, pa, pb = {}, {}, {}
    for s in range(num_samples):
        t = f"s{s}"
        gt[t], pa[t], pb[t] = [], [], []
        for k in range(3):
            name = CLASSES[k % 3]
            xy = rng.uniform(-20, 20, 2)
            gt[t].append(_entry(t, xy, name, None, int(rng.integers(1, 12))))
            pa[t].append(_entry(t, xy + rng.normal(0, 0.5, 2), name, float(rng.random())))
            pb[t].append(_entry(t, xy + rng.normal(0, 0.3, 2), name, float(rng.random())))
    return gt, pa, pb


def _save(folder: Path, gt: dict, pred: dict, scenes: dict | None = None, num_slices: int = 4) -> Path:
    folder.mkdir(parents=True)
    write_results_json(folder / "results.json", pred, META)
    write_results_json(folder / "gt.json", gt, META, ego_positions={t: [0.0, 0.0, 0.0] for t in gt})
    if scenes is not None:
        eye = np.eye(4)
        write_sample_info(folder / "samples.json", scenes, {t: (eye, eye) for t in gt}, num_slices)
    return folder


def _scenes(gt: dict) -> dict[str, str]:
    return {t: f"scene{i // 2}" for i, t in enumerate(gt)}


def _eval(args: list[str]):
    return CliRunner().invoke(eval_main, args)


def _one_line_error(res) -> None:
    assert res.exit_code != 0, res.output
    assert "Traceback" not in res.output
    assert sum(line.startswith("Error") for line in res.output.splitlines()) == 1, res.output


@pytest.fixture()
def runs(tmp_path):
    gt, pa, pb = _world()
    scenes = _scenes(gt)
    a = _save(tmp_path / "A", gt, pa, scenes)
    b = _save(tmp_path / "B", gt, pb, scenes)
    return gt, a, b


# ---- 1. --compare: the same ground truth for real, the same samples.json ------------------------------------------


def _rewrite(path: Path, change) -> None:
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def test_compare_refuses_moved_ground_truth_naming_the_sample(runs):
    _, a, b = runs
    ok = _eval(["--compare", str(a), str(b), "--bootstrap", "5", "--no-subsets"])
    assert ok.exit_code == 0, ok.output

    def move(doc):  # same tokens, same box counts: only the boxes moved 30 m
        for boxes in doc["results"].values():
            for box in boxes:
                box["translation"][0] += 30.0

    _rewrite(b / "gt.json", move)
    for first, second in ((a, b), (b, a)):  # either order: B's ground truth is no longer silently ignored
        res = _eval(["--compare", str(first), str(second), "--bootstrap", "5", "--no-subsets"])
        _one_line_error(res)
        assert "same ground truth" in res.output and "sample 's0' differs" in res.output
        assert str(b / "gt.json") in res.output


def test_compare_accepts_the_same_boxes_listed_in_another_order(runs):
    _, a, b = runs
    _rewrite(b / "gt.json", lambda doc: doc["results"].update({t: v[::-1] for t, v in doc["results"].items()}))
    res = _eval(["--compare", str(a), str(b), "--bootstrap", "5", "--no-subsets"])
    assert res.exit_code == 0, res.output


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("size", [1.0, 2.5, 1.5], "sample 's2' differs"),
        ("detection_name", "bus", "sample 's2' differs"),
        ("num_pts", 99, "sample 's2' differs"),
        ("rotation", [0.0, 0.0, 0.0, 1.0], "sample 's2' differs"),
        ("ego_positions", [50.0, 0.0, 0.0], "sample 's2' differs"),  # every box's distance to the ego changes
    ],
)
def test_ground_truth_difference_sees_every_field(runs, field, value, message):
    _, a, b = runs

    def change(doc):
        if field == "ego_positions":
            doc["ego_positions"]["s2"] = value
        else:
            doc["results"]["s2"][1][field] = value

    _rewrite(b / "gt.json", change)
    assert ground_truth_difference(load_run(a).gt, load_run(a).gt) is None
    assert message in ground_truth_difference(load_run(a).gt, load_run(b).gt)


def test_ground_truth_difference_names_a_missing_sample_and_a_count(tmp_path):
    gt, pa, _ = _world()
    full = load_run(_save(tmp_path / "full", gt, pa)).gt
    fewer = load_run(_save(tmp_path / "fewer", {t: v for t, v in gt.items() if t != "s3"},
                           {t: v for t, v in pa.items() if t != "s3"})).gt  # fmt: skip
    assert "sample 's3' is only in the first" in ground_truth_difference(full, fewer)
    assert "sample 's3' is only in the second" in ground_truth_difference(fewer, full)
    short = dict(gt, s1=gt["s1"][:2])
    assert "sample 's1' has 3 vs 2 boxes" in ground_truth_difference(full, load_run(_save(tmp_path / "short", short, pa)).gt)


def test_compare_refuses_runs_whose_samples_files_disagree_on_scenes(runs):
    _, a, b = runs
    _rewrite(b / "samples.json", lambda doc: [s.update(scene="one") for s in doc["samples"].values()])
    for first, second in ((a, b), (b, a)):  # A's file no longer decides for both
        res = _eval(["--compare", str(first), str(second), "--bootstrap", "5"])
        _one_line_error(res)
        assert "disagree" in res.output and "sample 's0'" in res.output and "samples.json" in res.output


def test_compare_refuses_other_slicings_with_subsets_and_takes_them_without(runs, tmp_path):
    gt, a, b = runs
    _rewrite(b / "samples.json", lambda doc: doc.update(num_slices=8))
    res = _eval(["--compare", str(a), str(b), "--bootstrap", "5"])
    _one_line_error(res)
    assert "4 vs 8 slices" in res.output and "--no-subsets" in res.output
    out = tmp_path / "c.json"
    res = _eval(["--compare", str(a), str(b), "--bootstrap", "5", "--no-subsets", "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert json.loads(out.read_text())["clustered_by"] == "scene"


def test_compare_notes_which_samples_file_serves_a_run_without_one(runs, tmp_path):
    _, a, b = runs
    (b / "samples.json").unlink()
    c = compare_runs(load_run(a), load_run(b), num_draws=5, subsets=False)
    assert c.clustered_by == "scene" and any(f"samples.json of {a} serves" in n and str(b) in n for n in c.notes)


def test_compare_skips_per_slice_subsets_above_the_cap(runs):
    _, a, b = runs
    for run in (a, b):
        _rewrite(run / "samples.json", lambda doc: doc.update(num_slices=4096))
    c = compare_runs(load_run(a), load_run(b), num_draws=3)
    assert not any(name.startswith("slice") for name in c.subsets) and "cut_by_slice_border" in c.subsets
    assert any(f"above {MAX_SLICE_SUBSETS} slices" in n for n in c.notes)
    for run in (a, b):  # the valid path: per-slice rows up to the cap
        _rewrite(run / "samples.json", lambda doc: doc.update(num_slices=MAX_SLICE_SUBSETS))
    c = compare_runs(load_run(a), load_run(b), num_draws=3)
    assert any(name.startswith("slice") for name in c.subsets) and not any("above" in n for n in c.notes)


# ---- 2. the sweep NMS: bounded memory, the same result ------------------------------------------------------------
# The implementation before the chunked greedy, verbatim in substance: every candidate pair at once.


def _reference_same_class_pairs(lo, hi, labels):
    firsts, seconds = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for label in np.unique(labels).tolist():
        members = np.flatnonzero(labels == label)
        i, j = overlapping_pairs(lo[members], hi[members])
        firsts.append(members[i])
        seconds.append(members[j])
    return np.concatenate(firsts), np.concatenate(seconds)


def _reference_greedy(num, first, second):
    keep = np.ones(num, dtype=bool)
    order = np.argsort(first, kind="stable")
    first, second = first[order], second[order]
    for head in np.unique(first).tolist():
        if keep[head]:
            keep[second[first == head]] = False
    return keep


def _reference_nms(boxes, scores, labels, config):
    n = boxes.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    rank = np.argsort(-scores.astype(np.float64), kind="stable")
    ranked = boxes[rank].astype(np.float64)
    ranked_labels = labels[rank]
    if config.kind is NmsKind.CIRCLE:
        radius = np.asarray(config.circle_radius_m)[ranked_labels]
        lo = ranked[:, :2] - radius[:, None]
        hi = ranked[:, :2] + radius[:, None]
        hi = np.where(hi > lo, hi, np.nextafter(hi, np.inf))
        i, j = _reference_same_class_pairs(lo, hi, ranked_labels)
        x, y = ranked[:, 0], ranked[:, 1]
        linked = (x[i] - x[j]) ** 2 + (y[i] - y[j]) ** 2 <= radius[i] ** 2
    else:
        threshold = (np.full(n, config.iou_threshold) if config.iou_threshold_per_class is None
                     else np.asarray(config.iou_threshold_per_class)[ranked_labels])  # fmt: skip
        lo, hi = bev_extent(ranked)
        i, j = _reference_same_class_pairs(lo, hi, ranked_labels)
        area = ranked[:, W] * ranked[:, L]
        overlap = (np.minimum(hi[i, 0], hi[j, 0]) - np.maximum(lo[i, 0], lo[j, 0])) * (
            np.minimum(hi[i, 1], hi[j, 1]) - np.maximum(lo[i, 1], lo[j, 1]))  # fmt: skip
        inter_max = np.minimum(overlap, np.minimum(area[i], area[j]))
        with np.errstate(divide="ignore", invalid="ignore"):
            possible = inter_max / (area[i] + area[j] - inter_max) > threshold[i]
        i, j = i[possible], j[possible]
        linked = paired_bev_iou(ranked[i], ranked[j]) > threshold[i]
    keep = _reference_greedy(n, i[linked], j[linked])
    return rank[keep][: config.max_out].astype(np.int64)


def _random_boxes(seed: int, n: int, spread: float):
    rng = np.random.default_rng(seed)
    boxes = np.zeros((n, BOX_DIM))
    boxes[:, :2] = rng.uniform(-spread, spread, (n, 2))
    boxes[:, 3:6] = rng.uniform(0.3, 5.0, (n, 3))
    boxes[:, 6] = rng.uniform(-math.pi, math.pi, n)
    if n >= 10:
        boxes[: n // 5] = boxes[rng.integers(0, n, n // 5)]  # exact duplicates, as neighbouring slices give
        boxes[n // 5 : n // 4, W] = 0.0  # boxes without area
    scores = rng.random(n).astype(np.float32)
    scores[: n // 10] = 0.5  # ties: the lower index first
    return boxes, scores, rng.integers(0, 10, n)


@pytest.mark.parametrize("kind", ["circle", "rotated"])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("n, spread", [(0, 1.0), (1, 1.0), (2, 0.1), (60, 3.0), (300, 5.0), (1500, 20.0)])
@pytest.mark.parametrize("max_out", [7, 500, 100_000])
def test_chunked_nms_equals_the_one_pass_implementation(monkeypatch, kind, seed, n, spread, max_out):
    boxes, scores, labels = _random_boxes(seed, n, spread)
    config = NmsConfig(kind=kind, max_out=max_out)
    want = _reference_nms(boxes, scores, labels, config)
    assert np.array_equal(nms(boxes, scores, labels, config), want)  # the default budget
    # A tiny budget and short windows: every head in chunks, runs of one head split in pieces.
    monkeypatch.setattr(nms_module, "PAIR_BUDGET", 40)
    monkeypatch.setattr(nms_module, "CHUNK_HEADS", 16)
    monkeypatch.setattr(nms_module, "IOU_BATCH", 8)
    assert np.array_equal(nms(boxes, scores, labels, config), want)


def test_chunked_nms_equals_the_reference_above_the_default_budget():
    """1600 boxes of one class in a 0.5 m wide band: every pair overlaps in x (1.3 M candidates > PAIR_BUDGET)."""
    rng = np.random.default_rng(4)
    n = 1600
    boxes = np.zeros((n, BOX_DIM))
    boxes[:, 0] = rng.uniform(0, 0.5, n)
    boxes[:, 1] = rng.uniform(0, 3 * n, n)
    boxes[:, 3:6] = 1.5
    labels = np.zeros(n, np.int64)
    scores = rng.random(n).astype(np.float32)
    assert nms_module._same_class_pairs(*bev_extent(boxes), labels, nms_module.PAIR_BUDGET) is None  # chunked
    for kind in ("circle", "rotated"):
        config = NmsConfig(kind=kind, max_out=100_000)
        assert np.array_equal(nms(boxes, scores, labels, config), _reference_nms(boxes, scores, labels, config))


def test_nms_memory_is_bounded_where_the_pairs_grow_quadratically():
    """8000 boxes whose x extents all overlap: 32 M candidate pairs, some 2.5 GB of index arrays in one pass."""
    rng = np.random.default_rng(5)
    n = 8000
    boxes = np.zeros((n, BOX_DIM))
    boxes[:, 0] = rng.uniform(0, 0.5, n)
    boxes[:, 1] = np.arange(n) * 3.0  # apart in y: nothing is suppressed, every head is examined
    boxes[:, 3:6] = 1.5
    labels = np.zeros(n, np.int64)
    scores = rng.random(n).astype(np.float32)
    tracemalloc.start()
    try:
        keep = nms(boxes, scores, labels, NmsConfig(max_out=100_000))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(keep) == n  # 3 m apart, circle radius 2 m: every box stays
    assert peak < 200e6, f"peak {peak / 1e6:.0f} MB"


def test_chunked_keep_margin_keeps_partners_at_float_limits(monkeypatch):
    """Partners whose extents touch within rounding of the widest extent are still paired (the exact test decides)."""
    monkeypatch.setattr(nms_module, "PAIR_BUDGET", 4)
    base = 1e6 / 3
    boxes = np.zeros((40, BOX_DIM))
    boxes[:, 0] = base + np.arange(40) * np.nextafter(1.0, 2.0) * 1.9  # circle radius of a car: 2 m
    boxes[:, 3:6] = 1.0
    labels = np.zeros(40, np.int64)
    scores = np.linspace(1, 0, 40, dtype=np.float32)
    config = NmsConfig()
    assert np.array_equal(nms(boxes, scores, labels, config), _reference_nms(boxes, scores, labels, config))


# ---- 3. outputs never replace inputs ------------------------------------------------------------------------------


def test_compare_json_over_a_run_file_is_refused_and_the_run_kept(runs, tmp_path):
    _, a, b = runs
    before = (a / "results.json").read_bytes()
    for target in (a / "results.json", a / "new.json", a):
        res = _eval(["--compare", str(a), str(b), "--bootstrap", "5", "--no-subsets", "--json", str(target)])
        _one_line_error(res)
        assert "--json" in res.output and str(a) in res.output
    assert (a / "results.json").read_bytes() == before and not (a / "new.json").exists()
    res = _eval(["--compare", str(a), str(b), "--bootstrap", "5", "--no-subsets", "--json", str(tmp_path / "c.json")])
    assert res.exit_code == 0 and (tmp_path / "c.json").is_file()


def test_compare_json_over_gt_or_a_results_file_run_is_refused(runs, tmp_path):
    _, a, b = runs
    gt = tmp_path / "gt.json"
    shutil.copy(a / "gt.json", gt)
    args = ["--compare", str(a / "results.json"), str(b / "results.json"), "--gt", str(gt), "--bootstrap", "5", "--no-subsets"]
    for target in (gt, b / "results.json"):
        res = _eval([*args, "--json", str(target)])
        _one_line_error(res)
        assert "is the input" in res.output
    assert _eval([*args, "--json", str(tmp_path / "ok.json")]).exit_code == 0


def test_files_mode_json_over_the_ground_truth_is_refused(runs, tmp_path):
    _, a, _ = runs
    link = tmp_path / "link.json"
    link.symlink_to(a / "gt.json")
    for target in (a / "gt.json", a / "results.json", link):  # a symlink to an input is that input
        res = _eval(["--gt", str(a / "gt.json"), "--results", str(a / "results.json"), "--json", str(target)])
        _one_line_error(res)
        assert "is the input" in res.output
    res = _eval(["--gt", str(a / "gt.json"), "--results", str(a / "results.json"), "--json", str(tmp_path / "m.json")])
    assert res.exit_code == 0, res.output


def test_data_mode_outputs_inside_the_dataset_or_export_are_refused(tmp_path):
    data, export = tmp_path / "ds", tmp_path / "exp"
    data.mkdir()
    export.mkdir()
    (data / "splits.json").write_text('{"val": []}')
    cases = [
        (["--json", str(data / "splits.json")], "lies inside the input --data"),
        (["--json", str(export / "m.json")], "lies inside the input --export-dir"),
        (["--save-results", str(data / "runs" / "A")], "lies inside the input --data"),
        (["--save-results", str(export)], "is the input --export-dir"),
        (["--save-results", str(tmp_path / "s"), "--json", str(tmp_path / "s" / "gt.json")], "--save-results"),
    ]
    for extra, message in cases:
        res = _eval(["--data", str(data), "--export-dir", str(export), *extra])
        _one_line_error(res)
        assert message in res.output, res.output
    assert (data / "splits.json").read_text() == '{"val": []}'


def test_study_outputs_over_inputs_are_refused_before_any_work(tmp_path):
    data, export = tmp_path / "ds", tmp_path / "exp"
    data.mkdir()
    export.mkdir()
    (data / "splits.json").write_text('{"val": []}')
    base = ["--export-dir", str(export), "--data", str(data)]
    cases = [
        (["slices", "--json", str(data / "splits.json")], "lies inside the input --data"),
        (["drop-camera", "--plot", str(export / "p.png")], "lies inside the input --export-dir"),
        (["calib-noise", "--json", str(tmp_path / "x.json"), "--plot", str(tmp_path / "x.json")], "also the --json"),
        (["resolution", "--json", str(export / "sub" / "r.json")], "lies inside the input --export-dir"),
        (["slices", "--baseline-export-dir", str(tmp_path), "--json", str(tmp_path / "t.json")], "--baseline-export-dir"),
    ]
    for args, message in cases:
        res = CliRunner().invoke(study_main, [*args, *base])
        _one_line_error(res)
        assert message in res.output, res.output
    checkpoint = tmp_path / "m.pt"
    checkpoint.write_bytes(b"weights")
    res = CliRunner().invoke(study_main, ["drop-camera", "--checkpoint", str(checkpoint), "--data", str(data),
                                          "--json", str(checkpoint)])  # fmt: skip
    _one_line_error(res)
    assert "is the input --checkpoint" in res.output and checkpoint.read_bytes() == b"weights"
    assert (data / "splits.json").read_text() == '{"val": []}'


def test_refuse_output_over_inputs_and_its_valid_paths(tmp_path):
    folder, file = tmp_path / "in", tmp_path / "in.json"
    folder.mkdir()
    file.write_text("{}")
    inputs = [("--data", folder), ("--gt", file), ("--unused", None)]
    for bad in (folder, folder / "a" / "b.json", file, tmp_path / "." / "in.json"):
        with pytest.raises(click.BadParameter, match=r"input --(data|gt)") as info:
            refuse_output_over_inputs(bad, "--json", inputs)
        assert repr(str(bad)) in str(info.value)
    for good in (tmp_path / "out.json", tmp_path / "in2" / "x.json", tmp_path / "in.json.bak", None):
        refuse_output_over_inputs(good, "--json", inputs)
    hard = tmp_path / "hard.json"
    hard.hardlink_to(file)
    with pytest.raises(click.BadParameter, match="is the input --gt"):
        refuse_output_over_inputs(hard, "--json", inputs)


# ---- 4. the study's baseline must be LiDAR-only -------------------------------------------------------------------


@pytest.fixture(scope="module")
def fused_checkpoint(tmp_path_factory) -> Path:
    import torch

    from streamdet.models.detector import build_detector
    from streamdet.models.presets import get_preset
    from streamdet.training.checkpoint import save_weights

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("fused_ckpt") / "fused.pt"
    save_weights(path, get_preset("tiny"), build_detector(get_preset("tiny")).eval())
    return path


def _slices(export, data, *extra):
    return CliRunner().invoke(study_main, ["slices", "--export-dir", str(export), "--data", str(data), "--split", "all",
                                           "--max-samples", "1", "--counts", "8", *extra])  # fmt: skip


def test_a_camera_lidar_baseline_export_is_refused(tiny_export_fp32, tiny_lidar_export, tiny_synth_data):
    res = _slices(tiny_export_fp32, tiny_synth_data, "--baseline-export-dir", str(tiny_export_fp32))
    _one_line_error(res)
    assert f"--baseline-export-dir {tiny_export_fp32} is a camera + LiDAR model" in res.output
    assert "LiDAR-only baseline  " not in res.output
    res = _slices(tiny_export_fp32, tiny_synth_data, "--baseline-export-dir", str(tiny_lidar_export))
    assert res.exit_code == 0 and "LiDAR-only baseline" in res.output, res.output


def test_a_camera_lidar_baseline_checkpoint_is_refused(tiny_export_fp32, tiny_synth_data, fused_checkpoint):
    res = _slices(tiny_export_fp32, tiny_synth_data, "--baseline-checkpoint", str(fused_checkpoint))
    _one_line_error(res)
    assert f"--baseline-checkpoint {fused_checkpoint} is a camera + LiDAR model" in res.output


# ---- 5. upper bounds and comma lists ------------------------------------------------------------------------------


def test_bootstrap_draws_have_an_upper_bound_in_the_help(runs):
    _, a, b = runs
    res = _eval(["--compare", str(a), str(b), "--bootstrap", str(MAX_DRAWS + 1)])
    assert res.exit_code == 2 and f"1<=x<={MAX_DRAWS}" in res.output
    assert f"1..{MAX_DRAWS}" in _eval(["--help"]).output
    assert _eval(["--compare", str(a), str(b), "--bootstrap", "5", "--no-subsets"]).exit_code == 0


@pytest.mark.parametrize(
    "args, message",
    [
        (["calib-noise", "--seeds", str(MAX_SEEDS + 1)], f"1<=x<={MAX_SEEDS}"),
        (["drop-camera", "--threads", "65"], "1<=x<=64"),
        (["drop-camera", "--slices", "4097"], "1<=x<=4096"),
        (["slices", "--counts", "8,8"], "slice count '8' is given twice"),
        (["slices", "--counts", "8,08"], "slice count '08' is given twice"),
        (["slices", "--counts", "8,,16"], "entry 2 of '8,,16' is empty"),
        (["slices", "--counts", "8,"], "entry 2 of '8,' is empty"),
        (["slices", "--counts", ",,,"], "no slice count given"),
        (["slices", "--counts", "8192"], "slice count 8192 is not in 1..4096"),
        (["slices", "--counts", "99999999999999999999999"], "is not in 1..4096"),
        (["slices", "--counts", "8_0"], "comma-separated integers"),
        (["calib-noise", "--level", "1,10", "--level", "1,10.0"], "level '1,10.0' is given twice"),
    ],
)
def test_study_bounds_and_lists(tmp_path, args, message):
    res = CliRunner().invoke(study_main, [*args, "--export-dir", str(tmp_path), "--data", str(tmp_path)])
    assert res.exit_code == 2, res.output
    assert message in res.output and "Traceback" not in res.output


def test_study_help_gives_the_ranges():
    assert f"1..{MAX_SEEDS}" in CliRunner().invoke(study_main, ["calib-noise", "--help"]).output
    assert "1..64" in CliRunner().invoke(study_main, ["slices", "--help"]).output
    assert "up to 4096" in CliRunner().invoke(study_main, ["slices", "--help"]).output


@pytest.mark.parametrize(
    "side, message",
    [
        ("{a},{a}", "run '{a}' is given twice"),
        ("{a},{dot}", "is given twice"),  # the same folder spelled twice
        ("{a},", "entry 2 of"),
        (",,,", "no run given"),
    ],
)
def test_compare_lists_refuse_empty_and_repeated_runs(runs, side, message):
    _, a, b = runs
    dot = a.parent / "." / a.name
    res = _eval(["--compare", side.format(a=a, dot=dot), str(b), "--bootstrap", "5"])
    assert res.exit_code == 2 and message.format(a=a) in res.output and "Traceback" not in res.output, res.output


def test_compare_groups_of_distinct_runs_still_work(runs, tmp_path):
    gt, a, b = runs
    a2 = _save(tmp_path / "A2", gt, _world(1)[1], _scenes(gt))
    res = _eval(["--compare", f"{a},{a2}", str(b), "--bootstrap", "5", "--no-subsets"])
    assert res.exit_code == 0 and "mean of 2 run(s)" in res.output, res.output


def test_eval_classes_refuse_repeats_and_empties(runs):
    _, a, _ = runs
    files = ["--gt", str(a / "gt.json"), "--results", str(a / "results.json")]
    for value, message in (("car,car", "class 'car' is given twice"), ("car,,pedestrian", "entry 2 of"), (",", "no class given")):
        res = _eval([*files, "--classes", value])
        assert res.exit_code == 2 and message in res.output, res.output
    assert _eval([*files, "--classes", "car, pedestrian"]).exit_code == 0


def test_split_list():
    assert split_list(" a, b ,c", "--x", "thing") == ["a", "b", "c"]
    with pytest.raises(click.BadParameter, match="thing 'A' is given twice in 'a,A' \\(entries 1 and 2\\)"):
        split_list("a,A", "--x", "thing", key=str.lower)
    with pytest.raises(click.BadParameter, match="entry 3 of 'a,b, ' is empty"):
        split_list("a,b, ", "--x", "thing")


def test_eval_slices_bound(tmp_path):
    res = _eval(["--data", str(tmp_path), "--slices", "4097"])
    assert res.exit_code == 2 and "1<=x<=4096" in res.output


# ---- 6. streamdet-run: a failed write is an error -----------------------------------------------------------------


def test_run_reports_a_failed_bev_write(tiny_export_fp32, tmp_path):
    from streamdet.evaluation.run_cli import main as run_main

    out = tmp_path / "o"
    (out / "bev.png").mkdir(parents=True)  # cv2.imwrite returns False, raises nothing
    res = CliRunner().invoke(run_main, ["--export-dir", str(tiny_export_fp32), "--out", str(out)])
    _one_line_error(res)
    assert f"cannot write {out / 'bev.png'}" in res.output and "wrote" not in res.output
    good = tmp_path / "good"
    res = CliRunner().invoke(run_main, ["--export-dir", str(tiny_export_fp32), "--out", str(good)])
    assert res.exit_code == 0 and f"wrote {good / 'bev.png'}" in res.output, res.output
    assert (good / "bev.png").read_bytes()[:4] == b"\x89PNG"


def test_run_out_inside_an_input_is_refused(tmp_path):
    from streamdet.data.sample import bundled_sample_dir
    from streamdet.evaluation.run_cli import main as run_main

    export = tmp_path / "exp"
    export.mkdir()
    (export / "manifest.json").write_text("{}")  # refused before the export is read
    sample = tmp_path / "sample"
    sample.mkdir()
    cases = [
        (["--sample", str(sample), "--out", str(sample)], "is the input --sample"),
        (["--out", str(export / "run")], "lies inside the input --export-dir"),
        (["--out", str(bundled_sample_dir())], "is the input --sample"),  # the default sample
    ]
    for args, message in cases:
        res = CliRunner().invoke(run_main, ["--export-dir", str(export), *args])
        _one_line_error(res)
        assert message in res.output, res.output
    assert list(sample.iterdir()) == []


# ---- 7. one-line errors, not tracebacks ---------------------------------------------------------------------------


def test_out_of_memory_is_one_line(monkeypatch, tmp_path):
    from streamdet.evaluation import run_cli

    def boom(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(run_cli, "run_sample", boom)
    export = tmp_path / "exp"
    export.mkdir()
    (export / "manifest.json").write_text("{}")
    res = CliRunner().invoke(run_cli.main, ["--export-dir", str(export), "--out", str(tmp_path / "o")])
    _one_line_error(res)
    assert "out of memory" in res.output and "--slices" in res.output


def test_study_plot_with_an_unknown_extension_names_the_file(tiny_export_fp32, tiny_synth_data, tmp_path):
    bad = tmp_path / "p.nosuchformat"
    res = _slices(tiny_export_fp32, tiny_synth_data, "--plot", str(bad))
    _one_line_error(res)
    assert f"cannot write --plot {bad}" in res.output
