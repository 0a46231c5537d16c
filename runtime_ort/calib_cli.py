"""``streamdet-calib``: calibration tools that run without PyTorch.

``streamdet-calib lut --calibration FILE --export-dir DIR`` rebuilds ``DIR/lut.npz`` for a new calibration of
the same rig, the only file a calibration change touches (the lifter graph takes the LUT as an input). The grid,
feature stride and image size come from ``DIR/manifest.json``; the calibration must name the export's cameras in
the export's order (the encoder's J axis) and have their aspect ratio (its intrinsics are scaled to the export's
image size, as the images are resized).

It writes exactly two files, both in that directory and both atomically (a hidden temp file, then a rename):
``lut.npz`` and ``manifest.json``. Whatever the manifest says, no other path is written: a ``lut.file`` naming a
path, or a ``lut.npz`` / ``manifest.json`` symlinked out of the directory, is refused before anything is written.
Two rebuilds of one export (an operator and a calibration service) take turns: each holds an exclusive lock on
the hidden ``.streamdet-calib.lock`` in the directory from before its LUT write until after its manifest write, so
the manifest always records the sha256 and calibration of the lut.npz beside it. That lock file is the only other
path it creates, and its holder removes it again; a run that waits past ``LOCK_WAIT_S`` gives up with `ExportBusy`,
writing nothing.

It lives in runtime_ort/ (it was calibration/cli.py) because it edits an export's manifest, which the runtime owns:
calibration/ stays below the runtime and imports none of it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import fcntl
import hashlib
import io
import json
import os
import stat
import time
from pathlib import Path
from typing import Iterator

import click

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut import (  # noqa: F401 (ASPECT_TOLERANCE, BlindCameraWarning: public here too)
    ASPECT_TOLERANCE, BlindCameraWarning, Lut, blind_cameras, check_rig_fits, moved_cameras,
)
from streamdet.calibration.lut_build import build_lut
from streamdet.runtime_ort.manifest import (
    LUT_NAME, MANIFEST_NAME, LutEntry, Manifest, ManifestError, atomic_write, export_file, read_manifest, sha256_file,
    write_manifest,
)


class LutMismatch(ValueError):
    """A calibration that does not fit an export; the message says why in one line."""


class ExportBusy(RuntimeError):
    """Another rebuild of the same export held its lock for longer than the wait allowed; nothing was written."""


LOCK_NAME = ".streamdet-calib.lock"  # hidden: no manifest names it, and its holder removes it again
LOCK_WAIT_S = 300.0  # how long a rebuild waits for another one of the same export (a paper-grid build takes seconds)
_LOCK_POLL_S = 0.05


def rebuild_lut(calibration: str | Path, export_dir: str | Path, lock_wait_s: float | None = None) -> tuple[Lut, bool]:
    """Rebuild ``export_dir/lut.npz`` from ``calibration`` and point the manifest at it.

    Returns the new LUT and whether the file changed. The LUT is built unlocked; writing it and the manifest holds
    the export's lock (module doc), waiting up to ``lock_wait_s`` (None: `LOCK_WAIT_S`) for another rebuild. Raises
    ManifestError, CalibrationError, LutMismatch or ExportBusy (and OSError from the file system).
    """
    export_dir = Path(export_dir)
    manifest = read_manifest(export_dir, verify_files=False)
    image = manifest.image
    if image is None:
        raise LutMismatch(f"{export_dir} is a LiDAR-only export: it has no image lane, so no LUT to rebuild")
    # the only two paths this writes, confined (symlinks resolved) before anything is computed or written
    lut_path = export_file(export_dir, LUT_NAME, "the LUT")
    export_file(export_dir, MANIFEST_NAME, "the manifest")
    rig = Rig.from_calibration_json(calibration)
    try:
        check_rig_fits(rig, image.camera_names, image.width, image.height)
    except CalibrationError as e:  # the rig read well but fits another export: name both
        raise LutMismatch(f"{calibration}: {e} (export {export_dir})") from None
    try:
        grid = GridSpec.from_dict(manifest.grid)
    except (KeyError, TypeError, ValueError) as e:
        raise ManifestError(f"{export_dir / 'manifest.json'}: grid: {e}") from None
    # the model's heights per voxel (models/presets.py LifterConfig; absent = 1, manifests written before it)
    lifter = manifest.preset.get("lifter", {})
    if not isinstance(lifter, dict):  # the schema refuses it too; kept so this never becomes an AttributeError
        raise ManifestError(f"{export_dir / MANIFEST_NAME}: preset.lifter: expected an object, got {type(lifter).__name__}")
    heights = lifter.get("lut_heights_per_voxel", 1)
    try:
        lut = build_lut(rig, grid, image.feature_stride, (image.width, image.height), heights_per_voxel=heights)
    except CalibrationError:
        raise
    except ValueError as e:  # the manifest's numbers (grid too big for a LUT, heights per voxel, stride): name it
        raise ManifestError(f"{export_dir / MANIFEST_NAME}: {e}") from None
    if (lut.feature_width, lut.feature_height) != (image.feature_width, image.feature_height):
        raise LutMismatch(
            f"the LUT's feature map {lut.feature_width}x{lut.feature_height} differs from the manifest's "
            f"{image.feature_width}x{image.feature_height}; the manifest is inconsistent"
        )
    buf = io.BytesIO()
    lut.write_npz(buf)
    data = buf.getbuffer()  # the bytes written are the bytes hashed: the file is never read back
    new_sha = hashlib.sha256(data).hexdigest()
    with export_lock(export_dir, lock_wait_s):
        current = read_manifest(export_dir, verify_files=False)  # another rebuild may have replaced it meanwhile
        if _without_lut(current) != _without_lut(manifest):  # only a rebuild's own field may have changed
            raise ManifestError(f"{export_dir / MANIFEST_NAME} changed while the LUT was built (re-exported?): "
                                "nothing was written; run streamdet-calib again")  # fmt: skip
        old_sha = sha256_file(lut_path) if lut_path.is_file() else None
        atomic_write(export_dir, LUT_NAME, lambda f: f.write(data))
        entry = LutEntry(LUT_NAME, new_sha, lut.calibration_sha256, str(Path(calibration)))
        write_manifest(dataclasses.replace(current, lut=entry), export_dir)
    return lut, new_sha != old_sha


def _without_lut(manifest: Manifest) -> str:
    """The manifest as JSON text without its LUT entry: equal for two reads of one export that differ only by a
    rebuild (text, not the dataclasses: a NaN the manifest may hold never equals itself)."""
    return json.dumps({**manifest.to_dict(), "lut": None}, sort_keys=True, allow_nan=True)


@contextlib.contextmanager
def export_lock(export_dir: str | Path, wait_s: float | None = None) -> Iterator[None]:
    """Hold the rebuild lock of ``export_dir``: an exclusive ``flock`` on its ``LOCK_NAME``, created if need be
    and removed again by the holder before it lets go (so an export keeps only its own files). A waiter that gets
    the lock of a file the holder has just removed locks the path's new file instead. ExportBusy after ``wait_s``
    (None: `LOCK_WAIT_S`); ManifestError when the lock path is a symlink or no regular file (it is neither followed
    nor removed)."""
    path = Path(export_dir).resolve() / LOCK_NAME
    deadline = time.monotonic() + (LOCK_WAIT_S if wait_s is None else wait_s)
    while True:
        fd = _open_lock_file(path)
        try:
            _flock_by(fd, deadline, path)
            held = _same_file(fd, path)
        except BaseException:
            os.close(fd)
            raise
        if held:
            break
        os.close(fd)  # removed (and maybe recreated) by the run that held it: lock what the path names now
    try:
        yield
    finally:
        try:
            path.unlink(missing_ok=True)  # under the lock: a waiter on this file sees it gone and retries
        finally:
            os.close(fd)


def _open_lock_file(path: Path) -> int:
    try:  # O_NOFOLLOW: never through a symlink; O_NONBLOCK: a FIFO there must not block the open
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o666)
    except OSError as e:
        if e.errno in (errno.ELOOP, errno.EISDIR):
            raise ManifestError(f"{path}: the rebuild lock is a symlink or a directory; remove it (nothing was written)") from None
        raise
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise ManifestError(f"{path}: the rebuild lock is no regular file; remove it (nothing was written)")
    return fd


def _flock_by(fd: int, deadline: float, path: Path) -> None:
    """An exclusive flock on ``fd``, polled until ``deadline`` (time.monotonic()), then ExportBusy."""
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() >= deadline:
                raise ExportBusy(f"another streamdet-calib run holds {path}: gave up waiting for it, nothing was written") from None
            time.sleep(_LOCK_POLL_S)


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``path`` still names the file open as ``fd`` (its holder removes it before unlocking)."""
    try:
        st = os.stat(path, follow_symlinks=False)
    except FileNotFoundError:
        return False
    mine = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino)


