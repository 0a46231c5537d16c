"""``streamdet-bag``: nuScenes scenes as ROS 2 MCAP bags (``export``), detections on a bag (``run``), a bag's camera
rig as calibration.json (``calibration``)."""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import click

from streamdet.bag.deps import MissingExtraError, require
from streamdet.cli_utils import (
    MAX_SLICES,
    PRECISION_CHOICES,
    camera_timeout_option,
    camera_timeout_s,
    check_fallback_options,
    check_folder_creatable,
    check_output_parent,
    fallback_after_s,
    fallback_options,
    image_precision_option,
    providers_option,
    refuse_image_lane_options,
    refuse_output_over_inputs,
    refuse_same_outputs,
    scan_layout_options,
    split_list,

    version_option,
    dataset_inputs,
    require_export_dir,
)
from streamdet.progress import counted

LIBRARY_ERRORS = (ValueError, KeyError, FileNotFoundError, OSError, MissingExtraError)
# run's options that only an export with cameras can use (parameter names): given with a LiDAR-only export, they are
# refused before any work, named (DetectorConfig refuses the first two too, but in its own field names, exit 1)
RUN_IMAGE_LANE_OPTIONS = ("image_precision", "fallback_export_dir", "fallback_after_ms")


# A bag is usually an irreplaceable drive recording (README's drive.mcap, car.mcap): `bag export --out` over one
# replaced it with rc 0. As `ros2 bag record -o` refuses an existing bag, export and run replace a file only on
# request. The write itself is atomic either way (a temporary file renamed when complete).
OVERWRITE_HELP = ("Replace an existing --out. Default: an existing file is refused (a recording is not replaced by "
                  "accident); the file is replaced only once the new one is complete.")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """ROS 2 bags in and out, viewable in Foxglove, without a ROS installation (needs the ros extra: `pip install 'streamdet[ros]'`, from a checkout `pip install '.[ros]'`)."""


@main.command("export")
@click.option("--data", "data_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="A nuScenes-format dataset folder (tables under VERSION/, e.g. streamdet-synth output), or a folder in "
                   "the bundled sample's layout (calibration.json). Default: the bundled real nuScenes sample.")
@click.option("--scene", default=None, help="Scene name (e.g. synth-0-0000). Default: the only scene of the dataset.")
@version_option()
@click.option("--out", type=click.Path(path_type=Path, dir_okay=False), required=True,
              help="The .mcap bag to write; an existing file is refused unless --overwrite is given.")
@click.option("--overwrite", is_flag=True, help=OVERWRITE_HELP)
def export_cmd(data_dir: Path | None, scene: str | None, version: str, out: Path, overwrite: bool) -> None:
    """Write one scene as the ROS 2 MCAP bag a car records: /LIDAR_TOP, /CAM_*/image_rect_compressed,
    /CAM_*/camera_info, /tf, /tf_static and the ground truth on /markers/annotations."""
    from streamdet.bag.export import export_recording
    from streamdet.bag.recording import read_recording
    from streamdet.data.sample import bundled_sample_dir

    try:
        _require_extra()
        recording = read_recording(data_dir, scene, version)  # reads the tables alone: --data is checked first
    except LIBRARY_ERRORS as e:
        raise click.ClickException(_one_line(e)) from None
    # the bag is written while the dataset's files are read: it must be none of them, nor lie among them
    data = ("--data", data_dir) if data_dir is not None else ("--data (default: the bundled sample)", bundled_sample_dir())
    refuse_output_over_inputs(out, "--out", dataset_inputs(data[1], data[0]))
    _check_output(out, "--out")
    _refuse_existing(out, "--out", overwrite)
    try:
        with counted(f"writing {out}") as progress:  # one step per sensor message
            summary = export_recording(recording, out, progress=progress)
    except LIBRARY_ERRORS as e:
        raise click.ClickException(_one_line(e)) from None
    click.echo(
        f"scene {summary.scene}: {summary.num_sweeps} sweeps ({summary.num_key_frames} key frames), "
        f"{summary.num_images} images, {summary.num_messages} messages over {summary.duration_s:.2f} s"
    )
    click.echo(f"wrote {summary.path}")


@main.command("run")
@click.option("--bag", "bag_path", type=click.Path(path_type=Path, exists=True), required=True,
              help="The input bag: a .mcap file, or a rosbag2 folder holding one.")
