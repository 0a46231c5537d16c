"""Reporting an exception in one line (numpy only; imports nothing else of streamdet)."""

from __future__ import annotations


def first_line(e: BaseException) -> str:
    """The first non-blank line of ``e``'s message, or its type's name where the message is empty.

    Torch's and ONNX's errors run over many lines (a list of every mismatched key); a CLI or a wrapping error
    quotes only the first. ``str(e).splitlines()[0]`` raised IndexError on an empty message.
    """
    for line in str(e).splitlines():
        if line.strip():
            return line.strip()
    return type(e).__name__
