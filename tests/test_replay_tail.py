"""benchmarks/replay_tail.py: where a replay's latency tail comes from, against a naive count over the records."""

from __future__ import annotations

import json

import numpy as np
import pytest

from streamdet.benchmarks.replay_tail import drive_tail, main, table


def _recording(seed: int, scale: float = 0.5, n: int = 200) -> dict:
    rng = np.random.default_rng(seed)
    slices, t = [], 0.0
    for i in range(n):
        t += 0.003
        wait, run = rng.exponential(0.002), rng.uniform(0.001, 0.004)
        slices.append({"scan_end_s": t - 1e-4, "release_s": t, "start_s": t + wait, "end_s": t + wait + run, "emit_s": t + wait + run + 1e-5,
                       "dropped": False, "coalesced": int(rng.integers(1, 3))})  # fmt: skip
    slices.append({"scan_end_s": t, "release_s": t, "start_s": None, "end_s": None, "emit_s": None, "dropped": True, "coalesced": 1})
    return {"drive": f"scene-{seed}", "time_scale": scale, "slices": slices}


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("near", [0.5, 0.8, 1.0])
def test_the_tail_matches_a_naive_count(seed, near):
    rec = _recording(seed)
    got = drive_tail(rec, near)
    kept = [s for s in rec["slices"] if not s["dropped"]]
    lat = [(s["emit_s"] - s["scan_end_s"]) * 1e3 for s in kept]  # drive ms whatever the time scale
    p99 = float(np.percentile(lat, 99))
    tail = [s for s, x in zip(kept, lat) if x >= near * p99]
    assert got["p99_ms"] == pytest.approx(p99)
    assert got["tail"] == len(tail) >= 1
    assert got["tail_wait_ms"] == pytest.approx(np.mean([(s["start_s"] - s["release_s"]) * 1e3 for s in tail]))
    assert got["tail_run_ms"] == pytest.approx(np.mean([(s["end_s"] - s["start_s"]) * 1e3 for s in tail]))
    assert got["tail_paired"] == pytest.approx(np.mean([s["coalesced"] > 1 for s in tail]))


def test_a_drive_with_nothing_emitted_has_no_tail():
    rec = _recording(0)
    rec["slices"] = [s for s in rec["slices"] if s["dropped"]]
    assert drive_tail(rec) is None
    with pytest.raises(ValueError, match="near"):
        drive_tail(_recording(0), 0.0)


def _write(out, name, recordings) -> None:
    (out / name).mkdir(parents=True)
    (out / name / "replay.json").write_text(json.dumps({"modes": {"streaming": {"recordings": recordings}}}))


def test_the_table_has_a_row_per_run_and_drive(tmp_path, capsys):
    _write(tmp_path, "r2_scale0.5_pl", [_recording(1), _recording(2)])
    _write(tmp_path, "r1_scale0.5_pl", [_recording(3)])
    _write(tmp_path, "r1_scale1_full", [_recording(4, scale=1.0)])
    text = table(tmp_path)
    rows = [line for line in text.splitlines() if line.startswith("| 0.5") or line.startswith("| 1 ")]
    assert [r.split(" | ")[1:4] for r in rows] == [["pl", "1", "scene-3"], ["pl", "2", "scene-1"], ["pl", "2", "scene-2"],
                                                   ["full", "1", "scene-4"]]  # fmt: skip
    assert main([str(tmp_path), "--near", "0.9"]) == 0 and "0.9 x the drive's p99" in capsys.readouterr().out


def test_bad_input_is_reported(tmp_path, capsys):
    assert main([]) == 2
    assert main([str(tmp_path), "--near"]) == 2
    assert main([str(tmp_path)]) == 1 and "holds no" in capsys.readouterr().err
    (tmp_path / "r1_scale1_x").mkdir()
    (tmp_path / "r1_scale1_x" / "replay.json").write_text("{not json")
    assert main([str(tmp_path)]) == 1
    (tmp_path / "r1_scale1_x" / "replay.json").write_text(json.dumps({"modes": {"full-sweep": {}}}))
    assert main([str(tmp_path)]) == 1 and "no streaming recordings" in capsys.readouterr().err


@pytest.mark.parametrize("seed", [0, 1])
def test_slices_the_player_released_late_are_counted(seed):
    """A stall of the whole process: the player releases a run of slices long after their scans ended; counted
    against a naive loop over every slice, dropped ones too."""
    rec = _recording(seed)
    stall = slice(40 + seed, 47 + seed)
    for s in rec["slices"][stall]:
        s["release_s"] = s["scan_end_s"] + 0.025 + 0.005 * seed
    rec["slices"][-1]["release_s"] = rec["slices"][-1]["scan_end_s"] + 0.05  # a dropped slice, released late too
    got = drive_tail(rec)
    late = [(s["release_s"] - s["scan_end_s"]) * 1e3 for s in rec["slices"]]
    assert got["released_late"] == sum(x > 10.0 for x in late) == 8
    assert got["release_late_max_ms"] == pytest.approx(max(late)) and got["release_late_max_ms"] == pytest.approx(50.0)
    assert drive_tail(_recording(seed))["released_late"] == 0
