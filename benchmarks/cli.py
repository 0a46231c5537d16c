"""``streamdet-bench``: the paper's Table 3 measured on this machine, plus the streaming latencies.

``--flops-only`` prints the MAC rows alone (no timing; default preset ``paper``, to compare with the paper's
column). Otherwise every row is exported, counted and timed (benchmarks/table.py), the streaming section runs on
an export (benchmarks/streaming.py), and the targets of the benchmark issue are checked (benchmarks/report.py).
"""

from __future__ import annotations

import json
import shlex
import sys
import time
from pathlib import Path

import click

from streamdet.cli_utils import (
    GIVEN_SOURCES,
    MAX_INTRA_OP_THREADS,
    MAX_SLICES,
    MAX_THREADS,
    PRECISION_CHOICES,
    RESOLUTION_RANGE_HELP,
    check_folder_creatable,
    check_output_parent,
    check_plot_format,
    image_precision_option,
    json_output_option,
    refuse_output_over_inputs,
    refuse_same_outputs,
    resolution_callback,
)
from streamdet.core.constants import DEFAULT_PRESET
from streamdet.core.file_output import write_text_atomic
from streamdet.models.presets import get_preset, preset_names

# --quick: PyTorch eager is timed only on rows whose first, cold onnxruntime fp32 run (a fresh session's, before
# any warm-up; not the median) is faster than this
QUICK_TORCH_SKIP_MS = 200.0
MAX_REPEAT = 10_000  # timed runs per measurement: 500x the default 20; more only takes hours
# Parameters that only steer the timing: --flops-only times nothing, so one of them given with it is a mistaken
# command (the user expects an effect), refused rather than silently dropped.
TIMING_ONLY = (
    "slices", "fp16", "int8", "stream_precision", "stream_image_precision", "stream_slice_workers", "repeat", "threads",
    "quick", "plot_path", "export_dir", "profile_dir",
)  # fmt: skip


def _write(path: Path, what: str, write) -> None:
    try:
        write(path)
    except OSError as e:
        raise click.ClickException(f"cannot write {what} {path}: {e.strerror or e}") from None


def _refuse_timing_options(ctx: click.Context) -> None:
    """With --flops-only: a timing option given on the command line is refused, naming every such option."""
    given = [p for p in ctx.command.params if p.name in TIMING_ONLY and ctx.get_parameter_source(p.name) in GIVEN_SOURCES]
    if given:
        names = ", ".join("/".join([*p.opts, *p.secondary_opts]) for p in given)
        apply, them = ("apply", "them") if len(given) > 1 else ("applies", "it")  # one option: "--repeat only applies"
        raise click.UsageError(f"--flops-only counts MACs and times nothing: {names} only {apply} to timing; drop {them} "
                               "or drop --flops-only")  # fmt: skip






def _refuse_inside_profile(path: Path | None, option: str, profile_dir: Path | None) -> None:
    # the profiles are named after the rows' graphs (ROW.PRECISION.json, streaming_PHASE.GRAPH.json): a report
    # among them may be replaced by one, and is lost in a folder of hundreds of files anyway
    if path is None or profile_dir is None:
        return
    try:
        inside = profile_dir.resolve() in path.resolve().parents
    except (OSError, RuntimeError):  # a symlink loop: the write will say so
        return
    if inside:
        raise click.BadParameter(f"{str(path)!r} lies inside the --profile folder {profile_dir}, where the profiles "
                                 "are written: write it elsewhere", param_hint=option)  # fmt: skip


