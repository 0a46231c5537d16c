"""Reading files ``torch.save`` wrote, as data: the one place every loader of weights goes through (torch only).

``read_torch_file`` reads with ``weights_only=True`` (tensors, containers and numbers: never code to unpickle) after
``check_torch_zip`` refused a zip that would inflate past its own size, and turns every failure into one ValueError
naming the file; ``check_state_dict`` checks that a loaded object is a state dict (str keys, tensor values) and
``check_fits`` that it loads into a given module's state dict (keys, shapes, float dtypes, finite values). Both
refuse a tensor that is no dense weight (sparse, meta, quantized or nested: ``weights_only`` loads them all, and the
finiteness check or the model would fail on them with a traceback).
``models/`` (backbone weights) and ``training/`` (checkpoints) both use it, so it lives below both.
"""

from __future__ import annotations

import os
import re
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from streamdet.core.errors import first_line

# What the members of a checkpoint's zip may declare in all, inflated: a checkpoint is read into memory whole, and
# torch.save stores every member uncompressed, so a real one declares no more than its own file size (the paper
# preset's training checkpoint, ResNet-50 and AdamW moments, is a few hundred MB).
MAX_CHECKPOINT_BYTES = 8 << 30


def check_torch_zip(path: str | os.PathLike, what: str = "checkpoint") -> None:
    """Refuse a zip-format torch file whose members would inflate past what the file holds, before ``torch.load``
    reads any of it: ``torch.save`` never compresses a member, so a deflated one (a 1 GiB tensor in 1 MB) is no
    checkpoint. ValueError (one line, naming ``what`` and the file); a file that is not a zip (torch's legacy
    format, or damage that ``torch.load`` then reports) passes."""
    path = Path(path)
    try:
        if not zipfile.is_zipfile(path):
            return
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
    except (OSError, zipfile.BadZipFile, ValueError, EOFError):  # torch.load reports an unreadable file itself
        return
    size = path.stat().st_size
    for info in infos:
        if info.compress_type != zipfile.ZIP_STORED:
            raise ValueError(f"{what} {path}: member {info.filename!r} is compressed ({info.file_size} bytes inflated); "
                             f"torch.save never compresses: not a checkpoint")  # fmt: skip
    total = sum(info.file_size for info in infos)
    if total > size or total > MAX_CHECKPOINT_BYTES:
        raise ValueError(f"{what} {path}: its members declare {total} bytes, more than the file's {size} bytes "
                         f"(or the cap {MAX_CHECKPOINT_BYTES}): not a checkpoint")  # fmt: skip


