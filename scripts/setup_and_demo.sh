#!/usr/bin/env bash
# Set-up command 1 of the README: create .venv, install everything (torch pinned first; a CPU build already in
# .venv is kept, else pip picks the build: on Linux x86-64 PyPI's is the multi-GB CUDA one, see the README),
# export the shipped model with its fp16 siblings, and benchmark it at 800x450.
# Command 2 (the tests) is the one .ci/run runs: .venv/bin/python -m pytest -q
set -euo pipefail
cd "$(dirname "$0")/.."
export PIP_DISABLE_PIP_VERSION_CHECK=1
if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
fi
.venv/bin/pip install -q torch==2.13.0
.venv/bin/pip install -q -e ".[export,dev]"
.venv/bin/streamdet-export --fp16
# the folder streamdet-export writes without --out (exports/<the shipped model's preset>)
export_dir=$(.venv/bin/python -c "from streamdet.core.constants import DEFAULT_EXPORT_DIR; print(DEFAULT_EXPORT_DIR)")
.venv/bin/streamdet-bench --resolution 800x450 --export-dir "$export_dir"
