"""Reading JSON that comes from outside: bounded, every failure a ValueError naming the file, numbers checked safely.

One place for what every reader of input JSON needs (dataset tables, boxes.json, splits.json, results files):

- ``read_json``: the document of a file of at most ``max_bytes`` (checked before reading where the size is known, a
  bounded read for a pipe or a device), with the parser's failures named: not UTF-8, not JSON, an integer literal
  past Python's 4300-digit limit, nesting past the parser's stack; with ``unique_keys`` also a key given twice in
  one object (``json`` keeps the last silently);
- ``is_finite_number``: a JSON number (not a bool) that is a finite float64, by comparison (JSON integers are
  unbounded: ``math.isfinite(10**400)`` raises OverflowError);
- ``short_repr``: a value cut for a one-line error (a 10**400 or a long list must not flood it).
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import numpy as np

FLOAT_MAX = sys.float_info.max


def is_finite_number(value: object) -> bool:
    """Whether ``value`` is a JSON number (not a bool; numpy scalars too) that is a finite float64."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, (int, np.integer)):
        return -FLOAT_MAX <= int(value) <= FLOAT_MAX  # an exact comparison: no OverflowError for 10**400
    return isinstance(value, (float, np.floating)) and math.isfinite(value)


def short_repr(value: object, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters; a huge integer by its digit count."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10**60:
        return f"an integer of {int(abs(value).bit_length() * math.log10(2)) + 1} digits"
    try:
        text = repr(value)
    except ValueError:  # a container holding an int past Python's 4300-digit str() limit
        return f"a {type(value).__name__} holding an integer too long to print"
    return text if len(text) <= limit else text[: limit - 3] + "..."


class DuplicateKeyError(ValueError):
    """A key given twice in one JSON object (``read_json(unique_keys=True)``)."""

    def __init__(self, key: str):
        super().__init__(f"key {short_repr(key)} appears twice in one object")
        self.key = key


def unique_keys_object(pairs: list[tuple[str, object]]) -> dict:
    """``json``'s ``object_pairs_hook`` that refuses a key given twice (DuplicateKeyError naming it) where ``json``
    keeps the last one silently: two entries for one sample in a results file merged by text, or a writer that
    flushed a sample twice, would lose boxes without a word. ``dict(pairs)`` first, the search only on a
    mismatch: the check then costs one length comparison per object."""
    out = dict(pairs)
    if len(out) != len(pairs):
        seen = set()
        for key, _ in pairs:
            if key in seen:
                raise DuplicateKeyError(key)
            seen.add(key)
    return out


def read_json(path: str | os.PathLike, what: str, max_bytes: int, unique_keys: bool = False) -> object:
    """The JSON document of ``path``, a ``what`` (named in errors: "splits file", "results file", ...) of at most
    ``max_bytes``; ValueError naming the file when it cannot be read or is not one.

    ``unique_keys``: a key given twice in one object is refused (ValueError naming the file and the key) instead of
    the last one winning. Off by default: the hook runs in Python once per object, a cost that shows on a large
    table of small objects (a nuScenes ``sample_data.json`` of hundreds of MB); the readers of results and
    ground-truth files, where a duplicate loses boxes, turn it on."""
    path = Path(path)
    try:
        with _open_input(path) as f:
            size = os.fstat(f.fileno()).st_size  # 0 for a pipe or a device: read in chunks, bounded
            raw = b"" if size > max_bytes else _read_at_most(f, max_bytes + 1, size)
    except OSError as e:
        raise ValueError(f"{what} {path}: cannot read: {e.strerror or e}") from None
    if not raw and size == 0 and not path.is_file():  # a named pipe nobody writes to reads as empty
        raise ValueError(f"{what} {path} is a pipe or device that gave no data (a FIFO without a writer?)")
    if size > max_bytes or len(raw) > max_bytes:
        limit = f"{max_bytes >> 20} MiB" if max_bytes >= 1 << 20 else f"{max_bytes} bytes"
        raise ValueError(f"{what} {path} is larger than {limit}: not a {what}")
    try:
        return json.loads(raw.decode("utf-8"), object_pairs_hook=unique_keys_object if unique_keys else None)
    except DuplicateKeyError as e:  # before ValueError: it is one, and not a syntax error
        raise ValueError(f"{what} {path}: {e}; the file must hold each key once") from None
    except UnicodeDecodeError as e:  # before ValueError: it is one
        raise ValueError(f"{what} {path} is not UTF-8 text (a binary file?): {e.reason} at byte {e.start}") from None
    except RecursionError:  # the parser recurses once per level: a hostile file can nest past the stack
        raise ValueError(f"{what} {path} nests too deeply to be a {what}") from None
    except ValueError as e:  # JSONDecodeError, and the 4300-digit limit on integer literals
        raise ValueError(f"{what} {path} is not valid JSON: {e}") from None


def _open_input(path: Path):
    """``path`` opened for reading, never blocking in the open: a named pipe (FIFO) without a writer would block
    ``open()`` for ever, so it is opened non-blocking and then switched back, where a pipe without a writer reads as
    empty. A pipe with one (``<(zcat gt.json.gz)``) reads as usual."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    try:
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)  # reads wait for a writer that is there
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def _read_at_most(f, limit: int, size: int) -> bytes:
    """Up to ``limit`` bytes of ``f``. Never ``f.read(limit)`` with a large limit: Python allocates the whole buffer
    before reading (16 GiB for a table cap), which fails under a memory limit; a file of known ``size`` is read at
    its size (plus one byte, to see it grew), anything else in 1 MiB chunks."""
    if size > 0:
        return f.read(min(size + 1, limit))
    chunks, total = [], 0
    while total < limit:
        chunk = f.read(min(1 << 20, limit - total))
        if not chunk:
            break
        chunks.append(chunk)
        total += len(chunk)
    return b"".join(chunks)

