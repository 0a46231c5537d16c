"""Timing statistics against numpy, the repeat/budget/warm-up logic on a fake clock, and malformed input."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.benchmarks import timing
from streamdet.benchmarks.timing import TimingConfig, summarize, time_callable, time_interleaved


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
     ({"slow_warmup_s": float("nan")}, "slow_warmup_s"), ({"settle_s": -0.1}, "settle_s")],
)
def test_timing_config_rejects_bad_values(kwargs, field):
    with pytest.raises(ValueError, match=f"TimingConfig.{field}"):
        TimingConfig(**kwargs)


def test_timing_config_min_repeat_is_at_most_repeat():
    with pytest.raises(ValueError, match=r"TimingConfig.min_repeat must be at most repeat, got min_repeat=5 > repeat=2"):
        TimingConfig(repeat=2, min_repeat=5)
    assert TimingConfig(repeat=2, min_repeat=2).min_repeat == 2
    # not given: 3, or every run where fewer are asked for (TimingConfig(repeat=2) stays valid)
    assert TimingConfig().min_repeat == timing.DEFAULT_MIN_REPEAT == 3
    assert TimingConfig(repeat=2).min_repeat == 2 and TimingConfig(repeat=1).min_repeat == 1


class Machine:
    """A fake machine whose speed changes at ``slow_after_s``: each callable costs its base seconds, ``slowdown``
    times more from then on. Records the order of the calls."""

    def __init__(self, base_s: dict[str, float], slow_after_s: float = float("inf"), slowdown: float = 1.0):
        self.now = 0.0
        self.base_s, self.slow_after_s, self.slowdown = base_s, slow_after_s, slowdown
        self.calls: list[str] = []

    def perf_counter(self):
        return self.now

    def fn(self, name):
        def run():
            factor = self.slowdown if self.now >= self.slow_after_s else 1.0
            self.now += self.base_s[name] * factor
            self.calls.append(name)

        return run


@pytest.fixture
def machine(monkeypatch):
    def make(*args, **kwargs):
        m = Machine(*args, **kwargs)
        monkeypatch.setattr(timing.time, "perf_counter", m.perf_counter)
        return m

    return make


def test_time_interleaved_takes_turns_and_settles(machine):
    m = machine({"a": 0.001, "b": 0.002})
    cfg = TimingConfig(repeat=8, warmup=2, budget_s=100.0, settle_s=0.0035)
    s = time_interleaved({"a": m.fn("a"), "b": m.fn("b")}, cfg, rounds=4)
    assert s["a"].count == s["b"].count == 8 and not s["a"].reduced
    assert s["a"].median_ms == pytest.approx(1.0) and s["b"].median_ms == pytest.approx(2.0)
    # warm-ups, then at each turn untimed runs for 4 ms (4 of a, 2 of b) before its 2 timed runs
    expected = ["a", "a", "b", "b"] + (["a"] * (4 + 2) + ["b"] * (2 + 2)) * 4
    assert m.calls == expected


@pytest.mark.parametrize("seed", range(3))
def test_time_interleaved_keeps_the_ratio_when_the_machine_slows(machine, seed):
    # the machine slows 1.5x part-way through: taking turns, both see it alike and the ratio stays 2
    rng = np.random.default_rng(seed)
    slow_after = float(rng.uniform(0.05, 0.25))
    m = machine({"a": 0.004, "b": 0.008}, slow_after_s=slow_after, slowdown=1.5)
    cfg = TimingConfig(repeat=20, warmup=1, budget_s=100.0)
    s = time_interleaved({"a": m.fn("a"), "b": m.fn("b")}, cfg, rounds=20)
    assert s["b"].mean_ms / s["a"].mean_ms == pytest.approx(2.0, rel=0.05)
    # one after the other, the same slowdown distorts the ratio
    m = machine({"a": 0.004, "b": 0.008}, slow_after_s=0.1, slowdown=1.5)
    a = time_callable(m.fn("a"), cfg)
    b = time_callable(m.fn("b"), cfg)
    assert b.mean_ms / a.mean_ms > 2.4


def test_time_interleaved_budget_and_slow_callables_apart(machine):
    m = machine({"fast": 0.001, "slow": 3.0})
    cfg = TimingConfig(repeat=8, warmup=2, budget_s=7.0, min_repeat=2, slow_warmup_s=2.0, settle_s=0.0015)
    s = time_interleaved({"fast": m.fn("fast"), "slow": m.fn("slow")}, cfg, rounds=4)
    assert s["fast"].count == 8 and not s["fast"].reduced
    # over its 7 / 4 s share of the budget in each round, but still one run a round; its budget does not stop the fast one
    assert s["slow"].count == 4 and s["slow"].reduced
    assert m.calls.count("slow") == 1 + 4  # one slow warm-up, no settling runs
    # warm-up, 2 settling runs at each turn (each follows the slow one), timed
    assert m.calls.count("fast") == 2 + 4 * 2 + 8


def test_time_interleaved_one_callable_settles_never(machine):
    m = machine({"a": 0.001})
    s = time_interleaved({"a": m.fn("a")}, TimingConfig(repeat=6, warmup=1, settle_s=1.0), rounds=3)
    assert s["a"].count == 6 and m.calls == ["a"] * 7  # its turns follow each other: nothing else ran


@pytest.mark.parametrize("fns, rounds, message", [({}, 4, "at least one callable"), ({"a": lambda: None}, 0, "rounds"),
                                                  ({"a": lambda: None}, True, "rounds")])  # fmt: skip
def test_time_interleaved_rejects_malformed(fns, rounds, message):
    with pytest.raises(ValueError, match=message):
        time_interleaved(fns, TimingConfig(repeat=2, warmup=0), rounds=rounds)


def _runs(calls: list[str]) -> str:
    """The call order with runs of one callable compressed: "A1 B1 A3 B6"."""
    out: list[list] = []
    for name in calls:
        if out and out[-1][0] == name:
            out[-1][1] += 1
        else:
            out.append([name, 1])
    return " ".join(f"{name}{n}" for name, n in out)


@pytest.mark.parametrize("a_s, timed_per_round", [(1.0, 1), (0.4, 2)])
def test_a_measurement_cut_by_the_budget_keeps_taking_turns(machine, a_s, timed_per_round):
    """The review's case (A slow, B fast, budget 3 s, repeat 20, 4 rounds): A spent its budget in the first round or
    two and was absent from the rest ("A1 B1 A4 B21"; at 0.4 s "A1 B1 A6 B6 A4 B16"), so B's last rounds ran back
    to back. With a per-round share of the budget A runs in every round, and B never runs two rounds in a row."""
    m = machine({"A": a_s, "B": 0.001})
    cfg = TimingConfig(repeat=20, warmup=1, budget_s=3.0, min_repeat=3, settle_s=0.0005)
    s = time_interleaved({"A": m.fn("A"), "B": m.fn("B")}, cfg, rounds=4)
    # warm-ups; then at each turn A settles with one untimed run, B with one, before the timed runs (5 a round for B)
    turn = f"A{1 + timed_per_round} B{1 + 5}"
    assert _runs(m.calls) == "A1 B1 " + " ".join([turn] * 4)
    assert s["A"].count == 4 * timed_per_round and s["A"].reduced and s["B"].count == 20
    # its budget is spread over the rounds: spent by the end, give or take a run in each round
    assert s["A"].count * a_s <= cfg.budget_s + 4 * a_s


def test_a_cut_measurement_samples_every_round_when_the_machine_slows(machine):
    # the machine slows 2x at 4.6 s, in the last round (A's turns: 1.0-2.0, 2.5-3.0, 3.5-4.5, 5.0-6.0 s): a cut A
    # that spent its budget at the start (0.5-4.0 s, before the change) would not see it, while B would
    m = machine({"A": 0.5, "B": 0.001}, slow_after_s=4.6, slowdown=2.0)
    cfg = TimingConfig(repeat=20, warmup=1, budget_s=3.0, min_repeat=3, settle_s=0.0005)
    s = time_interleaved({"A": m.fn("A"), "B": m.fn("B")}, cfg, rounds=4)
    assert s["A"].max_ms == pytest.approx(1000.0) and s["B"].max_ms == pytest.approx(2.0)


def test_min_repeat_is_spread_over_the_rounds(machine):
    # each run is over the whole budget: the floor of min_repeat runs still falls 2 to a round, not 8 at once
    m = machine({"A": 10.0, "B": 0.001})
    cfg = TimingConfig(repeat=20, warmup=1, budget_s=1.0, min_repeat=8, slow_warmup_s=20.0, settle_s=0.0005)
    s = time_interleaved({"A": m.fn("A"), "B": m.fn("B")}, cfg, rounds=4)
    assert s["A"].count == 8
    assert _runs(m.calls) == "A1 B1 " + " ".join(["A3 B6"] * 4)
