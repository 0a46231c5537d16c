"""Issue 19's decision rules (benchmarks/camera_claim.py) on made-up comparison, gate and probe files."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from streamdet.benchmarks.camera_claim import decide, format_decision, main


def _cmp(map_ab, bicycle_ab=(0.1, 0.1, 0.0, 0.0)) -> dict:
    """A --compare JSON: (A, B, lo, hi) as fractions for mAP and bicycle AP."""
    def d(a, b, lo, hi):
        return {"A": a, "B": b, "B_minus_A": b - a, "ci_lo": lo, "ci_hi": hi, "p_not_positive": 0.5}

    return {"subsets": {"all": {"mAP": d(*map_ab), "AP/bicycle": d(*bicycle_ab)}}}


def _gate(drop_cost: float, noise_cost: float) -> tuple[dict, dict]:
    drop = {"all_cameras": {"mAP": 0.5}, "no_cameras": {"mAP": 0.5 - drop_cost / 100}}
    noise = {"reference": {"mAP": 0.5}, "levels": [{"max_angle_deg": 5.0, "max_translation_m": 0.5, "mAP_mean": 0.5 - noise_cost / 100}]}
    return drop, noise


STRONG8 = _cmp((0.40, 0.45, 0.02, 0.08), (0.10, 0.22, 0.05, 0.18))
STRONG32 = _cmp((0.30, 0.37, 0.03, 0.11))
NULL8, NULL32 = _cmp((0.40, 0.405, -0.01, 0.02)), _cmp((0.30, 0.30, -0.02, 0.02))


def test_reproduced_needs_every_bar_with_an_interval_excluding_zero():
    d = decide(STRONG8, STRONG32, [("fused_s0", *_gate(6.0, 3.0))], [0.7])
    assert d.verdict == "reproduced" and all(r.met for r in d.rows)
    assert "**reproduced**" in format_decision(d)
    short = _cmp((0.40, 0.45, 0.02, 0.08), (0.10, 0.15, 0.01, 0.09))  # bicycle +5 only
    assert decide(short, STRONG32, [("s0", *_gate(6.0, 3.0))], [0.7]).verdict == "undecided"


def test_a_comparison_over_one_scene_reproduces_nothing():
    """One scene: every bootstrap draw is the data again and the interval collapses onto the difference
    (``interval_defined`` false, evaluation/bootstrap.py): no bar is met however large the difference."""
    one_scene = json.loads(json.dumps(STRONG8))
    for d in one_scene["subsets"]["all"].values():
        d["ci_lo"] = d["ci_hi"] = d["B_minus_A"]
        d["interval_defined"] = False
    d = decide(one_scene, STRONG32, [("fused_s0", *_gate(6.0, 3.0))], [0.7])
    eight = [r for r in d.rows if "8 slices" in r.label]
    assert d.verdict != "reproduced" and len(eight) == 2 and not any(r.met or r.excludes_zero for r in eight)


def test_a_fused_model_that_ignores_its_cameras_voids_the_comparison():
    d = decide(STRONG8, STRONG32, [("s0", *_gate(6.0, 3.0)), ("s1", *_gate(1.0, 3.0))], [0.7])
    assert d.verdict == "void" and "s1" in d.reason
    assert decide(NULL8, NULL32, [("s0", *_gate(6.0, 0.5))], [0.7]).verdict == "void"


GOOD_SCALES = [(1.0, 1.02), (0.6, 0.95)]


@pytest.mark.parametrize(
    "probe, scales, verdict, why",
    [([0.65, 0.7], GOOD_SCALES, "refuted", "reaches its figures"),
     ([0.65, 0.4], GOOD_SCALES, "undecided", "balanced accuracy 0.40"),
     ([], GOOD_SCALES, "undecided", "balanced accuracy nan"),
     ([0.65, 0.7], [(1.0, 1.0), (0.3, 1.0)], "undecided", "scale is off"),  # item 2: image / point RMS below 0.5
     ([0.65, 0.7], [(1.0, 1.0), (2.5, 1.0)], "undecided", "scale is off"),
     ([0.65, 0.7], [(1.0, 1.2), (1.0, 1.0)], "undecided", "scale is off"),  # train / eval RMS 20 % apart
     ([0.65, 0.7], [], "undecided", "no image BEV scale")],
)  # fmt: skip
def test_refuted_needs_the_image_lane_working_and_intervals_holding_zero(probe, scales, verdict, why):
    d = decide(NULL8, NULL32, [("s0", *_gate(4.0, 2.5))], probe, scales)
    assert d.verdict == verdict and why in d.reason
    assert decide(NULL8, NULL32, [], [0.7]).notes  # no gate files: said


def test_malformed_files_give_one_line_errors(tmp_path):
    with pytest.raises(ValueError, match="subsets.all.mAP"):
        decide({"subsets": {}}, STRONG32)
    with pytest.raises(ValueError, match="no_cameras"):
        decide(STRONG8, STRONG32, [("s0", {"all_cameras": {"mAP": 0.5}}, _gate(1, 1)[1])])
    with pytest.raises(ValueError, match="5 deg, 50 cm"):
        decide(STRONG8, STRONG32, [("s0", _gate(1, 1)[0], {"reference": {"mAP": 0.5}, "levels": []})])


def test_cli_writes_the_table_and_json(tmp_path):
    files = {}
    for name, doc in (("c8", STRONG8), ("c32", STRONG32), ("drop", _gate(6.0, 3.0)[0]), ("noise", _gate(6.0, 3.0)[1]),
                      ("probe", {"probe_balanced_accuracy_image": 0.7, "image_over_point_rms": 0.3, "train_over_eval_rms": 1.01})):  # fmt: skip
        files[name] = tmp_path / f"{name}.json"
        files[name].write_text(json.dumps(doc))
    out = tmp_path / "decision.json"
    args = ["--compare8", str(files["c8"]), "--compare32", str(files["c32"]), "--gate-drop", str(files["drop"]),
            "--gate-noise", str(files["noise"]), "--probe", str(files["probe"]), "--json", str(out)]  # fmt: skip
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "| mAP, 8 slices | 40.0 | 45.0 | +5.0 |" in res.output
    assert json.loads(out.read_text())["verdict"] == "reproduced"
    assert "image / point RMS at fusion: 0.30 (in [0.5, 2]); train / eval image BEV RMS: 1.01" in res.output
    assert json.loads(out.read_text())["image_over_point_rms"] == [0.3]
    res = CliRunner().invoke(main, args[:6])
    assert res.exit_code != 0 and "pair up" in res.output
    files["probe"].write_text(json.dumps({"probe_balanced_accuracy_image": 0.7}))
    res = CliRunner().invoke(main, args)
    assert res.exit_code != 0 and "image_over_point_rms" in res.output and "Traceback" not in res.output
    files["probe"].write_text(json.dumps({"probe_balanced_accuracy_image": 0.7, "image_over_point_rms": 1.0, "train_over_eval_rms": 1.0}))
    files["c8"].write_text("{broken")
    res = CliRunner().invoke(main, args)
    assert res.exit_code != 0 and "cannot read" in res.output and "Traceback" not in res.output


def test_fewer_than_three_seeds_per_side_is_preliminary():
    d = decide(STRONG8, STRONG32, [("s0", *_gate(6.0, 3.0))], [0.7])
    assert any("preliminary: 1 seed(s)" in n for n in d.notes)
    three = {**STRONG8, "A": ["a0", "a1", "a2"], "B": ["b0", "b1", "b2"]}
    three32 = {**STRONG32, "A": ["a0", "a1", "a2"], "B": ["b0", "b1", "b2"]}
    assert not any("preliminary" in n for n in decide(three, three32, [("s0", *_gate(6.0, 3.0))], [0.7]).notes)


def test_plot_rows_follow_the_comparison_and_skip_what_it_lacks():
    from streamdet.benchmarks.camera_claim_plot import _rows

    rows = _rows(STRONG8)  # mAP and bicycle AP only: no NDS, no other class, no subsets
    assert [r[0] for r in rows] == ["mAP", "AP bicycle"]
    label, diff, lo, hi = rows[0]
    assert (diff, lo, hi) == pytest.approx((5.0, 2.0, 8.0))  # points, from fractions
    assert _rows({}) == [] and _rows({"subsets": {"all": {}}}) == []


def test_cli_draws_the_decision(tmp_path):
    pytest.importorskip("matplotlib")
    c8, c32, png = tmp_path / "c8.json", tmp_path / "c32.json", tmp_path / "claim.png"
    c8.write_text(json.dumps(STRONG8))
    c32.write_text(json.dumps(STRONG32))
    res = CliRunner().invoke(main, ["--compare8", str(c8), "--compare32", str(c32), "--plot", str(png)])
    assert res.exit_code == 0, res.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"wrote {png}" in res.output
    # nothing to draw: a clear one-line error, no traceback (the decision itself still needs subsets.all.mAP)
    from streamdet.benchmarks.camera_claim_plot import plot_claim

    with pytest.raises(ValueError, match="none of the plotted figures"):
        plot_claim({}, {}, tmp_path / "empty.png")
    res = CliRunner().invoke(main, ["--compare8", str(c8), "--compare32", str(c32), "--plot", str(tmp_path / "no" / "dir.png")])
    assert res.exit_code != 0 and "cannot draw" in res.output and "Traceback" not in res.output
