"""Synthetic bags with exact ground truth for the tests (and tools/record_pinned.py)."""
from __future__ import annotations

from pathlib import Path


def make_bumpy_bag(path: Path, seconds: float = 6.0, seed: int = 3) -> Path:
    """Bumps x2 (suspension/bump events), IMU noise x2 (accelerometer vibration 1 m/s^2 RMS per
    axis), gentle curves, no road tilt, 620x188 images."""
    from bevo_ros.datasets.rosbag import write_drive_bag
    from bevo_ros.datasets.synthetic import RenderOptions, kitti_like_camera, make_drive

    cam = kitti_like_camera(scale=0.5)
    drive = make_drive(seed=seed, duration=seconds, bumps=2.0, noise=2.0, render="lazy", camera=cam, curvature=0.3,
                       road_tilt=False, speed_variation=0.3, ground_seed=0,
                       render_options=RenderOptions(supersample=1))
    return write_drive_bag(drive, path, overwrite=True)
