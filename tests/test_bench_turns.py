"""The streaming section's compared phases take turns (bench review M2): the slice lane idle, idle with more threads
and busy alternate in rounds on the tiny export, each phase keeps its own stage statistics, the wide detector is
closed after its rounds (L3), and the image-lane schedules alternate A B, B A."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from streamdet.benchmarks import report, streaming, streaming_schedules
from streamdet.benchmarks.streaming import StreamingConfig, copied_into, phase_rounds, sweeps_per_round
from streamdet.runtime_ort.stats import LatencyStats


@pytest.mark.parametrize("sweeps, rounds, expected", [(5, 5, [1] * 5), (5, 2, [3, 2]), (2, 2, [1, 1]), (7, 3, [3, 2, 2]),
                                                      (1, 1, [1])])  # fmt: skip
def test_sweeps_are_spread_over_the_rounds(sweeps, rounds, expected):
    assert sweeps_per_round(sweeps, rounds) == expected and sum(expected) == sweeps


def test_rounds_are_one_per_sweep_unless_stopping_the_busy_lane_waits_too_long():
    assert phase_rounds(5, 0.08, 20.0) == 5  # small_v3: an update stops in a tenth of a second
    assert phase_rounds(5, 8.0, 20.0) == 2  # the stops may wait 20 s in all
    assert phase_rounds(5, 60.0, 20.0) == 1  # the paper preset: one after the other, as before
    assert phase_rounds(3, 0.0, 20.0) == 3


def test_copied_into_copies_every_thread_and_restores_the_method():
    stats, phase = LatencyStats(), LatencyStats()
    stats.record("before", 1.0)
    with copied_into(stats, phase):
        with stats.time("pre"):
            pass
        worker = threading.Thread(target=lambda: stats.record("image_total", 5.0, gmac=2.0))
        worker.start()
        worker.join()
    stats.record("after", 1.0)
    assert set(phase.summary()) == {"pre", "image_total"} and phase.summary()["image_total"]["gmac_total"] == 2.0
    assert set(stats.summary()) == {"before", "pre", "image_total", "after"}
    assert "record" not in vars(stats)  # the class's method again


@pytest.fixture
def logged_section(monkeypatch, tiny_export):
    """measure_streaming on the tiny export with the order of its timed sweeps logged."""
    log: list[str] = []
    made = []
    real_time_slices, real_busy, real_detector = streaming._time_slices, streaming.busy_image_lane, streaming._detector
    busy = [False]

    def detector(*args, **kwargs):
        det = real_detector(*args, **kwargs)
        made.append(det)
        return det

    def time_slices(det, slices, sweeps):
        kind = "busy" if busy[0] else ("wide" if det is not made[0] else "idle")
        log.append(f"{kind}{sweeps}")
        return real_time_slices(det, slices, sweeps)

    class Busy:
        def __init__(self, det, images):
            self.inner = real_busy(det, images)

        def __enter__(self):
            busy[0] = True
            return self.inner.__enter__()

        def __exit__(self, *exc):
            busy[0] = False
            return self.inner.__exit__(*exc)

    monkeypatch.setattr(streaming, "_time_slices", time_slices)
    monkeypatch.setattr(streaming, "busy_image_lane", Busy)
    monkeypatch.setattr(streaming, "_detector", detector)
    cfg = StreamingConfig(sweeps=3, image_updates=1, queue_sweeps=1, schedule_seconds=0.0, wide_slice_threads=2)
    result = streaming.measure_streaming(tiny_export, cfg)
    return result, log, made


def test_idle_wide_and_busy_take_turns_in_rounds(logged_section):
    result, log, made = logged_section
    # warm-ups (wide first, as it is made before the rounds), then a sweep of each phase per round
    assert log == ["wide1", "idle1"] + ["idle1", "wide1", "busy1"] * 3
    assert result.phase_rounds == 3
    assert result.idle.latency.count == result.busy.latency.count == result.idle_all_cores.latency.count == 3 * 8
    # each phase's stages are its own: the image lane ran only in the busy phase
    assert "image_total" in result.busy.stages and "image_total" not in result.idle.stages
    assert result.idle.stages["slice_total"]["count"] == 3 * 8 and result.busy.stages["slice_total"]["count"] == 3 * 8
    assert "image_total" not in result.idle_all_cores.stages
    assert result.image_busy_updates >= 0
    wide = made[1]
    with pytest.raises(Exception, match="closed"):  # closed after its rounds (L3), not held to the end of the section
        wide.detect_slice(np.zeros((0, 6), np.float32), 0)


def test_the_report_says_how_the_phases_were_taken(logged_section):
    result, _, _ = logged_section
    text = report.format_streaming(result)
    assert "taken in turns: 3 rounds of 1 sweep(s) each" in text and "started and stopped every round" in text
    doc = report.streaming_to_dict(result)
    assert doc["phase_rounds"] == 3 and doc["phase_sweeps_per_round"] == [1, 1, 1]
    for key in ("slice_idle", "slice_busy", "slice_idle_all_cores", "busy_over_idle_p95", "image_lane_schedules"):
        assert key in doc  # the keys the report, the plot and older readers use


def _fake_recording(n: int, dropped: int) -> SimpleNamespace:
    return SimpleNamespace(
        staleness_ms=lambda: np.full(n, float(n)), image_ages_ms=lambda: np.full(n, 1.0), latencies_ms=lambda: np.full(n, 2.0),
        slices_dropped=dropped, slices=[None] * n, image_lane_cpu_s=0.5, rotations=5,
        phase_lock={"quadrant_lifts": n, "yielded_ms": 1.5},
    )  # fmt: skip


def test_schedules_alternate_a_b_b_a_and_pool_their_rounds(monkeypatch):
    calls = []

    def play(export_dir, precision, image_precision, seconds, trigger, lanes):
        calls.append((lanes.schedule, seconds))
        return _fake_recording(4 if lanes.schedule == "full" else 6, 1)

    monkeypatch.setattr(streaming_schedules, "_play", play)
    out = streaming_schedules.measure_schedules("unused", "fp32", None, 3.0, rounds=3)
    assert calls == [("full", 1.0), ("phase-locked", 1.0), ("phase-locked", 1.0), ("full", 1.0), ("full", 1.0),
                     ("phase-locked", 1.0)]  # fmt: skip
    full = out["full"]
    assert full["rounds"] == 3 and full["seconds_per_round"] == 1.0
    assert full["slices_total"] == 12 and full["slices_dropped"] == 3
    assert full["image_lane_cpu_ms_per_rotation"] == pytest.approx(1e3 * 1.5 / 15)
    assert full["phase_lock"] == {"quadrant_lifts": 12, "yielded_ms": 4.5}
    assert full["staleness_ms"]["p50"] == 4.0 and out["phase-locked"]["staleness_ms"]["p50"] == 6.0
    lines = streaming_schedules.format_schedules(out)
    assert all("in turns with the other schedule: 3 rounds of 1 s" in line for line in lines)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_bad_rounds_are_refused(bad):
    with pytest.raises(ValueError, match="rounds must be a positive integer"):
        streaming_schedules.measure_schedules("unused", "fp32", None, 1.0, rounds=bad)
    with pytest.raises(ValueError, match="StreamingConfig.schedule_rounds"):
        StreamingConfig(schedule_rounds=bad)
