"""Where things are: the repository, the KITTI sample; whether this is CI."""
from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
KITTI_ROOT = Path(os.environ.get("BEVO_KITTI_ROOT", REPO.parent / "shared" / "data" / "kitti"))


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def skip_outside_ci(reason: str) -> None:
    """Skip for a missing prerequisite that ``make setup`` provides; in CI (``CI=true``) the same is
    a failure: a green CI run must not have skipped what it was set up to test."""
    import pytest

    if in_ci():
        pytest.fail(f"{reason}; CI=true requires it", pytrace=False)
    pytest.skip(reason)


def import_outside_ci(name: str, reason: str):
    """``pytest.importorskip(name)``, a failure in CI (:func:`skip_outside_ci`)."""
    import importlib

    try:
        return importlib.import_module(name)
    except ImportError:
        skip_outside_ci(f"{name} cannot be imported ({reason})")
