"""The offline pipeline: a rosbag2 through bevo_node's very engine (no DDS) -> trajectory files ->
evaluation against ground truth -> a results folder. ``bevo run``, ``bevo evaluate``, ``bevo map``,
``bevo demo`` and the pinned-behaviour record use it.

Messages are fed to :class:`bevo_ros.core.odometry.BevoOdometry` in bag order, exactly as the node
feeds them, so the trajectory equals the node's. :func:`write_outputs` writes into a folder:

  trajectory_kitti.txt  camera-0 poses, 3x4 row-major per line, one per frame, first = identity
                        (directly comparable with KITTI poses/NN.txt)
  trajectory_tum.txt    base_link in odom: stamp tx ty tz qx qy qz qw
  gt_kitti.txt          ground truth in the same convention, when the bag has /ground_truth/odometry
  pitch_roll.csv        stamp, filtered pitch and roll, and the reference (OXTS) attitude

:func:`evaluate_files` scores such a folder (or any KITTI pose files) and writes the report;
:func:`map_from_steps` mosaics a run's BEVs at the ground-truth poses into a BEVO+ map (``bevo map``).
"""
from __future__ import annotations

import dataclasses
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from bevo_ros.config import BevoConfig, build_odometry, gyro_bias_prior_note
from bevo_ros.core.aerial_map import AerialMap
from bevo_ros.core.geometry import BevSpec
from bevo_ros.core.mosaic import mosaic_to_map
from bevo_ros.core.odometry import BevoOdometry, InvalidInputError, OdometryStep, OutOfOrderError
from bevo_ros.core.pose import pose_matrix
from bevo_ros.datasets import kitti
from bevo_ros.datasets.rosbag import (PARAMETERS_EXTRINSICS, RigSettings, calibration_for_recording, camera_for_recording,
                                      extrinsics_for_recording, gt_at, imu_rotation_for_recording,
                                      rig_disagreements)
from bevo_ros.evaluation.metrics import evaluate_trajectories, pitch_roll_errors, read_pitch_roll_csv
from bevo_ros.evaluation.report import write_report
from bevo_ros.io import bag
from bevo_ros.io.files import atomic_write_text
from bevo_ros.io.learned_params import load_learned_params
from bevo_ros.io.ros_conversions import forward_speed_from_msg, stamp_to_ns, stamp_to_sec
from bevo_ros.rotations import quaternion_from_rpy