def _check_outputs(json_path: Path | None, plot_path: Path | None, profile_dir: Path | None, export_dir: Path | None) -> None:
    """Before any timing: no output may replace or lie inside --export-dir, nor be or lie inside another output,
    and each needs a folder it can go in."""
    for path, option in ((json_path, "--json"), (plot_path, "--plot"), (profile_dir, "--profile")):
        refuse_output_over_inputs(path, option, [("--export-dir", export_dir)])
    refuse_same_outputs([("--profile", profile_dir), ("--json", json_path), ("--plot", plot_path)])
    _refuse_inside_profile(json_path, "--json", profile_dir)
    _refuse_inside_profile(plot_path, "--plot", profile_dir)
    check_output_parent(json_path, "--json")
    check_output_parent(plot_path, "--plot")
    check_folder_creatable(profile_dir, "--profile")
    if plot_path is not None:
        check_plot_format(plot_path)


def _export_preset(given: str | None, export_preset: str, export_dir: Path) -> str:
    """The rows' preset with --export-dir (run.rows_preset): --preset, else the export's; a --preset that is not the
    export's is refused, naming both."""
    from streamdet.benchmarks.run import rows_preset

    try:
        return rows_preset(given, export_preset)
    except ValueError as e:
        if given is None:  # an export of a preset this version does not know: the rows need one named
            raise click.UsageError(f"--export-dir {export_dir}: {e} with --preset") from None
        raise click.BadParameter(f"{e} (--export-dir {export_dir})", param_hint="--preset") from None


FLOPS_UNITS = "GMAC (1e9 multiply-accumulates; FLOPs = 2 x MACs)"


def _command() -> str:
    """The command line as typed, recorded in the JSON's meta."""
    return "streamdet-bench " + shlex.join(sys.argv[1:])


def _flops_only(preset: str, resolution: tuple[int, int] | None, json_path: Path | None) -> None:
    from streamdet.benchmarks.flops_report import PAPER_RESOLUTIONS, format_rows, gmac_rows  # torch: only when needed
    from streamdet.benchmarks.provenance import provenance

    resolutions = [resolution] if resolution else PAPER_RESOLUTIONS
    rows = gmac_rows(get_preset(preset), resolutions)
    click.echo(format_rows(preset, rows))
    if json_path is not None:
        doc = {
            # the timing mode's meta keys that apply to a count (no machine: MACs do not depend on it)
            "meta": {**provenance(_command(), "flops-only"), "preset": preset, "resolutions": [list(r) for r in resolutions]},
            "units": FLOPS_UNITS,  # the key the timing mode's JSON uses
            "unit": FLOPS_UNITS,  # the same under its older key (kept for readers of older files)
            "preset": preset,  # also in meta; kept where older files had it
            "rows": [r.to_dict() for r in rows],
        }
        _write(json_path, "--json", lambda p: write_text_atomic(p, json.dumps(doc, indent=2) + "\n"))


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--flops-only", is_flag=True,
              help="Only count multiply-accumulates (GMAC) per module; time nothing. Takes --preset, --resolution and "
                   "--json; the timing options are refused with it.")
@click.option(
    "--preset",
    type=click.Choice(preset_names()),
    default=None,
    help=f"Model preset of the Table 3 rows [default: the --export-dir export's preset, as --slices; else {DEFAULT_PRESET}, "
    "the shipped model's; paper with --flops-only, to compare with the paper's column]. One that is not the --export-dir "
    "export's is refused: the rows and the streaming section would time two models.",
)
@click.option(
    "--resolution",
    callback=resolution_callback(),
    metavar="WxH",
    help="Image size of the given image row and of the export made here for the streaming section, e.g. 800x450 "
    "(default: the preset's); the other image rows are the rest of 1600x900 / 1200x675 / 800x450. An --export-dir "
    "export keeps its own size: the streaming section runs at it and --resolution sets only the rows. With "
    "--flops-only: the only image row. "
    f"Sizes: {RESOLUTION_RANGE_HELP}. Even sides of the bundled cameras' aspect only where the export is made here "
    "(timing without --export-dir); --flops-only and the rows with --export-dir count any size, odd ones included "
    "(as the paper's 1200x675 row), though streamdet-export refuses odd sides.",
)
@click.option("--slices", type=click.IntRange(1, MAX_SLICES), default=None,
              help=f"Slices per sweep of the streaming section (1, 2 or a multiple of 4 up to {MAX_SLICES}) [default: "
                   "the --export-dir export's slice count, as streamdet-run and the other tools; 8 for the export "
                   "made here without --export-dir].")
