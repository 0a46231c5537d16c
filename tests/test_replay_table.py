"""benchmarks/replay_table.py: the A/B table of benchmarks/replay_ab.sh from replay outputs on disk."""

from __future__ import annotations

import json

import numpy as np
import pytest

from streamdet.benchmarks.replay_table import collect, main, table


def _summary(p95: float, dropped: int) -> dict:
    return {"staleness_ms": {"p50": p95 / 2, "p95": p95}, "image_age_ms": {"p95": p95 + 80}, "latency_ms": {"p99": 20.25},
            "slices_dropped": dropped, "image_lane_cpu_ms_per_rotation": 30.0, "map_streaming": 0.4125}  # fmt: skip


def _run(out, name, summary, cpu=None) -> None:
    (out / name).mkdir(parents=True)
    replay = {"modes": {"streaming": summary}} | ({"config": {"cpu": cpu}} if cpu else {})
    (out / name / "replay.json").write_text(json.dumps(replay))


AVX2 = {"model": "AMD EPYC 7B13", "flags": ["avx2", "fma"], "threads": 2, "logical_cpus": 2}
AVX512 = {"model": "AMD EPYC 9B14", "flags": ["avx2", "fma", "avx512f", "avx512_vnni"], "threads": 2, "logical_cpus": 2}


def test_the_table_names_the_cpu_and_each_lanes_cores(tmp_path):
    share = {"cpu_share": {"slice_lane": 1.295, "image_lane": 0.2754, "player": 0.03, "process": 1.9}}
    _run(tmp_path, "r1_scale1_lite", _summary(20, 0) | share, AVX2)
    _run(tmp_path, "r2_scale1_lite", _summary(20, 0) | share, AVX2)
    text = table(tmp_path)
    assert text.startswith("CPU: AMD EPYC 7B13, 2 threads usable (avx2, fma)\n\n| scale |")
    assert "| 30.0, 30.0 | 1.29 / 0.28, 1.29 / 0.28 | 41.2, 41.2 |" in text  # cores of the slice / image lane
    recs = {"recordings": [{"image_lane_cpu_s": 1.2, "wall_s": 2.0}, {"image_lane_cpu_s": 0.6, "wall_s": 1.0}]}
    _run(tmp_path, "r1_scale3_lite", _summary(20, 0) | share | recs, AVX2)  # the lane's own count where recorded
    assert "| 1.29 / 0.60 |" in table(tmp_path)
    _run(tmp_path, "r1_scale2_lite", _summary(20, 0), AVX512)
    first = table(tmp_path).splitlines()[0]  # runs of two machines: both named, and a warning
    assert first.startswith("CPUs (they differ across runs") and "7B13" in first and "9B14" in first


def test_rows_per_scale_and_variant_with_one_value_per_round(tmp_path):
    _run(tmp_path, "r2_scale1_lite", _summary(30, 1))
    _run(tmp_path, "r1_scale1_lite", _summary(20, 0))
    _run(tmp_path, "r1_scale2_v3+terms", _summary(100, 0))
    _run(tmp_path, "notarun", _summary(1, 1))  # ignored: not r<round>_scale<S>_<label>
    (tmp_path / "probes_gflops.txt").write_text("r1_scale1_lite 410.5\nr2_scale1_lite 150\n")
    rows = collect(tmp_path)
    assert sorted(rows) == [(1.0, "lite"), (2.0, "v3+terms")]
    assert [r for r, _, _ in rows[(1.0, "lite")]] == [1, 2]  # rounds in order
    text = table(tmp_path)
    assert "| 1 | lite | 10 / 20, 15 / 30 | 100, 110 | 20.2, 20.2 | 0, 1 | 30.0, 30.0 | -, - | 41.2, 41.2 | 410, 150 |" in text
    assert text.startswith("CPU: not recorded\n")  # replays written before they recorded it
    assert "| 2 | v3+terms | 50 / 100 |" in text and text.endswith("nan |")  # no probe recorded: nan


