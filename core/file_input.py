"""Reading a whole input file once, bounded (pure Python; imports nothing else of streamdet).

What every reader of a file someone else wrote needs before it parses a byte: the path must be a regular file (a
FIFO or a device would block or never end), no larger than the reader's limit (checked on the open file before
reading, and again on what was read, for a file that grows meanwhile), and read whole in one go, so that what is
hashed or checked is what is parsed (a file swapped between a check and a load by path is not seen).
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path


class InputFileError(ValueError):
    """A file that cannot be read as an input: ``reason`` says why (missing, not a regular file, an OS error, or
    over ``limit_bytes``; ``too_large`` tells the last apart)."""

    def __init__(self, path: Path, reason: str, too_large: bool = False) -> None:
        super().__init__(f"{path}: {reason}")
        self.path = path
        self.reason = reason
        self.too_large = too_large


def describe_bytes(n: int) -> str:
    """``n`` bytes in the largest binary unit that keeps it whole-ish: "64 MiB", "2 GiB", "512 bytes"."""
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if n >= 1 << shift:
            return f"{n / (1 << shift):.3g} {unit}"
    return f"{n} bytes"


def missing_reason(path: str | os.PathLike) -> str:
    """Why ``path``, which does not exist as far as ``Path.exists`` sees, is missing: "no such file", or, where it is
    a symlink (the link is there, so "missing" would send the user looking for a file they can see), "a symlink
    loop" or "a broken symlink (to '...', which does not exist)"."""
    if not os.path.islink(path):
        return "no such file"
    try:
        os.stat(path)
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "a symlink loop"
    return f"a broken symlink (to {os.readlink(path)!r}, which does not exist)"


def read_regular_file(path: str | os.PathLike, limit_bytes: int) -> bytes:
    """The whole content of ``path``, a regular file of at most ``limit_bytes``, else InputFileError.

    Symlinks are followed (confining them is the caller's business). The file is opened without blocking, so a
    FIFO swapped in after a check still cannot block, and judged by ``fstat`` of the open file.
    """
    path = Path(path)
    if not path.is_file():  # also a FIFO or a device: open() or read() could block for ever, or never end
        raise InputFileError(path, "missing" if not path.exists() else "not a regular file")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    except OSError as e:
        raise InputFileError(path, f"cannot be opened: {e.strerror or e}") from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise InputFileError(path, "not a regular file")
        if st.st_size > limit_bytes:
            raise InputFileError(path, f"is {st.st_size} bytes, over the {describe_bytes(limit_bytes)} limit; refused "
                                       "before reading", too_large=True)  # fmt: skip
        try:
            raw = f.read(st.st_size + 1)  # + 1: a file that grew meanwhile is seen growing
        except OSError as e:
            raise InputFileError(path, f"cannot be read: {e.strerror or e}") from None
    if len(raw) > limit_bytes:
        raise InputFileError(path, f"grew past the {describe_bytes(limit_bytes)} limit while being read", too_large=True)
    return raw