@click.option("--export-dir", type=click.Path(path_type=Path, file_okay=False), required=True,
              help="Export directory written by streamdet-export (holds manifest.json).")
@click.option("--out", type=click.Path(path_type=Path, dir_okay=False), required=True,
              help="The .mcap bag to write: the input topics plus /streamdet/detections and /streamdet/markers. An "
                   "existing file is refused unless --overwrite is given.")
@click.option("--results", "results_json", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="Where to write the nuScenes results JSON (an existing file is refused unless --overwrite is given). "
                   "Default: beside --out, named after it (det.mcap: det.results_nusc.json).")
@click.option("--overwrite", is_flag=True,
              help="Replace an existing --out and results JSON. Default: an existing one is refused (a recording is not "
                   "replaced by accident); each is replaced only once its new file is complete.")
@click.option("--topics", default=None,
              help="Topic names of a bag recorded elsewhere, KEY=/topic comma-separated: lidar, tf, tf_static, a camera "
                   "name (its image topic) or CAMERA.info (its CameraInfo topic; default: camera_info beside the image "
                   "topic). E.g. lidar=/points_raw,CAM_FRONT=/camera/front/image/compressed")
@click.option("--slice-per-message", is_flag=True,
              help="The LiDAR driver publishes slices: each message is one slice (its sector found from its points). "
                   "A message whose points do not fit in one slice's sector (a full sweep) is refused: leave the flag "
                   "off for a driver that publishes full sweeps, which are then cut into slices.")
@click.option("--ego-frame", default="base_link", show_default=True, help="TF frame of the vehicle.")
@click.option("--global-frame", default="map", show_default=True,
              help="TF frame of the ego poses; 'none' for a stack without localisation (ego motion between the LiDAR "
                   "and camera times is then ignored).")
@click.option("--slices", "num_slices", type=click.IntRange(1, MAX_SLICES), default=None,
              help="Slices per sweep (1, 2 or a multiple of 4). Default: the number the export was made for.")
@click.option("--precision", type=click.Choice(PRECISION_CHOICES), default="fp32", show_default=True,
              help="Which graphs of the export to run.")
