"""Measure the Table 3 rows: onnxruntime fp32, fp16 and int8, PyTorch eager, the graph's MACs, optional profiles.

For every row: export (``modules.export_row``), count the graph's MACs and compare with the torch counter, then
time the fp32 graph, the fp16 graph, the int8 graph and the same module in PyTorch eager (``torch.inference_mode``, the same
thread count) with ``timing.time_callable``. A row's throughput is its MACs over the fp32 median; its peak
fraction divides that by the matmul probe of the same run.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from streamdet.benchmarks.graph_macs import count_graph_macs
from streamdet.benchmarks.modules import Row, RowGraphs, export_row
from streamdet.benchmarks.ort_profile import ProfileSummary, summarize_profile
from streamdet.benchmarks.probe import row_session_config
from streamdet.benchmarks.timing import TimingConfig, TimingStats, time_callable
from streamdet.runtime_ort.sessions import GraphSession

Progress = Callable[[str], None]
PROFILE_RUNS = 3  # profiled runs per graph after one warm-up: enough for a per-op split, cheap for slow rows


@dataclass(frozen=True)
class TableConfig:
    threads: int = 2  # intra-op threads of onnxruntime and torch.set_num_threads
    timing: TimingConfig = field(default_factory=TimingConfig)
    torch_skip_ms: float | None = None  # skip PyTorch on rows whose fp32 median exceeds this (--quick); None: never
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


def _time_graph(path: Path, row: Row, cfg: TableConfig) -> TimingStats:
    session = GraphSession(path, row_session_config(cfg.threads))
    feeds = row.feeds()
    return time_callable(lambda: session.run(feeds), cfg.timing)


def _time_torch(net: torch.nn.Module, row: Row, cfg: TableConfig) -> TimingStats:
    torch.set_num_threads(cfg.threads)
    with torch.inference_mode():
        return time_callable(lambda: net(*row.inputs), cfg.timing)


def _profile_graph(path: Path, row: Row, precision: str, threads: int, profile_dir: Path) -> ProfileSummary:
    session = GraphSession(path, row_session_config(threads, profile=True))
    feeds = row.feeds()
    for _ in range(1 + PROFILE_RUNS):  # the first run (allocations, first-touch) is in the profile too; see runs
        session.run(feeds)
    written = Path(session.end_profiling())
    target = profile_dir / f"{row.key}.{precision}.json"
    shutil.move(written, target)
    return summarize_profile(target)


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

        progress(f"{step}: onnxruntime fp32")
        fp32 = _time_graph(graphs.fp32, row, cfg)
        fp16 = None
        if graphs.fp16 is not None:
            progress(f"{step}: onnxruntime fp16")
            fp16 = _time_graph(graphs.fp16, row, cfg)
        elif graphs.fp16_error is not None:
            notes.append(f"fp16 conversion failed: {graphs.fp16_error}")
        int8 = None
        if graphs.int8 is not None:
            progress(f"{step}: onnxruntime int8")
            int8 = _time_graph(graphs.int8, row, cfg)
        elif graphs.int8_error is not None:
            notes.append(f"int8 quantization failed: {graphs.int8_error}")
        torch_stats = torch_export = None
        if cfg.torch_skip_ms is not None and fp32.median_ms > cfg.torch_skip_ms:
            notes.append(f"PyTorch skipped (fp32 run {fp32.median_ms:.0f} ms > {cfg.torch_skip_ms:.0f} ms, --quick)")
        else:
            progress(f"{step}: PyTorch eager")
            torch_stats = _time_torch(row.net, row, cfg)
            if row.export_net is not None:
                progress(f"{step}: PyTorch eager, the export's form")
                torch_export = _time_torch(row.export_net, row, cfg)
                notes.append(
                    f"PyTorch times the module as trained; on the export's rewrite of it (same function) PyTorch takes "
                    f"{torch_export.median_ms:.3g} ms, onnxruntime fp32 is {torch_export.median_ms / fp32.median_ms:.2f}x faster"
                )
        measured = (("fp32", fp32), ("fp16", fp16), ("int8", int8), ("torch", torch_stats), ("torch export form", torch_export))
        cut = [f"{name} {st.count}/{st.requested}" for name, st in measured if st is not None and st.reduced]
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
