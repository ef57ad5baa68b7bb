#!/usr/bin/env python3
"""Run BEVO offline over a rosbag2, with the very engine bevo_node runs, and no DDS.

Messages are fed to bevo_ros.core.odometry.BevoOdometry in bag order, exactly as the node feeds
them, so the trajectory equals the node's. Writes into --out:

  trajectory_kitti.txt  camera-0 poses, 3x4 row-major per line, one per frame, first = identity
                        (directly comparable with KITTI poses/NN.txt)
  trajectory_tum.txt    base_link in odom: stamp tx ty tz qx qy qz qw
  gt_kitti.txt          ground truth in the same convention, when the bag has /ground_truth/odometry
  pitch_roll.csv        stamp, filtered pitch and roll, and the reference (OXTS) attitude
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

try:
    import bevo_ros  # noqa: F401
except ImportError:  # running from a source checkout without installing
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from bevo_ros import bag, kitti
from bevo_ros.config import BevoConfig, ConfigError, REPO_ROOT, atomic_write_text, build_odometry, load_config, \
    load_learned_params
from bevo_ros.core.odometry import BevoOdometry, OdometryStep, OutOfOrderError
from bevo_ros.core.pose import pose_matrix
from bevo_ros.datasets import camera_for_recording, gt_at
from bevo_ros.ros_conversions import quaternion_from_rpy, stamp_to_ns, stamp_to_sec

DEFAULT_PARAMS = REPO_ROOT / "params" / "kitti.yaml"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", help="rosbag2 directory (sqlite3 or mcap)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--params", default=str(DEFAULT_PARAMS), help="ROS parameters file (default params/kitti.yaml)")
    p.add_argument("--learned", help="learned-parameters YAML (default: the one named in --params)")
    p.add_argument("--imu-topic", default=bag.IMU_TOPIC)
    p.add_argument("--image-topic", default=bag.IMAGE_TOPIC)
    p.add_argument("--first-frame", type=int, default=0, help="start the odometry at this frame (IMU before it warms the filter)")
    p.add_argument("--mode", choices=("fused", "paper"), help="override odometry.mode of --params (fused: the default "
                   "acceleration-aware, gyro-yaw, motion-filtered odometry; paper: the paper's pipeline)")
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default 1, as bevo_node's torch_threads: same arithmetic, same result)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    return p


def run(bag_path: str | Path, config: BevoConfig, learned_path: str | Path, imu_topic: str = bag.IMU_TOPIC,
        image_topic: str = bag.IMAGE_TOPIC, first_frame: int = 0, progress: bool = False) -> tuple[list[OdometryStep], bag.Recording, BevoOdometry]:
    """Feed a bag through the engine; returns the per-frame results, the recording (no images) and the engine."""
    rec = bag.read_recording(bag_path, imu_topic=imu_topic, image_topic=image_topic, load_images=False)
    odo = build_odometry(config, load_learned_params(learned_path), camera=camera_for_recording(rec, config))
    first_stamp = rec.frame_stamps_ns[first_frame] if first_frame else None
    steps: list[OdometryStep] = []
    drops: dict[str, int] = {}
    total = len(rec.frame_stamps_ns)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", desc="run_bag")
    for topic, stamp_ns, msg in bag.iter_messages(bag_path, [imu_topic, image_topic]):
        stamp_ns = stamp_to_ns(msg.header.stamp)
        stamp = stamp_to_sec(msg.header.stamp)  # the node's conversion: bit-identical floats
        try:
            if topic == imu_topic:
                a, g = msg.linear_acceleration, msg.angular_velocity
                out = odo.add_imu(stamp, (g.x, g.y, g.z), (a.x, a.y, a.z))
            else:
                if bar is not None:
                    bar.update(1)
                if first_stamp is not None and stamp_ns < first_stamp:
                    continue
                out = odo.add_image(stamp, bag.decode_image(msg))
        except (ValueError, OutOfOrderError) as exc:  # the node drops and counts these too
            reason = getattr(exc, "reason", type(exc).__name__)
            drops[reason] = drops.get(reason, 0) + 1
            if drops[reason] <= 3:  # the first few of each reason, then a summary (no flood)
                print(f"run_bag: dropped {topic} at {stamp:.9f}: {exc}", file=sys.stderr)
            continue
        steps.extend(out)
    steps.extend(odo.flush())
    for reason, n in drops.items():
        if n > 3:
            print(f"run_bag: dropped {n} message(s) in all for {reason}", file=sys.stderr)
    if bar is not None:
        bar.close()
    return steps, rec, odo


def base_poses(steps: list[OdometryStep]) -> np.ndarray:
    """``(F, 4, 4)`` estimated base poses in odom."""
    pos = torch.tensor(np.array([s.position for s in steps]))
    rpy = torch.tensor(np.array([s.rpy for s in steps]))
    return pose_matrix(pos, rpy).numpy()


def camera_trajectory(base: np.ndarray, T_base_cam: np.ndarray) -> np.ndarray:
    """Base poses -> camera poses relative to the first camera (KITTI poses/NN.txt convention)."""
    cam = base @ T_base_cam
    return np.linalg.inv(cam[0]) @ cam


def write_outputs(out: Path, steps: list[OdometryStep], rec: bag.Recording, T_base_cam: np.ndarray) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    base = base_poses(steps)
    paths = [out / "trajectory_kitti.txt", out / "trajectory_tum.txt", out / "pitch_roll.csv"]
    kitti.write_poses(paths[0], camera_trajectory(base, T_base_cam))
    lines = []
    for s in steps:
        q = quaternion_from_rpy(*map(float, s.rpy))  # the node's published orientation
        lines.append(f"{s.stamp:.9f} " + " ".join(f"{v:.9f}" for v in (*s.position, *q)))
    atomic_write_text(paths[1], "\n".join(lines) + "\n")
    stamps = np.array([s.stamp for s in steps])
    ref_p = ref_r = np.full(len(steps), np.nan)
    if rec.gt_pitch is not None:
        ref_p = np.interp(stamps, rec.gt_att_stamps, rec.gt_pitch)
        ref_r = np.interp(stamps, rec.gt_att_stamps, rec.gt_roll)
    rows = ["stamp,pitch,roll,oxts_pitch,oxts_roll,road_pitch,road_roll,peak_quality"]
    for s, rp, rr in zip(steps, ref_p, ref_r):
        rows.append(f"{s.stamp:.9f},{s.rpy[1]:.9f},{s.rpy[0]:.9f},{rp:.9f},{rr:.9f},"
                    f"{s.pitch_roll_road[0]:.9f},{s.pitch_roll_road[1]:.9f},{s.peak_quality:.6f}")
    atomic_write_text(paths[2], "\n".join(rows) + "\n")
    if rec.gt_poses is not None:
        gt_cam = camera_trajectory(gt_at(stamps, rec.gt_stamps, rec.gt_poses), T_base_cam)
        paths.append(out / "gt_kitti.txt")
        kitti.write_poses(paths[-1], gt_cam)
    return paths


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    try:
        config, _ = load_config(args.params)
        if args.mode:
            config.odometry.mode = args.mode
        learned = args.learned or config.learned_params_file
        t0 = time.perf_counter()
        steps, rec, odo = run(args.bag, config, learned, args.imu_topic, args.image_topic, args.first_frame,
                              progress=not args.quiet)
        elapsed = time.perf_counter() - t0
        if len(steps) < 2:
            raise ValueError(f"{args.bag}: only {len(steps)} frame(s) produced odometry")
        T_base_cam = np.array(config.camera.base_T_camera, dtype=float).reshape(4, 4)
        paths = write_outputs(Path(args.out), steps, rec, T_base_cam)
    except (ConfigError, bag.BagError, FileNotFoundError, ValueError) as exc:
        print(f"run_bag: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("run_bag: interrupted", file=sys.stderr)
        return 130
    c = odo.counters
    print(f"run_bag: {len(steps)} frames in {elapsed:.1f} s ({len(steps) / elapsed:.1f} frames/s), "
          f"mode {config.odometry.mode}; imu {c.imu}, images {c.images}, gaps {c.imu_gaps}, "
          f"dropped (no imu) {c.dropped_no_imu}; rejected: textureless {c.rejected_textureless}, "
          f"translation {c.rejected_translation}, rotation {c.rejected_rotation}")
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())
