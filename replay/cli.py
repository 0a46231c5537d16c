"""`streamdet-replay`: play a dataset's scenes at sensor rates through the runtime and score what arrives when."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from streamdet.core.points import NUSCENES_CAMERA_HZ, NUSCENES_LIDAR_HZ
from streamdet.cli_utils import (
    FiniteFloatRange,
    MAX_INTRA_OP_THREADS,
    MAX_SLICES,
    MAX_THREADS,
    PRECISION_CHOICES,
    camera_terms_option,
    camera_timeout_option,
    camera_timeout_s,
    check_fallback_options,
    check_folder_creatable,
    check_output_parent,
    check_plot_format,
    check_results_folder,
    fallback_after_s,
    fallback_options,
    image_precision_option,
    json_output_option,
    providers_option,
    refuse_image_lane_options,
    refuse_output_over_inputs,
    refuse_same_outputs,
    scan_layout_options,

    version_option,
    dataset_inputs,
    require_export_dir,
)
from streamdet.core.file_output import write_text_atomic
from streamdet.evaluation.run_cli import OTHER_TOOLS_FOLDERS, export_reads_images
from streamdet.replay.modes import MODES
from streamdet.replay.schedule import MAX_DELIVERY_S, MAX_RATE_HZ, MAX_TIME_SCALE, MIN_RATE_HZ, MIN_TIME_SCALE
from streamdet.replay.triggers import DEFAULT_TRIGGER, TRIGGER_MODELS


# Upper bounds of the numeric options: far past any real rig or documented run (nuScenes: LiDAR 20 Hz, cameras 12 Hz,
# 20 s scenes, 1000 scenes), short of what allocates gigabytes (--camera-hz 1e9 asked for 5.7 GiB of trigger times),
# overflows the wall clock (--time-scale / --camera-delivery-ms 1e300) or sleeps for days (--time-scale 1e6).
MAX_SCENES = 10_000
MAX_DELIVERY_MS = MAX_DELIVERY_S * 1e3  # the library's bounds (replay/schedule.py), the options' ranges
MAX_SECONDS = 86_400.0  # a day of drive per scene
MAX_QUEUE = 1024  # LaneConfig's bound
OUT_FILES = ("replay.json", "report.md")  # the files --out receives
# The options of the image lane and of the cameras that feed it, by parameter name. A LiDAR-only export has neither
# (no images are even loaded), so one of them typed on the command line would be ignored, yet echoed in the report as
# if in effect: they are refused together, before any work (cli_utils.refuse_image_lane_options, as streamdet-run,
# streamdet-eval --data and streamdet-bag run refuse theirs). Their defaults are not "given" and pass. (The runtime
# refuses --image-precision and --fallback-export on its own, DetectorConfig, but only once the replay has started.)
IMAGE_LANE_OPTIONS = (
    "image_precision", "camera_hz", "camera_trigger", "camera_delivery_ms", "image_lane_threads", "schedule",
    "image_lane_nice", "image_lane_yield", "camera_terms", "fallback_export_dir", "fallback_after_ms", "camera_outages",
    "camera_timeout_ms",
)  # fmt: skip






def _scaled(timeout_s: float | None, time_scale: float) -> float | None:
    """--camera-timeout-ms (drive time) on the runner's clock, the wall's: a drive played slower sends frames slower."""
    return None if timeout_s is None else timeout_s * time_scale


def _check_outputs(json_path: Path | None, plot_path: Path | None, out_dir: Path | None, inputs) -> None:
    """Before the replay: no output may replace or lie inside an input (``inputs``: option, path pairs), nor be
    another output (--json == --plot, or one of the files --out receives), and each needs a folder to go in."""
    for path, option in ((json_path, "--json"), (plot_path, "--plot"), (out_dir, "--out")):
        refuse_output_over_inputs(path, option, inputs)
    out_files = [("--out", None if out_dir is None else out_dir / name) for name in OUT_FILES]
    refuse_same_outputs([("--out", out_dir), *out_files, ("--json", json_path), ("--plot", plot_path)])
    check_output_parent(json_path, "--json")
    check_output_parent(plot_path, "--plot")
    check_folder_creatable(out_dir, "--out")
    if plot_path is not None:
        check_plot_format(plot_path)
    # last: the note that an earlier replay's report is replaced comes only once nothing else is refused
    check_results_folder(out_dir, "--out", OUT_FILES, "replay report", OTHER_TOOLS_FOLDERS)


def _check_option_conflicts(schedule: str, image_lane_yield: int, coalesce_slices: int | None,
                            pair_hold_load: float | None, fallback_export_dir: Path | None,
                            fallback_after_ms: float | None) -> None:  # fmt: skip
    """Usage errors (exit 2) naming the options typed, before any work, for the pairs LaneConfig and DetectorConfig
    refuse only in their own field names (``image_lane_yield_slices``, exit 1)."""
    from streamdet.runtime_ort.lanes import LaneConfig

    check_fallback_options(fallback_export_dir, fallback_after_ms)
    coalesce = coalesce_slices or LaneConfig().coalesce_slices
    if pair_hold_load is not None and coalesce < 2:
        raise click.UsageError(f"--pair-hold-load {pair_hold_load:g} needs --coalesce-slices 2 or more (a held slice runs "
                               f"with its partner), got --coalesce-slices {coalesce}")  # fmt: skip
    if image_lane_yield and schedule != "phase-locked":
        raise click.UsageError(f"--image-lane-yield {image_lane_yield} needs --schedule phase-locked (the full schedule's "
                               f"update is one job that cannot hold back between quadrants), got --schedule {schedule}")  # fmt: skip


def _write(path: Path, option: str, write) -> None:
    # checked up front, but the disk can still fill or refuse: one line naming the option, not a traceback
    try:
        write(path)
    except OSError as e:
        raise click.ClickException(f"cannot write {option} {path}: {e.strerror or e}") from None


def _progress(message: str) -> None:
    # One line rewritten in place on a terminal; plain lines in a log.
    if sys.stderr.isatty():
        sys.stderr.write("\r\033[K" + message)
        sys.stderr.flush()
    else:
        sys.stderr.write(message + "\n")


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--data", type=click.Path(path_type=Path, file_okay=False), required=True,
              help="nuScenes-format dataset root (streamdet-synth output or real nuScenes tables).")
@version_option("table_version")
@click.option("--split", default="val", show_default=True, help="Scenes of this split (splits.json); 'all' for every scene.")
@click.option("--scenes", type=click.IntRange(1, MAX_SCENES), default=None,
              help=f"Play only the first N scenes of the split (1..{MAX_SCENES}).")
@click.option("--export-dir", type=click.Path(path_type=Path, file_okay=False), required=True,
              help="Export directory written by streamdet-export (holds manifest.json).")
@click.option("--precision", type=click.Choice(PRECISION_CHOICES), default="fp32", show_default=True,
              help="Precision of the slice graph.")
@image_precision_option()
@providers_option()
@click.option("--lidar-hz", type=FiniteFloatRange(MIN_RATE_HZ, MAX_RATE_HZ), default=NUSCENES_LIDAR_HZ, show_default=True,
              help=f"LiDAR rotations per second (the rotation period the slices are released over); {MIN_RATE_HZ:g}..{MAX_RATE_HZ:.0f} Hz.")
@click.option("--slices", "num_slices", type=click.IntRange(1, MAX_SLICES), default=None,
              help=f"Slices per rotation in streaming and sequential modes (1, 2 or a multiple of 4 up to {MAX_SLICES}). "
                   "Default: the export's.")
@click.option("--camera-hz", type=FiniteFloatRange(MIN_RATE_HZ, MAX_RATE_HZ), default=NUSCENES_CAMERA_HZ, show_default=True,
              help=f"Camera trigger rate; each trigger delivers the newest recorded image of every camera; "
                   f"{MIN_RATE_HZ:g}..{MAX_RATE_HZ:.0f} Hz.")
@click.option("--camera-trigger", type=click.Choice(TRIGGER_MODELS), default=DEFAULT_TRIGGER, show_default=True,
              help="How the cameras fire: 'lidar-synced' (nuScenes: each camera as the LiDAR crosses its optical axis, "
                   "at --camera-hz on average) or 'simultaneous' (all cameras at once at --camera-hz).")
@click.option("--camera-delivery-ms", type=FiniteFloatRange(0, MAX_DELIVERY_MS), default=0.0, show_default=True,
              help=f"0..{MAX_DELIVERY_MS:.0f} ms: every camera frame reaches the runtime this long after its capture (exposure, readout, ISP, "
                   "transport; real rigs: tens of ms); frames keep their capture time as timestamp, and staleness is "
                   "measured against the frames delivered by a slice's scan start. 0: delivered at capture.")
@click.option("--camera-outage", "camera_outages", multiple=True, metavar="CAM@START-END",
              help="A camera sends nothing from START to END drive seconds (END empty: to the end of each scene), e.g. "
                   "CAM_FRONT@3-8; repeat it for more. Its last frame counts until --camera-timeout-ms (phase-locked: fused; "
                   "full: the camera sets wait for it), then its features are zeros; the report says what the runtime did.")
@camera_timeout_option()
@click.option("--mode", type=click.Choice([*MODES, "all"]), default="all", show_default=True,
              help="streaming (two lanes), full-sweep (wait for the rotation), sequential (one queue), or all three.")
@click.option("--time-scale", type=FiniteFloatRange(MIN_TIME_SCALE, MAX_TIME_SCALE), default=1.0, show_default=True,
              help=f"Wall seconds per drive second ({MIN_TIME_SCALE:g}..{MAX_TIME_SCALE:.0f}): 2 plays twice as slowly, what a 2x "
                   "faster computer would see. Latencies are reported in drive time.")
@click.option("--max-seconds", type=FiniteFloatRange(0, MAX_SECONDS, min_open=True), default=None,
              help=f"Play only the first seconds of each scene (0 < s <= {MAX_SECONDS:.0f}).")
@click.option("--threads", type=click.IntRange(1, MAX_INTRA_OP_THREADS), default=1, show_default=True,
              help=f"Intra-op threads of each onnxruntime session (1..{MAX_INTRA_OP_THREADS}): per session, not in all; "
                   "the slice lane's and the image lane's run at once (so use about half the cores each), and every "
                   "session keeps its own pool (4 or more sessions: 4x the threads, asleep while idle).")
@click.option("--image-lane-threads", type=click.IntRange(1, MAX_INTRA_OP_THREADS), default=None,
              help=f"Intra-op threads of the image lane's sessions (encoder, lifter, per-camera terms; 1..{MAX_INTRA_OP_THREADS}). "
                   "Default: --threads.")
@click.option("--slice-workers", type=click.IntRange(1, MAX_THREADS), default=None,
              help=f"Slices processed at once in the slice lane (LaneConfig.max_in_flight, 1..{MAX_THREADS}). Default: the runtime's LaneConfig. "
                   "On two cores, 1 with --schedule phase-locked leaves the image lane a core of its own (docs/replay.md).")
@click.option("--queue-size", type=click.IntRange(1, MAX_QUEUE), default=None,
              help=f"Slices waiting in the slice lane before the oldest is dropped (1..{MAX_QUEUE}). Default: the runtime's LaneConfig.")
@click.option("--schedule", type=click.Choice(["full", "phase-locked"]), default="full", show_default=True,
              help="When the image lane works: 'full' (every image set, all cameras, all quadrants) or 'phase-locked' "
                   "(one quadrant at a time from its cameras, just before the LiDAR reaches it); LaneConfig.schedule.")
@click.option("--image-lane-nice", type=click.IntRange(0, 19), default=0, show_default=True,
              help="Added to the image lane's thread's nice value (Linux; 0..19): the slice lane is served first where the "
                   "lanes share cores; LaneConfig.image_lane_nice. The lane's own thread only: use it with one image-lane "
                   "thread (onnxruntime's pool threads keep nice 0).")
@click.option("--image-lane-yield", "image_lane_yield", type=click.IntRange(0, 1024), default=0, show_default=True,
              help="Phase-locked schedule only: the image lane starts no encode or lift while this many slices wait in "
                   "the slice lane's queue (0..1024; 0: never); LaneConfig.image_lane_yield_slices.")
@click.option("--coalesce-slices", type=click.IntRange(1, 64), default=None,
              help="The most waiting slices of one quadrant a slice worker detects in one run when the lane is behind "
                   "(1..64; 1: never, a full queue drops the oldest); LaneConfig.coalesce_slices. Default: the runtime's LaneConfig.")
@click.option("--pair-hold-load", type=FiniteFloatRange(0, 16), default=None,
              help="0..16: hold a quadrant's first slice for the next one and detect both in one run from when the slice lane's "
                   "measured load (a slice's run time over the slice period per worker) is above this until it is under "
                   "half of it (needs --coalesce-slices >= 2); LaneConfig.pair_hold_load. Default: the runtime's LaneConfig.")
@click.option("--freeze-heap/--no-freeze-heap", default=True, show_default=True,
              help="Freeze the Python heap alive when each drive starts out of the garbage collector's full collections "
                   "(gc.freeze, runtime_ort/heap.py), as a vehicle process would after its start-up; such a collection "
                   "otherwise stalls every thread for tens of ms mid-drive.")
@camera_terms_option()
@scan_layout_options(from_data=True)
@fallback_options(clock="drive")
@json_output_option("Write the per-mode summary (the issue's keys) to this JSON file.")
@click.option("--plot", "plot_path", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Write a PNG: a timeline of a few hundred ms of the first scene per mode, and latency CDFs.")
@click.option("--out", "out_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Write replay.json (every slice's record, per-class scores, lane CPU, stage GMAC) and report.md here. "
                   "An earlier replay's files there are replaced (a note on stderr says so); an export or a dataset folder is "
                   "refused. Default: none.")
def main(
    data: Path, table_version: str, split: str, scenes: int | None, export_dir: Path, precision: str,
    image_precision: str | None, providers: tuple[str, ...] | None, lidar_hz: float, num_slices: int | None, camera_hz: float, camera_trigger: str,
    camera_delivery_ms: float, camera_outages: tuple[str, ...], camera_timeout_ms: float, mode: str, time_scale: float,
    max_seconds: float | None, threads: int, image_lane_threads: int | None, slice_workers: int | None, queue_size: int | None, schedule: str,
    image_lane_nice: int, image_lane_yield: int, coalesce_slices: int | None, pair_hold_load: float | None, freeze_heap: bool, camera_terms: bool | None,
    scan_start_deg: float | None, clockwise: bool | None, fallback_export_dir: Path | None, fallback_after_ms: float | None, json_path: Path | None,
    plot_path: Path | None, out_dir: Path | None,
) -> None:
    """Play scenes at sensor rates (LiDAR slices released when scanned, cameras at their rate) through the runtime's
    StreamingRunner in each mode, and score every detection against the world at the moment it is emitted
    (streaming mAP) beside the same detections at their scan time (offline mAP).

    A LiDAR-only export has no image lane and no cameras: the options that steer them (--image-precision, the
    --camera-* options, --image-lane-*, --schedule, --camera-terms, --fallback-*) are refused with it."""
    from streamdet.replay.report import cpu_info, details_report, format_report, json_report
    from streamdet.replay.outages import CameraOutage
    from streamdet.replay.run import ReplayConfig, run_replay
    from streamdet.runtime_ort.lanes import LaneConfig

    inputs = [*dataset_inputs(data), ("--export-dir", export_dir), ("--fallback-export", fallback_export_dir)]
    _check_outputs(json_path, plot_path, out_dir, inputs)
    require_export_dir(export_dir)
    if not (data / table_version).is_dir():
        raise click.ClickException(f"{data / table_version} does not exist: --data must be a nuScenes-format dataset root")
    # first: with no image lane, drop them all
    refuse_image_lane_options(click.get_current_context(), export_dir, IMAGE_LANE_OPTIONS, export_reads_images)
    _check_option_conflicts(schedule, image_lane_yield, coalesce_slices, pair_hold_load, fallback_export_dir, fallback_after_ms)
    defaults = LaneConfig()
    try:
        lanes = LaneConfig(max_in_flight=slice_workers or defaults.max_in_flight, queue_size=queue_size or defaults.queue_size,
                           schedule=schedule, image_lane_nice=image_lane_nice, image_lane_yield_slices=image_lane_yield,
                           coalesce_slices=coalesce_slices or defaults.coalesce_slices,
                           pair_hold_load=defaults.pair_hold_load if pair_hold_load is None else pair_hold_load,
                           # on the runner's clock, the wall's: a drive played slower sends each camera's frames slower
                           camera_timeout_s=_scaled(camera_timeout_s(camera_timeout_ms), time_scale))  # fmt: skip
        config = ReplayConfig(
            data=data, export_dir=export_dir, version=table_version, split=None if split == "all" else split, scenes=scenes,
            precision=precision, image_precision=image_precision, lidar_hz=lidar_hz, num_slices=num_slices,
            camera_hz=camera_hz, camera_trigger=camera_trigger, modes=MODES if mode == "all" else (mode,), time_scale=time_scale,
            max_seconds=max_seconds, threads=threads, image_lane_threads=image_lane_threads, lanes=lanes, fallback_export_dir=fallback_export_dir,
            camera_terms=camera_terms, camera_delivery_ms=camera_delivery_ms, freeze_heap=freeze_heap,
            fallback_after_s=fallback_after_s(fallback_after_ms), providers=providers,
            camera_outages=tuple(CameraOutage.parse(spec) for spec in camera_outages),
            start_deg=scan_start_deg, clockwise=clockwise,
        )  # fmt: skip
        info = cpu_info()  # before the replay: a failure here must not throw a finished replay away
        result = run_replay(config, _progress)
    except (ValueError, KeyError, FileNotFoundError, OSError) as e:
        raise click.ClickException(str(e)) from None
    if sys.stderr.isatty():
        sys.stderr.write("\n")
    if scenes is not None and len(result.scenes) < scenes:
        click.echo(f"note: --scenes {scenes}, but split {split!r} holds {len(result.scenes)} scene(s): all of them were played",
                   err=True)  # fmt: skip
    report = format_report(result, info)
    click.echo(report)
    if json_path is not None:
        _write(json_path, "--json", lambda p: write_text_atomic(p, json.dumps(json_report(result, info), indent=1) + "\n"))
        click.echo(f"wrote {json_path}")
    if out_dir is not None:
        _write(out_dir, "--out", lambda p: p.mkdir(parents=True, exist_ok=True))
        _write(out_dir / OUT_FILES[0], "--out", lambda p: write_text_atomic(p, json.dumps(details_report(result, info)) + "\n"))
        _write(out_dir / OUT_FILES[1], "--out", lambda p: write_text_atomic(p, report + "\n"))
        click.echo(f"wrote {out_dir / OUT_FILES[0]} and {out_dir / OUT_FILES[1]}")
    if plot_path is not None:
        from streamdet.replay.plot import plot_replay

        _write(plot_path, "--plot", lambda p: plot_replay(result, p))
        click.echo(f"wrote {plot_path}")
