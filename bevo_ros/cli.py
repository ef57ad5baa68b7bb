"""Console entry points for the tools in ``tools/`` (installed as ``lib/bevo_ros/<name>``, so
``ros2 run bevo_ros play_bag BAG`` and the launch file's bag replay find them).

The tools stay scripts (``tools/<name>.py``, run from a checkout as they are); an installed
package carries them in ``share/bevo_ros/tools`` and these wrappers load them from there.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

TOOLS = ("play_bag", "kitti_to_bag", "run_bag", "evaluate", "train_from_bag", "calibrate_mounting", "map_from_bag")


def _tools_dir() -> Path:
    here = Path(__file__).resolve().parents[1] / "tools"  # source checkout / editable install
    if (here / "play_bag.py").is_file():
        return here
    from ament_index_python.packages import get_package_share_directory

    return Path(get_package_share_directory("bevo_ros")) / "tools"


def run_tool(name: str, argv: list[str] | None = None) -> int:
    """Import ``tools/<name>.py`` and return its ``main(argv)``."""
    path = _tools_dir() / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"bevo_tool_{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses in the tool need their module registered
    spec.loader.exec_module(module)
    return int(module.main(sys.argv[1:] if argv is None else argv) or 0)


def _entry(name: str):
    def main() -> int:
        try:
            return run_tool(name)
        except KeyboardInterrupt:
            print(f"{name}: interrupted", file=sys.stderr)
            return 130

    main.__name__ = name
    return main


play_bag = _entry("play_bag")
kitti_to_bag = _entry("kitti_to_bag")
run_bag = _entry("run_bag")
evaluate = _entry("evaluate")
train_from_bag = _entry("train_from_bag")
calibrate_mounting = _entry("calibrate_mounting")
map_from_bag = _entry("map_from_bag")
