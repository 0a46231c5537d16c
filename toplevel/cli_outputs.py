"""Output checks of the command-line tools, run before any work: an output must not replace or lie inside one of
the tool's inputs, two outputs must differ, a file output's folder must exist and take a file, and a report is
written atomically. The tools import these from ``streamdet.cli_utils``."""

from __future__ import annotations

import json
import os
import stat
import threading
from pathlib import Path

import click

from streamdet.core.constants import MANIFEST_NAME
from streamdet.core.file_output import write_text_atomic


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
        raise click.BadParameter("needs matplotlib (pip install matplotlib)", param_hint=option) from None
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
        hint = (f"run `streamdet-export --out {export_dir}` first (it needs PyTorch, the export extra; an export made on "
                "another machine can be copied here: the runtime itself needs no PyTorch)") if hint is None else hint
        raise click.ClickException(f"{export_dir} holds no {MANIFEST_NAME}: {hint}")


# ---- --json: one option, one rule for every tool ----------------------------------------------------------------
# `--json -` wrote a file named `-` (and `wrote -`), where a user meant stdout. Stdout is each tool's report (progress
# and notes go to stderr), so a JSON there would mix with it: `-` is refused, in words, before any work. A file named
# `-` is still written when spelled as a path (`./-`).
STDOUT_DASH = "-"
JSON_DASH_HELP = "Not '-': stdout carries the report; give a file path."


def _refuse_stdout_dash(ctx: click.Context, param: click.Parameter, value: str | None) -> Path | None:
    # the text as typed: a Path would read `./-` as `-` too
    if value is not None and value == STDOUT_DASH:
        raise click.BadParameter(f"{STDOUT_DASH!r} is not a path here: stdout carries the report (progress and notes "
                                 "go to stderr); give a file path (./- for a file named '-')",
                                 param_hint="/".join(param.opts))  # fmt: skip
    return None if value is None else Path(value)


def json_output_option(help: str, dest: str = "json_path"):
    """``--json``: the file a tool writes its figures to (a Path, or None when not given; default none). Every tool
    declares it here, so that every --json refuses ``-`` alike (``JSON_DASH_HELP`` ends its help)."""
    return click.option("--json", dest, type=click.Path(dir_okay=False), default=None,
                        callback=_refuse_stdout_dash, help=f"{help} Default: none. {JSON_DASH_HELP}")  # fmt: skip


# ---- a results folder: another tool's refused, this tool's own earlier results replaced with a note -----------
# `streamdet-run --out ds` wrote bev.png into a dataset root (after which `streamdet-synth --overwrite ds` refused the
# folder as holding other files), and a second `streamdet-eval --save-results runA` replaced a saved run, the input of
# a later --compare, without a word. A tool's results folder (eval --save-results, replay --out, run --out) must not
# be another tool's folder, and replacing the tool's own earlier results there is said.
EXPORT_FOLDER = f"a streamdet export ({MANIFEST_NAME})"


def check_results_folder(folder: Path | None, option: str, own_files, own_what: str, others=()) -> None:
    """Before any work, for ``folder`` (given as ``option``) where a tool writes ``own_files`` (its ``own_what``, e.g.
    "saved run"): click.BadParameter when it is an export (manifest.json) or a folder one of ``others`` recognises
    (callables folder -> what it is, e.g. "a dataset (world.json)", or None); else one note on stderr when it holds
    some of ``own_files``, an earlier result this run replaces. A folder that does not exist yet passes."""
    if folder is None or not Path(folder).is_dir():
        return
    folder = Path(folder)
    found = [EXPORT_FOLDER] if os.path.lexists(folder / MANIFEST_NAME) else []
    found += [what for what in (recognise(folder) for recognise in others) if what]
    if found:
        raise click.BadParameter(f"{str(folder)!r} is {found[0]}: the {own_what} must not be mixed into it (its readers "
                                 "would find these files among theirs); choose another folder", param_hint=option)  # fmt: skip
    held = [name for name in own_files if os.path.lexists(folder / name)]
    if held:
        click.echo(f"note: {option} {folder} holds an earlier {own_what} ({', '.join(held)}): this run replaces it",
                   err=True)  # fmt: skip


def write_json_output(path: Path, doc, option: str = "--json", *, indent: int | None = 1, allow_nan: bool = False) -> None:
    """``doc`` as JSON at ``path``, written atomically (a reader never sees half a report; a symlink there is replaced,
    not written through); a failure is one line naming the option. ``allow_nan=False`` refuses a non-finite figure,
    which strict JSON readers reject."""
    try:
        write_text_atomic(path, json.dumps(doc, indent=indent, allow_nan=allow_nan) + "\n")
    except (OSError, ValueError) as e:  # ValueError: a non-finite figure (allow_nan=False)
        raise click.ClickException(f"cannot write {option} {path}: {getattr(e, 'strerror', None) or e}") from None
