"""Staging and commit of an export directory: all files are written into a temporary directory beside the target and
renamed into place at the end (manifest last), so a failed or interrupted export never leaves a directory that looks
complete, and an older export is replaced only by a finished one.

Every staging folder this module makes (``.<out>.partial-<pid>-*`` for the export being written, ``.<out>.old-<pid>-*``
for the previous export moved aside during the commit) holds a marker file naming its writer's pid
(``STAGING_MARKER``). A later export removes only such folders whose writer no longer runs: a folder that merely
has the name (a user's, another tool's) is never touched. The partial folder's marker is removed just before the
folder is renamed into place, so an export never carries it."""

from __future__ import annotations

import glob
import json
import os
import shutil
import stat
import tempfile
from pathlib import Path

import onnx

from streamdet.core.file_input import read_regular_file
from streamdet.core.file_output import writer_alive
from streamdet.export.fp16 import check_model
from streamdet.export.options import ExportError
from streamdet.runtime_ort.manifest import MANIFEST_NAME, graph_file_name


STAGING_MARKER = ".streamdet-export-staging"  # in every staging folder made here; only such folders are ever removed
STAGING_MARKER_TEXT = "streamdet export staging folder of pid"
_MAX_MARKER_BYTES = 256


def _mark(folder: Path) -> None:
    """Write the marker that makes ``folder`` one of this module's staging folders (``_is_marked``)."""
    (folder / STAGING_MARKER).write_text(f"{STAGING_MARKER_TEXT} {os.getpid()}\n", encoding="ascii")


def _is_marked(folder: Path, pid: int) -> bool:
    """Whether ``folder`` (no symlink) holds the marker of a staging folder written by process ``pid``: a regular
    file (not a link) with exactly the text ``_mark`` writes."""
    marker = folder / STAGING_MARKER
    try:
        if folder.is_symlink() or not folder.is_dir():
            return False
        st = os.lstat(marker)
        if not stat.S_ISREG(st.st_mode) or st.st_size > _MAX_MARKER_BYTES:
            return False
        return marker.read_text(encoding="ascii") == f"{STAGING_MARKER_TEXT} {pid}\n"
    except (OSError, UnicodeDecodeError):
        return False


def _stale_dirs(parent: Path, name: str) -> list[tuple[str, Path]]:
    """("partial" | "old", path) of staging folders beside ``name`` left by an export process that no longer runs
    (killed with SIGKILL, or the machine went down); the writer's pid is part of the folder's name and of its
    marker (``STAGING_MARKER``). A folder without the marker is not one of ours, whatever its name: never listed."""
    stale = []
    for kind in ("partial", "old"):
        for path in parent.glob(f".{glob.escape(name)}.{kind}-*-*"):
            pid = path.name[len(f".{name}.{kind}-"):].split("-", 1)[0]
            if not (pid.isdigit() and len(pid) <= 10):
                continue
            if int(pid) != os.getpid() and not writer_alive(int(pid)) and _is_marked(path, int(pid)):
                stale.append((kind, path))
    return stale


def clean_stale_staging(out_dir: Path) -> None:
    """Remove what a killed export left beside out_dir; a previous export it had moved aside is put back first."""
    out_dir = out_dir.absolute()
    for kind, path in _stale_dirs(out_dir.parent, out_dir.name):
        moved_aside = path / "export"
        if kind == "old" and not out_dir.exists() and (moved_aside / MANIFEST_NAME).is_file():
            os.replace(moved_aside, out_dir)  # killed between the two renames of commit_staging_dir
        shutil.rmtree(path, ignore_errors=True)


# Files a streamdet process writes into an export besides those its manifest names: onnxruntime profiles
# (DetectorConfig.enable_profiling writes <graph>.profile_<time>.json beside the graph).
_PROFILE_SUFFIX = ".json"
_PROFILE_MARK = ".profile_"
MAX_OLD_MANIFEST_BYTES = 64 << 20  # runtime_ort's own cap on a manifest is far below; a bigger file is no manifest


