"""The ``bevo`` commands, one module each (``bevo_ros.cli`` runs them): ``build_parser()`` and
``main(argv) -> int``; argument parsing and messages only, the work is done by the package; errors
follow one convention (:func:`guarded`: message on stderr, exit code 2, Ctrl-C 130)."""
from __future__ import annotations

import argparse
import sys
from typing import Callable, Mapping


def add_threads_option(p: argparse.ArgumentParser, why: str = "") -> None:
    """``--threads N``: torch CPU threads of a command that runs the engine or trains (default 1)."""
    p.add_argument("--threads", type=int, default=1, help=f"torch CPU threads (default 1{why})")


def set_threads(threads: int) -> None:
    """Apply ``--threads`` (0 or less keeps torch's default)."""
    if threads > 0:
        import torch

        torch.set_num_threads(threads)


def guarded(prog: str, work: Callable[[], int], errors: tuple[type[BaseException], ...],
            codes: Mapping[type[BaseException], int] | None = None, interrupted: str = "interrupted") -> int:
    """The commands' one error convention around ``work() -> exit code``: an expected error (one of
    ``errors``) prints ``PROG: error: MESSAGE`` on stderr and returns 2 (or ``codes[type]`` for the
    first type it is an instance of); Ctrl-C prints ``PROG: INTERRUPTED`` and returns 130. Anything
    else is a bug and propagates with its traceback."""
    try:
        return work()
    except errors as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return next((code for kind, code in (codes or {}).items() if isinstance(exc, kind)), 2)
    except KeyboardInterrupt:
        print(f"{prog}: {interrupted}", file=sys.stderr)
        return 130
