"""core.errors.first_line: the one-line report of an exception, for empty and multi-line messages."""

from __future__ import annotations

import pytest

from streamdet.core.errors import first_line


@pytest.mark.parametrize(
    "error, expected",
    [
        (ValueError("bad value 3"), "bad value 3"),
        (RuntimeError("Error(s) in loading state_dict:\n\tMissing key(s): a.b\n\tUnexpected: c"), "Error(s) in loading state_dict:"),
        (RuntimeError("\n\n  first real line  \nsecond"), "first real line"),
        (ValueError(), "ValueError"),  # str(e).splitlines()[0] raised IndexError here
        (KeyError(""), "''"),  # a KeyError's message is the repr of its key
        (OSError("   \n \t"), "OSError"),
    ],
)
def test_first_line(error, expected):
    assert first_line(error) == expected