def check_replaceable(out_dir: Path, what: str | None = None) -> None:
    """ExportError unless ``out_dir`` is absent, empty, or a streamdet export holding nothing but its own files.

    A re-export replaces the whole folder, so a ``manifest.json`` alone is not enough: a web app's has the same
    name. The manifest must be a streamdet one (its ``graphs`` and ``preset``), and every entry must be a file it
    names, the manifest, or an onnxruntime profile of one of its graphs; anything else (a note, a calibration copy, a
    folder) would be deleted with it, so the folder is refused, naming those entries. ``what``: how the error names
    the folder (default ``--out <out_dir>``; ``check_parity_failed_dir`` names the folder beside it)."""
    what = f"--out {out_dir}" if what is None else what
    try:
        entries = sorted(out_dir.iterdir()) if out_dir.is_dir() else []
    except OSError as e:
        raise ExportError(f"{what} cannot be listed: {e.strerror or e}") from None
    if not entries:
        return
    named = _export_files(out_dir)
    if named is None:
        raise ExportError(f"{what} is a non-empty directory that is not a streamdet export (no streamdet "
                          "manifest.json); refusing to overwrite it")  # fmt: skip
    foreign = [e.name + ("/" if e.is_dir() else "") for e in entries if not _is_export_entry(e, named)]
    if foreign:
        shown = ", ".join(foreign[:6]) + (f" and {len(foreign) - 6} more" if len(foreign) > 6 else "")
        raise ExportError(f"{what} holds a streamdet export and other entries ({shown}), which a re-export "
                          "would delete with it: move them out, or choose another --out")  # fmt: skip


def _export_files(out_dir: Path) -> set[str] | None:
    """The names of the files the manifest of ``out_dir`` lists (itself included), None if it is no streamdet
    manifest. Read leniently: an export of an older version, or one whose graphs a hand edit broke, is still one."""
    try:
        raw = read_regular_file(out_dir / MANIFEST_NAME, MAX_OLD_MANIFEST_BYTES)
        doc = json.loads(raw)
    except (ValueError, OSError, RecursionError):  # InputFileError and JSONDecodeError are ValueErrors
        return None
    if not isinstance(doc, dict) or not isinstance(doc.get("graphs"), list) or not isinstance(doc.get("preset"), dict):
        return None
    names = {MANIFEST_NAME}
    for entry in [*doc["graphs"], doc.get("lut")]:
        if isinstance(entry, dict) and isinstance(entry.get("file"), str):
            names.add(entry["file"])
    return names


def _is_export_entry(entry: Path, named: set[str]) -> bool:
    if entry.is_symlink() or not entry.is_file():
        return False
    if entry.name in named:
        return True
    graph, mark, _ = entry.name.partition(_PROFILE_MARK)  # image_encoder.int8.profile_2026-12-05_08-25-13_754.json
    return bool(mark) and entry.name.endswith(_PROFILE_SUFFIX) and f"{graph}.onnx" in named


