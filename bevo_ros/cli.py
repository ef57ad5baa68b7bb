"""The ``bevo`` command and the per-command executables.

``bevo COMMAND [ARGS]`` runs one job; each command is a module of :mod:`bevo_ros.commands` with
``build_parser()`` and ``main(argv) -> int`` (the library logic they call lives in the package)::

    bevo convert  KITTI (odometry or raw layout) -> rosbag2           bevo_ros.commands.convert
    bevo play     replay a rosbag2 into ROS topics (with /clock)        bevo_ros.commands.play
    bevo run      offline odometry over a rosbag2 (bevo_node's engine)  bevo_ros.commands.run
    bevo train    learn O/Q (and the vehicle filter's noise) from bags  bevo_ros.commands.train
    bevo evaluate metrics and plots against ground truth                bevo_ros.commands.evaluate
    bevo ablation the paper's ablation study (Table 3)                  bevo_ros.commands.ablation
    bevo calibrate the rig's static attitude on the road                bevo_ros.commands.calibrate
    bevo map      a BEVO+ map from a bag with ground truth              bevo_ros.commands.map
    bevo demo     the whole pipeline on a synthetic drive               bevo_ros.commands.demo
    bevo dump-config  every setting with its default, as a parameters YAML

Installed into the venv and into ``lib/bevo_ros`` (``ros2 run bevo_ros bevo run BAG --out OUT``).
One error convention: bad input prints ``bevo COMMAND: error: MESSAGE`` on stderr and exits 2
(``bevo train`` exits 3 when training diverged, any command 130 when interrupted).

The per-command executables (``play_bag``, ``run_bag``, ...; :data:`EXECUTABLES`) stay for the
launch file (``ExecutableInPackage``) and scripts. A command's module is imported when it runs, not
before: ``bevo --help`` should not pay for torch.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

# bevo COMMAND (= module bevo_ros.commands.<COMMAND>) -> one-line help
COMMANDS: dict[str, str] = {
    "convert": "KITTI (odometry or raw layout) -> rosbag2",
    "play": "replay a rosbag2 into ROS topics, with /clock and the recorded QoS",
    "run": "offline odometry over a rosbag2 with bevo_node's engine; trajectories to a folder",
    "train": "learn the DUKF's O and Q (and the vehicle filter's noise) from bags",
    "evaluate": "KITTI t_rel/r_rel, RPE, ATE, drift and plots against ground truth",
    "ablation": "the paper's ablation study (Table 3) on bags",
    "calibrate": "the rig's static pitch/roll on the road from a calibration drive",
    "map": "a BEVO+ map (nav2 map_server YAML + PNG) from a bag with ground truth",
    "demo": "the whole pipeline on a synthetic drive (and the KITTI sample when present)",
}
# executables in lib/bevo_ros -> the command they run (setup.py keeps a literal copy: it must not import the package)
EXECUTABLES = {"play_bag": "play", "kitti_to_bag": "convert", "run_bag": "run", "evaluate": "evaluate",
               "train_from_bag": "train", "calibrate_mounting": "calibrate", "map_from_bag": "map"}
DUMP_CONFIG = "dump-config"
EXIT_USAGE = 2  # bad input: message on stderr, like argparse


def command_module(command: str):
    """The module of ``bevo COMMAND``: ``bevo_ros.commands.<COMMAND>``."""
    if command not in COMMANDS:
        raise KeyError(f"no bevo command {command!r}")
    return importlib.import_module(f"bevo_ros.commands.{command}")


def run_command(command: str, argv: list[str]) -> int:
    """``bevo COMMAND ARGV`` in this process: the command module's ``main(argv)``."""
    return int(command_module(command).main(argv) or 0)


def _entry(executable: str):
    def main() -> int:
        try:
            return run_command(EXECUTABLES[executable], sys.argv[1:])
        except KeyboardInterrupt:
            print(f"{executable}: interrupted", file=sys.stderr)
            return 130

    main.__name__ = executable
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
    lines = [f"  {name:<{width}}  {text}" for name, text in COMMANDS.items()]
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
        "for a params file: `bevo dump-config --params params/kitti.yaml > my.yaml`, then `bevo run BAG --params "
        "my.yaml`. Without --params the defaults describe no particular rig (the mounting 0: calibrate it, `bevo "
        "calibrate`; a KITTI bag run with them drifts ~37 %)."))
    p.add_argument("--engine-only", action="store_true", help="only the engine's settings (BevoConfig)")
    p.add_argument("--params", help="start from this parameters file: every setting it makes, the defaults for the "
                                    "rest (e.g. params/kitti.yaml, the KITTI rig)")
    p.add_argument("--out", "-o", help="write to this file (atomically) instead of stdout")
    args = p.parse_args(argv)
    from bevo_ros.io.files import atomic_write_text
    from bevo_ros.config import dump_params_yaml

    config, flat = None, {}
    if args.params:
        from bevo_ros.config import ConfigError, load_config

        try:
            config, flat = load_config(args.params)
        except (ConfigError, FileNotFoundError, ValueError) as exc:
            print(f"bevo {DUMP_CONFIG}: error: {exc}", file=sys.stderr)
            return 2
        if "learned_params_file" in flat:
            # as the file wrote it if that still names the same file beside the dump (load_config made it
            # absolute: a relative name resolves beside the file that sets it), else the absolute path
            from bevo_ros.config import resolve_path

            written = str(flat["learned_params_file"])
            dump_dir = Path(args.out).resolve().parent if args.out else Path.cwd()
            if resolve_path(written, dump_dir) == Path(config.learned_params_file):
                config.learned_params_file = written
    node = None
    if not args.engine_only:
        try:
            from bevo_ros.ros.settings import DESCRIPTIONS, settings_from_flat

            node = (settings_from_flat(flat), DESCRIPTIONS)
        except ImportError as exc:  # no ROS in this environment: the engine's part still helps
            print(f"bevo {DUMP_CONFIG}: note: bevo_node's settings left out ({exc})", file=sys.stderr)
    text = dump_params_yaml(config, node_settings=node[0] if node else None, descriptions=node[1] if node else None)
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
    sys.argv[0] = f"bevo {command}"  # the commands' usage lines read `bevo COMMAND`
    try:
        if command == DUMP_CONFIG:
            return dump_config_main(rest)
        return run_command(command, rest)
    except (ConfigError, FileNotFoundError, ValueError, OSError) as exc:  # bad input the command did not catch
        print(f"bevo {command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"bevo {command}: interrupted", file=sys.stderr)
        return 130
    except SystemExit as exc:  # argparse in the command: --help (0) or a usage error (2)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else EXIT_USAGE)
    finally:
        sys.argv[0] = prog


if __name__ == "__main__":
    sys.exit(main())