@click.option("--fp16/--no-fp16", default=True, show_default=True, help="Also time the fp16 graphs (and export them).")
@click.option("--int8/--no-int8", default=True, show_default=True,
              help="Also time int8 graphs of the rows (static QDQ, as streamdet-export --int8 writes them).")
@click.option("--stream-precision", type=click.Choice(PRECISION_CHOICES), default="fp32", show_default=True,
              help="Graphs the streaming section runs; --export-dir must hold them (streamdet-export --fp16 / --int8).")
@image_precision_option("--stream-image-precision", "stream_image_precision")
@click.option("--stream-slice-workers", type=click.IntRange(1, MAX_THREADS), default=None,
              help=f"Slice workers (LaneConfig.max_in_flight, 1..{MAX_THREADS}) of the streaming section's image-lane schedules [default: the "
              "runtime's LaneConfig]; 1 leaves the image lane a core of its own on a 2-core machine (docs/replay.md).")
@click.option("--repeat", type=click.IntRange(1, MAX_REPEAT), default=None,
              help=f"Timed runs per measurement of the Table 3 rows (each precision and PyTorch), 1..{MAX_REPEAT} [default: 20; "
                   "5 with --quick]. The streaming section has its own counts: 5 sweeps of slices per phase (2 with "
                   "--quick), 3 image updates (1), 50 runs of each pre/post-processing case (10 with --quick).")
@click.option("--threads", type=click.IntRange(1, MAX_INTRA_OP_THREADS), default=None,
              help=f"Threads for the Table 3 rows, 1..{MAX_INTRA_OP_THREADS} [default: every CPU this process may use "
                   f"(affinity, cgroup quota), at most {MAX_INTRA_OP_THREADS}].")
