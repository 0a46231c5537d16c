"""Option parsing shared by the command-line tools (click and streamdet.core only: no torch)."""

from __future__ import annotations

import math
from collections.abc import Callable, Collection
from pathlib import Path

import click
from click.core import ParameterSource

from streamdet.cli_outputs import (  # noqa: F401 (re-exported: every CLI imports them from here)
    refuse_output_over_inputs, dataset_inputs, not_a_file, refuse_same_outputs, check_output_parent, check_folder_creatable, check_plot_format, require_export_dir, write_json_output,
    json_output_option, check_results_folder)
from streamdet.core.camera_timeout import DEFAULT_CAMERA_TIMEOUT_S, MAX_CAMERA_TIMEOUT_S
from streamdet.core.providers import parse_providers
from streamdet.core.constants import MAX_RESOLUTION_PX, MAX_SESSION_THREADS, MIN_RESOLUTION_PX, PRECISIONS
from streamdet.core.sectors import MAX_NUM_SLICES, check_num_slices
from streamdet.core.table_version import DEFAULT_TABLE_VERSION, table_version_problem

# Every tool that takes an image size spells it the same way, within the same bounds (core/constants.py).
RESOLUTION_HELP = "WIDTHxHEIGHT in pixels, such as 800x450"
RESOLUTION_RANGE_HELP = f"each side {MIN_RESOLUTION_PX}..{MAX_RESOLUTION_PX} px"



class FiniteFloatRange(click.FloatRange):
    """click.FloatRange that also refuses "nan" (which passes FloatRange's bounds: every comparison with it is
    false), so that no option takes a NaN into a config, a sleep or a schedule. Every CLI's float ranges use it."""

    name = "float range"

    def convert(self, value, param, ctx):
        rv = super().convert(value, param, ctx)
        if isinstance(rv, float) and math.isnan(rv):
            self.fail(f"{value!r} is not a number", param, ctx)
        return rv

def parse_resolution(
    text: str, *, min_px: int = MIN_RESOLUTION_PX, max_px: int | None = MAX_RESOLUTION_PX, multiple_of: int = 1
) -> tuple[int, int]:
    """'800x450' -> (800, 450); raises click.BadParameter quoting the bad value.

    ``multiple_of`` is the stride the image size must divide by (the ResNet stem's 2 for tools that export);
    ``min_px``/``max_px`` bound each side (default MIN_RESOLUTION_PX..MAX_RESOLUTION_PX; None: no upper bound).
    """
    shown = text if len(text) <= 40 else text[:37] + "..."
    parts = text.lower().split("x")
    # isdecimal, not isdigit: '²' is a digit int() refuses; a side of more than 9 digits is no image size (and int()
    # refuses strings of thousands of digits); leading zeros do not count: 0800x450 is 800x450
    if len(parts) != 2 or not all(p.strip().isdecimal() and len(p.strip().lstrip("0")) <= 9 for p in parts):
        if len(parts) == 2 and all(p.strip().isdecimal() for p in parts):
            raise click.BadParameter(f"width and height must be {min_px}..{max_px} pixels, got {shown!r}")
        raise click.BadParameter(f"expected {RESOLUTION_HELP}, got {shown!r}")
    width, height = (int(p) for p in parts)
    if width <= 0 or height <= 0:
        raise click.BadParameter(f"width and height must be positive, got {shown!r}")
    if width < min_px or height < min_px or (max_px is not None and (width > max_px or height > max_px)):
        bound = f"{min_px}..{max_px}" if max_px is not None else f"at least {min_px}"
        raise click.BadParameter(f"width and height must be {bound} pixels, got {shown!r}")
    if width % multiple_of or height % multiple_of:
        raise click.BadParameter(
            f"{shown!r}: width and height must be positive and even (the ResNet stem has stride {multiple_of}); "
            "they need not be multiples of 4, 800x450 works"
        )
    return width, height


def resolution_callback(*, min_px: int = MIN_RESOLUTION_PX, max_px: int | None = MAX_RESOLUTION_PX, multiple_of: int = 1):
    """A click callback for a WxH option; ``multiple=True`` options get a tuple of sizes, None stays None."""

    def callback(ctx: click.Context | None, param: click.Parameter | None, value):
        if value is None:
            return None
        if isinstance(value, tuple):
            return tuple(parse_resolution(v, min_px=min_px, max_px=max_px, multiple_of=multiple_of) for v in value)
        return parse_resolution(value, min_px=min_px, max_px=max_px, multiple_of=multiple_of)

    return callback


