"""streamdet.replay stays torch-free: importing all of it loads neither torch nor the training-side packages."""

from __future__ import annotations

import subprocess
import sys

MODULES = ("clock", "source", "nuscenes_source", "schedule", "record", "modes", "player", "truth", "latency_eval", "run",
           "report", "plot", "cost", "cli")  # fmt: skip
FORBIDDEN = ("torch", "streamdet.models", "streamdet.export", "streamdet.training", "streamdet.benchmarks")


def test_replay_imports_no_torch_nor_training_side_packages():
    code = (
        "import sys\n"
        + "".join(f"import streamdet.replay.{m}\n" for m in MODULES)
        + f"bad = [m for m in sys.modules if any(m == f or m.startswith(f + '.') for f in {FORBIDDEN!r})]\n"
        + "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"streamdet.replay imported {out.stdout.strip()}"
