"""Review 40 of ``streamdet-eval``: duplicate keys (M1), strings and booleans as box numbers (M2), what makes two
``--compare`` runs one (M3), files the devkit refuses (L1), ``p_not_positive`` of an undefined interval (L2) and
errors naming the files (L3)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.core.json_input import read_json
from streamdet.evaluation import eval_boxes as eval_boxes_module
from streamdet.evaluation import cli as cli_module
from streamdet.evaluation.bootstrap import Difference
from streamdet.evaluation.cli import main
from streamdet.evaluation.compare import read_sample_info, write_sample_info
from streamdet.evaluation.eval_boxes import EvalBoxes
from streamdet.evaluation.results import load_eval_inputs, read_results_json

from result_entries import result_entry

META = {"use_camera": False, "use_lidar": True}
TOKENS = ("s0", "s1", "s2", "s3", "s4", "s5")


def _gt(tokens=TOKENS) -> dict:
    return {t: [result_entry(t, (5.0 + k, 5.0), "car", None, 8), result_entry(t, (-8.0, 3.0 + k), "pedestrian", None, 8)]
            for k, t in enumerate(tokens)}  # fmt: skip


def _pred(tokens=TOKENS, shift: float = 0.3) -> dict:
    return {t: [result_entry(t, (5.0 + k + shift, 5.0), "car", 0.9), result_entry(t, (-8.0, 3.0 + k - shift), "pedestrian", 0.6)]
            for k, t in enumerate(tokens)}  # fmt: skip


def _write(path, results: dict, meta=META, **extra) -> str:
    doc = {"results": results, **extra}
    if meta is not None:
        doc["meta"] = meta
    path.write_text(json.dumps(doc))
    return str(path)


def _files(tmp_path, pred: dict | None = None, meta=META):
    gt = _write(tmp_path / "gt.json", _gt(), meta=None, ego_positions={t: [0.0, 0.0, 0.0] for t in TOKENS})
    return gt, _write(tmp_path / "pred.json", _pred() if pred is None else pred, meta=meta)


def _eval(*args: str):
    return CliRunner().invoke(main, list(args))


# ---- M1: a key given twice ----------------------------------------------------------------------------------------


def test_read_json_refuses_a_key_given_twice_only_when_asked(tmp_path):
    path = tmp_path / "t.json"
    path.write_text('[{"token": "a", "x": 1, "x": 2}]')
    assert read_json(path, "nuScenes table", 1 << 20) == [{"token": "a", "x": 2}]  # tables: json's rule, no hook cost
    with pytest.raises(ValueError, match=r"results file .*t\.json: key 'x' appears twice in one object") as e:
        read_json(path, "results file", 1 << 20, unique_keys=True)
    assert str(path) in str(e.value)
    path.write_text('{"a": {"x": 1}, "b": {"x": 2}}')  # one key in two objects is no duplicate
    assert read_json(path, "results file", 1 << 20, unique_keys=True) == {"a": {"x": 1}, "b": {"x": 2}}


@pytest.mark.parametrize("which", ["gt", "pred"])
def test_a_sample_listed_twice_is_refused_naming_file_and_key(tmp_path, which):
    """The review's repro: GT {"s0": [3 cars], "s0": [1 car]} scored 3 correct predictions as 1 TP and 2 FP."""
    gt, pred = _files(tmp_path)
    target = gt if which == "gt" else pred
    doc = json.loads(open(target).read())
    s0 = json.dumps(doc["results"]["s0"])
    text = json.dumps(doc).replace('"s0": ' + s0, '"s0": ' + s0 + ', "s0": ' + json.dumps(doc["results"]["s0"][:1]), 1)
    open(target, "w").write(text)
    with pytest.raises(ValueError, match="key 's0' appears twice") as e:
        read_results_json(target)
    assert target in str(e.value)
    r = _eval("--gt", gt, "--results", pred)
    assert r.exit_code == 1 and "key 's0' appears twice" in r.output and target in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_a_field_given_twice_in_a_box_is_refused(tmp_path):
    gt, pred = _files(tmp_path)
    text = open(pred).read().replace('"detection_score": 0.9', '"detection_score": 0.9, "detection_score": 0.1', 1)
    open(pred, "w").write(text)
    r = _eval("--gt", gt, "--results", pred)
    assert r.exit_code == 1 and "key 'detection_score' appears twice" in r.output and pred in r.output