def run_bag(bag_path: str | Path, config: BevoConfig, learned_path: str | Path, imu_topic: str | None = None,
        image_topic: str | None = None, first_frame: int = 0, progress: bool = False,
        rig: RigSettings = RigSettings(), keep_bevs: bool = True, prog: str = "run_bag"
        ) -> tuple[list[OdometryStep], bag.BagContents, BevoOdometry]:
    """Feed a bag through the engine; returns the per-frame results, the recording (no images) and the engine.

    ``keep_bevs=False`` drops each step's BEV, mask and correlation surface (``None``) as it comes: ~0.2 MB a
    frame, 7 GB over an hour at 10 Hz, that only a map (``bevo map``) needs; the poses are the same.

    The rig and calibration as bevo_node takes them (``rig``: its parameters of the same names): the
    camera's intrinsics from the bag's CameraInfo (images undistorted where it says so), its
    extrinsics and the IMU's axes from the bag's ``/tf_static`` when there
    (:func:`~bevo_ros.datasets.rosbag.extrinsics_for_recording` of the recording returned says which).
    Its stderr lines start with ``prog``: the command that runs it (``bevo run``, ``bevo map``:
    ``bevo_ros.commands.prog_name``)."""
    topics = rig.read_topics()  # the params' (the node's) unless given
    imu_topic = topics["imu_topic"] = imu_topic or topics["imu_topic"]
    topics["image_topic"] = image_topic or topics["image_topic"]
    rec = bag.read_recording(bag_path, **topics, load_images=False)
    T_base_cam, source = extrinsics_for_recording(rec, config, rig)
    calib = calibration_for_recording(rec, config, rig)
    learned = load_learned_params(learned_path)
    odo = build_odometry(config, learned, camera=camera_for_recording(rec, config, rig, calib))
    if (note := gyro_bias_prior_note(config, learned, learned_path)) is not None:  # it overrides two parameters
        print(f"{prog}: {note}", file=sys.stderr)
    if progress or source != PARAMETERS_EXTRINSICS or calib.maps is not None:
        print(f"{prog}: camera calibration from {calib.describe()}; extrinsics from {source}: camera at "
              f"{np.round(T_base_cam[:3, 3], 3).tolist()} m in {rig.base_frame}", file=sys.stderr)
    for problem in rig_disagreements(rec, config, rig, calib):  # parameters that do not fit the bag: drift, silently
        print(f"{prog}: warning: {problem}", file=sys.stderr)
    rotations: dict[str, np.ndarray | None] = {}  # IMU frame -> R_base_imu (the node's Rig.imu_rotation)
    if not 0 <= first_frame < len(rec.frame_stamps_ns):
        raise ValueError(f"{bag_path}: first frame {first_frame} is not one of its {len(rec.frame_stamps_ns)} frames "
                         f"(0..{len(rec.frame_stamps_ns) - 1})")
    first_stamp = rec.frame_stamps_ns[first_frame] if first_frame else None
    steps: list[OdometryStep] = []
    kept = _with_bevs if keep_bevs else _without_bevs
    drops: dict[str, int] = {}
    total = len(rec.frame_stamps_ns)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", desc=prog)
    image_topic = rec.image_topic  # the topic read_recording took (old bags: /camera/image_raw)
    speed_topic = rig.speed_topic
    if speed_topic:
        topics = bag.bag_topics(bag_path)
        if topics.get(speed_topic, ("",))[0] not in bag.SPEED_MSGS:
            raise ValueError(f"{bag_path}: speed_topic {speed_topic} is not in the bag as one of "
                             f"{', '.join(bag.SPEED_MSGS)} (it has: {', '.join(sorted(topics))})")
    for topic, stamp_ns, msg in bag.iter_messages(bag_path, [imu_topic, image_topic] + ([speed_topic] if speed_topic else [])):
        stamp_ns = stamp_to_ns(msg.header.stamp)
        stamp = stamp_to_sec(msg.header.stamp)  # the node's conversion: bit-identical floats
        try:
            if topic == imu_topic:
                a, g = msg.linear_acceleration, msg.angular_velocity
                frame = msg.header.frame_id
                if frame not in rotations:
                    rotations[frame] = imu_rotation_for_recording(rec, frame, rig)
                    _log_imu_frame(prog, frame, rotations[frame], rig)
                R = rotations[frame]
                if R is None:
                    out = odo.add_imu(stamp, (g.x, g.y, g.z), (a.x, a.y, a.z))
                else:  # an IMU mounted in other axes (e.g. z down): into base_frame's, as the node does
                    out = odo.add_imu(stamp, R @ (g.x, g.y, g.z), R @ (a.x, a.y, a.z))
            elif topic == speed_topic:  # as the node's speed input
                odo.add_speed(stamp, *forward_speed_from_msg(msg, rig.base_frame, rig.speed_variance))
                continue
            else:
                if bar is not None:
                    bar.update(1)
                if first_stamp is not None and stamp_ns < first_stamp:
                    continue
                img = bag.decode_image(msg)
                if (problem := calib.size_problem(img)) is not None:  # dropped, as the node drops it
                    raise InvalidInputError(f"image size does not match the calibration: the image {problem}")
                out = odo.add_image(stamp, calib.rectify(img))
        except (ValueError, OutOfOrderError) as exc:  # the node drops and counts these too
            reason = getattr(exc, "reason", type(exc).__name__)
            drops[reason] = drops.get(reason, 0) + 1
            if drops[reason] <= 3:  # the first few of each reason, then a summary (no flood)
                print(f"{prog}: dropped {topic} at {stamp:.9f}: {exc}", file=sys.stderr)
            continue
        steps.extend(map(kept, out))
    steps.extend(map(kept, odo.flush()))
    for reason, n in drops.items():
        if n > 3:
            print(f"{prog}: dropped {n} message(s) in all for {reason}", file=sys.stderr)
    if bar is not None:
        bar.close()
    return steps, rec, odo


