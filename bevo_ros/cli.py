"""The ``bevo`` command and the console entry points of the tools in ``tools/``.

``bevo COMMAND [ARGS]`` runs one job; each command delegates to its tool's ``main(argv)``::

    bevo convert  KITTI (odometry or raw layout) -> rosbag2           tools/kitti_to_bag.py
    bevo play     replay a rosbag2 into ROS topics (with /clock)        tools/play_bag.py
    bevo run      offline odometry over a rosbag2 (bevo_node's engine)  tools/run_bag.py
    bevo train    learn O/Q (and the vehicle filter's noise) from bags  tools/train_from_bag.py
    bevo evaluate metrics and plots against ground truth                tools/evaluate.py
    bevo ablation the paper's ablation study (Table 3)                  tools/ablation.py
    bevo calibrate the rig's static attitude on the road                tools/calibrate_mounting.py
    bevo map      a BEVO+ map from a bag with ground truth              tools/map_from_bag.py
    bevo demo     the whole pipeline on a synthetic drive               tools/demo.py
    bevo dump-config  every setting with its default, as a parameters YAML

Installed into the venv and into ``lib/bevo_ros`` (``ros2 run bevo_ros bevo run BAG --out OUT``).
One error convention: bad input prints ``bevo COMMAND: error: MESSAGE`` on stderr and exits 2
(``bevo train`` exits 3 when training diverged, any command 130 when interrupted).

The tools stay scripts (``tools/<name>.py``, runnable from a checkout); an installed package
carries them in ``share/bevo_ros/tools`` and :func:`run_tool` loads them from there. The per-tool
executables (``play_bag``, ...) stay for the launch file (``ExecutableInPackage``) and scripts.
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

# per-tool executables in lib/bevo_ros (setup.py keeps a literal copy: it must not import the package)
TOOLS = ("play_bag", "kitti_to_bag", "run_bag", "evaluate", "train_from_bag", "calibrate_mounting", "map_from_bag")

# bevo COMMAND -> (tool, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "convert": ("kitti_to_bag", "KITTI (odometry or raw layout) -> rosbag2"),
    "play": ("play_bag", "replay a rosbag2 into ROS topics, with /clock and the recorded QoS"),
    "run": ("run_bag", "offline odometry over a rosbag2 with bevo_node's engine; trajectories to a folder"),
    "train": ("train_from_bag", "learn the DUKF's O and Q (and the vehicle filter's noise) from bags"),
    "evaluate": ("evaluate", "KITTI t_rel/r_rel, RPE, ATE, drift and plots against ground truth"),
    "ablation": ("ablation", "the paper's ablation study (Table 3) on bags"),
    "calibrate": ("calibrate_mounting", "the rig's static pitch/roll on the road from a calibration drive"),
    "map": ("map_from_bag", "a BEVO+ map (nav2 map_server YAML + PNG) from a bag with ground truth"),
    "demo": ("demo", "the whole pipeline on a synthetic drive (and the KITTI sample when present)"),
}
DUMP_CONFIG = "dump-config"
EXIT_USAGE = 2  # bad input: message on stderr, like argparse


def _tools_dir() -> Path:
    here = Path(__file__).resolve().parents[1] / "tools"  # source checkout / editable install
    if (here / "play_bag.py").is_file():
        return here
    from ament_index_python.packages import get_package_share_directory

    return Path(get_package_share_directory("bevo_ros")) / "tools"


def load_tool(name: str):
    """Import ``tools/<name>.py`` (the checkout's, else the installed share's) as a module: the one
    loader of the tools (tools/ holds scripts, not a package), for bevo, the tools and the tests."""
    path = _tools_dir() / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"bevo_tool_{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses in the tool need their module registered
    spec.loader.exec_module(module)
    return module


def run_tool(name: str, argv: list[str] | None = None) -> int:
    """Import ``tools/<name>.py`` and return its ``main(argv)``."""
    return int(load_tool(name).main(sys.argv[1:] if argv is None else argv) or 0)


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


def build_parser() -> argparse.ArgumentParser:
    width = max(map(len, [*COMMANDS, DUMP_CONFIG]))
    lines = [f"  {name:<{width}}  {text}" for name, (_, text) in COMMANDS.items()]
    lines.append(f"  {DUMP_CONFIG:<{width}}  every setting with its default, as a parameters YAML")
    p = argparse.ArgumentParser(
        prog="bevo", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="BEVO: BEV-based visual-inertial odometry. `bevo COMMAND --help` shows a command's options.",
        epilog="commands:\n" + "\n".join(lines) + "\n\nexit status: 0 done, 2 bad input (message on stderr), "
               "3 training diverged, 130 interrupted")
    p.add_argument("command", metavar="COMMAND", choices=[*COMMANDS, DUMP_CONFIG], help="one of the commands below")
    return p


def dump_config_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog=f"bevo {DUMP_CONFIG}", description=(
        "Print every setting with its default and description as a ROS 2 parameters YAML (the engine's "
        "bevo_ros.config.BevoConfig and, when rclpy is importable, bevo_node's own settings); a starting point "
        "for a params file: `bevo dump-config > my.yaml`, then `bevo run BAG --params my.yaml`."))
    p.add_argument("--engine-only", action="store_true", help="only the engine's settings (BevoConfig)")
    p.add_argument("--out", "-o", help="write to this file (atomically) instead of stdout")
    args = p.parse_args(argv)
    from bevo_ros.config import atomic_write_text, dump_params_yaml

    node = None
    if not args.engine_only:
        try:
            from bevo_ros.ros.settings import DESCRIPTIONS, NodeSettings

            node = (NodeSettings(), DESCRIPTIONS)
        except ImportError as exc:  # no ROS in this environment: the engine's part still helps
            print(f"bevo {DUMP_CONFIG}: note: bevo_node's settings left out ({exc})", file=sys.stderr)
    text = dump_params_yaml(node_settings=node[0] if node else None, descriptions=node[1] if node else None)
    if args.out:
        atomic_write_text(args.out, text)
    else:
        sys.stdout.write(text)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``bevo COMMAND [ARGS]``: the console script."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help(sys.stdout if argv else sys.stderr)
        return 0 if argv else EXIT_USAGE
    try:
        command, rest = parser.parse_args(argv[:1]).command, argv[1:]
    except SystemExit:  # an unknown command: argparse printed the usage and the choices
        return EXIT_USAGE
    from bevo_ros.config import ConfigError

    prog = sys.argv[0]
    sys.argv[0] = f"bevo {command}"  # the tools' usage lines read `bevo COMMAND`
    try:
        if command == DUMP_CONFIG:
            return dump_config_main(rest)
        return run_tool(COMMANDS[command][0], rest)
    except (ConfigError, FileNotFoundError, ValueError, OSError) as exc:  # bad input the tool did not catch
        print(f"bevo {command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"bevo {command}: interrupted", file=sys.stderr)
        return 130
    except SystemExit as exc:  # argparse in the tool: --help (0) or a usage error (2)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else EXIT_USAGE)
    finally:
        sys.argv[0] = prog


if __name__ == "__main__":
    sys.exit(main())