def make_staging_dir(out_dir: Path) -> Path:
    """A fresh temp dir beside out_dir (same filesystem, so the final rename is atomic); checks writability early.

    Staging folders left by an export that was killed (SIGKILL: no cleanup ran) are removed first."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"--out {out_dir} exists and is not a directory")
    check_replaceable(out_dir)
    parent = out_dir.absolute().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        clean_stale_staging(out_dir)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-{os.getpid()}-", dir=parent))
    except OSError as e:
        raise ExportError(f"--out {out_dir}: cannot write into {parent}: {e.strerror or e}") from None
    try:
        tmp.chmod(0o755)  # mkdtemp makes it private; the export is an ordinary directory
        _mark(tmp)
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise ExportError(f"--out {out_dir}: cannot write into {tmp}: {e.strerror or e}") from None
    return tmp


def check_out_dir_name(out_dir: str | os.PathLike) -> None:
    """ExportError unless ``out_dir`` (as spelled) names a folder the export can be renamed onto: not empty, not the
    root, not a path ending in '..', and not the current folder. An export is staged beside its --out and renamed
    into place, so even an empty current folder is no target: the rename would swap the folder the calling shell
    stands in for a new one, and leave the shell in a deleted folder that shows nothing."""
    raw = os.fspath(out_dir)
    hint = "give a named folder, e.g. --out exports/NAME"
    if raw == "":
        raise ExportError(f"--out '' is empty: {hint}")
    name = Path(raw).name  # pathlib drops '.' components: '.' and '/' have no name, 'a/.' is 'a'
    if name == "" and Path(raw).anchor and Path(raw) == Path(Path(raw).anchor):
        raise ExportError(f"--out {raw!r} is the root folder: {hint}")
    if name == "..":
        raise ExportError(f"--out {raw!r} ends in '..': {hint}")
    try:
        is_cwd = name == "" or (os.path.isdir(raw) and os.path.samefile(raw, "."))
    except OSError:
        is_cwd = False
    if is_cwd:
        raise ExportError(f"--out {raw!r} is the current folder: an export is staged beside its --out and renamed into "
                          f"place, which would swap the folder this shell stands in for a new one; {hint}, or run from "
                          "the parent folder")  # fmt: skip


PARITY_FAILED_SUFFIX = ".parity-failed"


def parity_failed_dir(out_dir: Path) -> Path:
    """Where an export whose parity check failed goes when ``out_dir`` holds an export already (``commit_target``)."""
    return out_dir.with_name(out_dir.name + PARITY_FAILED_SUFFIX)


def check_parity_failed_dir(out_dir: Path) -> Path:
    """``parity_failed_dir(out_dir)``, checked as ``check_replaceable`` checks --out (and refused where it is a file):
    the ExportError names it as the folder beside --out, not as an --out the user typed."""
    failed_dir = parity_failed_dir(out_dir)
    what = (f"{failed_dir} (beside --out {out_dir}, where an export that fails its parity check goes while --out "
            "holds an export)")  # fmt: skip
    if failed_dir.exists() and not failed_dir.is_dir():
        raise ExportError(f"{what} exists and is not a directory; move it away, or choose another --out")
    check_replaceable(failed_dir, what=what)
    return failed_dir


def commit_target(out_dir: Path, parity_passed: bool) -> Path:
    """``out_dir``, unless the new export failed its parity check and ``out_dir`` holds an export: a working export
    is never replaced by one the runtime refuses; the failed one goes beside it (``parity_failed_dir``), replacing
    an earlier failed one (never a folder ``check_replaceable`` refuses: checked again here, since ``out_dir`` may
    have filled while the export ran), for inspection."""
    if parity_passed or not out_dir.is_dir() or not any(out_dir.iterdir()):
        return out_dir
    return check_parity_failed_dir(out_dir)


def commit_staging_dir(tmp: Path, out_dir: Path) -> None:
    """Replace out_dir (absent, empty, or an older export) by tmp (a staging folder of ``make_staging_dir``, whose
    marker is removed first: the export must not carry it)."""
    out_dir = out_dir.absolute()
    (tmp / STAGING_MARKER).unlink(missing_ok=True)
    old = None
    if out_dir.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-{os.getpid()}-", dir=out_dir.parent))
        _mark(old)  # a kill before the export is back or removed leaves a folder the next export may clean
        os.replace(out_dir, old / "export")
    try:
        os.replace(tmp, out_dir)
    except OSError:
        if old is not None:
            os.replace(old / "export", out_dir)  # put the previous export back
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def discard_staging_dir(tmp: Path) -> None:
    shutil.rmtree(tmp, ignore_errors=True)


def save_checked(model: onnx.ModelProto, tmp: Path, name: str, precision: str) -> Path:
    """Write graph ``name`` in ``precision`` into the staging dir and check it with the ONNX checker."""
    path = tmp / graph_file_name(name, precision)
    onnx.save_model(model, str(path))
    check_model(str(path))
    return path