def _with_bevs(step: OdometryStep) -> OdometryStep:
    return step


def _without_bevs(step: OdometryStep) -> OdometryStep:
    return dataclasses.replace(step, bev=None, bev_mask=None, correlation=None)


def _log_imu_frame(prog: str, frame: str, R: np.ndarray | None, rig: RigSettings) -> None:
    """One stderr line per IMU frame that is not the base's axes, as the node logs it; ``prog`` starts it."""
    base = rig.base_frame
    if R is not None and not np.allclose(R, np.eye(3), rtol=0, atol=1e-12):
        print(f"{prog}: IMU frame '{frame}': rates and accelerations rotated into '{base}' (/tf_static), "
              f"rotation {np.round(R, 4).tolist()}", file=sys.stderr)
    elif R is None and frame.lstrip("/") and frame.lstrip("/") != base.lstrip("/"):
        print(f"{prog}: IMU frame '{frame}' is not base_frame '{base}' and "
              f"{'/tf_static has no ' + base + ' -> ' + frame if rig.extrinsics_from_tf else 'extrinsics_from_tf is off'}"
              ": the IMU axes are taken as the base axes (REP-103 x forward, y left, z up)", file=sys.stderr)


def base_poses(steps: list[OdometryStep]) -> np.ndarray:
    """``(F, 4, 4)`` estimated base poses in odom."""
    pos = torch.tensor(np.array([s.position for s in steps]))
    rpy = torch.tensor(np.array([s.rpy for s in steps]))
    return pose_matrix(pos, rpy).numpy()


def camera_trajectory(base: np.ndarray, T_base_cam: np.ndarray) -> np.ndarray:
    """Base poses -> camera poses relative to the first camera (KITTI poses/NN.txt convention)."""
    cam = base @ T_base_cam
    return np.linalg.inv(cam[0]) @ cam


