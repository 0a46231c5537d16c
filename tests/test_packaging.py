"""Packaging: every subpackage survives a regular (non-editable) install; the vehicle-side packages never need torch."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the dev extra installs tomli
    import tomli as tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TORCH_FREE = ("calibration", "core", "runtime_ort", "evaluation", "data")  # their sources: tests/test_import_graph.py

# Makes `import torch` (and onnxscript / onnxconverter_common, which pull torch-side helpers) fail.
BLOCK_TORCH = textwrap.dedent(
    """
    import sys
    class _Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("torch", "torchvision", "onnxscript", "onnxconverter_common"):
                raise ImportError(f"{name} is blocked in this test")
            return None
    sys.meta_path.insert(0, _Block())
    """
)


def _declared_packages() -> list[str]:
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return cfg["tool"]["setuptools"]["packages"]


def test_every_package_folder_is_declared():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    mapping = cfg["tool"]["setuptools"]["package-dir"]
    assert sorted(mapping) == sorted(_declared_packages())
    for pkg, folder in mapping.items():
        assert (ROOT / folder / "__init__.py").is_file(), f"{pkg} -> {folder}/ has no __init__.py"
    # A folder with Python code that is not mapped would silently vanish from a regular install.
    mapped = set(mapping.values())
    for d in ROOT.iterdir():
        if d.is_dir() and (d / "__init__.py").exists() and d.name not in ("tests",):
            assert d.name in mapped, f"{d.name}/ has an __init__.py but is not listed in pyproject.toml"


def test_the_version_is_written_once():
    """pyproject.toml takes its version from streamdet.__version__; the installed metadata says the same."""
    import importlib.metadata

    import streamdet

    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" not in cfg["project"] and "version" in cfg["project"]["dynamic"]
    assert cfg["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "streamdet.__version__"}
    assert importlib.metadata.version("streamdet") == streamdet.__version__


def test_the_licenses_ship_with_the_package():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    for path in cfg["project"]["license-files"]:
        assert (ROOT / path).is_file(), path
    assert "Apache License" in (ROOT / "LICENSE").read_text()


@pytest.mark.slow
def test_regular_install_imports(tmp_path):
    wheel_dir = tmp_path / "wheel"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(wheel_dir), str(ROOT)],
        check=True,
        capture_output=True,
    )
    (wheel,) = wheel_dir.glob("streamdet-*.whl")
    site = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site), str(wheel)],
        check=True,
        capture_output=True,
    )
    code = "import importlib, sys\n" + "".join(f"importlib.import_module({p!r})\n" for p in _declared_packages())
    code += "import streamdet, importlib.resources as r\n"
    code += "assert streamdet.__file__.startswith(sys.argv[1]), streamdet.__file__\n"
    code += "assert (r.files('streamdet.data') / 'nuscenes_sample' / 'calibration.json').is_file()\n"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = str(site)
    # -I would drop PYTHONPATH; run from tmp so the source tree is not on sys.path.
    subprocess.run([sys.executable, "-c", code, str(site)], check=True, cwd=tmp_path, env=env)
    # From the checkout's root, where a user of the installed package works (the README's paths are relative to it):
    # sys.path[0] is the checkout, and nothing there may hide the installed package (a streamdet/ folder did).
    subprocess.run([sys.executable, "-c", code, str(site)], check=True, cwd=ROOT, env=env)


def test_no_folder_of_the_checkout_hides_the_installed_package():
    """Python puts the current folder first on sys.path: a checkout folder named like the package (or an importable
    streamdet.py) would be imported instead of the installed package, without its subpackages."""
    assert not (ROOT / "streamdet").exists() and not (ROOT / "streamdet.py").exists()


@pytest.mark.parametrize("package", TORCH_FREE)
def test_vehicle_side_imports_without_torch(package):
    code = BLOCK_TORCH + f"import streamdet.{package}\n"
    code += "import pkgutil, importlib, streamdet.{0} as p\n".format(package)
    code += "for m in pkgutil.iter_modules(p.__path__):\n    importlib.import_module(p.__name__ + '.' + m.name)\n"
    code += "assert 'torch' not in sys.modules\n"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_every_module_imports():
    """Every module of every declared package imports (a module nothing else imports, such as a benchmark's entry
    point, would otherwise break unseen when a helper it imports moves). Optional extras absent here are skipped."""
    import importlib
    import pkgutil

    optional = ("mcap", "mcap_ros2", "rosbags", "matplotlib")  # the extras a module may need (pyproject.toml)
    failed = []
    for package in _declared_packages():
        pkg = importlib.import_module(package)
        for info in pkgutil.iter_modules(getattr(pkg, "__path__", [])):
            name = f"{package}.{info.name}"
            try:
                importlib.import_module(name)
            except ImportError as e:
                if getattr(e, "name", None) and e.name.split(".")[0] in optional:
                    continue
                failed.append(f"{name}: {e}")
    assert not failed, failed


def test_the_extras_hints_name_real_extras():
    """cli_utils.EXTRA_MODULES names the extras whose missing modules get a hint: each is one of pyproject.toml's, and
    each module is what one of its requirements installs."""
    import re

    from streamdet.cli_utils import EXTRA_MODULES

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for extra, modules in EXTRA_MODULES.items():
        assert extra in extras
        dists = {re.split(r"[<>=;\[ ]", r, maxsplit=1)[0].lower().replace("-", "_") for r in extras[extra]}
        for module in modules:
            assert any(d == module or d.startswith(module + "_") for d in dists), (extra, module, dists)
