"""Measure the Table 3 rows: onnxruntime fp32, fp16 and int8, PyTorch eager, the graph's MACs, optional profiles.

For every row: export (``modules.export_row``), count the graph's MACs and compare with the torch counter, then
time the fp32 graph, the fp16 graph, the int8 graph and the same module in PyTorch eager (``torch.inference_mode``, the same
thread count) taking turns (``timing.time_interleaved``), so that the ratios between them (onnxruntime against
PyTorch, int8 against fp32) compare runs made under the same machine conditions. A row's throughput is its MACs
over the fp32 median; its peak fraction divides that by the matmul probe of the same run.
"""

from __future__ import annotations

import shutil
import time
from functools import partial
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from streamdet.benchmarks.graph_macs import count_graph_macs
from streamdet.benchmarks.modules import Row, RowGraphs, export_row
from streamdet.benchmarks.ort_profile import ProfileSummary, summarize_profile
from streamdet.benchmarks.probe import row_session_config
from streamdet.benchmarks.timing import TimingConfig, TimingStats, time_callable, time_interleaved
from streamdet.runtime_ort.sessions import GraphSession

Progress = Callable[[str], None]
PROFILE_RUNS = 3  # profiled runs per graph after one warm-up: enough for a per-op split, cheap for slow rows
ROUNDS = 4  # the measurements of a row take turns in this many rounds
TORCH, TORCH_EXPORT = "PyTorch", "PyTorch on the export form"  # their names in progress lines and notes


@dataclass(frozen=True)
class TableConfig:
    threads: int = 2  # intra-op threads of onnxruntime and torch.set_num_threads
    timing: TimingConfig = field(default_factory=TimingConfig)
    torch_skip_ms: float | None = None  # skip PyTorch on rows whose first fp32 run exceeds this (--quick); None: never
    profile_dir: Path | None = None  # write onnxruntime profiles of every row graph here
    fp16: bool = True  # also convert, time (and profile) the fp16 sibling of every graph
    int8: bool = True  # also quantize, time (and profile) the int8 sibling of every graph

    def __post_init__(self) -> None:
        if isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1:
            raise ValueError(f"TableConfig.threads must be a positive integer, got {self.threads!r}")


@dataclass(frozen=True)
class RowResult:
    module: str
    key: str
    kind: str
    gmac: float  # torch counter (models/flops.py)
    graph_gmac: float | None  # counted on the exported ONNX graph; None if shape inference left a MAC node open
    fp32: TimingStats
    fp16: TimingStats | None  # None: the fp16 conversion failed (fp16_error)
    torch: TimingStats | None  # None: skipped (notes say why)
    fp16_error: str | None = None
    notes: tuple[str, ...] = ()
    profiles: dict[str, ProfileSummary] = field(default_factory=dict)  # precision -> summary
    int8: TimingStats | None = None  # None: not asked for, or the quantization failed (int8_error)
    int8_error: str | None = None
    torch_export: TimingStats | None = None  # PyTorch on the export's rewrite of the module (Row.export_net), if any

    @property
    def int8_speedup(self) -> float | None:
        """fp32 median over int8 median."""
        return None if self.int8 is None else self.fp32.median_ms / self.int8.median_ms

    @property
    def gflops_per_s(self) -> float:
        """Achieved fp32 throughput in GFLOP/s (FLOPs = 2 x MACs) at the median time."""
        return 2.0 * self.gmac / (self.fp32.median_ms / 1e3)

    @property
    def torch_over_ort(self) -> float | None:
        return None if self.torch is None else self.torch.median_ms / self.fp32.median_ms

    @property
    def graph_ratio(self) -> float | None:
        return None if self.graph_gmac is None or self.gmac == 0 else self.graph_gmac / self.gmac


def _graph_runner(path: Path, row: Row, threads: int) -> Callable[[], object]:
    session = GraphSession(path, row_session_config(threads))
    feeds = row.feeds()
    return lambda: session.run(feeds)


def _torch_runner(net: torch.nn.Module, row: Row) -> Callable[[], object]:
    def run() -> object:
        with torch.inference_mode():
            return net(*row.inputs)

    return run


