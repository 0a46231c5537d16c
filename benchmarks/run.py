"""One benchmark run, end to end: probe, Table 3 rows, probe again, export, streaming section, targets.

``streamdet-bench`` is a thin wrapper over ``run_benchmark``; the result renders as the text report and the JSON
document (benchmarks/report.py).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from streamdet.benchmarks import report
from streamdet.core.constants import DEFAULT_PRESET
from streamdet.benchmarks.flops_report import PAPER_RESOLUTIONS, slice_row_pillars
from streamdet.benchmarks.modules import build_rows
from streamdet.benchmarks.probe import OtherCpuUse, ProbeConfig, ProbeResult, machine_info, measure_peak
from streamdet.benchmarks.provenance import manifest_sha256, provenance
from streamdet.benchmarks.streaming import (
    StreamingConfig,
    StreamingResult,
    check_streaming_export,
    measure_streaming,
    profile_streaming,
)
from streamdet.benchmarks.table import ROUNDS, RowResult, TableConfig, measure_rows
from streamdet.benchmarks.thread_counts import check_session_threads, default_session_threads
from streamdet.benchmarks.timing import TimingConfig
from streamdet.models.presets import Preset, get_preset, preset_names

Progress = Callable[[str], None]


class BenchmarkError(Exception):
    """A problem with the benchmark's inputs (the export, the export directory), stated in one line."""


DEFAULT_SLICES = 8  # slices per sweep of the export the benchmark makes itself (no export_dir)


@dataclass(frozen=True)
class BenchConfig:
    # the Table 3 rows' preset; None: export_dir's (its manifest's preset_name), or DEFAULT_PRESET (the shipped
    # model's) without one. One given that differs from export_dir's is refused (resolve_stream_export).
    preset: str | None = None
    resolution: tuple[int, int] | None = None  # (W, H) of the given image row and the streaming export; None: preset's
    slices: int | None = None  # slices per sweep of the streaming section; None: export_dir's, or DEFAULT_SLICES
    fp16: bool = True  # also export and time fp16 graphs
    int8: bool = True  # also quantize and time int8 graphs of the rows
    stream_precision: str = "fp32"  # graphs of the streaming section (the export made here includes them)
    stream_image_precision: str | None = None  # its image lane's graphs; None: stream_precision
    stream_slice_workers: int | None = None  # slice workers of its image-lane schedules; None: LaneConfig's default
    repeat: int | None = None  # timed runs per measurement; None: 20, or 5 with quick
    threads: int | None = None  # threads of the row measurements (1..64); None: every usable CPU, at most 64
    quick: bool = False  # fewer repeats, shorter streaming runs
    # no PyTorch timing of rows whose first, cold onnxruntime fp32 run exceeds this (table.TableConfig.torch_skip_ms:
    # one run of a fresh session, taken before the warm-up, not the median)
    torch_skip_ms: float | None = None
    export_dir: Path | None = None  # existing export for the streaming section; None: export to a temporary folder
    profile_dir: Path | None = None  # onnxruntime profiles of every row graph
    command: str = ""  # the command line, recorded in the metadata

    @property
    def given_resolution(self) -> tuple[int, int]:
        if self.resolution is not None:
            return self.resolution
        image = get_preset(self.preset or DEFAULT_PRESET).image  # before resolve_stream_export: None is the default's
        return image.width_px, image.height_px

    def timing(self) -> TimingConfig:
        if self.quick:
            repeat = self.repeat or 5
            # TimingConfig refuses a floor above the count: --repeat 1 asks for one run
            return TimingConfig(repeat=repeat, warmup=1, budget_s=2.0, min_repeat=min(2, repeat), slow_warmup_s=1.0)
        return TimingConfig(repeat=self.repeat or 20, warmup=2, budget_s=15.0)  # min_repeat: 3, or repeat where fewer

    def row_threads(self) -> int:
        """Threads of the rows and the peak probe: ``threads``, or every CPU this process may use, at most
        MAX_SESSION_THREADS (benchmarks/thread_counts.py); ValueError for a ``threads`` outside 1..MAX_SESSION_THREADS."""
        if self.threads is None:
            return default_session_threads()
        return check_session_threads(self.threads, "BenchConfig.threads")

    def probe(self) -> ProbeConfig:
        return ProbeConfig(size=1024, runs=4, warmup=1) if self.quick else ProbeConfig()

    def streaming(self) -> StreamingConfig:
        cfg = StreamingConfig(num_slices=self.slices, precision=self.stream_precision, image_precision=self.stream_image_precision,
                              schedule_slice_workers=self.stream_slice_workers)  # fmt: skip
        return dataclasses.replace(cfg, sweeps=2, image_updates=1, queue_sweeps=1, schedule_seconds=1.0) if self.quick else cfg


