"""``streamdet-eval --compare`` over too few clusters (audit F3): with one scene every bootstrap draw is the whole
data, so the "interval" collapses onto B - A and must not be called significant; below ``FEW_CLUSTERS`` a note
says the interval is unreliable. Both also reach the --json, as added fields (the old ones keep their meaning)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.evaluation import EvalBoxes
from streamdet.evaluation.bootstrap import FEW_CLUSTERS, MIN_CLUSTERS, Difference, match_tables, paired_bootstrap
from streamdet.evaluation.cli import main
from streamdet.evaluation.compare import Comparison, cluster_notes, compare_runs, format_comparison, load_run, write_sample_info
from streamdet.evaluation.results import write_results_json

from result_entries import result_entry

CLASSES = ("car", "pedestrian")
META = {"use_camera": False, "use_lidar": True}
OLD_FIGURE_KEYS = {"A", "B", "B_minus_A", "ci_lo", "ci_hi", "p_not_positive"}
OLD_TOP_KEYS = {"A", "B", "seed", "num_samples", "num_clusters", "clustered_by", "num_draws", "notes", "subsets"}


def _entry(token: str, xy, name: str, score: float | None, num_pts: int = 8) -> dict:
    return result_entry(token, xy, name, score, num_pts)


def _world(num_samples: int, seed: int = 0):
    """Ground truth and two runs: A finds about half of the boxes, B nearly all (B - A is clearly positive)."""
    rng = np.random.default_rng(seed)
    gt, a, b = {}, {}, {}
    for s in range(num_samples):
        t = f"s{s}"
        gt[t], a[t], b[t] = [], [], []
        for k in range(4):
            name, xy = CLASSES[k % 2], rng.uniform(-20, 20, 2)
            gt[t].append(_entry(t, xy, name, None))
            if rng.random() < 0.5:
                a[t].append(_entry(t, xy + rng.normal(0, 0.3, 2), name, float(rng.uniform(0.1, 1))))
            b[t].append(_entry(t, xy + rng.normal(0, 0.3, 2), name, float(rng.uniform(0.1, 1))))
        a[t].append(_entry(t, rng.uniform(-20, 20, 2), "car", float(rng.uniform(0.1, 1))))
    return gt, a, b


def _boxes(results: dict) -> EvalBoxes:
    return EvalBoxes.from_results(results).with_ego_position({t: [0.0, 0.0, 0.0] for t in results})


def _tables(gt, pred):
    return match_tables(_boxes(gt), _boxes(pred), CLASSES)[1]


def _save(folder, gt, pred, scenes=None):
    folder.mkdir()
    write_results_json(folder / "results.json", pred, META)
    write_results_json(folder / "gt.json", gt, META, ego_positions={t: [0.0, 0.0, 0.0] for t in gt})
    if scenes is not None:
        eye = np.eye(4)
        write_sample_info(folder / "samples.json", scenes, {t: (eye, eye) for t in gt}, 4)
    return folder


def _saved_pair(tmp_path, num_samples: int, num_scenes: int | None):
    gt, a, b = _world(num_samples)
    scenes = None if num_scenes is None else {t: f"scene{i % num_scenes}" for i, t in enumerate(gt)}
    return _save(tmp_path / "a", gt, a, scenes), _save(tmp_path / "b", gt, b, scenes)


def _compare_cli(a, b, out, *extra):
    res = CliRunner().invoke(main, ["--compare", str(a), str(b), "--bootstrap", "50", "--json", str(out), *extra])
    assert res.exit_code == 0, res.output
    return res.output, json.loads(out.read_text())


# ---- the library -------------------------------------------------------------------------------------------------


def test_one_cluster_gives_an_undefined_interval_never_significant():
    gt, a, b = _world(4)
    out = paired_bootstrap(_tables(gt, a), _tables(gt, b), CLASSES, np.zeros(4, np.int64), num_draws=30)
    assert out["mAP"].diff > 0  # a real difference ...
    for d in out.values():  # ... whose collapsed "interval" [diff, diff] used to be starred
        assert not d.interval_defined and not d.significant
        assert d.lo == pytest.approx(d.diff, abs=1e-12) and d.hi == pytest.approx(d.diff, abs=1e-12)


def test_two_clusters_give_a_defined_interval():
    gt, a, b = _world(4)
    out = paired_bootstrap(_tables(gt, a), _tables(gt, b), CLASSES, np.array([0, 0, 1, 1]), num_draws=30)
    assert MIN_CLUSTERS == 2 and all(d.interval_defined for d in out.values())


def test_one_cluster_with_groups_of_runs_is_still_undefined():
    """Draws that resample seeds vary, but say nothing about other scenes: still no interval, nothing starred."""
    gt, a, b = _world(3)
    _, a2, b2 = _world(3, seed=1)  # other predictions, scored on the first ground truth
    out = paired_bootstrap([_tables(gt, a), _tables(gt, a2)], [_tables(gt, b), _tables(gt, b2)], CLASSES,
                           np.full(3, 7, np.int64), num_draws=30)  # fmt: skip
    assert all(not d.interval_defined and not d.significant for d in out.values())


@pytest.mark.parametrize(
    "lo, hi, defined, significant",
    [(0.1, 0.2, True, True), (-0.2, -0.1, True, True), (-0.1, 0.1, True, False), (0.0, 0.1, True, False),
     (0.1, 0.1, False, False), (-0.1, -0.1, False, False)],
)  # fmt: skip
def test_significant_needs_a_defined_interval_excluding_zero(lo, hi, defined, significant):
    d = Difference(a=0.0, b=lo, diff=lo, lo=lo, hi=hi, p_not_positive=0.0, interval_defined=defined)
    assert d.significant is significant
    doc = d.to_dict()
    assert OLD_FIGURE_KEYS <= set(doc) and doc["ci_lo"] == lo and doc["ci_hi"] == hi  # old fields unchanged
    assert doc["interval_defined"] is defined and doc["significant"] is significant


def test_a_difference_made_without_the_flag_is_defined():
    """Code that builds a Difference the old way (six fields) keeps the old meaning."""
    assert Difference(0.0, 0.1, 0.1, 0.05, 0.15, 0.0).significant


@pytest.mark.parametrize("n", [1, 2, FEW_CLUSTERS - 1, FEW_CLUSTERS, 40])
def test_cluster_notes_by_count(n):
    notes = cluster_notes(n, "scene")
    if n < MIN_CLUSTERS:
        assert len(notes) == 1 and "undefined" in notes[0] and "1 scene:" in notes[0]
    elif n < FEW_CLUSTERS:
        assert len(notes) == 1 and f"only {n} scenes" in notes[0] and "too narrow" in notes[0]
    else:
        assert notes == []


def test_format_marks_only_defined_intervals():
    def comparison(num_clusters, defined):
        d = Difference(a=0.1, b=0.3, diff=0.2, lo=0.2, hi=0.2, p_not_positive=0.0, interval_defined=defined)
        return Comparison(subsets={"all": {"mAP": d}}, num_samples=4, num_clusters=num_clusters, clustered_by="scene",
                          num_draws=10, notes=cluster_notes(num_clusters, "scene"))  # fmt: skip

    undefined = format_comparison(comparison(1, False), "a", "b")
    row = next(line for line in undefined.splitlines() if line.startswith("all"))
    assert "undefined" in row and "*" not in row and "[" not in row
    assert "over 1 scene (4 samples)" in undefined and "no interval" in undefined and "note: only 1 scene" in undefined
    defined = format_comparison(comparison(6, True), "a", "b")
    row = next(line for line in defined.splitlines() if line.startswith("all"))
    assert row.endswith("[+0.2000, +0.2000] *") and "95 % interval" in defined and "note:" not in defined


# ---- the CLI -----------------------------------------------------------------------------------------------------


def test_cli_one_scene_prints_no_star_and_flags_the_json(tmp_path):
    a, b = _saved_pair(tmp_path, 4, num_scenes=1)
    output, doc = _compare_cli(a, b, tmp_path / "c.json", "--no-subsets")
    rows = [line for line in output.splitlines() if line.startswith("all ")]
    assert rows and all("undefined" in r and not r.endswith("*") for r in rows)
    assert "over 1 scene (4 samples)" in output and "note: only 1 scene: the bootstrap interval is undefined" in output
    assert OLD_TOP_KEYS <= set(doc) and doc["num_clusters"] == 1
    assert doc["interval_defined"] is False and doc["few_clusters"] is True and doc["min_reliable_clusters"] == FEW_CLUSTERS
    assert any("undefined" in n for n in doc["notes"])
    mAP = doc["subsets"]["all"]["mAP"]
    assert OLD_FIGURE_KEYS <= set(mAP) and mAP["B_minus_A"] > 0
    assert mAP["interval_defined"] is False and mAP["significant"] is False
    assert all(not f["significant"] for f in doc["subsets"]["all"].values())


def test_cli_one_scene_with_subsets_stars_nothing(tmp_path):
    a, b = _saved_pair(tmp_path, 4, num_scenes=1)
    output, doc = _compare_cli(a, b, tmp_path / "c.json")
    assert len(doc["subsets"]) > 1 and " *" not in output
    assert all(not f["interval_defined"] and not f["significant"] for figs in doc["subsets"].values() for f in figs.values())


def test_cli_one_sample_without_samples_file_is_one_cluster_too(tmp_path):
    a, b = _saved_pair(tmp_path, 1, num_scenes=None)
    output, doc = _compare_cli(a, b, tmp_path / "c.json", "--no-subsets")
    assert doc["clustered_by"] == "sample" and doc["interval_defined"] is False
    assert "over 1 sample (1 samples)" in output and "only 1 sample:" in output and " *" not in output


def test_cli_few_scenes_warn_but_keep_the_interval(tmp_path):
    a, b = _saved_pair(tmp_path, 6, num_scenes=3)
    output, doc = _compare_cli(a, b, tmp_path / "c.json", "--no-subsets")
    assert doc["interval_defined"] is True and doc["few_clusters"] is True
    assert f"only 3 scenes: a bootstrap over fewer than {FEW_CLUSTERS} clusters" in output
    assert "undefined" not in output and "95 % interval" in output
    mAP = doc["subsets"]["all"]["mAP"]
    assert mAP["interval_defined"] is True and mAP["significant"] == (mAP["ci_lo"] > 0 or mAP["ci_hi"] < 0)


def test_cli_enough_scenes_add_no_note(tmp_path):
    a, b = _saved_pair(tmp_path, 2 * FEW_CLUSTERS, num_scenes=FEW_CLUSTERS)
    output, doc = _compare_cli(a, b, tmp_path / "c.json", "--no-subsets")
    assert doc["interval_defined"] is True and doc["few_clusters"] is False and doc["notes"] == []
    assert "note:" not in output and not math.isnan(doc["subsets"]["all"]["mAP"]["ci_lo"])


def test_compare_runs_counts_clusters_once_for_every_subset(tmp_path):
    a, b = _saved_pair(tmp_path, 4, num_scenes=1)
    c = compare_runs(load_run(a), load_run(b), num_draws=5)
    assert not c.interval_defined and c.few_clusters
    assert sum("undefined" in n for n in c.notes) == 1  # one note, not one per subset
    assert all(not d.interval_defined for figs in c.subsets.values() for d in figs.values())


def test_help_documents_the_one_scene_rule():
    res = CliRunner().invoke(main, ["--help"])
    assert res.exit_code == 0 and "interval is undefined" in " ".join(res.output.split())



def test_one_cluster_gives_the_same_figures_without_scoring_every_draw(monkeypatch):
    """Every draw over one scene is the whole data: the figures a thousand re-scorings gave, without them."""
    import streamdet.evaluation.bootstrap as bootstrap_mod

    gt, a, b = _world(4)
    ta, tb = _tables(gt, a), _tables(gt, b)
    calls = []
    real = bootstrap_mod.weighted_metrics

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(bootstrap_mod, "weighted_metrics", counting)
    out = paired_bootstrap(ta, tb, CLASSES, np.zeros(4, np.int64), num_draws=200)
    assert len(calls) == 2  # the full figures of each side; no draw scored
    for d in out.values():
        assert d.lo == d.hi == d.diff and not d.interval_defined and d.p_not_positive == float(d.diff <= 0)