# Upper bounds of the numeric options the tools share: far past any documented use, short of a value that allocates
# gigabytes, overflows a clock or runs for days.
MAX_SLICES = MAX_NUM_SLICES  # slices per sweep: core.sectors' bound (sectors of 0.09 deg; the slice index column's range)


def slices_callback(ctx: click.Context, param: click.Parameter, value: int | None) -> int | None:
    """A ``--slices`` value that is no slice count (6, 0, -8) as a usage error (exit 2), not a failed run."""
    if value is not None:
        try:
            check_num_slices(value)
        except ValueError as e:
            raise click.BadParameter(f"{e} (the detector's num_slices)") from None
    return value


MAX_THREADS = 1024  # slice workers: LaneConfig's 1..1024 for the lanes
MAX_INTRA_OP_THREADS = MAX_SESSION_THREADS  # --threads of one onnxruntime session (core/constants.py)
MAX_FALLBACK_AFTER_MS = 60_000.0  # an image BEV a minute old is no image BEV


# The graph precisions an export can hold.
PRECISION_CHOICES = PRECISIONS


# ---- comma-separated lists ---------------------------------------------------------------------------------
# "8,,16" or "8,8" is a slip of the keyboard, not a request: silently dropping the empty entry or scoring one run
# or slice count twice (a run counted as two seeds, two identical JSON columns) hides it.


def split_list(text: str, option: str, what: str, key=None) -> list[str]:
    """``'a, b,c'`` -> ``['a', 'b', 'c']`` (entries stripped); click.BadParameter naming an empty or repeated entry.

    ``what`` names one entry in messages ("run", "slice count"); ``key(entry)`` is what makes two entries the same
    (default: the text itself), e.g. a resolved path, so that ``runs/A`` and ``./runs/A`` count as one.
    """
    shown = text if len(text) <= 60 else text[:57] + "..."
    entries = [e.strip() for e in text.split(",")]
    if not any(entries):
        raise click.BadParameter(f"no {what} given in {shown!r}", param_hint=option)
    seen: dict = {}
    for k, entry in enumerate(entries, start=1):
        if not entry:
            raise click.BadParameter(f"entry {k} of {shown!r} is empty (a stray comma?)", param_hint=option)
        ident = entry if key is None else key(entry)
        if ident in seen:
            raise click.BadParameter(f"{what} {entry!r} is given twice in {shown!r} (entries {seen[ident]} and {k})",
                                     param_hint=option)  # fmt: skip
        seen[ident] = k
    return entries


def image_precision_option(flag: str = "--image-precision", dest: str = "image_precision"):
    """The option that runs the image lane (encoder + lifter) in another precision than the slices."""
    return click.option(
        flag,
        dest,
        type=click.Choice(PRECISION_CHOICES),
        default=None,
        help="Run the image lane's graphs (image encoder + lifter) in this precision instead; the export must hold "
        "them. On x86 CPUs int8 here with fp32 slices halves the image lane's time (fresher camera features) "
        "and keeps the slice graph exact. Default: the same precision as the slices.",
    )


# ---- options a LiDAR-only export has no use for ---------------------------------------------------------------
# A LiDAR-only export has no image lane and no cameras: an option that steers them, typed on the command line, would
# be ignored (or refused by DetectorConfig in its own field names, once the command has started: exit 1). Every tool
# refuses such options as a usage error naming them, before any work. A default is not "given" and passes.
GIVEN_SOURCES = (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT)  # typed by the user, not a default


def options_given(ctx: click.Context, names: Collection[str]) -> list[str]:
    """The options of ``ctx``'s command among ``names`` (parameter names) given by the user, as --help spells them."""
    return ["/".join([*p.opts, *p.secondary_opts]) for p in ctx.command.params
            if p.name in names and ctx.get_parameter_source(p.name) in GIVEN_SOURCES]  # fmt: skip


def refuse_image_lane_options(ctx: click.Context, export_dir: Path, names: Collection[str],
                              reads_images: Callable[[Path], bool | None]) -> None:  # fmt: skip
    """With a LiDAR-only export: click.UsageError (exit 2) naming every option of ``names`` (parameter names) that
    was given. ``reads_images(export_dir)`` is the export's modality (manifest preset use_image), None when it is no
    readable export: then nothing is refused here and the tool's own opening of the export says what is wrong. It is
    asked only when one of the options was given (this module reads no manifest: it imports streamdet.core only)."""
    given = options_given(ctx, names)
    if not given or reads_images(export_dir) is not False:
        return
    apply, them = ("apply", "them") if len(given) > 1 else ("applies", "it")
    raise click.UsageError(f"{export_dir} is a LiDAR-only export (manifest preset use_image=false) with no image lane "
                           f"and no cameras: {', '.join(given)} only {apply} to an export with cameras; drop {them}")  # fmt: skip


