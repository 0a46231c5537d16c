"""A training run's folder (``--out`` of ``streamdet-train`` and ``streamdet-train-image``): which files make a run,
what a new run may be written into, what it replaces, and what a run that never started leaves behind. Torch-free."""

from __future__ import annotations

import json
import os
import re
import stat
from pathlib import Path

from streamdet.core.constants import MANIFEST_NAME
from streamdet.core.file_output import atomic_write_file, writer_alive
from streamdet.data.splits import SPLITS_FILE
from streamdet.evaluation.saved_run import SAVED_FILES

# What a finished or running streamdet-train leaves in --out: another run there without --resume would replace it.
RUN_FILES = ("last.pt", "model.pt", "metrics.jsonl")
# config.json beside the run files: {"train": ...} for streamdet-train, {"pretrain": ...} for streamdet-train-image.
# Its top-level key tells a run's own config.json from another tool's (a model hub folder has one too).
CONFIG_FILE = "config.json"
RUN_TOOLS = {"train": "streamdet-train", "pretrain": "streamdet-train-image"}
MAX_CONFIG_BYTES = 1 << 20  # a run's config.json is a few kB: a bigger one is no run's and is not read
# Folders a training run must not be written into, told by a file only they hold: a run mixed into them replaces
# their files of the same name (config.json) or sits among files their readers list.
NOT_A_RUN = ((MANIFEST_NAME, "a streamdet export"), *((name, "a saved streamdet-eval run") for name in SAVED_FILES),
             (SPLITS_FILE, "a dataset"))  # fmt: skip
RUN_MAY_HOLD = SAVED_FILES  # NOT_A_RUN's files a run's folder may hold: an evaluation saved into it


def check_out_dir(out_dir: str | Path, run_files: tuple[str, ...], resume: str | Path | None, overwrite: bool,
                  config_key: str = "train") -> list[Path]:  # fmt: skip
    """The files of an earlier run in ``out_dir`` that a new run (no ``resume``) will replace: ValueError when there
    are some and ``overwrite`` is not set, so a finished run is never lost to a reused --out. ``out_dir`` must be new,
    empty, or a run of this tool (``config_key``: the key of its config.json, see ``check_out_contents``)."""
    if resume is not None and overwrite:
        raise ValueError("--resume continues the run in its folder and --overwrite replaces one: give only one of them")
    check_run_files_regular(out_dir, run_files)
    check_out_contents(out_dir, run_files, config_key)
    if resume is not None:
        check_resume_folder(out_dir, run_files, resume)
    found = [Path(out_dir) / name for name in run_files if (Path(out_dir) / name).is_file()]
    if found and resume is None and not overwrite:
        last = Path(out_dir) / "last.pt"
        resume_hint = f"pass --resume {last} to continue it, " if last.is_file() else ""  # a run that diverged has none
        raise ValueError(f"--out {out_dir} already holds a run ({', '.join(p.name for p in found)}): {resume_hint}"
                         "pass --overwrite to replace it, or choose another --out")  # fmt: skip
    try:  # now, not after minutes of reading the dataset: an --out that cannot be made or written
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        probe = Path(out_dir) / f".write_test_{os.getpid()}"
        probe.touch()
        probe.unlink()
    except OSError as e:
        raise ValueError(f"--out {out_dir} cannot be written: {e.strerror or e}") from None
    return found if resume is None else []


def check_run_files_regular(out_dir: str | Path, run_files: tuple[str, ...]) -> None:
    """ValueError naming the file when one of the run's files in ``out_dir`` (``run_files`` and config.json) is a
    symlink or no regular file. The run appends to or truncates metrics.jsonl in place: a FIFO there blocked the
    run for ever (--overwrite removes only regular files, so it stayed), and a link had the records written into
    whatever it points to. Refused before any work, --resume and --overwrite alike: the user removes it."""
    out = Path(out_dir)
    if not out.is_dir():
        return  # made later; a file in the way is refused by the write probe
    for name in (*run_files, CONFIG_FILE):
        path = out / name
        if path.is_symlink():
            raise ValueError(f"--out {out_dir}: {name} is a symlink (to {os.readlink(path)!r}): a run writes its own "
                             f"files, never through a link; remove {path}")  # fmt: skip
        if path.exists() and not path.is_file():
            raise ValueError(f"--out {out_dir}: {name} is not a regular file (a FIFO, a device or a folder): writing "
                             f"it would block or go elsewhere; remove {path}")  # fmt: skip


