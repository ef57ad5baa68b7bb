"""Where things are: the repository, the KITTI sample; whether this is CI."""
from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
KITTI_ROOT = Path(os.environ.get("BEVO_KITTI_ROOT", REPO.parent / "shared" / "data" / "kitti"))


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")