def test_samples_json_with_a_sample_twice_is_refused(tmp_path):
    path = tmp_path / "samples.json"
    write_sample_info(path, {"a": "scene-1", "b": "scene-2"}, {t: (np.eye(4), np.eye(4)) for t in "ab"}, 4)
    text = path.read_text().replace('"b": {', '"a": {', 1)
    path.write_text(text)
    with pytest.raises(ValueError, match="key 'a' appears twice") as e:
        read_sample_info(path)
    assert str(path) in str(e.value)


# ---- M2: numbers must be JSON numbers -----------------------------------------------------------------------------

BAD_VECTORS = {
    "translation strings": ("translation", ["5.1", "5", "1"]),
    "translation bools": ("translation", [True, True, False]),
    "size bools": ("size", [True, True, True]),
    "size strings": ("size", ["2", "4.5", "1e400"]),
    "rotation strings": ("rotation", ["1", "0", "0", "0"]),
    "velocity strings": ("velocity", ["nan", "0"]),
    "velocity bool": ("velocity", [0.0, False]),
    "ego_translation strings": ("ego_translation", ["5", "5", "1"]),
}


@pytest.mark.parametrize("key, value", list(BAD_VECTORS.values()), ids=list(BAD_VECTORS))
def test_both_parsing_paths_refuse_strings_and_booleans_as_numbers(key, value):
    entry = dict(result_entry("s0", (5.0, 5.0), "car", None, 8), **{key: value})
    # the fast path (whole columns) must not take them: numpy's float conversion parses "5.1" and True
    with pytest.raises((TypeError, ValueError)):
        eval_boxes_module._columns([entry], ("s0",), np.zeros(1, np.int64))
    # the entry path names the entry and the field
    with pytest.raises(ValueError, match=rf"^X\.{key} must be {len(value)} finite numbers \(JSON numbers, not strings or booleans\)"):
        eval_boxes_module._parse_entry(entry, "s0", "X")
    with pytest.raises(ValueError, match=rf"src\['s0'\]\[1\]\.{key} must be"):
        EvalBoxes.from_results({"s0": [result_entry("s0", (1.0, 1.0), "car", None, 8), entry]}, source="src")


@pytest.mark.parametrize("key, value", [("translation", ["5.1", "5", "1"]), ("velocity", [True, 0.0])])
@pytest.mark.parametrize("which", ["gt", "pred"])
def test_a_string_or_bool_coordinate_names_file_sample_box_and_field(tmp_path, key, value, which):
    pred = _pred()
    gt, pred_path = _files(tmp_path, pred)
    target = gt if which == "gt" else pred_path
    doc = json.loads(open(target).read())
    doc["results"]["s2"][1][key] = value
    open(target, "w").write(json.dumps(doc))
    r = _eval("--gt", gt, "--results", pred_path)
    assert r.exit_code == 1 and len(r.output.strip().splitlines()) == 1, r.output
    assert f"{target}: results['s2'][1].{key} must be" in r.output and "not strings or booleans" in r.output


def test_numbers_of_every_kind_still_parse():
    """JSON ints, floats, null / NaN velocity, and numpy scalars from Python callers."""
    e = result_entry("s0", (5.0, 5.0), "car", 0.5)
    e.update(translation=[5, np.float32(5.0), np.int64(1)], velocity=[None, math.nan])
    boxes = EvalBoxes.from_results({"s0": [e]})
    assert boxes.translation.tolist() == [[5.0, 5.0, 1.0]] and np.isnan(boxes.velocity).all()
    assert eval_boxes_module._parse_entry(e, "s0", "X")[0] == [5.0, 5.0, 1.0]