def fallback_options(clock: str = "sensor"):
    """``--fallback-export`` and ``--fallback-after-ms``: the runtime's LiDAR-only fallback
    (``DetectorConfig.fallback_export_dir`` / ``fallback_after_s``), spelled the same by every tool that runs slices.
    The command gets ``fallback_export_dir`` (Path or None) and ``fallback_after_ms`` (float or None)."""
    export = click.option(
        "--fallback-export", "fallback_export_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
        help="A LiDAR-only export (streamdet-export --checkpoint models/weights/small_lidar_only.pt --out DIR) whose "
        "slice graph runs the slices that have no image BEV (DetectorConfig.fallback_export_dir). Default: none, such "
        "slices read the camera-less BEV (the lift of zero features), far weaker than the LiDAR-only model.",
    )  # fmt: skip
    after = click.option(
        "--fallback-after-ms", type=FiniteFloatRange(0, MAX_FALLBACK_AFTER_MS), default=None,
        help=f"With --fallback-export, also fall back when the image BEV is older than this ({clock} ms, "
        f"0..{MAX_FALLBACK_AFTER_MS:.0f}). Default: only without one.",
    )  # fmt: skip

    def decorate(f):
        return export(after(f))

    return decorate


def camera_timeout_option():
    """``--camera-timeout-ms``: when a camera that stopped sending is left out (core/camera_timeout.py). The command
    gets ``camera_timeout_ms`` (float; 0: never); ``camera_timeout_s`` turns it into the configs' seconds."""
    return click.option(
        "--camera-timeout-ms", type=FiniteFloatRange(0, MAX_CAMERA_TIMEOUT_S * 1e3), default=DEFAULT_CAMERA_TIMEOUT_S * 1e3,
        show_default=True,
        help="A camera that has sent no image for this long (or three of its own frame periods where longer) is left "
        "out, its features zeros, until it sends again: a dead camera's last image is not fused on. 0: never left out.",
    )  # fmt: skip


def camera_timeout_s(camera_timeout_ms: float) -> float | None:
    """``--camera-timeout-ms`` as seconds (None for 0: never)."""
    return camera_timeout_ms / 1e3 if camera_timeout_ms > 0 else None


def fallback_after_s(fallback_after_ms: float | None) -> float | None:
    """``--fallback-after-ms`` as DetectorConfig.fallback_after_s."""
    return None if fallback_after_ms is None else fallback_after_ms / 1e3


def check_fallback_options(fallback_export_dir: Path | None, fallback_after_ms: float | None) -> None:
    """A usage error (exit 2) for --fallback-after-ms without --fallback-export, in the options' names: DetectorConfig
    refuses the pair too, but as ``fallback_after_s`` and only once the command has started (exit 1)."""
    if fallback_after_ms is not None and fallback_export_dir is None:
        raise click.UsageError(f"--fallback-after-ms {fallback_after_ms:g} needs --fallback-export (a LiDAR-only export "
                               "to fall back to)")  # fmt: skip


CAMERA_TERMS = {"auto": None, "on": True, "off": False}  # --camera-terms -> DetectorConfig.camera_terms


def camera_terms_option(default: str = "auto"):
    """``--camera-terms auto|on|off``: the runtime's per-camera lifts (``DetectorConfig.camera_terms``); the command
    gets ``camera_terms`` as None / True / False."""
    return click.option(
        "--camera-terms", type=click.Choice(list(CAMERA_TERMS)), default=default, show_default=True,
        callback=lambda ctx, param, value: CAMERA_TERMS[value],
        help="Per-camera lifts for image updates (full and per-quadrant): 'auto' where the export's lifter splits "
        "(the flat lifter, fp32 or int8 image lane), 'on' required, 'off' the lifter graph every time; "
        "DetectorConfig.camera_terms.",
    )  # fmt: skip


SCAN_STARTS_DEG = ("0", "90", "180", "270")


