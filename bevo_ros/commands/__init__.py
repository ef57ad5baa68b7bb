"""The ``bevo`` commands, one module each (``bevo_ros.cli`` runs them): ``build_parser()`` and
``main(argv) -> int``; argument parsing and messages only, the work is done by the package."""
from __future__ import annotations

import argparse


def add_threads_option(p: argparse.ArgumentParser, why: str = "") -> None:
    """``--threads N``: torch CPU threads of a command that runs the engine or trains (default 1)."""
    p.add_argument("--threads", type=int, default=1, help=f"torch CPU threads (default 1{why})")


def set_threads(threads: int) -> None:
    """Apply ``--threads`` (0 or less keeps torch's default)."""
    if threads > 0:
        import torch

        torch.set_num_threads(threads)