def test_full_collections_are_summed_per_round_under_the_table(tmp_path):
    def gc(*gen2):  # one recording per scene, each with its full collections (count, longest ms)
        return {"recordings": [{"gc_pauses": {"gen0": {"collections": 9, "total_ms": 1.0, "max_ms": 0.2},
                                              "gen2": {"collections": n, "total_ms": ms, "max_ms": ms}}} for n, ms in gen2]}  # fmt: skip

    _run(tmp_path, "r1_scale1_pl", _summary(20, 0) | gc((0, 0.0), (0, 0.0)))
    _run(tmp_path, "r1_scale1_thaw", _summary(20, 5) | gc((0, 0.0), (1, 66.7)))
    _run(tmp_path, "r2_scale1_thaw", _summary(20, 0) | gc((0, 0.0), (0, 0.0)))
    text = table(tmp_path)
    assert text.endswith("full garbage collections during the drives (per round: count, longest pause): "
                         "thaw (scale 1) 1 (66.7 ms), 0")  # fmt: skip
    _run(tmp_path / "quiet", "r1_scale1_pl", _summary(20, 0) | gc((0, 0.0)))
    _run(tmp_path / "quiet", "r1_scale1_old", _summary(20, 0))  # written before replays recorded the collector
    assert table(tmp_path / "quiet").endswith("full garbage collections during the drives: none in 1 run(s)")


def test_errors_are_one_line_and_a_non_zero_exit(tmp_path, capsys):
    assert main([str(tmp_path)]) == 1
    assert "no r<round>_scale<S>_<label>/replay.json" in capsys.readouterr().err
    assert main([]) == 2
    (tmp_path / "r1_scale1_x").mkdir()
    (tmp_path / "r1_scale1_x" / "replay.json").write_text(json.dumps({"modes": {"full-sweep": {}}}))
    assert main([str(tmp_path)]) == 1
    assert "no streaming mode" in capsys.readouterr().err
    with pytest.raises(ValueError):
        table(tmp_path)


