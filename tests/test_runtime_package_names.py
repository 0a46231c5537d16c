"""The runtime package's lazy names are the same objects whatever was imported before them: ``pillarize``, a
submodule and the function it defines, is not one of them (it was the function in a fresh process and the submodule
once StreamingDetector had been imported, which imports the submodule)."""

from __future__ import annotations

import importlib
import subprocess
import sys
import types

import pytest

import streamdet.runtime_ort as runtime

PROBE = """
import types
{before}
from streamdet.runtime_ort import pillarize
print(isinstance(pillarize, types.ModuleType), callable(pillarize.pillarize))
"""


@pytest.mark.parametrize("before", ["", "from streamdet.runtime_ort import StreamingDetector"])
def test_pillarize_from_the_package_is_its_module_whatever_came_first(before):
    out = subprocess.run([sys.executable, "-c", PROBE.format(before=before)], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "True"], out


@pytest.mark.parametrize("name", runtime.__all__)
def test_every_exported_name_is_its_modules_object_not_a_submodule(name):
    obj = getattr(runtime, name)
    assert not isinstance(obj, types.ModuleType), name
    assert obj is getattr(importlib.import_module(runtime._EXPORTS[name]), name)