def write_outputs(out: Path, steps: list[OdometryStep], rec: bag.BagContents, T_base_cam: np.ndarray,
                  prog: str = "run_bag", base_frame: str = "base_link") -> list[Path]:
    """The run's files in ``out``: the trajectory (KITTI camera poses, TUM), the attitude CSV and the
    bag's ground truth at the frames (``gt_kitti.txt``) where it has one stamped at the images; where
    it has none (or one at other stamps: said on stderr, the run's files still written) an earlier
    run's ``gt_kitti.txt`` is removed, as ``bevo evaluate`` would score this trajectory against it.
    The ground truth must be ``base_frame``'s poses (its messages' child frame): another frame's (a
    camera's, a GNSS antenna's) is not composed through the camera as if it were the base's."""
    stamps = np.array([s.stamp for s in steps])
    gt_cam = None
    child = rec.gt_child_frame_id.lstrip("/")
    if rec.gt_poses is not None and child and child != base_frame.lstrip("/"):
        print(f"{prog}: warning: no gt_kitti.txt written: the bag's ground truth is the pose of '{child}', not of "
              f"the base frame '{base_frame}' (its child_frame_id; base_frame in the parameters)", file=sys.stderr)
    elif rec.gt_poses is not None:  # before any file is written: a refusal here left a folder half new, half old
        try:
            gt_cam = camera_trajectory(gt_at(stamps, rec.gt_stamps, rec.gt_poses), T_base_cam)
        except ValueError as exc:
            print(f"{prog}: warning: no gt_kitti.txt written: the bag's {exc}", file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    base = base_poses(steps)
    paths = [out / "trajectory_kitti.txt", out / "trajectory_tum.txt", out / "pitch_roll.csv"]
    kitti.write_poses(paths[0], camera_trajectory(base, T_base_cam))
    lines = []
    for s in steps:
        q = quaternion_from_rpy(*map(float, s.rpy))  # the node's published orientation
        lines.append(f"{s.stamp:.9f} " + " ".join(f"{v:.9f}" for v in (*s.position, *q)))
    atomic_write_text(paths[1], "\n".join(lines) + "\n")
    ref_p = ref_r = np.full(len(steps), np.nan)
    if rec.gt_pitch is not None:
        ref_p = np.interp(stamps, rec.gt_att_stamps, rec.gt_pitch)
        ref_r = np.interp(stamps, rec.gt_att_stamps, rec.gt_roll)
    rows = ["stamp,pitch,roll,oxts_pitch,oxts_roll,road_pitch,road_roll,peak_quality"]
    for s, rp, rr in zip(steps, ref_p, ref_r):
        rows.append(f"{s.stamp:.9f},{s.rpy[1]:.9f},{s.rpy[0]:.9f},{rp:.9f},{rr:.9f},"
                    f"{s.pitch_roll_road[0]:.9f},{s.pitch_roll_road[1]:.9f},{s.peak_quality:.6f}")
    atomic_write_text(paths[2], "\n".join(rows) + "\n")
    if gt_cam is not None:
        paths.append(out / "gt_kitti.txt")
        kitti.write_poses(paths[-1], gt_cam)
    else:  # an earlier run's ground truth into the same folder would be evaluated against this trajectory
        (out / "gt_kitti.txt").unlink(missing_ok=True)
    return paths


def evaluate_files(gt_path: str | Path, est_path: str | Path, out: str | Path, pitch_roll: str | Path | None = None,
                   first: int = 0, convention: str = "camera", title: str = ""):
    """Score KITTI-format estimated poses against ground truth (frames ``first ..`` of it) and write
    the report into ``out``; returns ``(metrics, written paths)``. Bad input raises ValueError."""
    if first < 0:
        raise ValueError(f"--first {first}: the GT frame of the first estimated pose, counted from 0")
    gt = kitti.read_poses(gt_path)
    est = kitti.read_poses(est_path)
    if first + len(est) > len(gt):
        raise ValueError(f"{est_path}: {len(est)} poses from GT frame {first} need "
                         f"{first + len(est)} GT poses, {gt_path} has {len(gt)}")
    if len(gt) != len(est) or first:
        print(f"note: using GT frames {first}..{first + len(est) - 1} of {len(gt)}", file=sys.stderr)
    gt = gt[first: first + len(est)]
    pr = read_pitch_roll_csv(pitch_roll) if pitch_roll else None
    if pr is not None and len(pr["stamp"]) != len(est):
        # bevo run writes one row per pose; another count may be another run's attitude (scored on its own
        # columns all the same) or a CSV at another rate: said, not refused
        warnings.warn(f"{pitch_roll}: {len(pr['stamp'])} rows, but {est_path} has {len(est)} poses: not the same "
                      f"run's? (bevo run writes both, one row per pose, into its --out folder); its attitude is "
                      f"scored on its own rows", UserWarning, stacklevel=2)
    metrics = evaluate_trajectories(gt, est, convention)
    if pr is not None:
        metrics.pitch_roll = pitch_roll_errors(pr)
    title = title or f"{Path(est_path).name} vs {Path(gt_path).name}"
    return metrics, write_report(out, gt, est, metrics, pr, title)


def xy_yaw_from_4x4(T: np.ndarray) -> np.ndarray:
    """``(F, 4, 4)`` poses -> ``(F, 3)`` planar ``(x, y, yaw)``."""
    return np.stack([T[:, 0, 3], T[:, 1, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0])], axis=-1)


def map_from_steps(steps: list[OdometryStep], rec: bag.BagContents, spec: BevSpec, resolution: float,
                   margin: float) -> AerialMap:
    """A BEVO+ map ("a previous drive"): the engine's BEVs of ``steps`` mosaicked at the recording's
    ground-truth poses at their stamps (base_link in the bag's odom frame, which becomes the map frame)."""
    if rec.gt_poses is None:
        raise ValueError("the recording has no ground-truth poses: a map needs them")
    stamps = np.array([s.stamp for s in steps])
    poses = xy_yaw_from_4x4(gt_at(stamps, rec.gt_stamps, rec.gt_poses))
    bevs = torch.from_numpy(np.stack([s.bev for s in steps]).astype(np.float32))[:, None]
    masks = torch.from_numpy(np.stack([s.bev_mask for s in steps]).astype(np.float32))[:, None]
    return mosaic_to_map(bevs, masks, torch.from_numpy(poses).float(), spec, resolution, margin)
