"""The shell scripts of benchmarks/: each parses, and the issue-22 line check refuses bad arguments before any work."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = sorted((REPO / "benchmarks").glob("*.sh"))

pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_script_parses(script: Path) -> None:
    done = subprocess.run(["bash", "-n", str(script)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize(
    ("args", "env", "message"),
    [
        (["0"], {}, "ROUNDS must be a positive integer, got '0'"),
        (["two"], {}, "ROUNDS must be a positive integer, got 'two'"),
        (["1"], {"ISA": "avx512"}, "ISA must be avx2 or empty"),
    ],
)
def test_issue22_line_refuses_bad_arguments_before_any_work(tmp_path: Path, args, env, message) -> None:
    out = tmp_path / "out"
    done = subprocess.run(
        ["bash", str(REPO / "benchmarks" / "issue22_line.sh"), str(out), *args],
        capture_output=True, text=True, cwd=REPO, env={"PATH": "/usr/bin:/bin", "BIN": str(tmp_path / "nowhere"), **env},
    )  # fmt: skip
    assert done.returncode == 2
    assert message in done.stderr
    assert not out.exists()