@image_precision_option()
@providers_option()
@fallback_options(clock="bag time")
@camera_timeout_option()
@scan_layout_options(from_data=True)
@click.option("-v", "--verbose", is_flag=True, help="Log providers and sessions.")
def run_cmd(bag_path: Path, export_dir: Path, out: Path, results_json: Path | None, topics: str | None,
            slice_per_message: bool, ego_frame: str, global_frame: str, num_slices: int | None, precision: str,
            image_precision: str | None, providers: tuple[str, ...] | None, fallback_export_dir: Path | None, fallback_after_ms: float | None,
            camera_timeout_ms: float, scan_start_deg: float | None, clockwise: bool | None, verbose: bool,
            overwrite: bool = False) -> None:  # fmt: skip
    """Detect every LiDAR message of a bag in recorded order (images first when new ones arrived) and write the
    detections per slice as ROS 2 topics, stamped with the slice's scan time, plus the nuScenes results JSON."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(message)s")
    check_fallback_options(fallback_export_dir, fallback_after_ms)  # a usage error in the options' names, first
    require_export_dir(export_dir)
    from streamdet.evaluation.run_cli import export_reads_images

    # a LiDAR-only export has no image lane and is itself what a fallback runs: a usage error naming the options typed
    refuse_image_lane_options(click.get_current_context(), export_dir, RUN_IMAGE_LANE_OPTIONS, export_reads_images)
    from streamdet.bag.run import RunConfig, results_path_of, run_bag
    from streamdet.bag.topics import TopicMap
    from streamdet.runtime_ort.stats import format_latency
    from streamdet.runtime_ort.detector import DetectorConfig

    _check_run_outputs(bag_path, export_dir, fallback_export_dir, out, results_json, results_path_of(out, results_json),
                       overwrite)
    try:
        _require_extra()
        config = RunConfig(
            topics=TopicMap.parse(topics),
            detector=DetectorConfig(precision=precision, image_lane_precision=image_precision, num_slices=num_slices,
                                    fallback_export_dir=fallback_export_dir, providers=providers,
                                    fallback_after_s=fallback_after_s(fallback_after_ms)),
            start_deg=scan_start_deg,
            clockwise=clockwise,
            slice_per_message=slice_per_message,
            ego_frame=ego_frame,
            global_frame=None if global_frame.lower() == "none" else global_frame,
            camera_timeout_s=camera_timeout_s(camera_timeout_ms),  # on the header stamps
        )
        with _sweep_counter() as progress:
            summary = run_bag(bag_path, export_dir, out, results_json, config, progress=progress)
    except LIBRARY_ERRORS as e:
        raise click.ClickException(_one_line(e)) from None
    if sys.stderr.isatty():
        click.echo("", err=True)
    click.echo(
        f"{summary.num_sweeps} sweeps, {summary.num_slices} slices, {summary.num_image_sets} image sets "
        f"({summary.precision}, {', '.join(summary.providers)}, cameras {list(summary.cameras) or 'none'}): "
        f"{summary.num_detections} detections"
    )
    click.echo(summary.scan_layout)
    if summary.num_clouds_repeated or summary.num_clouds_behind:  # said: the sweep count is not the bag's LiDAR count
        click.echo(f"LiDAR messages not detected for their header stamp (copied to --out as recorded): "
                   f"{summary.num_clouds_repeated} stamped as one already read (republished, recorded twice), "
                   f"{summary.num_clouds_behind} stamped before one already read (a clock step back?)")  # fmt: skip
    if summary.num_duplicate_keys:
        click.echo(f"{summary.num_duplicate_keys} sweeps had the results key of an earlier one (the bag's sample tokens "
                   "give two stamps one token) and were left out of the results JSON, the first kept")  # fmt: skip
    if summary.input_dropped:  # the input is itself a run's output: its detections are not mixed with these
        click.echo("not copied from the input (this run writes these topics): "
                   + ", ".join(f"{n} messages on {topic}" for topic, n in summary.input_dropped.items()))
    if fallback_export_dir is not None:
        click.echo(f"{summary.num_fallback_slices} of {summary.num_slices} slices ran the LiDAR-only fallback "
                   f"({fallback_export_dir}): no image BEV for their quadrants"
                   + ("" if fallback_after_ms is None else f", or one older than {fallback_after_ms:g} ms"))  # fmt: skip
    if summary.cameras_without_info:
        click.echo(f"no CameraInfo for {list(summary.cameras_without_info)} at some image sets: the calibration in use "
                   "stayed (the export's until the bag's was complete); name their topics with --topics CAM.info=/topic")  # fmt: skip
    if summary.cameras_timed_out:
        said = ", ".join(f"{c} {n}x" for c, n in summary.cameras_timed_out.items())
        click.echo(f"cameras that stopped sending for --camera-timeout-ms and were left out (their features zeros): {said}")
    if summary.cameras_lagging:
        click.echo(f"{list(summary.cameras_lagging)} sent images stamped more than --camera-timeout-ms behind the LiDAR's and "
                   "were left out for it: is their clock synchronised with the LiDAR's?")  # fmt: skip
    click.echo(format_latency(summary.latency_ms))
    click.echo(f"wrote {summary.bag_out}")
    click.echo(f"wrote {summary.results_json}")


@main.command("calibration")
@click.option("--bag", "bag_path", type=click.Path(path_type=Path, exists=True), required=True,
              help="The bag: a .mcap file, or a rosbag2 folder holding one.")
@click.option("--out", type=click.Path(path_type=Path, dir_okay=False), required=True,
              help="The calibration.json to write (for streamdet-calib lut, or StreamingDetector.set_calibration).")
@click.option("--topics", default=None, help="Topic names of a bag recorded elsewhere, as for `run`.")
@click.option("--cameras", default=None,
              help="Comma-separated camera names in the export's order. Default: the nuScenes cameras whose image "
                   "topic the bag holds (in nuScenes order), then any other camera --topics names.")
@click.option("--ego-frame", default="base_link", show_default=True, help="TF frame of the vehicle.")
@click.option("--global-frame", default="map", show_default=True,
              help="TF frame of the ego poses; 'none' for a stack without localisation.")
def calibration_cmd(bag_path: Path, out: Path, topics: str | None, cameras: str | None, ego_frame: str,
                    global_frame: str) -> None:  # fmt: skip
    """Write the bag's camera rig (CameraInfo + TF at its first complete image set) as calibration.json."""
    from streamdet.bag.calibration import rig_from_bag, write_calibration_json
    from streamdet.bag.topics import TopicMap

    refuse_output_over_inputs(out, "--out", _bag_inputs(bag_path))
    _check_output(out, "--out")
    names = split_list(cameras, "--cameras", "camera") if cameras is not None else None
    try:
        _require_extra()
        rig, stamp = rig_from_bag(bag_path, TopicMap.parse(topics), names, ego_frame,
                                  None if global_frame.lower() == "none" else global_frame)  # fmt: skip
        write_calibration_json(rig, out, note=f"{bag_path.name} at LiDAR stamp {stamp} ns")
    except LIBRARY_ERRORS as e:
        raise click.ClickException(_one_line(e)) from None
    click.echo(f"rig of {len(rig)} cameras {list(rig.names)} at LiDAR stamp {stamp} ns")
    click.echo(f"wrote {out}")