@click.option(
    "--quick",
    is_flag=True,
    help=f"Fewer repeats, shorter streaming runs, no PyTorch timing of rows whose first, cold fp32 run (not the "
    f"median) exceeds {QUICK_TORCH_SKIP_MS:.0f} ms.",
)
@json_output_option(
    'Write the results here: {"meta": {"schema_version": ..., ...}, "units": ..., "peak": {...}, "rows": [...], '
    '"streaming": {...}, "targets": [...]}; with --flops-only {"meta", "units", "rows"}. The keys: docs/cli.md.'
)
@click.option(
    "--plot",
    "plot_path",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write a PNG of the rows here: ms per run of each precision and PyTorch, and fp32 % of the measured peak.",
)
@click.option(
    "--export-dir",
    type=click.Path(file_okay=False, exists=True, path_type=Path),
    help="Export (streamdet-export --out) for the streaming section; default: export the preset to a temporary directory.",
)
@click.option(
    "--profile",
    "profile_dir",
    type=click.Path(file_okay=False, path_type=Path),
    help="Write onnxruntime profiles of every row graph and of the slice lane (image lane idle / busy) here; print the top ops.",
)
def main(
    flops_only: bool,
    preset: str | None,
    resolution: tuple[int, int] | None,
    slices: int | None,
    fp16: bool,
    int8: bool,
    stream_precision: str,
    stream_image_precision: str | None,
    stream_slice_workers: int | None,
    repeat: int | None,
    threads: int | None,
    quick: bool,
    json_path: Path | None,
    plot_path: Path | None,
    export_dir: Path | None,
    profile_dir: Path | None,
) -> None:
    """Measure the streaming detector's modules (the paper's Table 3) and its streaming latency on this machine."""
    from streamdet.core.sectors import check_num_slices


    try:
        if slices is not None:
            check_num_slices(slices)  # in both modes: --slices 6 is the same mistake with --flops-only
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--slices") from None
    if flops_only:
        _refuse_timing_options(click.get_current_context())
        _flops_only(preset or "paper", resolution, json_path)
        return
    _check_outputs(json_path, plot_path, profile_dir, export_dir)
    from streamdet.core.cpu import cpuid_mask

    try:
        cpuid_mask()  # the report names the kernels' instruction set: a mask variable not in effect fails now, not later
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    if export_dir is not None:
        from streamdet.benchmarks.streaming import export_unfit  # torch-free: the rows' modules load later
        from streamdet.runtime_ort.manifest import ManifestError, read_manifest

        try:
            manifest = read_manifest(export_dir)  # fail now, not after minutes of row timing
        except (ManifestError, OSError) as e:
            raise click.BadParameter(f"{export_dir} is not a usable export: {e}", param_hint="--export-dir") from None
        preset = _export_preset(preset, manifest.preset_name, export_dir)  # the rows follow the export, as --slices
        for precision, flag in ((stream_precision, "--stream-precision"), (stream_image_precision, "--stream-image-precision")):
            if precision is not None and precision not in manifest.precisions:
                raise click.BadParameter(
                    f"{export_dir} has no {precision} graphs (it has {', '.join(manifest.precisions)}); re-export with "
                    f"--{precision}", param_hint=flag,
                )  # fmt: skip
        problem = export_unfit(manifest)  # a LiDAR-only export, other cameras: also before any timing
        if problem is not None:
            raise click.BadParameter(f"{export_dir} {problem}", param_hint="--export-dir")
        if slices is None:
            slices = manifest.num_slices  # the export's, as streamdet-run, -eval, -replay, -bag and -study take it
        from streamdet.benchmarks.streaming import StreamingConfig, verify_streaming_export

        try:  # the graphs too, as the runtime opens them: a swapped graph (its sha256 updated) fails now, not after the rows
            verify_streaming_export(export_dir, StreamingConfig(precision=stream_precision, image_precision=stream_image_precision,
                                                                num_slices=slices))  # fmt: skip
        except ValueError as e:
            raise click.BadParameter(str(e), param_hint="--export-dir") from None
        except MemoryError:
            raise click.ClickException(f"out of memory opening {export_dir}") from None
    elif resolution is not None:  # the export made here for the streaming section takes it too: its rules
        if resolution[0] % 2 or resolution[1] % 2:
            raise click.BadParameter(
                f"{resolution[0]}x{resolution[1]}: the export needs even sizes (ResNet stem stride 2)", param_hint="--resolution"
            )
        from streamdet.benchmarks.run import export_resolution_problem

        problem = export_resolution_problem(resolution)  # the export's aspect rule: now, not after the rows' timing
        if problem is not None:
            raise click.BadParameter(problem, param_hint="--resolution")

    from streamdet.benchmarks.run import BenchConfig, BenchmarkError, run_benchmark, write_plot

    cfg = BenchConfig(
        preset=preset or DEFAULT_PRESET,  # with --export-dir: settled above (_export_preset)
        resolution=resolution,
        slices=slices,
        fp16=fp16,
        int8=int8,
        stream_precision=stream_precision,
        stream_image_precision=stream_image_precision,
        stream_slice_workers=stream_slice_workers,
        repeat=repeat,
        threads=threads,
        quick=quick,
        torch_skip_ms=QUICK_TORCH_SKIP_MS if quick else None,
        export_dir=export_dir,
        profile_dir=profile_dir,
        command=_command(),
    )
    started = time.perf_counter()
    try:
        result = run_benchmark(cfg, lambda msg: click.echo(f"[{time.perf_counter() - started:6.1f} s] {msg}", err=True))
    except BenchmarkError as e:
        raise click.ClickException(str(e)) from None
    click.echo(result.text())
    if json_path is not None:
        _write(json_path, "--json", lambda path: write_text_atomic(path, json.dumps(result.document(), indent=2) + "\n"))
    if plot_path is not None:
        _write(plot_path, "--plot", lambda path: write_plot(result, path))