@dataclass(frozen=True)
class BenchResult:
    meta: dict
    peak: ProbeResult  # both probes' runs: the best of them is the peak the rows are divided by
    rows: tuple[RowResult, ...]
    streaming: StreamingResult
    targets: tuple[report.Target, ...]
    probes: tuple[ProbeResult, ProbeResult] | None = None  # the probe at the start and at the end, apart

    def text(self) -> str:
        return report.format_report(self.meta, self.rows, self.peak, self.streaming, self.targets, self.probes)

    def document(self) -> dict:
        return report.build_document(self.meta, self.rows, self.peak, self.streaming, self.targets, self.probes)


def image_resolutions(given: tuple[int, int]) -> list[tuple[int, int]]:
    """The given resolution first, then the paper's others (all three of them when the given one is not the paper's)."""
    return [given] + [r for r in PAPER_RESOLUTIONS if r != given]


def _export(cfg: BenchConfig, out_dir: Path, progress: Progress) -> str | None:
    """The export library's run (what streamdet-export does); a warning when its parity checks failed."""
    from streamdet.export.exporter import ExportError, ExportOptions, run_export

    streamed = (cfg.stream_precision, cfg.stream_image_precision)

    opts = ExportOptions(
        preset=cfg.preset, resolution=cfg.given_resolution, num_slices=cfg.slices, out_dir=str(out_dir),
        fp16=cfg.fp16 or "fp16" in streamed, int8="int8" in streamed,
    )
    try:
        result = run_export(opts, report=lambda msg: progress(f"  export: {msg}"))
    except ExportError as e:
        raise BenchmarkError(f"exporting {cfg.preset} for the streaming section: {e}") from None
    if result.parity_passed:
        return None
    return "the export's parity checks failed (see its manifest.json); latencies are still valid"


def _slice_pillars(preset: Preset) -> dict:
    """What the slice rows' 30,000 points became (benchmarks/sweep_pillars.py)."""
    full, crop = slice_row_pillars(preset, cropped=False), slice_row_pillars(preset, cropped=True)
    return {"uncropped": full.num_pillars, "cropped": crop.num_pillars, "cropped_quadrant": crop.quadrant}


def export_resolution_problem(resolution: tuple[int, int]) -> str | None:
    """Why the export the benchmark makes for the streaming section (no ``export_dir``) would refuse images of
    ``resolution`` (width, height), as the end of a sentence that starts with the option's name; None where it takes
    them. The export's own rules, not a copy: ``export.options.check_resolution`` (sides even and in range) and
    ``calibration.lut.check_rig_fits`` against the rig it exports with (``export.graph_steps.load_rig(None)``, the
    bundled calibration: images must have its cameras' aspect). Reads one file, so it runs before any timing: the
    export itself runs after the rows, minutes later."""
    from streamdet.calibration.camera import CalibrationError
    from streamdet.calibration.lut import check_rig_fits
    from streamdet.data.synth_writer import fitting_resolutions
    from streamdet.export.graph_steps import load_rig
    from streamdet.export.options import ExportError, check_resolution

    width, height = resolution
    try:
        check_resolution(width, height)
    except ExportError as e:
        return str(e)
    try:
        rig, source = load_rig(None)  # the calibration _export's ExportOptions leave at the default
    except (CalibrationError, ExportError) as e:  # a damaged install: the export would fail the same way
        return f"the export made for the streaming section cannot read its calibration: {e}"
    try:
        check_rig_fits(rig, rig.names, width, height)
    except (CalibrationError, ExportError) as e:
        near = " or ".join(f"{w}x{h}" for w, h in fitting_resolutions(width, height, rig))
        return (f"{width}x{height} does not fit the calibration of the export made for the streaming section ({source}): {e}; "
                f"give a size of the cameras' aspect" + (f" (nearest: {near})" if near else ""))  # fmt: skip
    return None


