"""Shared fixtures. ROS tests stay on localhost; KITTI tests skip only outside CI."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

REPO = Path(__file__).resolve().parents[1]
KITTI_ROOT = Path(os.environ.get("BEVO_KITTI_ROOT", REPO.parent / "shared" / "data" / "kitti"))


def domain_id_for(module_index: int) -> int:
    """A test module's own ROS_DOMAIN_ID: ``BEVO_TEST_DOMAIN_BASE`` (default 60) + its index, so
    two checkouts testing side by side on one host keep their DDS traffic apart."""
    return int(os.environ.get("BEVO_TEST_DOMAIN_BASE", "60")) + module_index


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    """The real KITTI sample. Skips with the reason on a fresh clone; fails in CI if absent."""
    if not (KITTI_ROOT / "odometry" / "sequences" / "06").is_dir():
        msg = f"KITTI sample not found at {KITTI_ROOT} (expected ../shared/data/kitti beside the repo)"
        if in_ci():
            pytest.fail(msg + "; CI=true requires it")
        pytest.skip(msg)
    return KITTI_ROOT


def load_tool(name: str):
    """Import ``tools/<name>.py`` as a module (bevo_ros.cli's loader)."""
    from bevo_ros.cli import load_tool as load

    return load(name)


def ros_context(domain_id: int):
    """Body of a module's ``context`` fixture (``yield from ros_context(DOMAIN_ID)``): an rclpy
    context on the module's own domain, localhost only; torch's thread count restored afterwards
    (a node sets torch_threads process-wide)."""
    import rclpy
    import torch

    threads = torch.get_num_threads()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    yield ctx
    rclpy.shutdown(context=ctx)
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def tool():
    """``tool("run_bag").main([...])``: the user-facing tools, called in-process."""
    return load_tool


def make_bumpy_bag(path: Path, seconds: float = 6.0, seed: int = 3) -> Path:
    """Bumps x2 (suspension/bump events), IMU noise x2 (accelerometer vibration 1 m/s^2 RMS per
    axis), gentle curves, no road tilt, 620x188 images."""
    from bevo_ros.core.geometry import CameraModel
    from bevo_ros.datasets import write_drive_bag
    from bevo_ros.synthetic import RenderOptions, kitti_like_camera, make_drive

    cam = kitti_like_camera()
    K = cam.K.clone()
    K[:2] *= 0.5
    cam = CameraModel(K, 620, 188, cam.T_base_cam, cam.mount_height)
    drive = make_drive(seed=seed, duration=seconds, bumps=2.0, noise=2.0, render="lazy", camera=cam, curvature=0.3,
                       road_tilt=False, speed_variation=0.3, ground_seed=0,
                       render_options=RenderOptions(supersample=1))
    return write_drive_bag(drive, path, overwrite=True)
