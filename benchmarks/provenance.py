"""Where a benchmark result came from: the JSON's schema version, the code (streamdet's version, the git commit), the
export it timed (its manifest's sha256), and when and how it was run.

``streamdet-bench`` writes these at the head of its JSON ``meta`` in both modes (timing, ``--flops-only``), so that a
result file can be traced to the code and the export that made it, and a reader can tell which keys to expect
(docs/cli.md, "streamdet-bench": the schema). Nothing here may fail a run: what cannot be found is None.
"""

from __future__ import annotations

import datetime
import subprocess
from pathlib import Path

import streamdet

# The version of the JSON that streamdet-bench writes (docs/cli.md documents each). Results without the key are
# version 1: the files written before it (benchmarks/results_2026-12-0*.json), whose keys appeared over time.
# 2: schema_version, provenance, machine.cpu_identity, peak start / end probes, streaming phase rounds; --flops-only
# writes the same meta and "units".
SCHEMA_VERSION = 2
GIT_TIMEOUT_S = 5.0  # a git that hangs (a network file system, a lock) costs the run this much, no more
HERE = Path(__file__).resolve().parent


def _git(args: list[str], cwd: Path) -> str | None:
    """git's stdout (stripped), or None where git is missing, fails or hangs. ``--no-optional-locks``: a read never
    takes the index lock, which another git working in the same tree may hold."""
    try:
        done = subprocess.run(["git", "--no-optional-locks", *args], cwd=cwd, capture_output=True, text=True,
                              timeout=GIT_TIMEOUT_S, check=False)  # fmt: skip
    except (OSError, subprocess.SubprocessError, ValueError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def git_commit(source: Path = HERE) -> dict[str, str | bool | None]:
    """{"commit": the HEAD commit of the git checkout this code runs from, "dirty": whether its tracked files differ
    from it}; both None where there is no checkout (an installed wheel), no git, or ``source`` holds no tracked
    ``__init__.py`` (an installed copy in a virtual environment inside another checkout would otherwise report that
    checkout's commit). ``source``: this package's folder."""
    unknown: dict[str, str | bool | None] = {"commit": None, "dirty": None}
    if _git(["ls-files", "--error-unmatch", "--", "__init__.py"], source) is None:  # the package's, tracked for good
        return unknown
    commit = _git(["rev-parse", "--verify", "HEAD"], source)
    if commit is None:
        return unknown
    status = _git(["status", "--porcelain", "--untracked-files=no"], source)
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def manifest_sha256(export_dir: str | Path) -> str | None:
    """sha256 of the export's manifest.json (which holds every graph's and the LUT's sha256, so it names the whole
    export); None where it cannot be read."""
    from streamdet.runtime_ort.manifest import sha256_file

    try:
        return sha256_file(Path(export_dir) / "manifest.json")
    except OSError:
        return None


def provenance(command: str, mode: str) -> dict:
    """The head of the JSON ``meta``: schema_version, mode ("timing" or "flops-only"), streamdet_version,
    git_commit, git_dirty, date (local time, ISO 8601) and the command line."""
    git = git_commit()
    return {
        "schema_version": SCHEMA_VERSION,
        "mode": mode,
        "streamdet_version": streamdet.__version__,
        "git_commit": git["commit"],
        "git_dirty": git["dirty"],
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "command": command,
    }
