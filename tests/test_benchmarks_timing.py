"""Timing statistics against numpy, the repeat/budget/warm-up logic on a fake clock, and malformed input."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.benchmarks import timing
from streamdet.benchmarks.timing import TimingConfig, summarize, time_callable


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("n", [1, 2, 7, 100])
def test_summarize_matches_numpy(seed, n):
    x = np.random.default_rng(seed).gamma(2.0, 3.0, size=n)
    s = summarize(x.tolist(), requested=n + 3)
    assert s.count == n and s.requested == n + 3 and s.reduced
    assert s.median_ms == pytest.approx(np.median(x))
    assert s.p95_ms == pytest.approx(np.percentile(x, 95))
    assert s.mean_ms == pytest.approx(x.mean())
    assert (s.min_ms, s.max_ms) == (x.min(), x.max())
    assert s.noise == pytest.approx((x.max() - x.min()) / np.median(x))
    assert set(s.to_dict()) == {"count", "requested", "median_ms", "p95_ms", "mean_ms", "min_ms", "max_ms"}


def test_summarize_not_reduced_by_default():
    s = summarize(np.array([1.0, 2.0]))
    assert s.requested == 2 and not s.reduced


@pytest.mark.parametrize(
    "bad, message",
    [
        ([], "non-empty 1-D"),
        ([[1.0, 2.0]], "non-empty 1-D"),
        ([1.0, float("nan")], "finite durations >= 0, got nan"),
        ([1.0, -0.5], "finite durations >= 0, got -0.5"),
        ([float("inf")], "got inf"),
    ],
)
def test_summarize_rejects_malformed(bad, message):
    with pytest.raises(ValueError, match=message):
        summarize(bad)


class FakeClock:
    """perf_counter replacement: each call of the timed function advances it by the next duration."""

    def __init__(self, durations_s):
        self.now = 0.0
        self.durations = list(durations_s)
        self.calls = 0

    def perf_counter(self):
        return self.now

    def work(self):
        self.now += self.durations[self.calls]
        self.calls += 1


@pytest.fixture
def clock(monkeypatch):
    def make(durations_s):
        fake = FakeClock(durations_s)
        monkeypatch.setattr(timing.time, "perf_counter", fake.perf_counter)
        return fake

    return make


def test_time_callable_warmup_then_repeats(clock):
    c = clock([1.0, 1.0] + [0.001 * (i + 1) for i in range(10)])  # warm-up runs are not in the statistics
    s = time_callable(c.work, TimingConfig(repeat=10, warmup=2, budget_s=100.0))
    assert c.calls == 12 and s.count == 10 and not s.reduced
    assert s.min_ms == pytest.approx(1.0) and s.max_ms == pytest.approx(10.0)
    assert s.median_ms == pytest.approx(5.5)


def test_time_callable_budget_cuts_repeats_but_keeps_minimum(clock):
    c = clock([1.0] + [4.0] * 20)
    s = time_callable(c.work, TimingConfig(repeat=20, warmup=1, budget_s=10.0, min_repeat=2))
    assert s.count == 3 and s.requested == 20 and s.reduced  # 4 + 4 + 4 s >= 10 s
    c = clock([1.0] + [30.0] * 20)
    s = time_callable(c.work, TimingConfig(repeat=20, warmup=1, budget_s=10.0, min_repeat=3))
    assert s.count == 3  # over budget after one run, still the minimum


def test_time_callable_slow_warmup_stops_early(clock):
    c = clock([3.0, 3.0, 3.0] + [0.01] * 4)
    time_callable(c.work, TimingConfig(repeat=4, warmup=3, slow_warmup_s=2.0))
    assert c.calls == 1 + 4  # one slow warm-up run is enough


@pytest.mark.parametrize(
    "kwargs, field",
    [({"repeat": 0}, "repeat"), ({"warmup": -1}, "warmup"), ({"budget_s": 0.0}, "budget_s"), ({"min_repeat": True}, "min_repeat"),
     ({"slow_warmup_s": float("nan")}, "slow_warmup_s")],
)
def test_timing_config_rejects_bad_values(kwargs, field):
    with pytest.raises(ValueError, match=f"TimingConfig.{field}"):
        TimingConfig(**kwargs)
