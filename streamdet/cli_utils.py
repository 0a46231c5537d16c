"""Option parsing shared by the command-line tools (click and streamdet.core only: no torch)."""

from __future__ import annotations

import json
import math
import os
import stat
import threading
from pathlib import Path

import click

from streamdet.core.camera_timeout import DEFAULT_CAMERA_TIMEOUT_S, MAX_CAMERA_TIMEOUT_S
from streamdet.core.providers import parse_providers
from streamdet.core.file_output import write_text_atomic
from streamdet.core.constants import MANIFEST_NAME, MAX_RESOLUTION_PX, MAX_SESSION_THREADS, MIN_RESOLUTION_PX, PRECISIONS
from streamdet.core.sectors import MAX_NUM_SLICES
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


# ---- outputs that would replace inputs ---------------------------------------------------------------------
# `--json ds/splits.json` replaced a dataset's split file and `--json runs/A/results.json` a saved run: a tool's
# output must not be one of its inputs nor lie inside an input folder (a dataset, an export, a run), where it
# would replace or pollute what the next run reads.


def _real(path: Path) -> Path:
    try:
        return Path(path).resolve()  # symlinks too: a link to an input is that input
    except (OSError, RuntimeError):  # a symlink loop: compare the spelled path
        return Path(path).absolute()


def refuse_output_over_inputs(output: Path | None, option: str, inputs) -> None:
    """Raise click.BadParameter if ``output`` (a file or folder the tool writes, given as ``option``) is one of
    ``inputs`` — pairs (option, path or None) — or lies inside an input folder. None entries are skipped."""
    if output is None:
        return
    out = _real(output)
    ancestors = _existing_ancestors(out)
    for in_option, path in inputs:
        if path is None:
            continue
        inp = _real(path)
        same = out == inp
        if not same and output.exists() and Path(path).exists():
            try:
                same = os.path.samefile(output, path)  # a hard link or a bind mount of the input
            except OSError:
                pass
        if same:
            raise click.BadParameter(f"{str(output)!r} is the input {in_option} {path}: writing there would replace "
                                     "or add to that input; choose another path", param_hint=option)  # fmt: skip
        if inp in out.parents or _same_as_any(inp, ancestors):
            raise click.BadParameter(f"{str(output)!r} lies inside the input {in_option} {path}: write outside the "
                                     "tool's inputs", param_hint=option)  # fmt: skip
    _refuse_hard_link(output, option)


def dataset_inputs(data_dir: Path | None, option: str = "--data") -> list[tuple[str, Path]]:
    """The input pairs a dataset stands for in ``refuse_output_over_inputs``: its root, and the entries of it that
    are symlinks (its table folder above all, which the tools read as ``DATA/<version>``): an output beside a
    link's target is inside the dataset though outside ``data_dir``."""
    if data_dir is None:
        return []
    pairs = [(option, Path(data_dir))]
    try:
        links = sorted(e for e in Path(data_dir).iterdir() if e.is_symlink())
    except OSError:  # no folder (yet): the tool's own check names it
        links = []
    pairs += [(f"{option}'s {e.name} (a link to {_real(e)})", e) for e in links]
    return pairs


def _refuse_hard_link(output: Path, option: str) -> None:
    """An existing output file with another name too (a hard link) would be written through: a link made inside a
    dataset or a saved run (``ln ds/splits.json out.json``) is that input's file, wherever the link lies."""
    try:
        st = os.stat(output)
    except OSError:  # absent (the usual case), or unreadable: the write says why
        return
    if stat.S_ISREG(st.st_mode) and st.st_nlink > 1:
        raise click.BadParameter(f"{str(output)!r} is a hard link of another file ({st.st_nlink} names): writing "
                                 "would change that file too; remove the link or choose another path", param_hint=option)  # fmt: skip


def _existing_ancestors(path: Path) -> list[Path]:
    """The folders above ``path`` that exist (a case-insensitive file system or a bind mount can make one of them an
    input folder under another spelling: ``os.path.samefile`` tells)."""
    return [a for a in path.parents if a.exists()]


def _same_as_any(folder: Path, candidates: list[Path]) -> bool:
    if not folder.is_dir():
        return False
    for candidate in candidates:
        try:
            if os.path.samefile(folder, candidate):
                return True
        except OSError:
            continue
    return False


def not_a_file(path: Path) -> str:
    """Why ``path``, which is no regular file, cannot be read as one: for a one-line error after the path."""
    return "is not a regular file (a folder, a FIFO or a device?)" if Path(path).exists() else "does not exist"


def refuse_same_outputs(outputs) -> None:
    """Raise click.BadParameter if two of ``outputs`` — pairs (option, path or None) — are the same file (spelled
    alike, through a symlink, or a hard link): the later write would replace the earlier one."""
    seen: list[tuple[str, Path, Path]] = []
    for option, path in outputs:
        if path is None:
            continue
        real = _real(path)
        for other_option, other, other_real in seen:
            same = real == other_real
            if not same and Path(path).exists() and other.exists():
                try:
                    same = os.path.samefile(path, other)
                except OSError:
                    pass
            if same:
                raise click.BadParameter(f"{str(path)!r} is also the {other_option} file: one would replace the other",
                                         param_hint=option)  # fmt: skip
        seen.append((option, Path(path), real))


