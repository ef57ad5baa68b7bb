"""Shared fixtures. ROS tests stay on localhost; KITTI tests skip only outside CI. Helpers that are
not fixtures live in test/helpers/ (``from helpers.ros import domain_id_for``)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from helpers.env import KITTI_ROOT, in_ci

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    """The real KITTI sample. Skips with the reason on a fresh clone; fails in CI if absent."""
    if not (KITTI_ROOT / "odometry" / "sequences" / "06").is_dir():
        msg = f"KITTI sample not found at {KITTI_ROOT} (expected ../shared/data/kitti beside the repo)"
        if in_ci():
            pytest.fail(msg + "; CI=true requires it")
        pytest.skip(msg)
    return KITTI_ROOT


@pytest.fixture(scope="session")
def tool():
    """``tool("run_bag").main([...])``: the user-facing tools, called in-process."""
    from bevo_ros.cli import load_tool

    return load_tool
