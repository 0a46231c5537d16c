"""LatencyStats: percentiles against np.percentile, bounded memory, thread safety, the timing context."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from streamdet.runtime_ort.stats import LatencyStats


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_summary_matches_numpy_over_the_last_capacity_samples(seed):
    rng = np.random.default_rng(seed)
    stats = LatencyStats(capacity=100)
    pre = rng.gamma(2.0, 3.0, 250)
    post = rng.uniform(0, 1, 40)
    for v in pre:
        stats.record("pre", v)
    for v in post:
        stats.record("post", v)
    summary = stats.summary()
    for stage, values in (("pre", pre[-100:]), ("post", post)):
        s = summary[stage]
        assert s["p50_ms"] == pytest.approx(np.percentile(values, 50))
        assert s["p95_ms"] == pytest.approx(np.percentile(values, 95))
        assert s["mean_ms"] == pytest.approx(values.mean())
        assert (s["min_ms"], s["max_ms"]) == (values.min(), values.max())
    assert summary["pre"]["count"] == 250 and summary["post"]["count"] == 40


def test_memory_stays_bounded():
    stats = LatencyStats(capacity=8)
    for v in range(10_000):
        stats.record("slice", float(v))
    ring = stats._rings["slice"]
    assert ring.values_ms.size == 8
    assert stats.summary()["slice"]["min_ms"] == 9992.0


def test_time_context_records_perf_counter_duration_even_on_error():
    stats = LatencyStats()
    with stats.time("sleep"):
        time.sleep(0.02)
    with pytest.raises(RuntimeError):
        with stats.time("fails"):
            raise RuntimeError("boom")
    summary = stats.summary()
    assert 15.0 <= summary["sleep"]["p50_ms"] < 500.0
    assert summary["fails"]["count"] == 1


def test_concurrent_recording_loses_nothing():
    stats = LatencyStats(capacity=64)

    def worker(stage):
        for _ in range(2000):
            stats.record(stage, 1.0)

    threads = [threading.Thread(target=worker, args=(f"s{i % 2}",)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    summary = stats.summary()
    assert summary["s0"]["count"] == summary["s1"]["count"] == 6000
    assert summary["s0"]["mean_ms"] == 1.0


def test_empty_reset_and_bad_input():
    stats = LatencyStats()
    assert stats.summary() == {}
    stats.record("a", 1.0)
    stats.reset()
    assert stats.summary() == {}
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="duration_ms"):
            stats.record("a", bad)
    with pytest.raises(ValueError, match="stage"):
        stats.record("", 1.0)
    with pytest.raises(ValueError, match="capacity"):
        LatencyStats(capacity=0)
