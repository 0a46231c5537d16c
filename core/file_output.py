"""Writing a whole output file atomically (pure Python; imports nothing else of streamdet).

A reader never sees half a file: the bytes go to a hidden temp file beside the target, are flushed to disk, and a
rename puts them in place (replacing a symlink at the target rather than writing through it). The file gets the
permissions of a plain ``open()`` (0666 minus the umask), like every other file a tool writes, not mkstemp's 0600.
A failure removes the temp file and leaves the target as it was.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Callable


def open_beside(path: str | os.PathLike, suffix: str = ".tmp") -> tuple[Path, BinaryIO]:
    """(name, binary file open for writing) of a new hidden temp file beside ``path``, in the same folder so that a
    rename can put it in place, with the permissions a plain ``open(path, "wb")`` would have given ``path``. The
    caller renames it onto ``path`` when complete, or removes it."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    try:
        umask = os.umask(0o022)  # read the process umask (there is no getter) and restore it at once
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        return Path(tmp), os.fdopen(fd, "wb")
    except BaseException:
        os.close(fd)
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_file(path: str | os.PathLike, write: Callable[[BinaryIO], Any], suffix: str = ".tmp") -> Path:
    """Write ``path`` atomically with ``write(f)`` on an open binary file (the temp file beside it ends in
    ``suffix``); returns ``path``."""
    path = Path(path)
    tmp, f = open_beside(path, suffix)
    try:
        with f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (``atomic_write_file``); returns ``path``."""
    return atomic_write_file(path, lambda f: f.write(text.encode("utf-8")))


def writer_alive(pid: int) -> bool:
    """Whether the process ``pid``, named in a temporary output of its (a staging folder, a half-written cache), still
    runs: a reused pid counts as alive, so a live writer's folder is never removed, at worst a dead one's kept."""
    if os.name != "posix" or pid <= 0:
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):  # another user's process; a pid past the platform's range
        return True
    return True
