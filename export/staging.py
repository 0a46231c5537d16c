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


def make_staging_dir(out_dir: Path) -> Path:
    """A fresh temp dir beside out_dir (same filesystem, so the final rename is atomic); checks writability early."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"--out {out_dir} exists and is not a directory")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not (out_dir / MANIFEST_NAME).is_file():
        raise ExportError(f"--out {out_dir} is a non-empty directory that is not a streamdet export; refusing to overwrite it")
    parent = out_dir.absolute().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=parent))
    except OSError as e:
        raise ExportError(f"--out {out_dir}: cannot write into {parent}: {e.strerror or e}") from None
    tmp.chmod(0o755)  # mkdtemp makes it private; the export is an ordinary directory
    return tmp


def commit_staging_dir(tmp: Path, out_dir: Path) -> None:
    """Replace out_dir (absent, empty, or an older export) by tmp."""
    out_dir = out_dir.absolute()
    old = None
    if out_dir.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
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
