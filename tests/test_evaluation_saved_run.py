"""``saved_run``: the folder ``streamdet-eval --save-results`` writes, written and read in one place.

Reference: what was handed to ``save_run`` (entries, ego positions, scenes, poses, racks) must come back from
``load_run`` unchanged, and scoring the loaded run must give what scoring the entries directly gives.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from streamdet.evaluation import EvalBoxes, evaluate
from streamdet.evaluation import saved_run
from streamdet.evaluation.saved_run import GT_FILE, RESULTS_FILE, SAMPLES_FILE, SAVED_FILES, load_run, save_run

from result_entries import result_entry as _entry

RACK = [10.0, 0.0, 1.0, 2.0, 4.0, 2.0, 1.0, 0.0, 0.0, 0.0]


def _run(num_samples: int = 3):
    gt = {f"s{i}": [_entry(f"s{i}", (10.0, 0.5), "bicycle", None, 8), _entry(f"s{i}", (4.0, 4.0), "car", None, 3)]
          for i in range(num_samples)}  # fmt: skip
    pred = {t: [_entry(t, (10.1, 0.5), "bicycle", 0.5), _entry(t, (4.2, 4.0), "car", 0.9)] for t in gt}
    pred["s0"] = pred["s0"][1:]  # the bicycle in s0's rack is missed: it counts only without the bike-rack rule
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 0.0]
    return dict(predictions=pred, ground_truth=gt, ego_positions={t: [0.0, 0.0, 0.0] for t in gt},
                scenes={t: f"scene-{i // 2}" for i, t in enumerate(gt)}, poses={t: (np.eye(4), pose) for t in gt},
                num_slices=4, use_camera=True, bike_racks={"s0": np.array([RACK])})  # fmt: skip


def test_save_run_writes_the_saved_files_and_load_run_reads_them_back(tmp_path):
    run = _run()
    written = save_run(tmp_path / "new" / "run", **run)  # parents made
    assert [p.name for p in written] == list(SAVED_FILES) == [RESULTS_FILE, GT_FILE, SAMPLES_FILE]
    assert sorted(os.listdir(tmp_path / "new" / "run")) == sorted(SAVED_FILES)  # no staged file left
    loaded = load_run(tmp_path / "new" / "run")
    assert json.loads((tmp_path / "new" / "run" / RESULTS_FILE).read_text())["meta"]["use_camera"] is True
    assert json.loads((tmp_path / "new" / "run" / GT_FILE).read_text())["meta"]["use_camera"] is False
    np.testing.assert_array_equal(loaded.bike_racks["s0"], [RACK])
    assert set(loaded.bike_racks) == {"s0"}
    assert loaded.info.scenes == run["scenes"] and loaded.info.num_slices == 4
    np.testing.assert_array_equal(loaded.info.ego2global["s1"], run["poses"]["s1"][1])
    gt = EvalBoxes.from_results(run["ground_truth"]).with_ego_position(run["ego_positions"])
    pred = EvalBoxes.from_results(run["predictions"]).with_ego_position(run["ego_positions"])
    racks = {"s0": np.array([RACK])}
    direct = evaluate(gt, pred, bike_racks=racks)
    again = evaluate(loaded.gt, loaded.pred, bike_racks=loaded.bike_racks)
    assert again.mean_ap == direct.mean_ap and again.nd_score == direct.nd_score
    assert again.mean_ap != evaluate(loaded.gt, loaded.pred).mean_ap  # the racks matter here


def test_a_failed_write_leaves_an_earlier_run_whole(tmp_path, monkeypatch):
    """OSError in the last file, or entries the evaluation would refuse (ValueError): nothing of the new run, no staged
    file, and the earlier run's three files untouched."""
    first = _run()
    save_run(tmp_path, **first)
    before = {name: (tmp_path / name).read_bytes() for name in SAVED_FILES}

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(saved_run, "write_sample_info", full_disk)
    with pytest.raises(OSError, match="No space"):
        save_run(tmp_path, **_run(num_samples=5))
    monkeypatch.undo()
    bad = _run()
    bad["predictions"]["s0"][0]["detection_name"] = "lorry"
    with pytest.raises(ValueError, match="lorry"):
        save_run(tmp_path, **bad)
    bad = _run()
    bad["bike_racks"] = {"s0": [[*RACK[:9], float("nan")]]}
    with pytest.raises(ValueError, match=r"bike_racks\['s0'\]\[0\] must be 10 finite numbers"):
        save_run(tmp_path, **bad)
    assert sorted(os.listdir(tmp_path)) == sorted(SAVED_FILES)
    assert {name: (tmp_path / name).read_bytes() for name in SAVED_FILES} == before


def test_empty_run_and_a_run_without_racks(tmp_path):
    empty = dict(_run(), predictions={}, ground_truth={}, ego_positions={}, scenes={}, poses={}, bike_racks={})
    save_run(tmp_path / "empty", **empty)
    loaded = load_run(tmp_path / "empty")
    assert len(loaded.gt) == 0 and len(loaded.pred) == 0 and loaded.bike_racks == {} and loaded.info.scenes == {}
    save_run(tmp_path / "norack", **dict(_run(), bike_racks=None))
    assert load_run(tmp_path / "norack").bike_racks is None  # racks unknown, as in a folder saved before they were


def test_old_folders_and_a_results_file_with_gt_still_load(tmp_path):
    """A folder saved before samples.json (two files) and before bike_racks reads; a results file needs --gt."""
    save_run(tmp_path / "run", **dict(_run(), bike_racks=None))
    (tmp_path / "run" / SAMPLES_FILE).unlink()
    old = load_run(tmp_path / "run")
    assert old.info is None and old.bike_racks is None and old.info_where == ""
    with pytest.raises(ValueError, match="give the ground truth with --gt"):
        load_run(tmp_path / "run" / RESULTS_FILE)
    by_file = load_run(tmp_path / "run" / RESULTS_FILE, tmp_path / "run" / GT_FILE)
    assert by_file.gt_where == str(tmp_path / "run" / GT_FILE) and len(by_file.pred) == len(old.pred)
    with pytest.raises(ValueError, match="does not exist"):
        load_run(tmp_path / "nowhere")
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / RESULTS_FILE).write_text((tmp_path / "run" / RESULTS_FILE).read_text())
    with pytest.raises(ValueError, match="gt.json is missing"):
        load_run(tmp_path / "half")


def test_the_format_has_one_home():
    """The CLI writes and compare reads through saved_run; the names compare exported stay importable from it."""
    from streamdet.evaluation import cli, compare

    assert cli.SAVED_FILES is SAVED_FILES and cli.save_run is save_run
    for name in ("SAMPLES_FILE", "SampleInfo", "Run", "load_run", "read_sample_info", "write_sample_info"):
        assert getattr(compare, name) is getattr(saved_run, name), name
