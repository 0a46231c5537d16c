"""Wall-clock timing of a callable: warm-up, repeats under a time budget, and robust statistics.

Every figure the benchmark prints is a ``TimingStats``: the median and p95 over the repeats (numpy's default linear
interpolation, as ``runtime_ort/stats.py`` uses), the min-max spread as the noise, and the repeat count it rests on.
Slow rows (the paper preset's uncropped 3D convolutions take seconds) get fewer repeats automatically; ``reduced``
says so, and the report prints it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np


DEFAULT_MIN_REPEAT = 3  # TimingConfig.min_repeat where not given (or repeat, where that is fewer)
# Fewer samples than this give no p95 worth printing or judging (linear interpolation between the two largest, or the
# maximum itself): "n/a" in the text and no verdict on a p95 target; the JSON keeps every figure with its count.
# Here, not in report.py, so that report.py and prepost.py (which report.py imports) both read it.
MIN_P95_SAMPLES = 20


@dataclass(frozen=True)
class TimingConfig:
    repeat: int = 20  # timed runs per measurement, unless the budget below cuts them
    warmup: int = 2  # untimed runs first (allocator, thread pools, caches)
    budget_s: float = 20.0  # a measurement stops adding repeats once this much time is spent on timed runs (time_interleaved: spread over its rounds)
    # ... but never fewer than this many timed runs (nor, in time_interleaved, fewer than one a round); at most
    # ``repeat``. None: DEFAULT_MIN_REPEAT, or ``repeat`` where that is fewer
    min_repeat: int | None = None
    slow_warmup_s: float = 2.0  # a warm-up run longer than this ends the warm-up after one run
    settle_s: float = 0.1  # time_interleaved: untimed runs at each turn this long (other thread pools stop spinning)

    def __post_init__(self) -> None:
        if self.min_repeat is None and isinstance(self.repeat, int) and not isinstance(self.repeat, bool):
            object.__setattr__(self, "min_repeat", min(DEFAULT_MIN_REPEAT, self.repeat))
        for name in ("repeat", "min_repeat"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"TimingConfig.{name} must be a positive integer, got {v!r}")
        if self.min_repeat > self.repeat:
            # the floor would overrule the count asked for: one of the two is a mistake
            raise ValueError(f"TimingConfig.min_repeat must be at most repeat, got min_repeat={self.min_repeat!r} "
                             f"> repeat={self.repeat!r}")  # fmt: skip
        if isinstance(self.warmup, bool) or not isinstance(self.warmup, int) or self.warmup < 0:
            raise ValueError(f"TimingConfig.warmup must be an integer >= 0, got {self.warmup!r}")
        for name in ("budget_s", "slow_warmup_s", "settle_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"TimingConfig.{name} must be a positive number of seconds, got {v!r}")


@dataclass(frozen=True)
class TimingStats:
    """Statistics of ``count`` durations in milliseconds."""

    count: int
    median_ms: float
    p95_ms: float
    mean_ms: float
    min_ms: float
    max_ms: float
    requested: int  # repeats asked for; count < requested when the time budget cut them

    @property
    def reduced(self) -> bool:
        return self.count < self.requested

    @property
    def noise(self) -> float:
        """(max - min) / median: the relative spread of the repeats."""
        return (self.max_ms - self.min_ms) / self.median_ms if self.median_ms > 0 else 0.0

    def to_dict(self) -> dict:
        return {
            "count": self.count,
            "requested": self.requested,
            "median_ms": self.median_ms,
            "p95_ms": self.p95_ms,
            "mean_ms": self.mean_ms,
            "min_ms": self.min_ms,
            "max_ms": self.max_ms,
        }


def summarize(samples_ms: Sequence[float] | np.ndarray, requested: int | None = None) -> TimingStats:
    """Statistics of the durations ``samples_ms`` (finite, >= 0, at least one)."""
    x = np.asarray(samples_ms, dtype=np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"samples_ms must be a non-empty 1-D sequence of durations, got shape {x.shape}")
    if not np.all(np.isfinite(x)) or np.any(x < 0):
        bad = x[~np.isfinite(x) | (x < 0)][0]
        raise ValueError(f"samples_ms must be finite durations >= 0, got {bad}")
    p50, p95 = np.percentile(x, [50, 95])
    return TimingStats(
        count=int(x.size),
        median_ms=float(p50),
        p95_ms=float(p95),
        mean_ms=float(x.mean()),
        min_ms=float(x.min()),
        max_ms=float(x.max()),
        requested=int(x.size) if requested is None else int(requested),
    )


def time_callable(fn: Callable[[], object], config: TimingConfig = TimingConfig()) -> TimingStats:
    """Run ``fn`` ``config.warmup`` times untimed, then time up to ``config.repeat`` runs within ``config.budget_s``."""
    return time_interleaved({"fn": fn}, config, rounds=1)["fn"]


def time_interleaved(
    fns: Mapping[str, Callable[[], object]], config: TimingConfig = TimingConfig(), rounds: int = 4
) -> dict[str, TimingStats]:
    """Time several callables taking turns, in ``rounds`` rounds, so that a change of the machine's speed during
    the measurement (a neighbour on a shared cache, a clock change) falls on all of them alike and the ratios
    between them stay fair: two medians measured a minute apart can differ by what such a change costs on this
    guest (benchmarks/RESULTS.md, "Measurements behind design choices").

    Each callable is warmed up first (``config.warmup`` runs; one when a run takes longer than ``slow_warmup_s``).
    At each of its turns it then runs untimed for ``settle_s`` before its timed runs: the thread pool of the
    callable before it (onnxruntime's, PyTorch's OpenMP) keeps spinning for a while after its last run and slows
    a small graph timed at once (measured: benchmarks/RESULTS.md, section "Measurements behind design choices
    (moved from code docstrings on 2026-12-01)", **Timing**). Callables that slow skip the settling.

    ``repeat``, ``budget_s`` and ``min_repeat`` apply to each callable on its own, and each is spread evenly over the
    rounds: by the end of round r (of R) a callable has made at most (r + 1) / R of its ``repeat`` runs, stops adding
    runs once it has spent (r + 1) / R of ``budget_s``, and has made at least (r + 1) / R of ``min_repeat``. A
    callable the budget cuts still runs at least once in every round (until it has its ``repeat`` runs), so its
    samples span the whole measurement as the others' do: spending its budget in the first rounds would leave the
    others to run their last rounds back to back, and the ratios would compare different stretches of time. The
    price is that a callable slower than its share of the budget per round runs once a round, up to R runs.
    """
    if not fns:
        raise ValueError("time_interleaved needs at least one callable, got none")
    if isinstance(rounds, bool) or not isinstance(rounds, int) or rounds < 1:
        raise ValueError(f"rounds must be a positive integer, got {rounds!r}")
    slow = {name: _warm_up(fn, config) for name, fn in fns.items()}
    samples: dict[str, list[float]] = {name: [] for name in fns}
    spent = dict.fromkeys(fns, 0.0)
    per_round = -(-config.repeat // rounds)
    last = next(reversed(fns))  # the last one warmed up
    for r in range(rounds):
        target = min(config.repeat, (r + 1) * per_round)  # runs by the end of this round
        quota_s = config.budget_s * (r + 1) / rounds  # the budget spent by then, cumulative: an overrun costs later
        floor = -(-config.min_repeat * (r + 1) // rounds)  # min_repeat, spread over the rounds alike (<= target)
        for name, fn in fns.items():
            done = samples[name]
            if len(done) >= target:
                continue
            if name != last and not slow[name]:
                _settle(fn, config.settle_s)
            last = name
            least = max(floor, len(done) + 1)  # one run a round at least, so a cut measurement keeps taking turns
            while len(done) < target:
                start = time.perf_counter()
                fn()
                elapsed = time.perf_counter() - start
                done.append(elapsed * 1e3)
                spent[name] += elapsed
                if spent[name] >= quota_s and len(done) >= least:
                    break
    return {name: summarize(done, requested=config.repeat) for name, done in samples.items()}


def _settle(fn: Callable[[], object], seconds: float) -> None:
    """Untimed runs of ``fn`` until ``seconds`` have passed (at least one)."""
    start = time.perf_counter()
    fn()
    while time.perf_counter() - start < seconds:
        fn()


def _warm_up(fn: Callable[[], object], config: TimingConfig) -> bool:
    """``config.warmup`` untimed runs; True when one took longer than ``slow_warmup_s`` (and ended the warm-up)."""
    for _ in range(config.warmup):
        start = time.perf_counter()
        fn()
        if time.perf_counter() - start > config.slow_warmup_s:
            return True  # one run of a multi-second graph warms it as well as several
    return False


def ort_session(model_or_path, threads: int = 1):
    """An onnxruntime CPU session of a graph file or an in-memory ``onnx.ModelProto`` with ``threads`` intra-op
    threads, opened with the runtime's own options (``runtime_ort.sessions.session_options``: optimisation level,
    sequential execution, no spinning), so a graph is timed as the vehicle runs it."""
    from streamdet.runtime_ort.sessions import CPU_ONLY, SessionConfig
    from streamdet.runtime_ort.sessions import ort_session as runtime_session

    src = model_or_path.SerializeToString() if hasattr(model_or_path, "SerializeToString") else model_or_path
    return runtime_session(src, SessionConfig(providers=CPU_ONLY, intra_op_threads=threads))
