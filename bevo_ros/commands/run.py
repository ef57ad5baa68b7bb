"""``bevo run``: BEVO offline over a rosbag2, with the very engine bevo_node runs, and no DDS
(bevo_ros.pipeline).

Messages are fed to the engine in bag order, exactly as the node feeds them, and the rig and
calibration are taken as the node takes them with the same --params (the bag's CameraInfo, images
undistorted where it says so, /tf_static camera extrinsics and IMU axes; base_frame,
extrinsics_from_tf, use_camera_info, camera_info_use_p, undistort), so the trajectory equals the
node's. Writes into --out:

  trajectory_kitti.txt  camera-0 poses, 3x4 row-major per line, one per frame, first = identity
                        (directly comparable with KITTI poses/NN.txt)
  trajectory_tum.txt    base_link in odom: stamp tx ty tz qx qy qz qw
  gt_kitti.txt          ground truth in the same convention, when the bag has /ground_truth/odometry
  pitch_roll.csv        stamp, filtered pitch and roll, and the reference (OXTS) attitude
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

from bevo_ros.commands import DEFAULT_PARAMS  # noqa: F401 (re-exported: tests load the default parameters)
from bevo_ros.commands import (add_params_option, add_threads_option, bag_errors, guarded, new_parser, prog_name,
                                set_threads)
from bevo_ros.core.frame_clock import fast_camera_note
from bevo_ros.config import load_config, mounting_in_use, shipped_learned_for_mode
from bevo_ros.datasets.rosbag import RigSettings, extrinsics_for_recording
from bevo_ros.pipeline import run_bag, write_outputs


# --tilt-from-images reads the direction of travel over at most this many frames (a minute at 10 Hz: the
# median of ~600 pairs, ~0.02 deg; each pair ~0.14 s of feature tracking on a core)
TILT_FRAMES = 600


def build_parser() -> argparse.ArgumentParser:
    p = new_parser(__doc__)
    p.add_argument("bag", help="rosbag2 directory (sqlite3 or mcap)")
    p.add_argument("--out", required=True, help="output directory")
    add_params_option(p, learned=True)
    p.add_argument("--imu-topic", help="default: the params' imu_topic under / (/imu/data)")
    p.add_argument("--image-topic", help="default: the params' image_topic under / (/camera/image_rect); the "
                   "CameraInfo is read from the params' camera_info_topic")
    p.add_argument("--speed-topic", help="a vehicle speed the motion filter fuses (wheel odometry nav_msgs/Odometry, or "
                   "a TwistStamped / TwistWithCovarianceStamped: in base_frame its linear.x, else its horizontal speed); "
                   "overrides the params' speed_topic, '' = none. Its scale must be right: the odometry's scale is then its")
    p.add_argument("--first-frame", type=int, default=0, help="start the odometry at this frame (IMU before it warms the filter)")
    p.add_argument("--tilt-from-images", action="store_true",
                   help="before the run, measure the camera's tilt to the road from the bag's images (their direction "
                        "of travel, as `bevo calibrate --from-images`; from --first-frame on, at most "
                        f"{TILT_FRAMES} frames) and run with it instead of the params' filter.mounting_pitch (and "
                        "instead of the engine's own measurement over the first filter.tilt_from_images pairs, "
                        "which bevo_node makes too). Prints the params lines, for bevo_node; a drive too short or "
                        "standing still keeps the params' (a warning)")
    p.add_argument("--mode", choices=("fused", "paper"), help="override odometry.mode of --params (fused: the default "
                   "acceleration-aware, gyro-yaw, motion-filtered odometry; paper: the paper's pipeline)")
    add_threads_option(p, ", as bevo_node's torch_threads: same arithmetic, same result")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    set_threads(args.threads)
    return guarded("run_bag", lambda: _run(args), bag_errors())


def _tilt_from_images(args: argparse.Namespace, config, rig: RigSettings) -> None:
    """``--tilt-from-images``: ``config.filter``'s mounting pitch (and reference) set to the one the bag's
    images show, said with the params lines; the params' kept, with a warning, where they show none."""
    from bevo_ros.commands.calibrate import mounting_from_images
    from bevo_ros.datasets.rosbag import load_sequence

    say = prog_name("run_bag")
    seq = load_sequence(args.bag, config, require_gt=False, rig=rig)
    first = min(max(args.first_frame, 0), len(seq) - 2)
    try:
        pitch, roll, direction, _ = mounting_from_images(seq.frames(first, min(len(seq), first + TILT_FRAMES)), config)
    except ValueError as exc:
        print(f"{say}: warning: --tilt-from-images: {exc}; the params' filter.mounting_pitch "
              f"{config.filter.mounting_pitch:.4f} kept", file=sys.stderr)
        return
    T_bag = seq.camera.T_base_cam.double().numpy()
    before = mounting_in_use(config, T_bag)[0]
    config.filter.mounting_pitch, config.filter.mounting_roll = pitch, roll
    config.filter.mounting_reference = "camera"  # the angles are for camera.base_T_camera
    config.filter.tilt_from_images = 0  # measured here, over more frames than the engine's start would
    change = math.degrees(mounting_in_use(config, T_bag)[0] - before)
    print(f"{say}: the camera's tilt from the images' direction of travel ({direction.pairs} frame pairs, +- "
          f"{math.degrees(direction.elevation_sem):.2f} deg): {change:+.2f} deg from the params' (nose down +; "
          f"~2 % of scale per 0.1 deg on KITTI); for bevo_node's params:\n"
          f"    filter.mounting_pitch: {pitch:.4f}\n    filter.mounting_roll: {roll:.4f}\n"
          "    filter.mounting_reference: camera\n    filter.tilt_from_images: 0", file=sys.stderr)


