"""The scripts in tools/ (benchmarks and build helpers, not part of the package) imported as modules;
the ``bevo`` commands are package modules (``bevo_ros.commands``) and are imported as such."""
from __future__ import annotations

import importlib.util
import sys

from helpers.env import REPO


def load_tool(name: str):
    """Import ``tools/<name>.py`` (e.g. ``record_pinned``, ``opencv_reference``)."""
    spec = importlib.util.spec_from_file_location(f"bevo_tool_{name}", REPO / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses in the script need their module registered
    spec.loader.exec_module(module)
    return module
