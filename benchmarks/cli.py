"""``streamdet-bench``: the paper's Table 3 measured on this machine, plus the streaming latencies.

``--flops-only`` prints the MAC rows alone (no timing; default preset ``paper``, to compare with the paper's
column). Otherwise every row is exported, counted and timed (benchmarks/table.py), the streaming section runs on
an export (benchmarks/streaming.py), and the targets of the benchmark issue are checked (benchmarks/report.py).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

import click

from streamdet.models.presets import get_preset, preset_names

QUICK_TORCH_SKIP_MS = 200.0  # --quick: PyTorch eager is timed only on rows faster than this in onnxruntime fp32


def parse_resolution(ctx: click.Context | None, param: click.Parameter | None, value: str | None) -> tuple[int, int] | None:
    """'800x450' -> (800, 450)."""
    if value is None:
        return None
    parts = value.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise click.BadParameter(f"expected WIDTHxHEIGHT in pixels like 800x450, got {value!r}", ctx=ctx, param=param)
    w, h = (int(p) for p in parts)
    if w < 1 or h < 1:
        raise click.BadParameter(f"width and height must be positive, got {value!r}", ctx=ctx, param=param)
    return w, h


def image_resolutions(given: tuple[int, int]) -> list[tuple[int, int]]:
    """The given resolution first, then the paper's others (all three of them when the given one is not the paper's)."""
    from streamdet.benchmarks.flops_report import PAPER_RESOLUTIONS  # torch import: only when needed

    return [given] + [r for r in PAPER_RESOLUTIONS if r != given]


def _write(path: Path, what: str, write) -> None:
    try:
        write(path)
    except OSError as e:
        raise click.ClickException(f"cannot write {what} {path}: {e.strerror or e}") from None


def _flops_only(preset: str, resolution: tuple[int, int] | None, json_path: Path | None) -> None:
    from streamdet.benchmarks.flops_report import PAPER_RESOLUTIONS, format_rows, gmac_rows  # torch: only when needed

    rows = gmac_rows(get_preset(preset), [resolution] if resolution else PAPER_RESOLUTIONS)
    click.echo(format_rows(preset, rows))
    if json_path is not None:
        doc = {
            "preset": preset,
            "unit": "GMAC (1e9 multiply-accumulates; FLOPs = 2 x MACs)",
            "rows": [r.to_dict() for r in rows],
        }
        _write(json_path, "--json", lambda p: p.write_text(json.dumps(doc, indent=2) + "\n"))


def export_for_streaming(preset: str, resolution: tuple[int, int], slices: int, fp16: bool, out_dir: Path, progress) -> str | None:
    """Export with the export library (streamdet-export's function); returns a warning when its parity checks failed."""
    from streamdet.export.exporter import ExportError, ExportOptions, run_export

    opts = ExportOptions(preset=preset, resolution=resolution, num_slices=slices, fp16=fp16, out_dir=str(out_dir))
    try:
        result = run_export(opts, report=lambda msg: progress(f"  export: {msg}"))
    except ExportError as e:
        raise click.ClickException(f"exporting {preset} for the streaming section: {e}") from None
    return None if result.parity_passed else f"the export's parity checks failed (see {out_dir}/manifest.json); latencies are still valid"


@click.command()
@click.option("--flops-only", is_flag=True, help="Only count multiply-accumulates (GMAC) per module; time nothing.")
@click.option(
    "--preset",
    type=click.Choice(preset_names()),
    default=None,
    help="Model preset to measure [default: small; paper with --flops-only, to compare with the paper's column].",
)
@click.option(
    "--resolution",
    callback=parse_resolution,
    metavar="WxH",
    help="Image size of the given image row and of the streaming export, e.g. 800x450 (default: the preset's); the "
    "other image rows are the rest of 1600x900 / 1200x675 / 800x450. With --flops-only: the only image row.",
)
@click.option("--slices", type=click.IntRange(min=1), default=8, show_default=True, help="Slices per sweep of the streaming section.")
@click.option("--fp16/--no-fp16", default=True, show_default=True, help="Also time the fp16 graphs (and export them).")
@click.option("--repeat", type=click.IntRange(min=1), default=None, help="Timed runs per measurement [default: 20; 5 with --quick].")
@click.option("--threads", type=click.IntRange(min=1), default=None, help="Threads for the Table 3 rows [default: all cores].")
@click.option(
    "--quick",
    is_flag=True,
    help=f"Fewer repeats, shorter streaming runs, no PyTorch timing of rows whose fp32 run exceeds {QUICK_TORCH_SKIP_MS:.0f} ms.",
)
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), help='Write {"rows": [...], "streaming": {...}, ...} here.')
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), help="Write a PNG bar chart of the rows here.")
@click.option(
    "--export-dir",
    type=click.Path(file_okay=False, exists=True, path_type=Path),
    help="Export (streamdet-export --out) for the streaming section; default: export the preset to a temporary directory.",
)
@click.option("--profile", "profile_dir", type=click.Path(file_okay=False, path_type=Path), help="Write onnxruntime profiles of every row graph here and print the top ops.")
def main(
    flops_only: bool,
    preset: str | None,
    resolution: tuple[int, int] | None,
    slices: int,
    fp16: bool,
    repeat: int | None,
    threads: int | None,
    quick: bool,
    json_path: Path | None,
    plot_path: Path | None,
    export_dir: Path | None,
    profile_dir: Path | None,
) -> None:
    """Measure the streaming detector's modules (the paper's Table 3) and its streaming latency on this machine."""
    if flops_only:
        _flops_only(preset or "paper", resolution, json_path)
        return
    try:
        from streamdet.calibration.grid import check_num_slices

        check_num_slices(slices)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--slices") from None
    for path, what in ((json_path, "--json"), (plot_path, "--plot")):
        if path is not None and not path.parent.is_dir():
            raise click.BadParameter(f"folder {str(path.parent)!r} does not exist", param_hint=what)
    if export_dir is not None:
        from streamdet.export.manifest import ManifestError, read_manifest

        try:
            read_manifest(export_dir)  # fail now, not after minutes of row timing
        except (ManifestError, OSError) as e:
            raise click.BadParameter(f"{export_dir} is not a usable export: {e}", param_hint="--export-dir") from None
    preset = preset or "small"
    p = get_preset(preset)
    given = resolution or (p.image.width_px, p.image.height_px)
    repeat = repeat or (5 if quick else 20)
    threads = threads or os.cpu_count() or 1
    started = time.perf_counter()

    def progress(msg: str) -> None:
        click.echo(f"[{time.perf_counter() - started:6.1f} s] {msg}", err=True)

    from streamdet.benchmarks import report
    from streamdet.benchmarks.modules import build_rows
    from streamdet.benchmarks.probe import OtherCpuUse, ProbeConfig, machine_info, measure_peak
    from streamdet.benchmarks.streaming import StreamingConfig, measure_streaming
    from streamdet.benchmarks.table import TableConfig, measure_rows
    from streamdet.benchmarks.timing import TimingConfig

    if quick:
        timing = TimingConfig(repeat=repeat, warmup=1, budget_s=2.0, min_repeat=2, slow_warmup_s=1.0)
    else:
        timing = TimingConfig(repeat=repeat, warmup=2, budget_s=15.0)
    other_cpu = OtherCpuUse()
    meta = {
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "command": "streamdet-bench " + shlex.join(sys.argv[1:]),
        "preset": preset,
        "resolutions": [list(r) for r in image_resolutions(given)],
        "slices": slices,
        "threads": threads,
        "repeat": repeat,
        "warmup": timing.warmup,
        "budget_s": timing.budget_s,
        "quick": quick,
        "fp16": fp16,
        "machine": machine_info(threads),
    }
    with tempfile.TemporaryDirectory(prefix="streamdet_bench_") as tmp:
        work = Path(tmp)
        probe_cfg = ProbeConfig(size=1024, runs=4, warmup=1) if quick else ProbeConfig()
        progress(f"peak probe ({threads} threads)")
        peak = measure_peak(threads, probe_cfg)
        progress(f"building the {preset} rows")
        rows = build_rows(p, image_resolutions(given))
        table_cfg = TableConfig(threads=threads, timing=timing, torch_skip_ms=QUICK_TORCH_SKIP_MS if quick else None, profile_dir=profile_dir, fp16=fp16)
        results = measure_rows(rows, work, table_cfg, progress)
        del rows  # the paper preset's modules and inputs hold gigabytes
        progress("peak probe again (the best run of both counts: the machine is shared)")
        peak = peak.merged(measure_peak(threads, probe_cfg))

        stream_dir = export_dir
        if stream_dir is None:
            stream_dir = work / "export"
            progress(f"exporting {preset} at {given[0]}x{given[1]}, {slices} slices for the streaming section")
            export_warning = export_for_streaming(preset, given, slices, fp16, stream_dir, progress)
            if export_warning:
                progress(f"warning: {export_warning}")
                meta["export_warning"] = export_warning
        stream_cfg = StreamingConfig(num_slices=slices)
        if quick:
            stream_cfg = dataclasses.replace(stream_cfg, sweeps=2, image_updates=1, queue_sweeps=1)
        try:
            streaming = measure_streaming(stream_dir, stream_cfg, progress)
        except ValueError as e:  # a foreign or broken --export-dir
            raise click.ClickException(f"streaming section on {stream_dir}: {e}") from None
        meta["export_dir"] = str(export_dir) if export_dir is not None else "(temporary export)"
        meta["seconds"] = round(time.perf_counter() - started, 1)
        meta["other_cpu_use"] = other_cpu.cores()

        targets = report.evaluate_targets(results, peak, streaming)
        click.echo(report.format_report(meta, results, peak, streaming, targets))
        if json_path is not None:
            doc = report.build_document(meta, results, peak, streaming, targets)
            _write(json_path, "--json", lambda path: path.write_text(json.dumps(doc, indent=2) + "\n"))
        if plot_path is not None:
            from streamdet.benchmarks.plot import plot_rows

            title = f"streamdet {preset}, {meta['machine']['cpu_model']}, {threads} threads"
            _write(plot_path, "--plot", lambda path: plot_rows(results, path, title))
    progress("done")
