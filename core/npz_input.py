"""The members of an .npz archive judged from their headers before anything is inflated (numpy only).

A small .npz can declare gigabytes: numpy allocates what an ``.npy`` header declares, and a zip member inflates to
its declared size. A reader of an archive someone else wrote (a LUT, a mask) reads each member's header first,
refuses object dtypes (pickles: never loaded), checks shape and dtype against what it expects, and requires the
member to be exactly its header plus that data (a truncated or padded member is refused), before reading it.
"""

from __future__ import annotations

import math
import zipfile
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class NpyHeader:
    """What an ``.npy`` member declares: shape, memory order and dtype, and its header's length in bytes."""

    shape: tuple[int, ...]
    fortran_order: bool
    dtype: np.dtype
    header_bytes: int

    @property
    def data_bytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


def npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> NpyHeader:
    """The header of member ``info``, read from its first bytes only; ValueError for an object (pickled) dtype, and
    for a member whose header cannot be read at all (naming the member and what went wrong)."""
    try:
        with zf.open(info) as f:
            version = np.lib.format.read_magic(f)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran_order, dtype = read(f)
            header_bytes = f.tell()
    except Exception as e:
        # Not only ValueError: numpy parses the header dict with Python's tokenizer (a damaged byte there raises
        # tokenize.TokenError or SyntaxError), and zipfile raises NotImplementedError / RuntimeError for flags it does
        # not support (patched data, encryption), BadZipFile and zlib.error for damaged entries. Every caller is a
        # reader of someone else's file that reports a ValueError as "not a readable .npz"; anything else escaped it.
        raise ValueError(f"{info.filename}: cannot read its .npy header: {type(e).__name__}: {e}") from None
    if dtype.hasobject:
        raise ValueError(f"{info.filename} holds Python objects (dtype {dtype}): a pickle, never loaded")
    return NpyHeader(tuple(shape), bool(fortran_order), dtype, header_bytes)


def check_member_size(info: zipfile.ZipInfo, header: NpyHeader) -> None:
    """ValueError unless member ``info`` is exactly its header plus the data it declares: the zip reader never
    inflates past the declared size, so this bounds the read."""
    want = header.header_bytes + header.data_bytes
    if info.file_size != want:
        raise ValueError(f"{info.filename} declares {info.file_size} bytes, but its header implies {want} "
                         f"({header.dtype.str} {header.shape}): truncated or padded")  # fmt: skip