def rows_preset(given: str | None, export_preset: str | None) -> str:
    """The preset of the Table 3 rows: ``given``, else the export's (``export_preset``, the streaming export's
    manifest ``preset_name``; None: no export given, the benchmark makes one of the rows' preset), else
    DEFAULT_PRESET. A ValueError, naming both, where ``given`` is not the export's preset: the rows and the
    streaming section would time two models under one report and one set of targets. An export whose preset this
    version does not know (a renamed preset) needs ``given``: then the rows are of ``given``, the streaming section
    of the export, and the report names each."""
    if export_preset is None:
        return given or DEFAULT_PRESET
    known = export_preset in preset_names()
    if given is None:
        if known:
            return export_preset
        raise ValueError(f"the export's preset {export_preset!r} is not one this version knows ({', '.join(preset_names())}): "
                         "name the preset of the Table 3 rows")  # fmt: skip
    if known and given != export_preset:
        raise ValueError(f"{given!r} is not the export's preset {export_preset!r}: the Table 3 rows and the streaming "
                         f"section would time two models in one report; leave the preset out (the rows follow the "
                         f"export) or give an export of {given!r}")  # fmt: skip
    return given


def resolve_stream_export(cfg: BenchConfig) -> BenchConfig:
    """``cfg`` with its preset (``rows_preset``) and slice count settled, after checking that the streaming section
    can time ``export_dir`` (``streaming.check_streaming_export``: camera + LiDAR, the streamed precisions' graphs,
    the bundled sample's cameras) and that every thread count the run will use (``row_threads``, the streaming section's) is one a
    session takes. Without ``export_dir``, that the export the benchmark makes takes its image size
    (``export_resolution_problem``). ``slices`` None becomes the export's count, or DEFAULT_SLICES for the export
    the benchmark makes; ``preset`` None becomes the export's, or DEFAULT_PRESET, and one that differs from the
    export's is refused. Raises BenchmarkError; reads files only, so it runs before any timing."""
    try:
        cfg.row_threads()
        stream = cfg.streaming()  # StreamingConfig checks its own thread and worker counts
    except ValueError as e:
        raise BenchmarkError(str(e)) from None
    if cfg.export_dir is None:
        problem = export_resolution_problem(cfg.given_resolution)
        if problem is not None:
            raise BenchmarkError(f"BenchConfig.resolution: {problem}")
        slices = DEFAULT_SLICES if cfg.slices is None else cfg.slices
        return dataclasses.replace(cfg, preset=rows_preset(cfg.preset, None), slices=slices)
    try:
        manifest = check_streaming_export(cfg.export_dir, stream)
    except ValueError as e:
        raise BenchmarkError(f"streaming section: {e}") from None
    try:
        preset = rows_preset(cfg.preset, manifest.preset_name)
    except ValueError as e:
        raise BenchmarkError(f"BenchConfig.preset: {e} (BenchConfig.export_dir {cfg.export_dir})") from None
    return dataclasses.replace(cfg, preset=preset, slices=manifest.num_slices if cfg.slices is None else cfg.slices)