def _previous_lut(export_dir: str) -> Lut | None:
    """The LUT about to be replaced, to warn about moved cameras; None when there is none or it is broken.

    A broken lut.npz is exactly what a rebuild may be run to replace, so no error reading it (Lut.load's
    LutFileError / CalibrationError, an I/O error, or whatever a damaged file makes numpy or zipfile raise) may stop
    the rebuild: it is logged and skipped."""
    try:
        path = export_file(export_dir, LUT_NAME, "the LUT")
    except ManifestError:
        return None  # a path outside the export: rebuild_lut refuses it with this same message
    if not path.is_file():
        return None  # a first build: nothing to compare with, nothing to report
    try:
        return Lut.load(path)
    except Exception as e:  # any Exception: the old file only feeds a warning, and a rebuild is how it gets repaired
        reason = str(e) if isinstance(e, (CalibrationError, OSError)) else f"{type(e).__name__}: {e}"
        click.echo(f"note: the previous {LUT_NAME} is unreadable, so it is replaced without comparing cameras: {reason}", err=True)
        return None


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Calibration tools for streamdet exports (no PyTorch needed)."""


@main.command("lut")
@click.option("--calibration", required=True, type=click.Path(dir_okay=False),
              help="calibration.json of the rig (the bundled sample's format).")
@click.option("--export-dir", required=True, type=click.Path(file_okay=False),
              help="An existing export directory (with manifest.json); its lut.npz is replaced.")
def lut_command(calibration: str, export_dir: str) -> None:
    """Rebuild lut.npz of an export for a new calibration; no re-export needed."""
    previous = _previous_lut(export_dir)
    try:
        lut, changed = rebuild_lut(calibration, export_dir)
    except (ManifestError, CalibrationError, LutMismatch, ExportBusy) as e:
        raise click.ClickException(str(e)) from None
    except OSError as e:
        raise click.ClickException(f"cannot write into {export_dir}: {e.strerror or e}") from None
    for name, slots in blind_cameras(lut):
        click.echo(f"warning: camera {name} sees no voxel of the grid ({slots} LUT slots): check its calibration", err=True)
    for name, iou in moved_cameras(previous, lut) if previous is not None else ():
        click.echo(
            f"warning: camera {name} now sees other voxels than with the previous LUT (overlap {iou:.2f}): "
            "turned around or swapped? check its calibration", err=True,
        )  # fmt: skip
    seen = float((lut.weight.sum(axis=1) > 0).mean())
    state = "rebuilt" if changed else "rebuilt (unchanged)"
    click.echo(
        f"{state} {Path(export_dir) / 'lut.npz'} from {calibration}: {lut.num_cameras} cameras at "
        f"{lut.image_width}x{lut.image_height}, K = {lut.num_slots} slots, {100 * seen:.1f} % of voxels seen"
    )


if __name__ == "__main__":
    main()