def _run(args: argparse.Namespace) -> int:
    if Path(args.out).exists() and not Path(args.out).is_dir():  # before the whole run, not after it
        raise ValueError(f"--out {args.out} is a file: give the output directory")
    config, flat = load_config(args.params)
    rig = RigSettings.from_params(flat, str(args.params))
    if args.speed_topic is not None:
        rig = dataclasses.replace(rig, speed_topic=args.speed_topic)
    learned = args.learned or config.learned_params_file
    if args.mode:
        config.odometry.mode = args.mode
        if not args.learned:
            swapped = shipped_learned_for_mode(learned, args.mode)
            if swapped != Path(learned):
                print(f"{prog_name('run_bag')}: note: --mode {args.mode}: the learned parameters from {swapped} "
                      "(the shipped file for that mode; "
                      f"--learned FILE to choose another)", file=sys.stderr)
                learned = str(swapped)
    if args.tilt_from_images:
        _tilt_from_images(args, config, rig)
    t0 = time.perf_counter()
    steps, rec, odo = run_bag(args.bag, config, learned, args.imu_topic, args.image_topic, args.first_frame,
                              progress=not args.quiet, rig=rig, keep_bevs=False,
                              prog=prog_name("run_bag"))
    elapsed = time.perf_counter() - t0
    if len(steps) < 2:
        c = odo.counters  # why: the counts the summary below would have printed
        raise ValueError(f"{args.bag}: only {len(steps)} frame(s) produced odometry (imu {c.imu}, images {c.images}, "
                         f"dropped without IMU {c.dropped_no_imu}, invalid BEV {c.dropped_invalid_bev})")
    T_base_cam, _ = extrinsics_for_recording(rec, config, rig)  # the extrinsics the engine used (float64)
    paths = write_outputs(Path(args.out), steps, rec, T_base_cam, prog=prog_name("run_bag"), base_frame=rig.base_frame)
    c = odo.counters
    print(f"{prog_name('run_bag')}: {len(steps)} frames in {elapsed:.1f} s ({len(steps) / elapsed:.1f} frames/s), "
          f"mode {config.odometry.mode}; imu {c.imu}, images {c.images}, gaps {c.imu_gaps}, "
          f"dropped (no imu) {c.dropped_no_imu}; rejected: textureless {c.rejected_textureless}, "
          f"translation {c.rejected_translation}, rotation {c.rejected_rotation}"
          + (f", speed {c.rejected_speed} (of {rig.speed_topic})" if rig.speed_topic else "") + f"; at rest {c.standstill}; "
          f"peak off the highest (second motion in view, direction of travel) {c.gated_peak}; "
          f"pitch-change correction off (DUKF pull, turn) {c.pitch_correction_off}"
          + (f"; skipped (odometry.min_frame_interval) {c.skipped_frame_rate}" if c.skipped_frame_rate else "")
          + (f"; near the BEV's reach (README, Limitations: Top speed) {c.beyond_reach}" if c.beyond_reach else ""))
    print("wrote " + ", ".join(str(p) for p in paths))
    if odo.tilt_measurement is not None:  # filter.tilt_from_images: the engine measured it at the start
        print(f"{prog_name('run_bag')}: {odo.tilt_measurement.describe()}", file=sys.stderr)
    if (note := fast_camera_note(odo.frame_period, odo.min_frame_interval)) is not None:
        print(f"{prog_name('run_bag')}: note: {note}", file=sys.stderr)
    # The trajectory has a row per frame with odometry, not per image of the bag: the bag's images from
    # --first-frame on, those refused before the engine counted them (a wrong size) included; an image
    # whose stamp is not after an earlier one is left out by read_recording already (its warning).
    images = len(rec.frame_stamps_ns) - args.first_frame - c.skipped_frame_rate  # skipped on purpose: no fault
    if len(steps) < images:
        print(f"{prog_name('run_bag')}: warning: {images - len(steps)} of {images} frames gave no odometry (see the counts above): "
              f"trajectory_kitti.txt has {len(steps)} rows; evaluate against gt_kitti.txt (the same frames), "
              f"not a sequence's poses file counted from its first frame", file=sys.stderr)
    return 0
