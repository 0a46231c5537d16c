"""``streamdet-calib``: calibration tools that run without PyTorch.

``streamdet-calib lut --calibration FILE --export-dir DIR`` rebuilds ``DIR/lut.npz`` for a new calibration of
the same rig, the only file a calibration change touches (the lifter graph takes the LUT as an input). The grid,
feature stride and image size come from ``DIR/manifest.json``; the calibration must name the export's cameras in
the export's order (the encoder's J axis) and have their aspect ratio (its intrinsics are scaled to the export's
image size, as the images are resized).

It writes exactly two files, both in that directory and both atomically (a hidden temp file, then a rename):
``lut.npz`` and ``manifest.json``. Whatever the manifest says, no other path is written: a ``lut.file`` naming a
path, or a ``lut.npz`` / ``manifest.json`` symlinked out of the directory, is refused before anything is written.

It lives in runtime_ort/ (it was calibration/cli.py) because it edits an export's manifest, which the runtime owns:
calibration/ stays below the runtime and imports none of it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut import (  # noqa: F401 (ASPECT_TOLERANCE, BlindCameraWarning: public here too)
    ASPECT_TOLERANCE, BlindCameraWarning, Lut, blind_cameras, check_rig_fits, moved_cameras,
)
from streamdet.calibration.lut_build import build_lut
from streamdet.runtime_ort.manifest import (
    LUT_NAME, MANIFEST_NAME, LutEntry, ManifestError, atomic_write, export_file, read_manifest, sha256_file,
    write_manifest,
)


class LutMismatch(ValueError):
    """A calibration that does not fit an export; the message says why in one line."""


def rebuild_lut(calibration: str | Path, export_dir: str | Path) -> tuple[Lut, bool]:
    """Rebuild ``export_dir/lut.npz`` from ``calibration`` and point the manifest at it.

    Returns the new LUT and whether the file changed. Raises ManifestError, CalibrationError or LutMismatch.
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
    old_sha = sha256_file(lut_path) if lut_path.is_file() else None
    atomic_write(export_dir, LUT_NAME, lambda f: lut.write_npz(f))
    new_sha = sha256_file(lut_path)
    entry = LutEntry(LUT_NAME, new_sha, lut.calibration_sha256, str(Path(calibration)))
    write_manifest(dataclasses.replace(manifest, lut=entry), export_dir)
    return lut, new_sha != old_sha


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
    except (ManifestError, CalibrationError, LutMismatch) as e:
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
