"""Writing a synthetic dataset so that an error, Ctrl-C or SIGTERM leaves its folder as it was (``streamdet-synth
generate``).

The dataset is written into a staging folder beside ``OUT`` and its entries are renamed into ``OUT`` at the end;
``generate_dataset`` (synth_writer.py) itself writes in place.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

from streamdet.data.synth_writer import LAYOUT_DIRS, LAYOUT_FILES, GenerationSummary, SynthConfig, generate_dataset

log = logging.getLogger(__name__)

STAGING_PREFIX = ".streamdet-synth-staging-"  # the staging folder beside OUT (in its parent) of a run in progress


class StagedDataset:
    """One run of ``generate_dataset`` that leaves ``out_dir`` as it was unless it completes (streamdet-synth
    generate): the dataset is written into a staging folder beside ``out_dir`` (in its parent, so that the final
    moves are renames on one file system; inside ``out_dir`` where the parent is not writable), and its entries are
    renamed into ``out_dir`` at the end. On any exception (`generate`: errors, KeyboardInterrupt, and the SystemExit
    that streamdet-synth generate's SIGTERM handler raises) or a call of `abandon`, everything this run created is
    removed: the staging folder, the entries it moved into ``out_dir`` and ``out_dir`` itself (with the parents it
    made) where it did not exist before, if empty. Nothing that was there before the run is touched, nor anything
    foreign: a file that appears in ``out_dir`` meanwhile stays.

    Constructing it does the checks that need no simulation and makes the folders (an ``out_dir`` that cannot be
    made, a parent that cannot be written: before minutes of work). The final layout is ``generate_dataset``'s.
    A run killed outright leaves at most a ``.streamdet-synth-staging-*`` folder beside ``out_dir``, never a part of
    a dataset in it (bar the moment of the final renames): SIGKILL, power loss, and SIGTERM in a program that leaves
    it its default action (which runs no ``except`` or ``finally``; streamdet-synth generate turns it into an
    exception for the run)."""

    def __init__(self, out_dir: str | Path, config: SynthConfig) -> None:
        self.out = Path(out_dir)
        self.config = config
        self._moved: list[Path] = []
        self.left: list[str] = []  # what `abandon` could not remove ("path (error)")
        self.done = False  # True once `generate` has moved the whole dataset into out_dir (abandon removes none of it)
        self._created = _missing_folders(self.out)  # outermost first: made by this run
        self.staging: Path | None = None
        try:
            self.out.mkdir(parents=True, exist_ok=True)
            self.staging = _make_staging(self.out)
            # the table folder now: a name or path the file system refuses fails here, not after the simulation
            (self.staging / config.version).mkdir()
        except BaseException:
            self.abandon()
            raise

    def clashes(self) -> list[str]:
        """The entries of ``out_dir`` a dataset's own would replace (its layout names and the table folder)."""
        names = (*LAYOUT_FILES, *LAYOUT_DIRS, self.config.version)
        return [n for n in names if os.path.lexists(self.out / n)]

    def generate(
        self, progress: Callable[[int], None] | None = None, workers: int = 1, finish: Callable[[Path], None] | None = None
    ) -> GenerationSummary:
        """Write the dataset (``generate_dataset``), run ``finish(root)`` on its staging root (more files that
        belong to it: previews), then move it into ``out_dir``. ``out_dir`` must hold none of the dataset's names by
        then (FileExistsError before any simulation). Any exception (KeyboardInterrupt and SystemExit too) abandons
        the run, then propagates."""
        try:
            clash = self.clashes()
            if clash:
                raise FileExistsError(errno.EEXIST, f"{self.out} already holds {', '.join(clash)}: a dataset is written "
                                      "into a new or empty folder")  # fmt: skip
            summary = generate_dataset(self.staging, self.config, progress=progress, workers=workers)
            if finish is not None:
                finish(self.staging)
            entries = sorted(self.staging.iterdir())
            clash = [e.name for e in entries if os.path.lexists(self.out / e.name)]
            if clash:  # written meanwhile, by someone else: theirs stays, and this run is abandoned
                raise FileExistsError(errno.EEXIST, f"{self.out} now holds {', '.join(clash)}, written during the run")
            for entry in entries:
                target = self.out / entry.name
                self._moved.append(target)
                _move(entry, target)
            shutil.rmtree(self.staging)  # empty, or the sources of copies (_move)
            self.staging = None
            self._moved, self._created, self.done = [], [], True  # the dataset's now: abandon() removes nothing of it
        except BaseException:
            self.abandon()
            raise
        return dataclasses.replace(summary, out_dir=self.out)

    def abandon(self) -> None:
        """Remove what this run created (best effort: what cannot be removed is logged and kept in ``left``)."""
        left = self.left = []
        for path in [*reversed(self._moved), self.staging]:
            if path is not None and os.path.lexists(path):
                try:
                    _remove(path)
                except OSError as e:
                    left.append(f"{path} ({e})")
        self._moved = []
        for folder in reversed(self._created):  # innermost first
            try:
                folder.rmdir()
            except OSError:  # gone, or someone else's files arrived in it meanwhile: they stay, and so does it
                pass
        if left:
            log.warning("streamdet-synth: could not remove what the abandoned run wrote: %s", "; ".join(left))


def generate_dataset_staged(
    out_dir: str | Path,
    config: SynthConfig = SynthConfig(),
    progress: Callable[[int], None] | None = None,
    workers: int = 1,
    finish: Callable[[Path], None] | None = None,
) -> GenerationSummary:
    """``generate_dataset`` that leaves ``out_dir`` as it was unless it completes (`StagedDataset`)."""
    return StagedDataset(out_dir, config).generate(progress, workers, finish)


def _missing_folders(path: Path) -> list[Path]:
    """``path`` and its parents that do not exist, outermost first: the folders making ``path`` makes."""
    missing = []
    p = path
    while not os.path.lexists(p) and p != p.parent:
        missing.append(p)
        p = p.parent
    return missing[::-1]


def _make_staging(out: Path) -> Path:
    """A new staging folder in ``out``'s parent, else (a parent this user cannot write) inside ``out``."""
    try:
        return Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=out.parent))
    except OSError:
        return Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=out))


def _move(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst`` (which does not exist); a copy where they are on two file systems (an ``out``
    that is a mount point)."""
    try:
        os.rename(src, dst)
    except OSError as e:
        if e.errno != errno.EXDEV:
            raise
        if src.is_dir() and not src.is_symlink():
            shutil.copytree(src, dst, symlinks=True)
        else:
            shutil.copy2(src, dst, follow_symlinks=False)


def _remove(path: Path) -> None:
    if path.is_symlink() or not path.is_dir():
        path.unlink()
    else:
        shutil.rmtree(path)
