"""BEVO+ on the KITTI sample: a map mosaicked by bevo map from the even frames' BEVs
with the ground-truth poses (a "previous drive"), then the odometry of the drive localised in it
with the odd frames' BEVs only, from a wrong initial pose."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from bevo_ros.commands import convert, map as map_command, run
from bevo_ros.config import load_config
from bevo_ros.core.geometry import BevSpec
from bevo_ros.core.map_localization import LocalizerConfig, MapLocalizer, se2_compose, wrap
from bevo_ros.datasets.rosbag import gt_at
from bevo_ros.io.maps import load_map
from bevo_ros.pipeline import run_bag, xy_yaw_from_4x4

pytestmark = [pytest.mark.kitti, pytest.mark.timeout(300)]


def test_kitti_localises_in_a_previous_drive_map_from_a_wrong_start(kitti_root, tmp_path):
    torch.set_num_threads(1)
    bag_path = tmp_path / "kitti06"
    assert convert.main(["--odometry", str(kitti_root / "odometry"), "--sequence", "06",
                                      "-o", str(bag_path), "-q"]) == 0
    map_yaml = tmp_path / "map" / "kitti06.yaml"
    assert map_command.main([str(bag_path), "--out", str(map_yaml), "--every", "2",
                                      "--resolution", "0.2"]) == 0
    aerial = load_map(map_yaml)
    assert aerial.valid is not None and aerial.resolution == pytest.approx(0.2, rel=1e-3)

    config, _ = load_config(run.DEFAULT_PARAMS)
    steps, rec, _ = run_bag(bag_path, config, config.learned_params_file)
    gt4 = gt_at(np.array([s.stamp for s in steps]), rec.gt_stamps, rec.gt_poses)
    gt = xy_yaw_from_4x4(gt4)
    spec = BevSpec(config.bev.size, config.bev.metres_per_pixel, config.bev.forward_offset)
    cfg = LocalizerConfig(match=LocalizerConfig().match.__class__(resolution=0.2), mosaic_length=16.0,
                          min_mosaic_length=8.0, update_distance=2.0)
    loc = MapLocalizer(aerial, spec, cfg)
    start = se2_compose(gt[0], np.array([2.0 / math.sqrt(2), 2.0 / math.sqrt(2), math.radians(3.0)]))
    loc.set_initial_pose(start, np.diag([2.0**2, 2.0**2, math.radians(3.0) ** 2]))
    est, first_fix = [start], None
    for i, s in enumerate(steps[1:], start=1):
        out = loc.step_odometry(s, use_bev=(i % 2 == 1))  # odd frames: not in the map
        est.append(out.pose)
        if out.accepted and first_fix is None:
            first_fix = i
    est = np.array(est)
    odo = se2_compose(np.broadcast_to(start, est.shape),
                      np.array([[s.position[0], s.position[1], s.rpy[2]] for s in steps]))
    err = np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)
    yaw = np.degrees(np.abs(wrap(est[:, 2] - gt[:, 2])))
    err_odo = np.linalg.norm(odo[:, :2] - gt[:, :2], axis=1)
    c = loc.counters
    print(f"\n[KITTI BEVO+] {len(steps)} frames, {c.measurements} map measurements, {c.accepted} accepted, "
          f"{c.rejected_quality} low quality, {c.rejected_gate} gated; start error 2.0 m / 3.0 deg; "
          f"first accepted update at frame {first_fix}: error {err[first_fix - 1]:.2f} m -> {err[first_fix]:.2f} m; "
          f"after it: mean {err[first_fix:].mean():.2f} m / {yaw[first_fix:].mean():.2f} deg, max {err[first_fix:].max():.2f} m "
          f"(odometry alone from the same start: mean {err_odo[first_fix:].mean():.2f} m / "
          f"{np.degrees(np.abs(wrap(odo[first_fix:, 2] - gt[first_fix:, 2]))).mean():.2f} deg)")
    assert c.accepted >= 0.8 * c.measurements >= 8
    assert first_fix is not None and err[first_fix] < 0.5 < err[first_fix - 1]
    assert err[first_fix:].mean() < 0.8 and yaw[first_fix:].mean() < 2.0
    assert err[first_fix:].mean() < 0.5 * err_odo[first_fix:].mean()
