"""Paired bootstrap of ``streamdet-eval --compare`` against a naive reference: scenes copied, then ``evaluate``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.evaluation import DetectionConfig, EvalBoxes, evaluate, filter_eval_boxes
from streamdet.evaluation.bootstrap import GtSubset, match_tables, paired_bootstrap, summary, weighted_metrics
from streamdet.evaluation.cli import main
from streamdet.evaluation.compare import compare_runs, load_run, read_sample_info, write_sample_info

from result_entries import result_entry as _entry

CFG = DetectionConfig()
CLASSES = ("car", "pedestrian", "traffic_cone")
META = {"use_camera": False, "use_lidar": True}


def _world(seed: int, num_samples: int = 8, quality: float = 0.5):
    """GT and two prediction sets (a weak and a better run) over ``num_samples`` samples; continuous scores."""
    rng = np.random.default_rng(seed)
    gt, runs = {}, ({}, {})
    for s in range(num_samples):
        t = f"s{s}"
        gt[t], runs[0][t], runs[1][t] = [], [], []
        for _ in range(rng.integers(0, 7)):
            name = CLASSES[rng.integers(len(CLASSES))]
            xy = rng.uniform(-25, 25, 2)
            gt[t].append(_entry(t, xy, name, None, int(rng.integers(0, 12))))
            for r, q in enumerate((quality, quality + 0.3)):
                if rng.random() < q:
                    runs[r][t].append(_entry(t, xy + rng.normal(0, 0.7, 2), name, float(rng.random()), -1))
        for r in range(2):
            for _ in range(rng.integers(0, 3)):
                runs[r][t].append(_entry(t, rng.uniform(-25, 25, 2), CLASSES[rng.integers(3)], float(rng.random()), -1))
    return gt, runs


def _boxes(results: dict) -> EvalBoxes:
    return EvalBoxes.from_results(results).with_ego_position({t: [0.0, 0.0, 0.0] for t in results})


def _duplicated(results: dict, weights: dict[str, int]) -> dict:
    """The naive multiset: every sample copied as often as it was drawn, under fresh tokens."""
    out = {}
    for t, entries in results.items():
        for copy in range(weights[t]):
            token = f"{t}#{copy}"
            out[token] = [dict(e, sample_token=token) for e in entries]
    return out


def _figures(gt: dict, pred: dict, classes=CLASSES) -> dict[str, float]:
    return summary(evaluate(_boxes(gt), _boxes(pred), classes=classes))


@pytest.mark.parametrize("seed", range(4))
def test_weighted_metrics_equal_evaluate_on_copied_samples(seed):
    gt, (pred, _) = _world(seed)
    _, tables = match_tables(_boxes(gt), _boxes(pred), CLASSES)
    rng = np.random.default_rng(100 + seed)
    for weights in (np.ones(len(gt), np.int64), rng.integers(0, 4, len(gt))):
        if weights.sum() == 0:
            continue
        fast = summary(weighted_metrics(tables, CLASSES, weights))
        naive = _figures(_duplicated(gt, dict(zip(gt, weights.tolist()))), _duplicated(pred, dict(zip(gt, weights.tolist()))))
        assert fast == pytest.approx(naive, abs=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_paired_bootstrap_matches_naive_loop(seed):
    gt, (pa, pb) = _world(seed, num_samples=6)
    scenes = np.array([0, 0, 1, 1, 2, 2])
    _, ta = match_tables(_boxes(gt), _boxes(pa), CLASSES)
    _, tb = match_tables(_boxes(gt), _boxes(pb), CLASSES)
    draws = 5
    got = paired_bootstrap(ta, tb, CLASSES, scenes, num_draws=draws, seed=seed)
    rng = np.random.default_rng(seed)
    diffs = []
    for _ in range(draws):
        counts = np.bincount(rng.integers(0, 3, 3), minlength=3)
        w = dict(zip(gt, counts[scenes].tolist()))
        a, b = _figures(_duplicated(gt, w), _duplicated(pa, w)), _figures(_duplicated(gt, w), _duplicated(pb, w))
        diffs.append(b["mAP"] - a["mAP"])
    assert got["mAP"].lo == pytest.approx(np.percentile(diffs, 2.5), abs=1e-12)
    assert got["mAP"].hi == pytest.approx(np.percentile(diffs, 97.5), abs=1e-12)
    full = _figures(gt, pb)["mAP"] - _figures(gt, pa)["mAP"]
    assert got["mAP"].diff == pytest.approx(full, abs=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_subset_of_whole_samples_equals_evaluating_those_samples(seed):
    gt, (pred, _) = _world(seed)
    g, p = filter_eval_boxes(_boxes(gt), CFG.class_range_m), filter_eval_boxes(_boxes(pred), CFG.class_range_m)
    chosen = {"s0", "s2", "s5"}
    in_g = np.isin(np.array(g.sample_tokens)[g.sample_index], list(chosen))
    in_p = np.isin(np.array(p.sample_tokens)[p.sample_index], list(chosen))
    present = tuple(c for c in CLASSES if np.any(g.detection_name[in_g] == c))
    if not present:
        pytest.skip("no ground truth in the chosen samples")
    _, tables = match_tables(g, p, present, subset=GtSubset(in_g, in_p), filtered=True)
    got = summary(weighted_metrics(tables, present, np.ones(len(g.sample_tokens), np.int64)))
    ref = _figures({t: gt[t] for t in sorted(chosen)}, {t: pred[t] for t in sorted(chosen)}, present)
    assert got == pytest.approx(ref, abs=1e-12)


def test_identical_runs_differ_by_exactly_zero():
    gt, (pred, _) = _world(0)
    _, t = match_tables(_boxes(gt), _boxes(pred), CLASSES)
    out = paired_bootstrap(t, t, CLASSES, np.arange(len(gt)), num_draws=20)
    assert all(d.diff == 0 and d.lo == 0 and d.hi == 0 for d in out.values())


def test_bootstrap_rejects_empty_and_malformed_clusters():
    gt, (pred, _) = _world(1)
    _, t = match_tables(_boxes(gt), _boxes(pred), CLASSES)
    with pytest.raises(ValueError, match="no sample"):
        paired_bootstrap(t, t, CLASSES, np.zeros(0, np.int64))
    with pytest.raises(ValueError, match="integers"):
        paired_bootstrap(t, t, CLASSES, np.zeros(len(gt)))
    with pytest.raises(ValueError, match="num_draws"):
        paired_bootstrap(t, t, CLASSES, np.arange(len(gt)), num_draws=0)
    with pytest.raises(ValueError, match="gt_keep"):
        match_tables(_boxes(gt), _boxes(pred), CLASSES, subset=GtSubset(np.ones(1, bool)))


def _save(folder, gt, pred, scenes=None, num_slices=4):
    from streamdet.evaluation.results import write_results_json

    folder.mkdir()
    write_results_json(folder / "results.json", pred, META)
    write_results_json(folder / "gt.json", gt, META, ego_positions={t: [0.0, 0.0, 0.0] for t in gt})
    if scenes is not None:
        eye = np.eye(4)
        write_sample_info(folder / "samples.json", scenes, {t: (eye, eye) for t in gt}, num_slices)
    return folder


def test_cli_compare_saved_runs_with_subsets(tmp_path):
    gt, (pa, pb) = _world(3, num_samples=8)
    scenes = {t: f"scene{i // 2}" for i, t in enumerate(gt)}
    a = _save(tmp_path / "a", gt, pa, scenes, num_slices=32)  # narrow sectors: some boxes are cut
    b = _save(tmp_path / "b", gt, pb, scenes, num_slices=32)
    out = tmp_path / "cmp.json"
    res = CliRunner().invoke(main, ["--compare", str(a), str(b), "--bootstrap", "30", "--json", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["clustered_by"] == "scene" and doc["num_clusters"] == 4
    assert {"all", "gt<=5pts", "cut_by_slice_border", "slice0"} <= set(doc["subsets"])
    assert doc["subsets"]["all"]["mAP"]["ci_lo"] <= doc["subsets"]["all"]["mAP"]["ci_hi"]
    assert "AP/car" in doc["subsets"]["all"]


def test_cli_compare_without_sample_info_warns_and_results_file_needs_gt(tmp_path):
    gt, (pa, pb) = _world(4)
    a, b = _save(tmp_path / "a", gt, pa), _save(tmp_path / "b", gt, pb)
    res = CliRunner().invoke(main, ["--compare", str(a), str(b), "--bootstrap", "5"])
    assert res.exit_code == 0, res.output
    assert "too narrow" in res.output
    res = CliRunner().invoke(main, ["--compare", str(a / "results.json"), str(b / "results.json"), "--bootstrap", "5"])
    assert res.exit_code != 0 and "--gt" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(main, ["--compare", str(a / "results.json"), str(b / "results.json"), "--gt",
                                    str(a / "gt.json"), "--bootstrap", "5"])  # fmt: skip
    assert res.exit_code == 0, res.output


def test_cli_compare_errors_are_one_line(tmp_path):
    gt, (pa, pb) = _world(5)
    a = _save(tmp_path / "a", gt, pa)
    other = _save(tmp_path / "o", {t: v for t, v in list(gt.items())[:3]}, {t: v for t, v in list(pb.items())[:3]})
    res = CliRunner().invoke(main, ["--compare", str(a), str(other)])
    assert res.exit_code != 0 and "same ground truth" in res.output
    empty = tmp_path / "e"
    empty.mkdir()
    res = CliRunner().invoke(main, ["--compare", str(a), str(empty)])
    assert res.exit_code != 0 and "results.json is missing" in res.output
    b = _save(tmp_path / "b", gt, pb)
    for twice in ([str(a), str(a)], [str(a), str(a / "results.json")], [f"{b},{a}", str(a)]):
        res = CliRunner().invoke(main, ["--compare", *twice])
        assert res.exit_code == 2 and f"{a.resolve()} is on both sides" in res.output, twice
    (a / "samples.json").write_text("{not json")
    res = CliRunner().invoke(main, ["--compare", str(a), str(b)])
    assert res.exit_code != 0 and "samples.json" in res.output and "Traceback" not in res.output
    nothing = _save(tmp_path / "n", {"s0": []}, {"s0": []})
    nothing_too = _save(tmp_path / "n2", {"s0": []}, {"s0": []})
    res = CliRunner().invoke(main, ["--compare", str(nothing), str(nothing_too)])
    assert res.exit_code != 0 and "nothing to compare" in res.output


def test_sample_info_round_trip_and_malformed(tmp_path):
    p = tmp_path / "samples.json"
    write_sample_info(p, {"t": "scene-1"}, {"t": (np.eye(4), np.eye(4))}, 8)
    info = read_sample_info(p)
    assert info.num_slices == 8 and info.scenes == {"t": "scene-1"}
    p.write_text(json.dumps({"num_slices": 3, "samples": {}}))
    with pytest.raises(ValueError, match="not a samples file"):
        read_sample_info(p)
    with pytest.raises(ValueError, match="does not exist"):
        load_run(tmp_path / "missing")


def _world_runs(seed: int, num_samples: int, runs_per_side: int):
    """One ground truth and ``runs_per_side`` prediction sets per side (seeds of a weak and of a better recipe)."""
    gt, _ = _world(seed, num_samples)
    sides = ([], [])
    for r in range(runs_per_side):
        _, (pa, pb) = _world(seed, num_samples)  # the same gt draw ...
        rng = np.random.default_rng(1000 * seed + r)
        for side, pred in zip(sides, (pa, pb)):  # ... predictions jittered per run
            side.append({t: [dict(e, detection_score=float(rng.random())) for e in v] for t, v in pred.items()})
    return gt, sides


@pytest.mark.parametrize("seed", range(2))
@pytest.mark.parametrize("runs", [(2, 3), (3, 1)])
def test_groups_of_runs_match_a_naive_two_level_loop(seed, runs):
    """A side of several runs is their mean; every draw resamples scenes (shared) and each side's runs."""
    gt, (side_a, side_b) = _world_runs(seed, 6, max(runs))
    side_a, side_b = side_a[: runs[0]], side_b[: runs[1]]
    scenes = np.array([0, 0, 1, 1, 2, 2])
    ta = [match_tables(_boxes(gt), _boxes(p), CLASSES)[1] for p in side_a]
    tb = [match_tables(_boxes(gt), _boxes(p), CLASSES)[1] for p in side_b]
    draws = 4
    got = paired_bootstrap(ta, tb, CLASSES, scenes, num_draws=draws, seed=seed)
    rng = np.random.default_rng(seed)
    diffs = []
    for _ in range(draws):
        counts = np.bincount(rng.integers(0, 3, 3), minlength=3)
        picks_a = rng.integers(0, len(side_a), len(side_a)) if len(side_a) > 1 else [0]
        picks_b = rng.integers(0, len(side_b), len(side_b)) if len(side_b) > 1 else [0]
        w = dict(zip(gt, counts[scenes].tolist()))
        a = np.mean([_figures(_duplicated(gt, w), _duplicated(side_a[i], w))["mAP"] for i in picks_a])
        b = np.mean([_figures(_duplicated(gt, w), _duplicated(side_b[i], w))["mAP"] for i in picks_b])
        diffs.append(b - a)
    assert got["mAP"].lo == pytest.approx(np.percentile(diffs, 2.5), abs=1e-12)
    assert got["mAP"].hi == pytest.approx(np.percentile(diffs, 97.5), abs=1e-12)
    mean_a = np.mean([_figures(gt, p)["mAP"] for p in side_a])
    mean_b = np.mean([_figures(gt, p)["mAP"] for p in side_b])
    assert got["mAP"].a == pytest.approx(mean_a, abs=1e-12) and got["mAP"].b == pytest.approx(mean_b, abs=1e-12)


