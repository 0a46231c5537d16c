"""The optional MCAP libraries, imported on first use with a one-line hint when they are missing."""

from __future__ import annotations

import importlib
from types import ModuleType

INSTALL_HINT = "pip install 'streamdet[ros]'; from a checkout: pip install '.[ros]'"


class MissingExtraError(ImportError):
    """The ``ros`` extra (mcap, mcap-ros2-support) is not installed."""


def require(module: str) -> ModuleType:
    """``importlib.import_module(module)``, or MissingExtraError naming the extra to install."""
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise MissingExtraError(f"streamdet-bag needs {e.name or module} ({INSTALL_HINT})") from None
