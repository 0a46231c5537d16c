"""Measure the Table 3 rows: onnxruntime fp32, fp16 and int8, PyTorch eager, the graph's MACs, optional profiles.

For every row: export (``modules.export_row``), count the graph's MACs and compare with the torch counter, then
time the fp32 graph, the fp16 graph, the int8 graph and the same module in PyTorch eager (``torch.inference_mode``, the same
thread count) taking turns (``timing.time_interleaved``), so that the ratios between them (onnxruntime against
PyTorch, int8 against fp32) compare runs made under the same machine conditions; the two rows of a cropping pair
(``CROP_PAIRS``) take turns together, for the same reason. Rows whose runs take seconds are timed one after the
other instead, one session at a time (memory). A row's throughput is its MACs over the fp32 median; its peak
fraction divides that by the matmul probe of the same run.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from functools import partial
from dataclasses import dataclass, field
from pathlib import Path

import torch

from streamdet.benchmarks.graph_macs import GraphMacs, count_graph_macs
from streamdet.benchmarks.modules import Row, RowGraphs, export_row
from streamdet.benchmarks.ort_profile import ProfileSummary, summarize_profile
from streamdet.benchmarks.probe import row_session_config
from streamdet.benchmarks.timing import TimingConfig, TimingStats, time_callable, time_interleaved
from streamdet.runtime_ort.sessions import GraphSession

Progress = Callable[[str], None]
PROFILE_RUNS = 3  # profiled runs per graph after one warm-up: enough for a per-op split, cheap for slow rows
ROUNDS = 4  # the measurements of a row take turns in this many rounds
# (uncropped row key, cropped row key, what): the cropping targets' ratios; each pair is timed taking turns too
CROP_PAIRS = (
    ("slice_single_head", "slice_single_head_cropped", "slice graph"),
    ("conv3d", "conv3d_cropped", "lifter convolutions"),  # 3D, or the flat lifter's 2D ones
)
TORCH, TORCH_EXPORT = "PyTorch", "PyTorch on the export form"  # their names in progress lines and notes


@dataclass(frozen=True)
class TableConfig:
    threads: int = 2  # intra-op threads of onnxruntime and torch.set_num_threads
    timing: TimingConfig = field(default_factory=TimingConfig)
    torch_skip_ms: float | None = None  # skip PyTorch on rows whose first, cold fp32 run exceeds this (--quick); None: never
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
    session = GraphSession(path, row_session_config(threads, profile=True, profile_dir=profile_dir))
    feeds = row.feeds()
    for _ in range(1 + PROFILE_RUNS):  # the first run (allocations, first-touch) is in the profile too; see runs
        session.run(feeds)
    written = Path(session.end_profiling())
    target = profile_dir / f"{row.key}.{precision}.json"
    shutil.move(written, target)
    return summarize_profile(target)


def _timing_groups(rows: list[Row]) -> list[list[int]]:
    """Indices of the rows timed together: a cropping pair (its speed-up is a ratio of two rows), else one row."""
    index = {row.key: i for i, row in enumerate(rows)}
    partner = {}
    for full, cropped, _ in CROP_PAIRS:
        if full in index and cropped in index:
            partner[index[full]], partner[index[cropped]] = index[cropped], index[full]
    groups, seen = [], set()
    for i in range(len(rows)):
        if i not in seen:
            group = sorted({i, partner.get(i, i)})
            seen.update(group)
            groups.append(group)
    return groups


def _time_rows(rows: list[Row], graphs: list[RowGraphs], notes: list[list[str]], cfg: TableConfig,
               progress: Progress) -> list[dict[str, TimingStats]]:  # fmt: skip
    """Every graph and PyTorch module of the rows timed taking turns (``time_interleaved``), or one after the other
    when a run takes seconds: then turns gain little over the few repeats, and the sessions held together would
    cost gigabytes (the paper preset's benchmark: 19.6 instead of 16.2 GB resident)."""
    makers: dict[str, Callable[[], Callable[[], object]]] = {}
    slowest_ms = 0.0
    for i, (row, g) in enumerate(zip(rows, graphs)):
        for name, path in (("fp32", g.fp32), ("fp16", g.fp16), ("int8", g.int8)):
            if path is not None:
                makers[f"{i}:{name}"] = partial(_graph_runner, path, row, cfg.threads)
        first_ms = _first_run_ms(makers[f"{i}:fp32"]())  # its own session, dropped again
        slowest_ms = max(slowest_ms, first_ms)
        if cfg.torch_skip_ms is not None and first_ms > cfg.torch_skip_ms:
            notes[i].append(f"PyTorch skipped (first, cold fp32 run {first_ms:.0f} ms > {cfg.torch_skip_ms:.0f} ms, --quick)")
            continue
        makers[f"{i}:{TORCH}"] = partial(_torch_runner, row.net, row)
        if row.export_net is not None:
            makers[f"{i}:{TORCH_EXPORT}"] = partial(_torch_runner, row.export_net, row)
    torch.set_num_threads(cfg.threads)
    what = ", ".join(dict.fromkeys(key.split(":", 1)[1] for key in makers))  # each name once, in order
    if len(rows) > 1:
        what += f" of {len(rows)} rows (a cropping pair)"
    if slowest_ms > cfg.timing.slow_warmup_s * 1e3:
        progress(f"{what} one after the other (a run takes up to {slowest_ms / 1e3:.1f} s)")
        for n in notes:
            n.append(f"measured one after the other, not taking turns (a run takes up to {slowest_ms / 1e3:.1f} s)")
        stats = {key: time_callable(make(), cfg.timing) for key, make in makers.items()}  # one session at a time
    else:
        progress(f"{what} taking turns in {ROUNDS} rounds")
        stats = time_interleaved({key: make() for key, make in makers.items()}, cfg.timing, ROUNDS)
    per_row: list[dict[str, TimingStats]] = [{} for _ in rows]
    for key, st in stats.items():
        i, name = key.split(":", 1)
        per_row[int(i)][name] = st
    return per_row


def measure_rows(rows: list[Row], work_dir: Path, cfg: TableConfig, progress: Progress = lambda msg: None) -> list[RowResult]:
    """Export, count and time every row; graphs go to ``work_dir``. A cropping pair is timed together."""
    if cfg.profile_dir is not None:
        cfg.profile_dir.mkdir(parents=True, exist_ok=True)
    exported: dict[str, RowGraphs] = {}
    results: list[RowResult | None] = [None] * len(rows)
    for group in _timing_groups(rows):
        group_rows = [rows[i] for i in group]
        steps = [f"[row {i + 1}/{len(rows)}] {rows[i].module}" for i in group]
        graphs, macs, notes = [], [], []
        for row, step in zip(group_rows, steps):
            if row.graph_stem not in exported:
                progress(f"{step}: exporting fp32" + (" + fp16" if cfg.fp16 else "") + (" + int8" if cfg.int8 else ""))
                exported[row.graph_stem] = export_row(row, work_dir, cfg.fp16, cfg.int8)
            g = exported[row.graph_stem]
            m = count_graph_macs(g.model, row.input_shapes())
            n: list[str] = list(row.notes)
            if not m.complete:
                n.append(f"graph MACs unresolved at {len(m.unresolved)} node(s)")
            if g.fp16 is None and g.fp16_error is not None:
                n.append(f"fp16 conversion failed: {g.fp16_error}")
            if g.int8 is None and g.int8_error is not None:
                n.append(f"int8 quantization failed: {g.int8_error}")
            graphs.append(g)
            macs.append(m)
            notes.append(n)
        label = steps[0] if len(group) == 1 else f"{steps[0]} + row {group[1] + 1}"
        timed = _time_rows(group_rows, graphs, notes, cfg, lambda msg: progress(f"{label}: {msg}"))
        for i, row, step, g, m, n, stats in zip(group, group_rows, steps, graphs, macs, notes, timed):
            results[i] = _row_result(row, step, g, m, n, stats, cfg, progress)
    return [r for r in results if r is not None]


def _row_result(row: Row, step: str, graphs: RowGraphs, macs: GraphMacs, notes: list[str],
                stats: dict[str, TimingStats], cfg: TableConfig, progress: Progress) -> RowResult:  # fmt: skip
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
    return RowResult(
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