def _bag_inputs(bag_path: Path) -> list[tuple[str, Path]]:
    """The input paths of ``--bag``: the bag itself and, for a .mcap inside a rosbag2 folder (metadata.yaml beside
    it), that folder: an output written into it would become part of the recording (a second .mcap makes the
    folder unreadable as one bag)."""
    inputs = [("--bag", bag_path)]
    if bag_path.is_file() and (bag_path.parent / "metadata.yaml").is_file():
        inputs.append(("--bag's rosbag2 folder", bag_path.parent))
    return inputs


def _check_run_outputs(bag_path: Path, export_dir: Path, fallback_export_dir: Path | None, out: Path,
                       results_json: Path | None, results_path: Path, overwrite: bool = False) -> None:  # fmt: skip
    """`run` writes the output bag and the results JSON: neither may replace or land inside an input (the bag, the
    exports), nor be the other one, nor replace an existing file without --overwrite. Checked before the export is
    loaded."""
    results_option = "--results" if results_json is not None else "--results (default: beside --out)"
    if bag_path.is_file() and out.resolve() == bag_path.resolve():  # the commonest slip, in run_bag's own words
        raise click.BadParameter(f"{str(out)!r} is the input bag (--bag); write the detections to another file",
                                 param_hint="--out")  # fmt: skip
    inputs = [*_bag_inputs(bag_path), ("--export-dir", export_dir), ("--fallback-export", fallback_export_dir)]
    refuse_output_over_inputs(out, "--out", inputs)
    refuse_output_over_inputs(results_path, results_option, inputs)
    refuse_same_outputs([("--out", out), (results_option, results_path)])
    _check_output(out, "--out")
    _check_output(results_path, results_option)
    _refuse_existing(out, "--out", overwrite)
    _refuse_existing(results_path, results_option, overwrite)


def _refuse_existing(path: Path, option: str, overwrite: bool) -> None:
    """click.BadParameter (exit 2) when ``path`` (given as ``option``) exists and ``overwrite`` is not set."""
    if overwrite or not (path.exists() or path.is_symlink()):
        return
    another = "another --out" if option == "--out" or option.endswith("(default: beside --out)") else f"another {option}"
    raise click.BadParameter(f"{str(path)!r} exists: pass --overwrite to replace it, or choose {another}", param_hint=option)


def _check_output(path: Path, option: str) -> None:
    """check_output_parent, except that a missing folder is fine (the bag tools create it): then the nearest
    existing ancestor must be a folder, so that creating it cannot fail after the work."""
    parent = path.parent if str(path.parent) else Path(".")
    if parent.exists():
        check_output_parent(path, option)
    else:
        check_folder_creatable(parent, option)


@contextlib.contextmanager
def _sweep_counter() -> Iterator[Callable[[int], None]]:
    """The count of sweeps done (the bag's total is not known): rewritten in place on a terminal, lines in a log."""
    if sys.stderr.isatty():
        yield lambda done: click.echo(f"\rsweeps detected: {done}", nl=False, err=True)
        return
    with counted("sweeps detected") as progress:
        yield progress


def _require_extra() -> None:
    """Fail before any work when the ``ros`` extra is missing."""
    for module in ("mcap.reader", "mcap_ros2.writer", "mcap_ros2.decoder"):
        require(module)


def _one_line(e: BaseException) -> str:
    text = str(e.args[0]) if isinstance(e, KeyError) and e.args else str(e)
    return " ".join(text.split())