def scan_layout_options(from_data: bool):
    """``--scan-start-deg`` and ``--clockwise/--counter-clockwise``: the LiDAR's scan layout (core/sectors.py;
    ``DetectorConfig.start_deg`` / ``clockwise``), which decides the order slices arrive in, never the points'
    features. ``from_data``: both default to None (the command reads them from its data); else 0 and
    counter-clockwise. The command gets ``scan_start_deg`` (float or None) and ``clockwise`` (bool or None)."""
    auto = " (default: from the data)" if from_data else ""

    def apply(f):
        f = click.option("--clockwise/--counter-clockwise", "clockwise", default=None if from_data else False,
                         show_default=not from_data,
                         help="Which way the LiDAR turns, seen from above: slices are numbered and released in the order "
                         f"it scans them (nuScenes' LIDAR_TOP, a Velodyne, turns clockwise){auto}.")(f)  # fmt: skip
        return click.option("--scan-start-deg", "scan_start_deg", type=click.Choice(SCAN_STARTS_DEG),
                            default=None if from_data else "0", show_default=not from_data,
                            callback=lambda ctx, param, value: None if value is None else float(value),
                            help="Azimuth (deg, LiDAR frame, counter-clockwise from +x) where the LiDAR's sweep, and slice 0, "
                            f"starts: the axis nearest its real start (nuScenes' LIDAR_TOP: 180){auto}.")(f)  # fmt: skip

    return apply


def _providers_callback(ctx, param, value: str | None):
    if value is None:
        return None
    try:
        return parse_providers(value, "--providers")
    except ValueError as e:
        raise click.BadParameter(str(e).removeprefix("--providers: "), param_hint="--providers") from None


def _version_callback(ctx, param, value):
    problem = table_version_problem(value)
    if problem is not None:
        raise click.BadParameter(problem, param_hint="--version")
    return value


def version_option(dest: str = "version", default: str = DEFAULT_TABLE_VERSION, help: str = "Table folder of the dataset under --data."):
    """``--version``: the dataset's table folder, one plain folder name under the dataset root (core/table_version.py)."""
    return click.option("--version", dest, default=default, show_default=True, callback=_version_callback, help=help)


def providers_option():
    """``--providers``: onnxruntime's execution providers of every session the command opens
    (``DetectorConfig.providers``); the command gets ``providers`` as a tuple of onnxruntime names, or None (auto)."""
    return click.option(
        "--providers", default=None, callback=_providers_callback, metavar="LIST",
        help="onnxruntime execution providers by preference, comma-separated: cpu, cuda, tensorrt (also rocm, openvino, "
        "dml, coreml, or onnxruntime's names such as CUDAExecutionProvider), or auto; the CPU is always added for ops "
        "an accelerator lacks. A provider named here that this onnxruntime lacks, or cannot start, is an error. "
        "Default: $STREAMDET_PROVIDERS, else auto: cuda,cpu where this onnxruntime has CUDA, else cpu (tensorrt only "
        "when asked: its engines take minutes to build; they are cached in $STREAMDET_TENSORRT_CACHE, else "
        "~/.cache/streamdet/tensorrt).",
    )  # fmt: skip


# ---- the edge of every command-line tool ---------------------------------------------------------------------
# The console scripts call these light functions (pyproject [project.scripts]); each imports its command inside
# `run_edge`, so a missing optional dependency, a Ctrl-C while torch loads, or a bad input deep in a library all
# end the same way: one line on stderr naming the tool and what is wrong, and a non-zero exit (130 for Ctrl-C).
# Errors outside these classes are bugs and keep their traceback.

EXIT_ERROR = 1
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports a process ended by Ctrl-C


def run_edge(module: str, prog: str, *, extra: str | None = None, args: list[str] | None = None) -> int:
    """Run the click command ``module.main`` as ``prog``; returns the exit code (``main`` style entries exit with it).

    ``extra`` names the pyproject extra that provides the command's optional dependencies (torch for export).
    """
    import importlib
    import sys

    try:
        try:
            command = importlib.import_module(module).main
        except ModuleNotFoundError as e:
            if e.name is None or e.name.split(".")[0] == "streamdet":
                raise
            return _fail(prog, _missing_package(e.name, extra))
        # click's own main() would print a bare newline on Ctrl-C and turn it into Abort: parse and invoke directly
        try:
            with command.make_context(prog, list(sys.argv[1:] if args is None else args)) as ctx:
                command.invoke(ctx)
        except ModuleNotFoundError as e:  # a command that imports its extra's packages lazily (bench: torch)
            if e.name is None or e.name.split(".")[0] not in EXTRA_MODULES.get(extra, ()):
                raise  # not the extra's: installing it would not help
            return _fail(prog, _missing_package(e.name, extra))
        return 0
    except (KeyboardInterrupt, click.exceptions.Abort):
        click.echo(f"{prog}: interrupted", err=True)
        return EXIT_INTERRUPTED
    except click.exceptions.Exit as e:
        return e.exit_code
    except click.ClickException as e:  # a usage error, or a command's own one-line error
        e.show()
        return e.exit_code
    except BrokenPipeError:  # `streamdet-x | head`: the reader left; nothing to report
        sys.stderr.close()
        return EXIT_ERROR
    except Exception as e:
        if not is_input_error(e):
            raise  # a bug: its traceback is what a report needs
        return _fail(prog, describe_error(e))