def read_torch_file(path: str | os.PathLike, what: str = "checkpoint", map_location: str | torch.device = "cpu",
                    mmap: bool = False) -> Any:  # fmt: skip
    """What ``torch.save`` wrote to ``path``, read with ``weights_only=True`` (tensors, containers and numbers: a file
    is data, never code to unpickle); ValueError (one line, naming ``what`` and the file) when it is missing,
    unreadable that way, or a zip that would inflate past its size (``check_torch_zip``). ``mmap``: the tensors are
    mapped, not read, for a caller that wants only the small entries (a checkpoint's config) of a large file."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{what} {path} does not exist or is not a file")
    check_torch_zip(path, what)
    try:
        return torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except Exception as e:  # UnpicklingError (code or classes in the pickle), RuntimeError, EOFError, ... for a damaged file
        raise ValueError(f"{what} {path} cannot be read with weights_only=True: {_why_unreadable(path, e)}; streamdet "
                         "reads a checkpoint as data only (tensors, containers, numbers), never otherwise") from None


# The global a weights-only unpickler refused, as torch words it ("GLOBAL posix.system whose module ...", "GLOBAL
# __main__.C was not an allowed global").
_REFUSED_GLOBAL = re.compile(r"GLOBAL ([\w.]+)")
_WEIGHTS_UNPICKLER = "WeightsUnpickler error:"


def _why_unreadable(path: Path, e: Exception) -> str:
    """Why ``torch.load(weights_only=True)`` failed on ``path``, in words that name what the file holds.

    torch's own message leads with a banner that advises re-running with ``weights_only=False``: that is exactly the
    unsafe load streamdet never does (docs/trust.md), and the banner was all the first line showed. The reason is
    further down (the refused global, the pickle opcode); a file that is no pickle at all would fail that way too."""
    text = str(e)
    found = _REFUSED_GLOBAL.search(text)
    if found:
        return (f"it is a pickle that names the Python global {found.group(1)} (code or a class, not tensors and "
                "numbers), which a weights-only load refuses: not a plain checkpoint")  # fmt: skip
    kind = _file_kind(path)
    if kind is not None:
        return f"it is {kind}, not a file torch.save wrote"
    if _WEIGHTS_UNPICKLER in text:  # a pickle whose contents the weights-only unpickler does not know
        detail = " ".join(text.split(_WEIGHTS_UNPICKLER, 1)[1].split("Check the documentation", 1)[0].split())
        return f"its pickle holds what a weights-only load refuses ({detail or type(e).__name__})"
    # torch's zip reader appends advice on a corrupted file ("This is an internal miniz error. ..."): the first
    # sentence says what failed
    detail = first_line(e).split(". ", 1)[0].rstrip(".")
    if "weights_only" in detail:  # never repeat torch's advice to load without it
        detail = type(e).__name__
    return f"a damaged or cut-short torch file ({detail})"


def _file_kind(path: Path) -> str | None:
    """What ``path`` holds when it is surely no torch.save file (an empty file, text, a zip of other members, other
    bytes); None when it may be a damaged one (it starts as a zip or as a pickle, torch's legacy format)."""
    try:
        with open(path, "rb") as f:
            head = f.read(64)
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as z:
                names = z.namelist()
            if any(n.endswith("data.pkl") for n in names):
                return None
            return f"a zip archive without torch's data.pkl ({len(names)} member(s))"
    except (OSError, zipfile.BadZipFile, ValueError, EOFError):
        return None
    if not head:
        return "an empty file"
    if head.startswith((b"PK\x03\x04", b"\x80")):  # a zip cut short, or a pickle's PROTO opcode
        return None
    try:
        sample = head.decode("utf-8")
    except UnicodeDecodeError:
        return "neither a zip archive nor a pickle (binary data)"
    if all(c.isprintable() or c in "\r\n\t" for c in sample):
        return f"a text file (it starts {short_text(sample)})"
    return "neither a zip archive nor a pickle"


def short_text(text: str, limit: int = 24) -> str:
    """The first ``limit`` characters of ``text``, quoted, on one line."""
    line = " ".join(text.split())
    return repr(line[:limit] + ("..." if len(line) > limit else ""))


def check_state_dict(state: object, path: str | os.PathLike, what: str = "checkpoint", part: str = "model") -> dict[str, torch.Tensor]:
    """``state`` itself when it is a state dict: a dict of str keys and tensor values; ValueError naming the file
    and the first key that is not."""
    if not isinstance(state, Mapping):
        raise ValueError(f"{what} {path}: {part!r} is a {type(state).__name__}, not a state dict")
    for k, v in state.items():
        if not isinstance(k, str):
            raise ValueError(f"{what} {path}: {part!r} has a key {k!r} of type {type(k).__name__}, not a str")
        if not isinstance(v, torch.Tensor):
            raise ValueError(f"{what} {path}: {part}[{k!r}] is a {type(v).__name__}, not a tensor")
        check_dense(v, k, path, what)
    return dict(state)


def check_dense(tensor: torch.Tensor, key: str, path: str | os.PathLike, what: str = "checkpoint") -> None:
    """ValueError (one line, naming the file and ``key``) unless ``tensor`` is a dense tensor with data: a sparse
    (any non-strided layout), meta (shape only, no values), quantized or nested tensor loads under ``weights_only``
    but is no weight (``torch.isfinite`` and ``load_state_dict`` fail on it with a traceback, or load it silently)."""
    kind = None
    if tensor.is_meta:
        kind = "a meta tensor (a shape without values)"
    elif getattr(tensor, "is_nested", False):
        kind = "a nested tensor"
    elif tensor.layout != torch.strided:
        kind = f"a sparse tensor (layout {str(tensor.layout).removeprefix('torch.')})"
    elif tensor.is_quantized:
        kind = f"a quantized tensor ({tensor.dtype})"
    if kind is not None:
        raise ValueError(f"{what} {path}: {key} is {kind}, not a dense weight")


def check_fits(own: Mapping[str, torch.Tensor], state: Mapping[str, torch.Tensor], path: str | os.PathLike,
               what: str = "checkpoint", target: str = "the model", partial: bool = False) -> None:  # fmt: skip
    """ValueError (one line, naming the file) unless ``state`` (tensors, ``check_state_dict``) loads into a module whose
    state dict is ``own``: no missing keys (unless ``partial``), no unexpected ones, the same shapes, floating
    tensors where ``own`` has them, and finite values. Shapes only are read from ``own`` (a model on the meta
    device will do)."""
    for k, v in state.items():  # before the shapes: a sparse or meta tensor has one, and fails only on its values
        if isinstance(v, torch.Tensor):
            check_dense(v, k, path, what)
    missing = [] if partial else sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    mismatched = sorted(k for k in set(own) & set(state) if tuple(own[k].shape) != tuple(state[k].shape))
    if missing or unexpected or mismatched:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing keys (e.g. {missing[0]})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected keys (e.g. {unexpected[0]})")
        if mismatched:
            k = mismatched[0]
            parts.append(f"{len(mismatched)} shape mismatches (e.g. {k}: {tuple(state[k].shape)} vs {tuple(own[k].shape)})")
        raise ValueError(f"{what} {path} does not fit {target}: {'; '.join(parts)}")
    for k, v in state.items():
        if own[k].is_floating_point() and not v.is_floating_point():
            raise ValueError(f"{what} {path}: {k} holds {v.dtype} values where {target} has {own[k].dtype} weights")
        if (v.is_floating_point() or v.is_complex()) and v.numel() and not bool(torch.isfinite(v).all()):
            raise ValueError(f"{what} {path}: {k} holds non-finite values (NaN or inf)")
