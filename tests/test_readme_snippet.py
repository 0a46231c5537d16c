"""The README's Python API snippet runs as written (on a test export in place of the shipped one): a newcomer's first
copy-paste must not fail (it named a calibration file that does not exist)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from streamdet.runtime_ort import DetectorClosed

ROOT = Path(__file__).resolve().parents[1]
EXPORT_IN_README = '"exports/small_v3"'


def _api_snippet() -> str:
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Python API"):]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, "README: no python block under '## Python API'"
    return match.group(1)


def test_the_readme_api_snippet_runs(tiny_export, monkeypatch):
    code = _api_snippet()
    assert EXPORT_IN_README in code, "the snippet's export path changed: update this test"
    monkeypatch.chdir(ROOT)  # the snippet's relative paths are the repository's
    namespace: dict = {}
    exec(compile(code.replace(EXPORT_IN_README, repr(str(tiny_export))), "README.md", "exec"), namespace)
    det = namespace["det"]
    assert namespace["res"].slice_index == 2 and namespace["rec"].feeds("slice_head")
    with pytest.raises(DetectorClosed):  # the snippet ends with det.close()
        det.detect_slice(namespace["slices"][0], 0)