# ---- M3: what makes two --compare runs one ------------------------------------------------------------------------


def test_compare_two_results_files_in_one_folder_are_two_runs(tmp_path):
    gt, a = _files(tmp_path)
    b = _write(tmp_path / "b.json", _pred(shift=0.1))
    out = tmp_path / "cmp.json"
    r = _eval("--compare", a, b, "--gt", gt, "--bootstrap", "20", "--no-subsets", "--json", str(out))
    assert r.exit_code == 0, r.output
    assert json.loads(out.read_text())["A"] == a


def test_compare_a_folder_and_its_own_results_file_are_one_run(tmp_path):
    gt, _ = _files(tmp_path)
    run = tmp_path / "R"
    run.mkdir()
    _write(run / "results.json", _pred())
    other = _write(tmp_path / "b.json", _pred(shift=0.1))
    r = _eval("--compare", f"{run},{run / 'results.json'}", other, "--gt", gt, "--no-subsets")
    assert r.exit_code == 2 and "is given twice" in r.output  # was: "A is the mean of 2 run(s)"
    r = _eval("--compare", str(run / "results.json"), str(run), "--gt", gt, "--no-subsets")
    assert r.exit_code == 2 and f"{(run / 'results.json').resolve()} is on both sides" in r.output


# ---- L1: what the devkit refuses ----------------------------------------------------------------------------------


def test_a_results_file_without_meta_is_refused_a_ground_truth_without_is_not(tmp_path):
    gt, pred = _files(tmp_path, meta=None)
    r = _eval("--gt", gt, "--results", pred)
    assert r.exit_code == 1 and f"{pred} has no 'meta' object" in r.output and len(r.output.strip().splitlines()) == 1
    _write(tmp_path / "pred.json", _pred(), meta={})  # the devkit reads meta, not its keys
    assert _eval("--gt", gt, "--results", pred).exit_code == 0


def test_a_meta_flag_that_is_not_a_boolean_is_refused(tmp_path):
    gt, pred = _files(tmp_path, meta={"use_camera": "yes", "use_lidar": True})
    r = _eval("--gt", gt, "--results", pred)
    assert r.exit_code == 1 and f"{pred}: meta['use_camera'] must be true or false, got 'yes'" in r.output


def test_a_negative_score_is_refused_naming_the_box(tmp_path):
    pred = _pred()
    pred["s3"][1]["detection_score"] = -0.4
    gt, pred_path = _files(tmp_path, pred)
    with pytest.raises(ValueError, match=r"results\['s3'\]\[1\]\.detection_score must be >= 0, got -0\.4") as e:
        load_eval_inputs(gt, pred_path)
    assert pred_path in str(e.value)
    r = _eval("--gt", gt, "--results", pred_path)
    assert r.exit_code == 1 and "must be >= 0" in r.output and "Traceback" not in r.output


def test_a_prediction_without_a_score_is_refused(tmp_path):
    pred = _pred()
    del pred["s1"][0]["detection_score"]
    gt, pred_path = _files(tmp_path, pred)
    with pytest.raises(ValueError, match=r"results\['s1'\]\[0\] has no 'detection_score' field"):
        load_eval_inputs(gt, pred_path)


def test_a_prediction_without_attribute_name_is_scored_with_a_note(tmp_path):
    """Not refused (test_evaluation_cli scores the bundled devkit oracle, whose predictions carry no attribute)."""
    pred = _pred()
    for entries in pred.values():
        for e in entries:
            del e["attribute_name"]
    gt, pred_path = _files(tmp_path, pred)
    inputs = load_eval_inputs(gt, pred_path)
    assert len(inputs.notes) == 1 and "12 of 12 boxes have no attribute_name (first results['s0'][0])" in inputs.notes[0]
    r = _eval("--gt", gt, "--results", pred_path)
    assert r.exit_code == 0 and "note: " + pred_path in r.output and "the devkit refuses" in r.output


