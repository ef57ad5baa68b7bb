"""``bevo calibrate``: the rig's static attitude on the road (filter.mounting_pitch / mounting_roll).

The BEV's metric scale hangs on the camera's pitch relative to the road (~25 % per degree at
KITTI's geometry) and a roll error biases every yaw estimate. The road-tilt low-pass removes
every constant from the filtered attitude, so the static tilt of the IMU/camera rig on the road
is a calibration, like the camera height. This command measures it on a short stretch of a bag (a
"calibration drive") against a reference: the bag's ground truth, or, for a car that has none, its
own forward speed (``--speed-topic``: wheel odometry, a CAN or GNSS speed) with the yaw from the gyro:

  pitch: bisection until the distance travelled in the BEV matches the reference's;
  roll:  bisection until the summed BEV yaw matches the reference's (a roll error shears the BEV).

Both use a constant attitude (no filter), so the result is the rig's, not the road's.
Prints the YAML lines for params/*.yaml: the two angles and `filter.mounting_reference: camera`. The
fit runs through the bag's rig as bevo_node takes it (its /tf_static, else `camera.base_T_camera`);
what it measures is the camera's tilt to the road, and the angles are printed for
`camera.base_T_camera`, the extrinsics the params file pairs them with.
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from bevo_ros.commands import add_params_option, bag_errors, guarded, new_parser
from bevo_ros.config import bev_spec, load_config
from bevo_ros.datasets.rosbag import RigSettings, load_sequence
from bevo_ros.core.geometry import mounting_for_extrinsics
from bevo_ros.io.bag import read_speed
from bevo_ros.training.mounting import calibrate, reference_from_ground_truth, reference_from_speed


def build_parser() -> argparse.ArgumentParser:
    p = new_parser(__doc__)
    p.add_argument("bag", help="rosbag2 with images, IMU, CameraInfo and /ground_truth/odometry (or --speed-topic)")
    add_params_option(p)
    p.add_argument("--frames", default="0:11", help="frame range START:STOP of the calibration drive (default 0:11)")
    p.add_argument("--speed-topic", metavar="TOPIC",
                   help="the reference without ground truth: the car's speed on TOPIC (nav_msgs/Odometry, e.g. wheel "
                        "odometry, or geometry_msgs/TwistStamped / TwistWithCovarianceStamped from CAN or GNSS: the "
                        "twist's horizontal speed), driving forward; the yaw from the bag's gyro, its bias read "
                        "where the speed says the car stood (start the bag at rest); as good as the speed's scale")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # the commands' one convention: `bevo calibrate: error: ...` and exit 2, warnings one line each
    return guarded("calibrate_mounting", lambda: _calibrate(args), bag_errors())


def _calibrate(args: argparse.Namespace) -> int:
    config, flat = load_config(args.params)
    seq = load_sequence(args.bag, config, require_gt=False, rig=RigSettings.from_params(flat, str(args.params)))
    if args.speed_topic is None and seq.gt_poses is None:
        raise ValueError(f"{args.bag}: no /ground_truth/odometry to calibrate against; without one, give the "
                         "car's speed (--speed-topic)")
    try:
        start, stop = (int(v) for v in args.frames.split(":"))
    except ValueError:
        raise ValueError(f"--frames {args.frames!r}: expected START:STOP, two frame numbers") from None
    if not 0 <= start < stop - 1 < len(seq):
        raise ValueError(f"--frames {args.frames}: need at least 2 frames within 0..{len(seq)} (STOP excluded), "
                         f"the bag has {len(seq)}")
    seq = seq.frames(start, stop)
    if args.speed_topic:
        reference = reference_from_speed(seq, *read_speed(args.bag, args.speed_topic))
        source = f"{args.speed_topic}'s speed and the gyro's yaw" + (
            f", its bias {math.degrees(reference.gyro_bias):+.3f} deg/s taken off over {reference.rest_seconds:.1f} s "
            "at rest" if reference.rest_seconds else ", no rest to read its bias from")
    else:
        reference, source = reference_from_ground_truth(seq), "the ground truth"
    spec = bev_spec(config)
    pitch, roll = calibrate(seq, spec, dpc=config.dpc, reference=reference)  # ValueError: no fit (exit 2)
    # Measured through the bag's rig (its /tf_static, as the node takes it): the camera's tilt to the
    # road. Written for camera.base_T_camera, with which the params lines below go.
    params_chain = np.asarray(config.camera.base_T_camera, dtype=np.float64).reshape(4, 4)
    pitch, roll = mounting_for_extrinsics((pitch, roll), seq.camera.T_base_cam, params_chain)
    print(f"calibrated on frames {args.frames} ({reference[0]:.1f} m, {math.degrees(reference[1]):+.1f} deg of yaw "
          f"by {source}):")
    print(f"    filter.mounting_pitch: {pitch:.4f}   # {math.degrees(pitch):+.2f} deg, "
          f"{'nose down' if pitch >= 0 else 'nose up'}")
    print(f"    filter.mounting_roll: {roll:.4f}    # {math.degrees(roll):+.2f} deg, "
          f"{'left side up' if roll >= 0 else 'left side down'}")
    # Written for camera.base_T_camera: the camera's tilt to the road is what was measured.
    print("    filter.mounting_reference: camera   # for camera.base_T_camera (kept with /tf_static extrinsics)")
    return 0