def run_benchmark(cfg: BenchConfig, progress: Progress = lambda msg: None) -> BenchResult:
    cfg = resolve_stream_export(cfg)  # a wrong export fails now, not after minutes of row timing
    preset = get_preset(cfg.preset)
    threads = cfg.row_threads()
    timing = cfg.timing()
    other_cpu = OtherCpuUse()
    started = time.perf_counter()
    meta = {
        **provenance(cfg.command, "timing"),  # schema_version, mode, streamdet_version, git_commit, git_dirty, date, command
        "preset": cfg.preset,
        "resolutions": [list(r) for r in image_resolutions(cfg.given_resolution)],
        "slices": cfg.slices,
        "threads": threads,
        "repeat": timing.repeat,
        "warmup": timing.warmup,
        "budget_s": timing.budget_s,
        "min_repeat": timing.min_repeat,  # the runs a measurement cut by its budget still gets, spread over the rounds
        "rounds": ROUNDS,
        "settle_s": timing.settle_s,
        "quick": cfg.quick,
        "fp16": cfg.fp16,
        "int8": cfg.int8,
        "stream_precision": cfg.stream_precision,
        "stream_image_precision": cfg.stream_image_precision or cfg.stream_precision,
        "export_dir": str(cfg.export_dir) if cfg.export_dir is not None else "(temporary export)",
        # the manifest names every graph and the LUT by sha256: this names the export timed (set once it exists)
        "export_manifest_sha256": None,
        "machine": machine_info(threads),
        "slice_pillars": _slice_pillars(preset),
    }
    with tempfile.TemporaryDirectory(prefix="streamdet_bench_") as tmp:
        work = Path(tmp)
        progress(f"peak probe ({threads} threads)")
        peak_start = measure_peak(threads, cfg.probe())
        progress(f"building the {cfg.preset} rows")
        rows = build_rows(preset, image_resolutions(cfg.given_resolution))
        table_cfg = TableConfig(
            threads=threads,
            timing=timing,
            torch_skip_ms=cfg.torch_skip_ms,
            profile_dir=cfg.profile_dir,
            fp16=cfg.fp16,
            int8=cfg.int8,
        )
        results = measure_rows(rows, work, table_cfg, progress)
        del rows  # the paper preset's modules and inputs hold gigabytes
        progress("peak probe again (the best run of both counts: the machine is shared)")
        peak_end = measure_peak(threads, cfg.probe())
        peak = peak_start.merged(peak_end)  # the report shows both apart too: a drift flags a slowed host

        stream_dir = cfg.export_dir
        if stream_dir is None:
            stream_dir = work / "export"
            w, h = cfg.given_resolution
            progress(f"exporting {cfg.preset} at {w}x{h}, {cfg.slices} slices for the streaming section")
            warning = _export(cfg, stream_dir, progress)
            if warning:
                progress(f"warning: {warning}")
                meta["export_warning"] = warning
        meta["export_manifest_sha256"] = manifest_sha256(stream_dir)
        try:
            streaming = measure_streaming(stream_dir, cfg.streaming(), progress)
            if cfg.profile_dir is not None:
                profiles = profile_streaming(stream_dir, cfg.streaming(), cfg.profile_dir, progress)
                streaming = dataclasses.replace(streaming, profiles=profiles)
        except ValueError as e:  # a foreign or broken export directory
            raise BenchmarkError(f"streaming section on {stream_dir}: {e}") from None
    meta["seconds"] = round(time.perf_counter() - started, 1)
    meta["other_cpu_use"] = other_cpu.cores()
    targets = report.evaluate_targets(results, peak, streaming)
    return BenchResult(meta, peak, tuple(results), streaming, tuple(targets), (peak_start, peak_end))


def write_plot(result: BenchResult, path: Path) -> Path:
    from streamdet.benchmarks.plot import plot_rows

    m = result.meta
    title = f"streamdet {m['preset']}, {m['machine']['cpu_model']}, {m['threads']} threads"
    return plot_rows(result.rows, path, title, result.peak.gflops_per_s)