def test_ground_truth_keeps_its_negative_scores_and_no_meta(tmp_path):
    gt, pred = _files(tmp_path)
    inputs = load_eval_inputs(gt, pred)
    assert (inputs.gt.detection_score == -1.0).all() and inputs.notes == ()


# ---- L2: an undefined interval ------------------------------------------------------------------------------------


def test_p_not_positive_is_null_when_the_interval_is_undefined():
    undefined = Difference(a=0.1, b=0.3, diff=0.2, lo=0.2, hi=0.2, p_not_positive=0.0, interval_defined=False)
    doc = json.loads(json.dumps(undefined.to_dict()))
    assert doc["p_not_positive"] is None and doc["ci_lo"] == 0.2 and doc["significant"] is False
    assert undefined.p_not_positive == 0.0  # the object keeps the draws' share
    defined = Difference(a=0.1, b=0.3, diff=0.2, lo=0.1, hi=0.3, p_not_positive=0.0)
    assert defined.to_dict()["p_not_positive"] == 0.0


def test_compare_over_one_scene_writes_null_and_prints_undefined(tmp_path):
    gt, a = _files(tmp_path)
    b = _write(tmp_path / "b.json", _pred(shift=0.1))
    for name, path in (("A", a), ("B", b)):
        run = tmp_path / name
        run.mkdir()
        (run / "results.json").write_text(open(path).read())
        (run / "gt.json").write_text(open(gt).read())
        write_sample_info(run / "samples.json", {t: "one-scene" for t in TOKENS}, {t: (np.eye(4), np.eye(4)) for t in TOKENS}, 1)
    out = tmp_path / "cmp.json"
    r = _eval("--compare", str(tmp_path / "A"), str(tmp_path / "B"), "--bootstrap", "20", "--no-subsets", "--json", str(out))
    assert r.exit_code == 0, r.output
    figures = json.loads(out.read_text())["subsets"]["all"]
    assert all(f["p_not_positive"] is None and f["interval_defined"] is False for f in figures.values())
    assert all(isinstance(f["ci_lo"], float) for f in figures.values())  # kept numbers: readers index them
    rows = [line for line in r.output.splitlines() if line.startswith("all ")]
    assert rows and all(line.rstrip().endswith("undefined") for line in rows)


# ---- L3: errors that name the files -------------------------------------------------------------------------------


def test_more_than_500_boxes_names_the_file(tmp_path):
    pred = _pred()
    pred["s0"] = [result_entry("s0", (1 + i * 0.01, 0.0), "car", 0.5) for i in range(501)]
    gt, pred_path = _files(tmp_path, pred)
    r = _eval("--gt", gt, "--results", pred_path)
    assert r.exit_code == 1 and len(r.output.strip().splitlines()) == 1
    assert f"{pred_path} (against {gt}): sample 's0' has 501 predictions" in r.output


@pytest.mark.parametrize("change", ["missing", "extra"])
def test_samples_not_covering_the_ground_truth_name_the_file(tmp_path, change):
    pred = _pred()
    if change == "missing":
        del pred["s4"]
    else:
        pred["zz"] = []
    gt, pred_path = _files(tmp_path, pred)
    r = _eval("--gt", gt, "--results", pred_path)
    assert r.exit_code == 1 and f"{pred_path} (against {gt}): predictions must cover exactly the ground-truth samples" in r.output
    r = _eval("--compare", pred_path, _write(tmp_path / "b.json", _pred()), "--gt", gt, "--no-subsets")
    assert r.exit_code == 1 and f"{pred_path} (against {gt}): predictions must cover exactly" in r.output


def test_an_error_of_evaluate_in_the_files_mode_names_the_files(tmp_path, monkeypatch):
    gt, pred = _files(tmp_path)

    def refuse(*args, **kwargs):
        raise ValueError("something about the boxes")

    monkeypatch.setattr(cli_module, "evaluate", refuse)
    r = _eval("--gt", gt, "--results", pred)
    assert r.exit_code == 1 and f"Error: {pred} (against {gt}): something about the boxes" in r.output