def check_resume_folder(out_dir: str | Path, run_files: tuple[str, ...], resume: str | Path) -> None:
    """ValueError naming both folders when ``out_dir`` holds a run (a run file or config.json) and ``resume`` does not
    lie in it: the continuation would replace that other run's weights and config and append to its log, a finished
    run lost without --overwrite. A resume continues in its checkpoint's own folder, or in a new or empty one (a copy
    of the run that leaves the checkpoint's folder as it was)."""
    out = Path(out_dir)
    if not out.is_dir():
        return
    held = [name for name in (*run_files, CONFIG_FILE) if os.path.lexists(out / name)]
    own = Path(resume).parent
    if not held or _same_folder(own, out):
        return
    raise ValueError(f"--resume {resume} continues the run in {own}, but --out {out_dir} holds another run "
                     f"({', '.join(held)}): resuming there would replace it; give --out {own} to continue the run in "
                     "its own folder, or a new or empty --out")  # fmt: skip


def _same_folder(a: Path, b: Path) -> bool:
    """Whether two paths name one folder (another spelling, a symlink, a bind mount)."""
    try:
        return a.resolve() == b.resolve() or os.path.samefile(a, b)
    except (OSError, RuntimeError):  # missing, or a link loop: no folder to be the same
        return False


def open_run_log(path: str | Path, append: bool):
    """``path`` (a run's metrics.jsonl) opened for text writing, appended to (a resume) or truncated (a new run);
    ValueError when it is a symlink or no regular file. check_run_files_regular refuses those before any work; this
    holds when one appears while the data is read: O_NOFOLLOW never writes through a link, O_NONBLOCK makes a FIFO
    fail (ENXIO, no reader) instead of blocking, and the descriptor is checked to be a regular file."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | (os.O_APPEND if append else os.O_TRUNC)
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as e:
        raise ValueError(f"{path} cannot be written as the run's log (a symlink, a FIFO or a device?): "
                         f"{e.strerror or e}") from None  # fmt: skip
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ValueError(f"{path} is not a regular file (a FIFO, a device or a socket): the run's log must be one; remove it")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "a" if append else "w")
    except BaseException:
        os.close(fd)
        raise


def check_out_contents(out_dir: str | Path, run_files: tuple[str, ...], config_key: str) -> None:
    """ValueError unless ``out_dir`` is missing, empty, or a run of the tool whose config.json has ``config_key``.

    A run's folder may hold files of the user's beside the run's (a note, an export made from model.pt): they are
    kept, and --overwrite replaces only the run's own files. Any other non-empty folder is refused, --overwrite or
    not: an export, a saved eval run, a dataset or another tool's folder would get a config.json replaced or a run
    mixed among its files, and --overwrite never deletes what is not a run's."""
    out = Path(out_dir)
    if not out.is_dir():
        return  # made later; a file in the way is refused by the write probe
    tool = RUN_TOOLS.get(config_key, config_key)
    try:
        names = {entry.name for entry in out.iterdir()}
    except OSError as e:
        raise ValueError(f"--out {out_dir} cannot be listed: {e.strerror or e}") from None
    config = out / CONFIG_FILE
    if CONFIG_FILE in names and not _is_run_config(config, config_key):
        raise ValueError(f"--out {out_dir} holds a {CONFIG_FILE} that is not a {tool} run's: the run would replace it; "
                         "choose another --out")  # fmt: skip
    is_run = any((out / name).exists() for name in (*run_files, CONFIG_FILE))
    for name, what in NOT_A_RUN:
        # a run's folder may hold the user's evaluation of it (streamdet-eval --save-results RUN): only an export or
        # a dataset mixed into it is refused
        if name in names and not (is_run and name in RUN_MAY_HOLD):
            raise ValueError(f"--out {out_dir} is {what} ({name}): a {tool} run must not be mixed into it; choose "
                             "another --out")  # fmt: skip
    if is_run:
        return  # a run of this tool: what else is there is the user's and stays
    foreign = sorted(n for n in names if not _is_transient(n))
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise ValueError(f"--out {out_dir} is not empty and holds no {tool} run ({shown}): a run there would mix with "
                         "those files (--overwrite replaces only a run's own files); choose a new or empty folder")  # fmt: skip


def _is_run_config(path: Path, config_key: str) -> bool:
    """Whether ``path`` is the config.json of a run of the tool whose config has ``config_key`` (a FIFO, a huge or
    unparsable file is not)."""
    try:
        if not path.is_file() or path.stat().st_size > MAX_CONFIG_BYTES:
            return False
        doc = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and config_key in doc


def _is_transient(name: str) -> bool:
    """The write probe of check_out_dir (another torchrun process may be making its own right now)."""
    return name.startswith(".write_test_")