def test_a_group_of_one_run_is_that_run():
    gt, (pa, pb) = _world(7)
    _, ta = match_tables(_boxes(gt), _boxes(pa), CLASSES)
    _, tb = match_tables(_boxes(gt), _boxes(pb), CLASSES)
    single = paired_bootstrap(ta, tb, CLASSES, np.arange(len(gt)), num_draws=15, seed=2)
    grouped = paired_bootstrap([ta], [tb], CLASSES, np.arange(len(gt)), num_draws=15, seed=2)
    assert single == grouped
    with pytest.raises(ValueError, match="at least one run"):
        paired_bootstrap([], [tb], CLASSES, np.arange(len(gt)))


def test_cli_compare_groups_of_runs(tmp_path):
    gt, (side_a, side_b) = _world_runs(2, 8, 2)
    scenes = {t: f"scene{i // 2}" for i, t in enumerate(gt)}
    a = [_save(tmp_path / f"a{i}", gt, p, scenes) for i, p in enumerate(side_a)]
    b = [_save(tmp_path / f"b{i}", gt, p, scenes) for i, p in enumerate(side_b)]
    out = tmp_path / "cmp.json"
    res = CliRunner().invoke(main, ["--compare", f"{a[0]},{a[1]}", f"{b[0]},{b[1]}", "--bootstrap", "10", "--json", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["A"] == [str(a[0]), str(a[1])] and doc["B"] == [str(b[0]), str(b[1])]
    assert any("mean of 2 run(s)" in n for n in doc["notes"]) and "slice0" in doc["subsets"]
    res = CliRunner().invoke(main, ["--compare", f"{a[0]},{tmp_path / 'missing'}", str(b[0])])
    assert res.exit_code != 0 and "does not exist" in res.output and "Traceback" not in res.output


def test_compare_reports_progress_once_per_subset(tmp_path):
    """The bootstrap of each subset is the long part: progress(subset, done, total) follows every one, in order."""
    gt, (pa, pb) = _world(6, num_samples=8)
    scenes = {t: f"scene{i // 2}" for i, t in enumerate(gt)}
    a = load_run(_save(tmp_path / "a", gt, pa, scenes, num_slices=4))
    b = load_run(_save(tmp_path / "b", gt, pb, scenes, num_slices=4))
    calls = []
    c = compare_runs(a, b, num_draws=5, progress=lambda name, done, total: calls.append((name, done, total)))
    total = calls[0][2]
    assert [d for _, d, _ in calls] == list(range(1, total + 1)) and all(t == total for _, _, t in calls)
    assert total == 2 + 1 + 4  # all, few points, cut by a border, four slices
    assert set(c.subsets) <= {name for name, _, _ in calls}


def test_cli_compare_no_subsets_keeps_the_headline_only(tmp_path):
    gt, (pa, pb) = _world(7, num_samples=8)
    scenes = {t: f"scene{i // 2}" for i, t in enumerate(gt)}
    a = _save(tmp_path / "a", gt, pa, scenes, num_slices=8)
    b = _save(tmp_path / "b", gt, pb, scenes, num_slices=8)
    full, head = tmp_path / "full.json", tmp_path / "head.json"
    for extra, out in (([], full), (["--no-subsets"], head)):
        res = CliRunner().invoke(main, ["--compare", str(a), str(b), "--bootstrap", "20", "--json", str(out), *extra])
        assert res.exit_code == 0, res.output
    full_doc, head_doc = json.loads(full.read_text()), json.loads(head.read_text())
    assert set(head_doc["subsets"]) == {"all"} and len(full_doc["subsets"]) > 1
    assert head_doc["subsets"]["all"] == full_doc["subsets"]["all"]  # the same draws for the headline


def test_a_run_whose_files_are_no_regular_files_says_so(tmp_path):
    """A FIFO or a folder where results.json goes was reported "missing", a FIFO run "does not exist"."""
    import os

    from streamdet.evaluation.compare import load_run

    run = tmp_path / "run"
    (run / "results.json").mkdir(parents=True)
    (run / "gt.json").write_text("{}")
    with pytest.raises(ValueError, match="results.json is not a regular file"):
        load_run(run)
    os.mkfifo(tmp_path / "fifo.json")
    with pytest.raises(ValueError, match="neither a saved run's folder nor a results file"):
        load_run(tmp_path / "fifo.json", tmp_path / "gt.json")
    with pytest.raises(ValueError, match="does not exist"):
        load_run(tmp_path / "absent")


# ---- a class without ground truth, bike racks, one TP-error definition ------------------------------------------


def test_a_class_with_predictions_and_no_ground_truth_scores_as_evaluate_does():
    """match_tables used to raise IndexError for it; now its table is all false positives and weighted_metrics gives
    evaluate's figures bit for bit (the devkit's AP 0 and TP errors 1 for the class), for every class set."""
    gt, (pred, _) = _world(2)
    pred = {t: v + [_entry(t, (3.0, 4.0), "truck", 0.7, -1)] for t, v in pred.items()}  # trucks: no GT anywhere
    g, p = _boxes(gt), _boxes(pred)
    for classes in (CFG.class_names, ("car", "truck"), ("truck",)):
        samples, tables = match_tables(g, p, classes)
        fast = weighted_metrics(tables, CFG.class_names if classes is CFG.class_names else tuple(
            c for c in CFG.class_names if c in classes), np.ones(len(samples), np.int64))  # fmt: skip
        ref = evaluate(g, p, classes=classes)
        assert summary(fast) == summary(ref) and fast.label_tp_errors == ref.label_tp_errors
        assert fast.mean_dist_aps["truck"] == 0.0 and all(e == 1.0 for e in fast.label_tp_errors["truck"].values())
    empty = {t: [] for t in gt}  # no ground truth at all: every class is such a class
    samples, tables = match_tables(_boxes(empty), p, ("car",))
    assert weighted_metrics(tables, ("car",), np.ones(len(samples), np.int64)).mean_ap == 0.0


def test_compare_keeps_named_classes_without_ground_truth(tmp_path):
    """--classes car,truck with trucks only predicted: the comparison averages both, as evaluate(classes=...) does
    (it used to drop truck silently), and says so."""
    gt, (pa, pb) = _world(6)
    pb = {t: v + [_entry(t, (3.0, 4.0), "truck", 0.7, -1)] for t, v in pb.items()}
    a, b = load_run(_save(tmp_path / "a", gt, pa)), load_run(_save(tmp_path / "b", gt, pb))
    c = compare_runs(a, b, classes=("truck", "car"), num_draws=3)
    assert {"AP/car", "AP/truck"} <= set(c.subsets["all"])
    assert c.subsets["all"]["mAP"].a == evaluate(a.gt, a.pred, classes=("car", "truck")).mean_ap
    assert c.subsets["all"]["mAP"].b == evaluate(b.gt, b.pred, classes=("car", "truck")).mean_ap
    assert any("no ground-truth box of truck" in n for n in c.notes)
    default = compare_runs(a, b, num_draws=3)  # default: the classes present, as before
    assert "AP/truck" not in default.subsets["all"]
    with pytest.raises(ValueError, match="subset of"):
        compare_runs(a, b, classes=("lorry",), num_draws=3)


def _racked_world():
    """Two samples; in s0 a rack holds a GT bicycle that run A misses and run B finds, and A predicts a motorcycle
    in it. The devkit's rule removes all of them, so A and B score the same with the racks and differ without."""
    rack = [10.0, 0.0, 1.0, 2.0, 4.0, 2.0, 1.0, 0.0, 0.0, 0.0]
    gt = {"s0": [_entry("s0", (10.0, 0.5), "bicycle", None, 8), _entry("s0", (-5.0, 3.0), "bicycle", None, 8)],
          "s1": [_entry("s1", (4.0, 4.0), "car", None, 8)]}  # fmt: skip
    common = [_entry("s0", (-5.1, 3.0), "bicycle", 0.9, -1)]
    pa = {"s0": common + [_entry("s0", (10.0, -0.8), "motorcycle", 0.8, -1)], "s1": [_entry("s1", (4.1, 4.0), "car", 0.9, -1)]}
    pb = {"s0": common + [_entry("s0", (10.1, 0.5), "bicycle", 0.5, -1)], "s1": [_entry("s1", (4.1, 4.0), "car", 0.9, -1)]}
    return gt, pa, pb, {"s0": [rack]}


def _save_with_racks(folder, gt, pred, racks):
    from streamdet.evaluation.results import write_results_json

    folder.mkdir()
    write_results_json(folder / "results.json", pred, META)
    write_results_json(folder / "gt.json", gt, META, ego_positions={t: [0.0, 0.0, 0.0] for t in gt}, bike_racks=racks)
    return folder


def test_compare_applies_the_ground_truths_bike_racks(tmp_path):
    gt, pa, pb, racks = _racked_world()
    a = load_run(_save_with_racks(tmp_path / "a", gt, pa, racks))
    b = load_run(_save_with_racks(tmp_path / "b", gt, pb, racks))
    assert a.bike_racks is not None and a.bike_racks["s0"].shape == (1, 10)
    c = compare_runs(a, b, num_draws=3, subsets=False)
    bike_racks = {t: np.asarray(r) for t, r in racks.items()}
    for side, run in (("a", a), ("b", b)):
        ref = summary(evaluate(run.gt, run.pred, classes=("car", "bicycle"), bike_racks=bike_racks))
        assert {k: getattr(d, side) for k, d in c.subsets["all"].items()} == ref
    assert c.subsets["all"]["mAP"].diff == 0.0  # all that differed stood in the rack
    assert evaluate(a.gt, a.pred).mean_ap != evaluate(b.gt, b.pred).mean_ap  # without the rule it counts
    # saved before racks were: the other run's racks serve it, with a note; racks that disagree are refused
    old = load_run(_save(tmp_path / "old", gt, pb))
    assert old.bike_racks is None
    c_old = compare_runs(a, old, num_draws=3, subsets=False)
    assert c_old.subsets["all"]["mAP"].diff == 0.0 and any("bike_racks of" in n for n in c_old.notes)
    moved = load_run(_save_with_racks(tmp_path / "moved", gt, pb, {"s0": [[12.0, *racks["s0"][0][1:]]]}))
    with pytest.raises(ValueError, match=r"same ground truth .* sample 's0' has another bicycle rack"):
        compare_runs(a, moved, num_draws=3)
    two = load_run(_save_with_racks(tmp_path / "two", gt, pb, {"s0": racks["s0"] * 2}))
    with pytest.raises(ValueError, match="sample 's0' has 1 vs 2 bicycle racks"):
        compare_runs(a, two, num_draws=3)


def test_ground_truth_difference_names_the_field():
    """A gt.json saved before attributes and unknown velocities were kept differs from a new one only there: the
    message says which field, with both values."""
    from streamdet.evaluation.compare import ground_truth_difference

    gt, _ = _world(7)
    with_attr = {t: [dict(e, attribute_name="vehicle.parked") if e["detection_name"] == "car" else e for e in v]
                 for t, v in gt.items()}  # fmt: skip
    msg = ground_truth_difference(_boxes(gt), _boxes(with_attr))
    assert "differs in attribute_name" in msg and "attribute_name ''" in msg and "'vehicle.parked'" in msg
    nan_vel = {t: [dict(e, velocity=[float("nan")] * 2) for e in v] for t, v in gt.items()}
    assert "differs in velocity" in ground_truth_difference(_boxes(gt), _boxes(nan_vel))
    assert ground_truth_difference(_boxes(nan_vel), _boxes(nan_vel)) is None


def test_bootstrap_and_evaluate_share_one_tp_error_definition():
    """The bootstrap's TP errors are detection_eval's own function, not a copy that could drift from the official
    figure (and its matching, class order and summary too)."""
    import streamdet.evaluation.bootstrap as bootstrap
    import streamdet.evaluation.detection_eval as detection_eval

    for name in ("tp_errors", "greedy_match", "ordered_classes", "score_order", "metric_curves", "detection_metrics"):
        assert getattr(bootstrap, name) is getattr(detection_eval, name), name
    assert not hasattr(detection_eval, "_greedy_match") and not hasattr(detection_eval, "_ordered_classes")
