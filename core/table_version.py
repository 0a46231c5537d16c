"""The table folder of a nuScenes-format dataset, ``ROOT/<version>/``: one plain folder name inside the root.

Every tool that reads or writes a dataset takes it as ``--version``. A path there (``../elsewhere``, ``/etc``, ``.``)
would read tables from outside the dataset, and an output checked against ``--data`` alone could then replace the
very table being read; so the name is checked once, here, for the reader (``data/nuscenes.py``), the writer
(``data/synth_writer.py``) and every CLI option (``streamdet.cli_utils.version_option``).
"""

from __future__ import annotations

DEFAULT_TABLE_VERSION = "v1.0-synth"  # the table folder streamdet-synth writes and every tool reads by default
MAX_NAME_BYTES = 255  # one file-system name (NAME_MAX on Linux and macOS)


def table_version_problem(version: object) -> str | None:
    """Why ``version`` cannot name a dataset's table folder, or None."""
    if type(version) is not str or version in ("", ".", "..") or any(c in version for c in "/\\\x00"):
        return (f"must be one folder name inside the dataset root (not empty, '.' or '..'; no '/', '\\' or NUL), "
                f"got {version!r}")
    if len(version.encode("utf-8", "surrogateescape")) > MAX_NAME_BYTES:
        return f"must be a folder name of at most {MAX_NAME_BYTES} bytes, got one of {len(version.encode('utf-8', 'surrogateescape'))}"
    return None