def check_output_parent(output: Path | None, option: str) -> None:
    """Raise click.BadParameter, before any work, if ``output`` (a file to write) could not be created: its folder
    is missing or not a folder, takes no new file (read-only, /proc: a file made and removed at once tells, where
    access checks pass every root process), or ``output`` is a folder, a FIFO, a device, a broken link or a loop."""
    if output is None:
        return
    output = Path(output)
    if output.is_dir():
        raise click.BadParameter(f"{str(output)!r} is a folder; give a file path", param_hint=option)
    if output.exists() and not output.is_file():  # through a link too: /dev/stdout, a FIFO (opening it would block)
        raise click.BadParameter(f"{str(output)!r} is not a regular file (a FIFO, a device or a socket): writing "
                                 "would block or go elsewhere; give a file path", param_hint=option)  # fmt: skip
    if output.is_symlink() and not output.exists():
        raise click.BadParameter(f"{str(output)!r} is a broken link or a link loop; give a file path", param_hint=option)
    parent = output.parent if str(output.parent) else Path(".")
    if not parent.is_dir():
        raise click.BadParameter(f"the folder of {str(output)!r} does not exist (or is not a folder)", param_hint=option)
    probe = parent / f".streamdet-write-probe-{os.getpid()}-{threading.get_ident()}"
    try:
        os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
    except OSError as e:
        raise click.BadParameter(f"cannot write into the folder of {str(output)!r}: {e.strerror or e}", param_hint=option) from None
    try:
        os.unlink(probe)
    except OSError:
        pass


def check_folder_creatable(folder: Path | None, option: str) -> None:
    """Raise click.BadParameter, before any work, if ``folder`` (made with its parents after the work) could not be:
    it, or its nearest existing ancestor, is not a folder, or it is a broken link or a link loop (found only when the
    work was done, as "File exists")."""
    if folder is None:
        return
    for existing in (Path(folder), *Path(folder).absolute().parents):
        if existing.is_symlink() and not existing.exists():
            raise click.BadParameter(f"{str(folder)!r} cannot be made: {existing} is a broken link or a link loop",
                                     param_hint=option)  # fmt: skip
        if existing.exists():
            if not existing.is_dir():
                raise click.BadParameter(f"{str(folder)!r} cannot be made: {existing} is not a folder", param_hint=option)
            return


def check_plot_format(plot_path: Path | None, option: str = "--plot") -> None:
    """Raise click.BadParameter, before any work, unless matplotlib can write ``plot_path``: it is installed and the
    suffix names one of its formats (savefig picks the format from it, and fails only once the figure is drawn; no
    suffix is its default, PNG). matplotlib is imported only here, for a plot that was asked for."""
    if plot_path is None:
        return
    try:
        from matplotlib.backend_bases import FigureCanvasBase
    except ImportError:
        raise click.BadParameter("needs matplotlib (pip install matplotlib, or '.[dev]' in the streamdet checkout)", param_hint=option) from None
    suffix = Path(plot_path).suffix[1:].lower()
    formats = FigureCanvasBase.get_supported_filetypes()
    if suffix and suffix not in formats:
        raise click.BadParameter(f"cannot write {option} {plot_path}: matplotlib has no .{suffix} format (it writes "
                                 f"{', '.join('.' + f for f in sorted(formats))})", param_hint=option)  # fmt: skip


def require_export_dir(export_dir: Path, hint: str | None = None) -> None:
    """A one-line error (exit 1) before any work unless ``export_dir`` holds a manifest; ``hint``: how to make one
    (default: the streamdet-export command for that folder). A manifest that is a FIFO or a folder is named by the
    manifest reader later."""
    if not (export_dir / MANIFEST_NAME).exists():
        hint = f"run `streamdet-export --out {export_dir}` first" if hint is None else hint
        raise click.ClickException(f"{export_dir} holds no {MANIFEST_NAME}: {hint}")


def write_json_output(path: Path, doc, option: str = "--json", *, indent: int | None = 1, allow_nan: bool = False) -> None:
    """``doc`` as JSON at ``path``, written atomically (a reader never sees half a report; a symlink there is replaced,
    not written through); a failure is one line naming the option. ``allow_nan=False`` refuses a non-finite figure,
    which strict JSON readers reject."""
    try:
        write_text_atomic(path, json.dumps(doc, indent=indent, allow_nan=allow_nan) + "\n")
    except (OSError, ValueError) as e:  # ValueError: a non-finite figure (allow_nan=False)
        raise click.ClickException(f"cannot write {option} {path}: {getattr(e, 'strerror', None) or e}") from None


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
            hint = f": pip install '.[{extra}]' in the streamdet checkout (install torch first: pip install torch==2.13.0, with --index-url https://download.pytorch.org/whl/cpu for the CPU build)" if extra else ""
            return _fail(prog, f"needs the Python package {e.name!r}, which is not installed{hint}")
        # click's own main() would print a bare newline on Ctrl-C and turn it into Abort: parse and invoke directly
        with command.make_context(prog, list(sys.argv[1:] if args is None else args)) as ctx:
            command.invoke(ctx)
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
