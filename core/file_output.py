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


def atomic_write_file(path: str | os.PathLike, write: Callable[[BinaryIO], Any]) -> Path:
    """Write ``path`` atomically with ``write(f)`` on an open binary file; returns ``path``."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        umask = os.umask(0o022)  # read the process umask (there is no getter) and restore it at once
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