def describe_error(e: BaseException) -> str:
    """One line: what went wrong, naming the file where the error knows it."""
    if isinstance(e, UnicodeDecodeError):
        text = f"cannot decode the input as {e.encoding} text at byte {e.start} (a binary or corrupted file?)"
    elif isinstance(e, OSError) and e.filename is not None:
        text = f"{e.filename}: {e.strerror or e}"
    elif isinstance(e, RecursionError):
        text = "the input nests too deeply to read"
    elif _is_symlink_loop(e):
        text = f"{str(e).removeprefix(SYMLINK_LOOP)}: a symlink loop (a link that leads back to itself)"
    elif type(e).__module__.startswith("onnxruntime"):
        text = f"onnxruntime: {str(e).rsplit(' : ', 1)[-1]}"
    else:
        text = str(e) or type(e).__name__
    return " ".join(text.split())


def is_input_error(e: BaseException) -> bool:
    """Whether a tool reports ``e`` in one line: bad input (ValueError, and the project's named errors: any class
    defined in a streamdet module), OS and decode errors, onnxruntime's errors. Anything else is a bug."""
    if isinstance(e, (ValueError, OSError, RecursionError)):
        return True
    if _is_symlink_loop(e):
        return True
    return any(k.__module__.startswith(("streamdet.", "onnxruntime.")) for k in type(e).__mro__)


SYMLINK_LOOP = "Symlink loop from "  # how pathlib's resolve() words the RuntimeError of a link loop


def _is_symlink_loop(e: BaseException) -> bool:
    return isinstance(e, RuntimeError) and str(e).startswith(SYMLINK_LOOP)


# The top-level modules each extra of pyproject.toml installs (a late ModuleNotFoundError of another is a bug).
EXTRA_MODULES: dict[str, tuple[str, ...]] = {
    "export": ("torch", "onnxscript", "onnxconverter_common", "matplotlib"),
    "ros": ("mcap", "mcap_ros2", "rosbags"),
}
TORCH_FIRST = ("install torch first: pip install torch==2.13.0, with --index-url https://download.pytorch.org/whl/cpu for "
               "the CPU build")


def _missing_package(name: str, extra: str | None) -> str:
    if extra is None:
        return f"needs the Python package {name!r}, which is not installed"
    first = f"; {TORCH_FIRST}" if extra == "export" else ""
    return (f"needs the Python package {name!r}, which is not installed: pip install 'streamdet[{extra}]' (from a "
            f"checkout: pip install '.[{extra}]'{first})")


def _fail(prog: str, message: str) -> int:
    click.echo(f"{prog}: error: {message}", err=True)
    return EXIT_ERROR


def _entry(module: str, prog: str, extra: str | None = None):
    def main() -> None:
        raise SystemExit(run_edge(module, prog, extra=extra))

    main.__name__ = prog.replace("-", "_")
    main.__doc__ = f"Console script {prog}: {module}.main behind run_edge."
    return main


export_main = _entry("streamdet.export.cli", "streamdet-export", "export")
bench_main = _entry("streamdet.benchmarks.cli", "streamdet-bench", "export")
run_main = _entry("streamdet.evaluation.run_cli", "streamdet-run")
calib_main = _entry("streamdet.runtime_ort.calib_cli", "streamdet-calib")
synth_main = _entry("streamdet.data.synth_cli", "streamdet-synth")
train_main = _entry("streamdet.training.cli", "streamdet-train", "export")
eval_main = _entry("streamdet.evaluation.cli", "streamdet-eval")
study_main = _entry("streamdet.studies.cli", "streamdet-study")
train_image_main = _entry("streamdet.training.image_pretrain_cli", "streamdet-train-image", "export")
bag_main = _entry("streamdet.bag.cli", "streamdet-bag", "ros")
replay_main = _entry("streamdet.replay.cli", "streamdet-replay")