def missing_folders(path: str | Path) -> list[Path]:
    """``path`` and those of its parents that do not exist yet, deepest first: what check_out_dir's mkdir makes."""
    missing = []
    path = Path(path).absolute()
    while not os.path.lexists(path) and path != path.parent:
        missing.append(path)
        path = path.parent
    return missing


def discard_unstarted_run(out_dir: str | Path, run_files: tuple[str, ...], made: list[Path]) -> None:
    """After a new run (no resume) failed: if it left no checkpoint and logged no record, remove its config.json and
    empty metrics.jsonl, and the folders it made (``made``, from ``missing_folders``). Such a folder holds nothing to
    resume or read, and left there it made the next attempt fail as "already holds a run".

    After a failed resume the callers call it only when this invocation made ``out_dir`` (``made`` not empty): then
    everything in it is this invocation's; a resume in an existing folder must leave that run's files alone."""
    out = Path(out_dir)
    log = out / "metrics.jsonl"
    try:
        logged = log.is_file() and log.stat().st_size > 0
        kept = [name for name in run_files if name != log.name and (out / name).exists()]
        if logged or kept:
            return
        for name in (log.name, CONFIG_FILE):
            (out / name).unlink(missing_ok=True)
    except OSError:
        return  # what cannot be checked or removed stays; the error that ended the run is the one to report
    for folder in made:
        try:
            folder.rmdir()  # only an empty folder: a cache or a user's file inside keeps it
        except OSError:
            break


# The temp file a run's atomic writes (training/checkpoint.save_atomic, trim_run_log) stage beside their target:
# ".<name>.<random>.<pid>.tmp". A SIGKILL mid-save leaves it (a Python exception removes it), for the paper preset
# hundreds of MB each; the writer's pid in its name tells a dead save's file from a live one's.
_RUN_TEMP = re.compile(r"^\.(?P<name>.+)\.[A-Za-z0-9_]+\.(?P<pid>[0-9]+)\.tmp$")


def run_temp_suffix() -> str:
    """The suffix of this process's temp files beside a run's outputs (``_RUN_TEMP``)."""
    return f".{os.getpid()}.tmp"


def write_run_file(path: str | Path, write) -> Path:
    """Write ``path`` atomically with ``write(f)`` on an open binary file (core/file_output.atomic_write_file), the
    temp named with this process's pid so that ``remove_stale_temps`` can clear it after a kill. A Ctrl-C mid-write
    (a KeyboardInterrupt) removes it and leaves ``path`` as it was."""
    return atomic_write_file(path, write, run_temp_suffix())


def remove_stale_temps(out_dir: str | Path, run_files: tuple[str, ...]) -> list[Path]:
    """Remove the temp files of ``run_files`` (``_RUN_TEMP``) in ``out_dir`` whose writer is dead (a save killed
    mid-write); the ones removed. A live writer's (another process saving right now) and anything else stay."""
    removed = []
    try:
        entries = list(Path(out_dir).iterdir())
    except OSError:
        return removed  # no folder yet, or unlistable: check_out_dir reports that
    for entry in entries:
        m = _RUN_TEMP.match(entry.name)
        if m is None or m.group("name") not in run_files or writer_alive(int(m.group("pid"))):
            continue
        try:
            if entry.is_file() and not entry.is_symlink():
                entry.unlink()
                removed.append(entry)
        except OSError:
            continue  # what cannot be removed stays; the run goes on
    return removed


def trim_run_log(path: str | Path, last_step: int) -> int:
    """Keep the records of a run's metrics.jsonl up to and including ``last_step`` (the checkpoint a resume
    continues), rewritten atomically; the count dropped. A run killed after its last checkpoint logged steps the
    resume trains again: appended after them, the log repeated that stretch (a plot or a mean counted it twice, and
    elapsed_s went backwards). A line cut short by the kill (no valid JSON, or no integer step) goes too."""
    path = Path(path)
    if not path.is_file():
        return 0
    try:
        lines = path.read_bytes().decode("utf-8", errors="replace").splitlines(keepends=True)
    except OSError as e:
        raise ValueError(f"{path} cannot be read to continue the run's log: {e.strerror or e}") from None
    keep = []
    for line in lines:
        try:
            record = json.loads(line)
        except ValueError:
            continue
        step = record.get("step") if isinstance(record, dict) else None
        if isinstance(step, int) and not isinstance(step, bool) and step <= last_step:
            keep.append(line if line.endswith("\n") else line + "\n")  # the next record must start a line
    if keep != lines:
        write_run_file(path, lambda f: f.write("".join(keep).encode("utf-8")))
    return len(lines) - len(keep)