def test_staleness_pools_the_fused_slices_of_every_round_and_the_plot_is_written(tmp_path):
    pytest.importorskip("matplotlib")
    from streamdet.benchmarks.replay_table import staleness

    def slices(pairs):  # (newest, used) capture times; None: not fused / not emitted
        return [{"emit_s": None if n is None else 1.0, "newest_capture_s": n, "image_capture_s": u} for n, u in pairs]

    for rnd, pairs in ((1, [(0.10, 0.05), (0.2, 0.2), (None, 0.1)]), (2, [(0.3, None), (0.4, 0.39)])):
        summary = dict(_summary(10, 0), recordings=[{"slices": slices(pairs)}])
        _run(tmp_path, f"r{rnd}_scale1_lite", summary)
    got = staleness(tmp_path)[(1.0, "lite")]
    np.testing.assert_allclose(np.sort(got), [0.0, 10.0, 50.0], atol=1e-9)
    png = tmp_path / "ab.png"
    assert main([str(tmp_path), "--plot", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main([str(tmp_path), "--plot"]) == 2


def test_stale_slices_by_the_image_sets_of_the_rotation_before_are_pooled_over_rounds(tmp_path):
    from streamdet.replay.record import ImageRecord, Recording, SliceRecord

    def recording(stale: bool) -> dict:
        s = SliceRecord(1, 0, 8, 0.05625, 10, start_s=0.06, emit_s=0.06, image_capture_s=0.0 if stale else 0.04,
                        newest_capture_s=0.04)  # fmt: skip
        images = tuple(ImageRecord(i, t, release_s=t) for i, t in enumerate((0.01, 0.02, 0.04)))  # all before 0.05
        return Recording("streaming", "s", 1.0, (s,), images, 1.0, 0.0, 0.0).to_dict()

    for rnd, stale in ((1, True), (2, False)):
        summary = dict(_summary(10, 0), recordings=[recording(stale)])
        (tmp_path / f"r{rnd}_scale1_lite").mkdir()
        (tmp_path / f"r{rnd}_scale1_lite" / "replay.json").write_text(
            json.dumps({"modes": {"streaming": summary}, "config": {"cpu": AVX2, "lidar_hz": 20.0}}))
    text = table(tmp_path)
    assert "by image sets released in the rotation before the scan start (rounds pooled):" in text
    assert "- lite (scale 1): 3: 1 of 2 (50 %)" in text


def test_no_stale_slice_lines_without_the_lidar_rate_or_fused_slices(tmp_path):
    _run(tmp_path, "r1_scale1_lite", dict(_summary(10, 0), recordings=[]), AVX2)
    assert "rotation before the scan start" not in table(tmp_path)


def test_malformed_recordings_are_one_line_and_a_non_zero_exit(tmp_path, capsys):
    summary = dict(_summary(10, 0), recordings=[{"slices": [{"emit_s": 1.0}]}])
    (tmp_path / "r1_scale1_lite").mkdir()
    (tmp_path / "r1_scale1_lite" / "replay.json").write_text(json.dumps({"modes": {"streaming": summary}, "config": {"lidar_hz": 20.0}}))
    assert main([str(tmp_path)]) == 1
    assert "r1_scale1_lite: recordings not as streamdet-replay writes them" in capsys.readouterr().err


def _line_run(out, name, p95, dropped, p99, cpu=AVX2, map_streaming=0.4125):
    summary = _summary(p95, dropped) | {"latency_ms": {"p99": p99}, "map_streaming": map_streaming}
    _run(out, name, summary, cpu)


def test_the_line_against_a_baseline_counts_rounds_paired_with_it(tmp_path):
    from streamdet.benchmarks.replay_table import line_against

    _line_run(tmp_path, "r1_scale0.5_full", 150, 0, 40.0)
    _line_run(tmp_path, "r2_scale0.5_full", 150, 3, 20.0)
    _line_run(tmp_path, "r1_scale0.5_pl", 58, 0, 30.0, map_streaming=0.40)  # meets all three, mAP below
    _line_run(tmp_path, "r2_scale0.5_pl", 58, 0, 25.0, map_streaming=None)  # p99 above the baseline's of its round
    _line_run(tmp_path, "r3_scale0.5_pl", 58, 0, 1.0)  # no baseline round: its p99 is not counted
    _line_run(tmp_path, "r1_scale1_pl", 120, 2, 5.0)  # no baseline at this scale
    text = line_against(tmp_path, "full")
    assert "staleness added p95 <= 100 ms" in text  # the AVX2-only CPU's target
    # r1 meets all but mAP, r2 has no score and a p99 above full's, r3 has no baseline round: it meets no paired term
    assert ("- scale 0.5, pl: staleness 3 of 3, none dropped 3 of 3, p99 1 of 3, streaming mAP >= `full`'s 0 of 3; "
            "the whole line 0 of 3 (no `full` run in round(s) 3)") in text
    assert ("- scale 1, pl: staleness 0 of 1, none dropped 0 of 1, p99 0 of 1, streaming mAP >= `full`'s 0 of 1; "
            "the whole line 0 of 1 (no `full` run in round(s) 1)") in text
    assert "full:" not in text
    assert "<= 25 ms" in line_against(tmp_path, "full", target_ms=25.0)


def test_the_line_refuses_an_unknown_baseline_and_mixed_cpus_without_a_target(tmp_path, capsys):
    from streamdet.benchmarks.replay_table import line_against

    _line_run(tmp_path, "r1_scale1_full", 20, 0, 10.0, AVX512)
    _line_run(tmp_path, "r1_scale1_pl", 20, 0, 9.0, AVX2)
    with pytest.raises(ValueError, match="no variant 'nope'"):
        line_against(tmp_path, "nope")
    with pytest.raises(ValueError, match="give --target-ms"):
        line_against(tmp_path, "full")
    assert "p99 1 of 1," in line_against(tmp_path, "full", target_ms=25.0)
    assert main([str(tmp_path), "--baseline", "full", "--target-ms", "25"]) == 0
    assert "the whole line 1 of 1" in capsys.readouterr().out
    assert main([str(tmp_path), "--target-ms", "25"]) == 2  # a target without a baseline
    assert main([str(tmp_path), "--baseline"]) == 2
    assert main([str(tmp_path), "--baseline", "full", "--target-ms", "x"]) == 2
    assert main([str(tmp_path), "--baseline", "nope"]) == 1


# ---- review 41: rounds a variant lacks, values a replay could not give, the capture clock, the target -------------


def test_a_round_one_variant_lacks_is_a_miss_and_named(tmp_path):
    from streamdet.benchmarks.replay_table import line_against

    for rnd in (1, 2, 3):
        _line_run(tmp_path, f"r{rnd}_scale1_full", 150, 0, 40.0)
    for rnd in (1, 2):  # an interrupted A/B: round 3 of the variant never ran
        _line_run(tmp_path, f"r{rnd}_scale1_pl", 50, 0, 20.0, map_streaming=0.5)
    text = line_against(tmp_path, "full")
    assert "the whole line 2 of 3 (no `pl` run in round(s) 3)" in text
    assert "staleness 2 of 3, none dropped 2 of 3, p99 2 of 3, streaming mAP >= `full`'s 2 of 3" in text


@pytest.mark.parametrize("field", ["p95", "p99", "map", "slices_total"])
def test_a_value_the_replay_could_not_give_fails_its_term_without_a_traceback(tmp_path, field, capsys):
    from streamdet.benchmarks.replay_table import line_against

    _line_run(tmp_path, "r1_scale1_full", 150, 0, 40.0)
    summary = _summary(50, 0) | {"latency_ms": {"p99": 20.0}, "map_streaming": 0.5, "slices_total": 1600}
    if field == "p95":  # no fused slice: every percentile of no value is null in replay.json
        summary["staleness_ms"] = {"p50": None, "p95": None}
        summary["image_age_ms"] = {"p95": None}
    elif field == "p99":  # no emitted slice
        summary["latency_ms"] = {"p99": None}
    elif field == "map":
        summary["map_streaming"] = None
    else:  # no slice at all: "none dropped" must not pass vacuously
        summary["slices_total"] = 0
    _run(tmp_path, "r1_scale1_pl", summary, AVX2)
    text = line_against(tmp_path, "full")
    assert "the whole line 0 of 1" in text
    assert main([str(tmp_path)]) == 0  # the table shows "-" for what is missing
    assert "Traceback" not in capsys.readouterr().err


def test_the_staleness_target_reads_the_p95_at_the_capture_clock(tmp_path):
    from streamdet.benchmarks.replay_table import line_against
    from streamdet.replay.record import SliceRecord, capture_gap_ms

    _line_run(tmp_path, "r1_scale1_full", 150, 0, 40.0)
    _line_run(tmp_path, "r1_scale1_pl", 100.00000000000009, 0, 20.0, map_streaming=0.5)  # float seconds' 100 ms
    _line_run(tmp_path, "r2_scale1_full", 150, 0, 40.0)
    _line_run(tmp_path, "r2_scale1_pl", 100.002, 0, 20.0, map_streaming=0.5)  # 2 us over: over
    assert "staleness 1 of 2" in line_against(tmp_path, "full")
    # two stamps one 100 ms camera interval apart, as float seconds of a drive and of a Unix epoch
    for base in (1.25, 1533151603.512404):
        assert capture_gap_ms(base + 0.1, base) == 100.0
        rec = SliceRecord(sweep=0, slice_index=0, num_slices=8, scan_end_s=0.0, num_points=1)
        rec.newest_capture_s, rec.image_capture_s = base + 0.1, base
        assert rec.staleness_ms == 100.0
    assert np.isnan(capture_gap_ms(float("nan"), 1.0))
    assert capture_gap_ms(1.0, 1.0000004) == 0.0 and capture_gap_ms(1.0, 1.0000006) == -0.001


@pytest.mark.parametrize("bad", ["inf", "nan", "-5", "0"])
def test_the_target_must_be_finite_and_positive(tmp_path, bad, capsys):
    _line_run(tmp_path, "r1_scale1_full", 150, 0, 40.0)
    _line_run(tmp_path, "r1_scale1_pl", 50, 0, 20.0)
    assert main([str(tmp_path), "--baseline", "full", "--target-ms", bad]) == 2
    assert f"got {float(bad)!r}" in capsys.readouterr().err


def test_replay_ab_refuses_an_out_holding_an_earlier_ab(tmp_path):
    import subprocess
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "replay_ab.sh"
    (tmp_path / "r4_scale1_pl").mkdir()  # a round of an earlier, longer A/B
    env = {"PATH": "/usr/bin:/bin", "DATA": str(tmp_path)}
    done = subprocess.run(["bash", str(script), str(tmp_path), "3", "1", f"pl={tmp_path},full,on"], env=env,
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2
    assert "already holds runs of an earlier A/B" in done.stderr