def _first_run_ms(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return (time.perf_counter() - start) * 1e3


def _profile_graph(path: Path, row: Row, precision: str, threads: int, profile_dir: Path) -> ProfileSummary:
    session = GraphSession(path, row_session_config(threads, profile=True))
    feeds = row.feeds()
    for _ in range(1 + PROFILE_RUNS):  # the first run (allocations, first-touch) is in the profile too; see runs
        session.run(feeds)
    written = Path(session.end_profiling())
    target = profile_dir / f"{row.key}.{precision}.json"
    shutil.move(written, target)
    return summarize_profile(target)


def _time_row(row: Row, graphs: RowGraphs, cfg: TableConfig, notes: list[str], progress: Progress) -> dict[str, TimingStats]:
    """The row's graphs and PyTorch modules timed taking turns (``time_interleaved``), or one after the other when
    a run takes seconds: then turns gain little over the few repeats, and the row's sessions held together would
    cost gigabytes (the paper preset's benchmark: 19.6 instead of 16.2 GB resident)."""
    makers = {name: partial(_graph_runner, path, row, cfg.threads) for name, path in
              (("fp32", graphs.fp32), ("fp16", graphs.fp16), ("int8", graphs.int8)) if path is not None}  # fmt: skip
    fp32 = makers.pop("fp32")()
    first_ms = _first_run_ms(fp32)
    if cfg.torch_skip_ms is not None and first_ms > cfg.torch_skip_ms:
        notes.append(f"PyTorch skipped (fp32 run {first_ms:.0f} ms > {cfg.torch_skip_ms:.0f} ms, --quick)")
    else:
        torch.set_num_threads(cfg.threads)
        makers[TORCH] = partial(_torch_runner, row.net, row)
        if row.export_net is not None:
            makers[TORCH_EXPORT] = partial(_torch_runner, row.export_net, row)
    names = ", ".join(["fp32", *makers])
    if first_ms > cfg.timing.slow_warmup_s * 1e3:
        progress(f"{names} one after the other (a run takes {first_ms / 1e3:.1f} s)")
        notes.append(f"measured one after the other, not taking turns (a run takes {first_ms / 1e3:.1f} s)")
        stats = {"fp32": time_callable(fp32, cfg.timing)}
        del fp32  # one session at a time
        for name, make in makers.items():
            stats[name] = time_callable(make(), cfg.timing)
        return stats
    progress(f"{names} taking turns in {ROUNDS} rounds")
    return time_interleaved({"fp32": fp32, **{name: make() for name, make in makers.items()}}, cfg.timing, ROUNDS)


def measure_rows(rows: list[Row], work_dir: Path, cfg: TableConfig, progress: Progress = lambda msg: None) -> list[RowResult]:
    """Export, count and time every row; graphs go to ``work_dir``."""
    if cfg.profile_dir is not None:
        cfg.profile_dir.mkdir(parents=True, exist_ok=True)
    exported: dict[str, RowGraphs] = {}
    results = []
    for i, row in enumerate(rows, 1):
        step = f"[row {i}/{len(rows)}] {row.module}"
        if row.graph_stem not in exported:
            progress(f"{step}: exporting fp32" + (" + fp16" if cfg.fp16 else "") + (" + int8" if cfg.int8 else ""))
            exported[row.graph_stem] = export_row(row, work_dir, cfg.fp16, cfg.int8)
        graphs = exported[row.graph_stem]
        macs = count_graph_macs(graphs.model, row.input_shapes())
        notes: list[str] = list(row.notes)
        if not macs.complete:
            notes.append(f"graph MACs unresolved at {len(macs.unresolved)} node(s)")

        if graphs.fp16 is None and graphs.fp16_error is not None:
            notes.append(f"fp16 conversion failed: {graphs.fp16_error}")
        if graphs.int8 is None and graphs.int8_error is not None:
            notes.append(f"int8 quantization failed: {graphs.int8_error}")
        stats = _time_row(row, graphs, cfg, notes, lambda msg: progress(f"{step}: {msg}"))
        fp32, fp16, int8 = stats["fp32"], stats.get("fp16"), stats.get("int8")
        torch_stats, torch_export = stats.get(TORCH), stats.get(TORCH_EXPORT)
        if torch_export is not None:
            notes.append(
                f"PyTorch times the module as trained; on the export's rewrite of it (same function) PyTorch takes "
                f"{torch_export.median_ms:.3g} ms, onnxruntime fp32 is {torch_export.median_ms / fp32.median_ms:.2f}x faster"
            )
        cut = [f"{name} {st.count}/{st.requested}" for name, st in stats.items() if st.reduced]
        if cut:
            notes.append(f"repeats cut by the {cfg.timing.budget_s:g} s budget per measurement: {', '.join(cut)}")

        profiles: dict[str, ProfileSummary] = {}
        if cfg.profile_dir is not None:
            progress(f"{step}: profiling")
            profiles["fp32"] = _profile_graph(graphs.fp32, row, "fp32", cfg.threads, cfg.profile_dir)
            if graphs.fp16 is not None:
                profiles["fp16"] = _profile_graph(graphs.fp16, row, "fp16", cfg.threads, cfg.profile_dir)
            if graphs.int8 is not None:
                profiles["int8"] = _profile_graph(graphs.int8, row, "int8", cfg.threads, cfg.profile_dir)
        results.append(
            RowResult(
                module=row.module,
                key=row.key,
                kind=row.kind,
                gmac=row.gmac,
                graph_gmac=macs.gmac if macs.complete else None,
                fp32=fp32,
                fp16=fp16,
                torch=torch_stats,
                fp16_error=graphs.fp16_error,
                notes=tuple(notes),
                profiles=profiles,
                int8=int8,
                int8_error=graphs.int8_error,
                torch_export=torch_export,
            )
        )
    return results
