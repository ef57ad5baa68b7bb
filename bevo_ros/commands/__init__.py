"""The ``bevo`` commands, one module each (``bevo_ros.cli`` runs them): ``build_parser()`` and
``main(argv) -> int``; argument parsing and messages only, the work is done by the package; errors
follow one convention (:func:`guarded`: message on stderr, exit code 2, Ctrl-C 130)."""
from __future__ import annotations

import argparse
import sys
import warnings
from typing import Callable, Mapping

from bevo_ros.config import package_file

DEFAULT_PARAMS = package_file("params/kitti.yaml")


def new_parser(doc: str | None, epilog: str | None = None) -> argparse.ArgumentParser:
    """A command's parser: its module docstring as the description, layout kept (examples, tables)."""
    return argparse.ArgumentParser(description=doc, epilog=epilog, formatter_class=argparse.RawDescriptionHelpFormatter)


def add_params_option(p: argparse.ArgumentParser, learned: bool = False) -> None:
    """``--params FILE``: the ROS parameters file (default params/kitti.yaml); with ``learned`` also
    ``--learned FILE``, the learned-parameters YAML overriding the one the parameters file names."""
    p.add_argument("--params", default=str(DEFAULT_PARAMS), help="ROS parameters file (default params/kitti.yaml)")
    if learned:
        p.add_argument("--learned", help="learned-parameters YAML (default: the one named in --params)")


def add_threads_option(p: argparse.ArgumentParser, why: str = "") -> None:
    """``--threads N``: torch CPU threads of a command that runs the engine or trains (default 1)."""
    p.add_argument("--threads", type=int, default=1, help=f"torch CPU threads (default 1{why})")


def set_threads(threads: int) -> None:
    """Apply ``--threads`` (0 or less keeps torch's default)."""
    if threads > 0:
        import torch

        torch.set_num_threads(threads)


def prog_name(prog: str) -> str:
    """What a command's messages start with: ``bevo COMMAND`` when run as that (``bevo_ros.cli`` sets
    ``sys.argv[0]``), else ``prog``, the executable's own name (``kitti_to_bag``)."""
    return sys.argv[0] if sys.argv and sys.argv[0].startswith("bevo ") else prog


def guarded(prog: str, work: Callable[[], int], errors: tuple[type[BaseException], ...],
            codes: Mapping[type[BaseException], int] | None = None, interrupted: str = "interrupted") -> int:
    """The commands' one error convention around ``work() -> exit code``: an expected error (one of
    ``errors``) prints ``PROG: error: MESSAGE`` on stderr and returns 2 (or ``codes[type]`` for the
    first type it is an instance of); Ctrl-C prints ``PROG: INTERRUPTED`` and returns 130. Anything
    else is a bug and propagates with its traceback. Run as ``bevo COMMAND`` (``bevo_ros.cli`` sets
    ``sys.argv[0]`` to it) PROG is that, as in the usage lines; ``prog`` names the executable run alone."""
    prog = prog_name(prog)

    def one_line(message, category, filename, lineno, line=None) -> str:
        # a warning is for the user, as an error is: one line naming the command, no source line
        # (the format only: a caller recording warnings, pytest.warns, still gets them)
        return f"{prog}: warning: {message}\n"

    previous = warnings.formatwarning  # (catch_warnings does not restore it)
    warnings.formatwarning = one_line
    try:
        return work()
    except errors as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return next((code for kind, code in (codes or {}).items() if isinstance(exc, kind)), 2)
    except KeyboardInterrupt:
        print(f"{prog}: {interrupted}", file=sys.stderr)
        return 130
    finally:
        warnings.formatwarning = previous


def bag_errors(*extra: type[BaseException]) -> tuple[type[BaseException], ...]:
    """The expected errors of a command that reads a parameters file and bags (``extra`` appended)."""
    from bevo_ros.config import ConfigError
    from bevo_ros.io.bag import BagError

    return (ConfigError, BagError, FileNotFoundError, ValueError, *extra)
