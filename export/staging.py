"""Staging and commit of an export directory: all files are written into a temporary directory beside the target and
renamed into place at the end (manifest last), so a failed or interrupted export never leaves a directory that looks
complete, and an older export is replaced only by a finished one."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import onnx

from streamdet.export.fp16 import check_model
from streamdet.export.options import ExportError
from streamdet.runtime_ort.manifest import MANIFEST_NAME, graph_file_name


def _stale_dirs(parent: Path, name: str) -> list[tuple[str, Path]]:
    """("partial" | "old", path) of staging folders beside ``name`` left by an export process that no longer runs
    (killed with SIGKILL, or the machine went down); the writer's pid is part of the folder's name."""
    stale = []
    for kind in ("partial", "old"):
        for path in parent.glob(f".{name}.{kind}-*-*"):
            pid = path.name[len(f".{name}.{kind}-"):].split("-", 1)[0]
            if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)) and path.is_dir():
                stale.append((kind, path))
    return stale


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def clean_stale_staging(out_dir: Path) -> None:
    """Remove what a killed export left beside out_dir; a previous export it had moved aside is put back first."""
    out_dir = out_dir.absolute()
    for kind, path in _stale_dirs(out_dir.parent, out_dir.name):
        moved_aside = path / "export"
        if kind == "old" and not out_dir.exists() and (moved_aside / MANIFEST_NAME).is_file():
            os.replace(moved_aside, out_dir)  # killed between the two renames of commit_staging_dir
        shutil.rmtree(path, ignore_errors=True)


def make_staging_dir(out_dir: Path) -> Path:
    """A fresh temp dir beside out_dir (same filesystem, so the final rename is atomic); checks writability early.

    Staging folders left by an export that was killed (SIGKILL: no cleanup ran) are removed first."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"--out {out_dir} exists and is not a directory")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not (out_dir / MANIFEST_NAME).is_file():
        raise ExportError(f"--out {out_dir} is a non-empty directory that is not a streamdet export; refusing to overwrite it")
    parent = out_dir.absolute().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        clean_stale_staging(out_dir)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-{os.getpid()}-", dir=parent))
    except OSError as e:
        raise ExportError(f"--out {out_dir}: cannot write into {parent}: {e.strerror or e}") from None
    tmp.chmod(0o755)  # mkdtemp makes it private; the export is an ordinary directory
    return tmp


def commit_staging_dir(tmp: Path, out_dir: Path) -> None:
    """Replace out_dir (absent, empty, or an older export) by tmp."""
    out_dir = out_dir.absolute()
    old = None
    if out_dir.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-{os.getpid()}-", dir=out_dir.parent))
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
