"""``bevo calibrate``: the rig's static attitude on the road (filter.mounting_pitch / mounting_roll), or
the IMU's clock against the camera's (odometry.imu_time_offset).

The BEV's metric scale hangs on the camera's pitch relative to the road (~25 % per degree at
KITTI's geometry) and a roll error biases every yaw estimate. The road-tilt low-pass removes
every constant from the filtered attitude, so the static tilt of the IMU/camera rig on the road
is a calibration, like the camera height. This command measures it on a short stretch of a bag (a
"calibration drive") against a reference: the bag's ground truth, or, for a car that has none, its
own forward speed (``--speed-topic``: wheel odometry, a CAN or GNSS speed) with the yaw from the gyro:

  pitch: bisection until the distance travelled in the BEV matches the reference's;
  roll:  bisection until the summed BEV yaw matches the reference's (a roll error shears the BEV).

Both use a constant attitude (no filter), so the result is the rig's, not the road's.

With no reference at all, ``--from-images`` measures the pitch from the images alone: the direction
the camera travels in between frames (their epipolar geometry, OpenCV) lies along the road, and its
elevation is the camera's tilt to the road (bevo_ros.core.travel_direction). It is the physical
tilt, so the scale then rests on camera.mount_height too; the roll is not observable this way and
the params' own is kept. Use a drive of a minute or more: one frame pair scatters by ~0.4 deg.

``--imu-time-offset`` measures, instead of the mounting, the IMU's clock against the camera's
(``odometry.imu_time_offset``, searched within +-1 s): the offset at which the gyro's rotation between
frames matches the rotation the images show (their epipolar geometry; bevo_ros.training.time_offset). It
needs a drive through bends or over bumps (the rate's change times the offset is what it sees) and
prints one params line.

Otherwise it prints the YAML lines for params/*.yaml: the two angles and `filter.mounting_reference: camera`. The
fit runs through the bag's rig as bevo_node takes it (its /tf_static, else `camera.base_T_camera`);
what it measures is the camera's tilt to the road, and the angles are printed for
`camera.base_T_camera`, the extrinsics the params file pairs them with.
"""
from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from bevo_ros.commands import add_params_option, bag_errors, guarded, new_parser, prog_name
from bevo_ros.config import bev_spec, load_config, mounting_in_use
from bevo_ros.datasets.rosbag import RigSettings, load_sequence
from bevo_ros.core.geometry import mounting_for_extrinsics
from bevo_ros.io.bag import read_speed
from bevo_ros.training.mounting import calibrate, reference_from_ground_truth, reference_from_speed
from bevo_ros.training.time_offset import image_rotations, imu_time_offset
from bevo_ros.core.travel_direction import TravelDirection, mounting_pitch_from_travel, travel_direction


def build_parser() -> argparse.ArgumentParser:
    p = new_parser(__doc__)
    p.add_argument("bag", help="rosbag2 with images, IMU, CameraInfo and /ground_truth/odometry (or --speed-topic, "
                               "or --from-images, or --imu-time-offset: images and IMU only)")
    add_params_option(p)
    p.add_argument("--frames", help="frame range START:STOP of the calibration drive (default 0:11; with "
                   "--from-images or --imu-time-offset every frame)")
    ref = p.add_mutually_exclusive_group()
    ref.add_argument("--from-images", action="store_true",
                     help="no reference: the pitch from the direction of travel the images show (their epipolar "
                          "geometry); the roll kept from --params; a drive of a minute or more, mostly forward")
    ref.add_argument("--imu-time-offset", action="store_true",
                     help="instead of the mounting: the offset to add to the IMU's stamps to put them on the images' "
                          "clock (odometry.imu_time_offset, within +-1 s), from the gyro's rotation between "
                          "frames against the images'; a drive through bends or over bumps")
    ref.add_argument("--speed-topic", metavar="TOPIC",
                   help="the reference without ground truth: the car's speed on TOPIC (nav_msgs/Odometry, e.g. wheel "
                        "odometry, or geometry_msgs/TwistStamped / TwistWithCovarianceStamped from CAN or GNSS: in "
                        "base_frame its linear.x, signed, else the twist's horizontal speed: then drive forward); the yaw from the bag's gyro, its bias read "
                        "where the speed says the car stood (start the bag at rest); as good as the speed's scale")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # the commands' one convention: `bevo calibrate: error: ...` and exit 2, warnings one line each
    return guarded("calibrate_mounting", lambda: _calibrate(args), bag_errors())


def _calibrate(args: argparse.Namespace) -> int:
    config, flat = load_config(args.params)
    rig = RigSettings.from_params(flat, str(args.params))
    seq = load_sequence(args.bag, config, require_gt=False, rig=rig)
    whole = args.from_images or args.imu_time_offset  # image-only measurements: every frame by default
    if args.speed_topic is None and not whole and seq.gt_poses is None:
        raise ValueError(f"{args.bag}: no /ground_truth/odometry to calibrate against; without one, give the "
                         "car's speed (--speed-topic) or measure the pitch from the images (--from-images)")
    frames = args.frames or (f"0:{len(seq)}" if whole else "0:11")
    try:
        start, stop = (int(v) for v in frames.split(":"))
    except ValueError:
        raise ValueError(f"--frames {frames!r}: expected START:STOP, two frame numbers") from None
    if not 0 <= start < stop - 1 < len(seq):
        raise ValueError(f"--frames {frames}: need at least 2 frames within 0..{len(seq)} (STOP excluded), "
                         f"the bag has {len(seq)}")
    imu = seq.imu_stamps.numpy(), seq.gyro.numpy()  # the whole recording's: IMU past the last frame too
    seq = seq.frames(start, stop)
    params_chain = np.asarray(config.camera.base_T_camera, dtype=np.float64).reshape(4, 4)
    if args.from_images:
        return _from_images(seq, frames, config)
    if args.imu_time_offset:
        return _imu_time_offset(seq, frames, config, *imu)
    if args.speed_topic:
        speed_stamps, speeds, signed = read_speed(args.bag, args.speed_topic, rig.base_frame)
        if not signed:  # as the node says it: an east/north velocity has no direction of travel
            print(f"{prog_name('calibrate_mounting')}: warning: {args.speed_topic}'s twist is not in base_frame "
                  f"'{rig.base_frame}': its horizontal speed is taken, unsigned (reversing would read as forward)",
                  file=sys.stderr)
        reference = reference_from_speed(seq, speed_stamps, speeds)
        source = f"{args.speed_topic}'s speed and the gyro's yaw" + (
            f", its bias {math.degrees(reference.gyro_bias):+.3f} deg/s taken off over {reference.rest_seconds:.1f} s "
            "at rest" if reference.rest_seconds else ", no rest to read its bias from")
    else:
        reference, source = reference_from_ground_truth(seq), "the ground truth"
    spec = bev_spec(config)
    pitch, roll = calibrate(seq, spec, dpc=config.dpc, reference=reference)  # ValueError: no fit (exit 2)
    # Measured through the bag's rig (its /tf_static, as the node takes it): the camera's tilt to the
    # road. Written for camera.base_T_camera, with which the params lines below go.
    pitch, roll = mounting_for_extrinsics((pitch, roll), seq.camera.T_base_cam, params_chain)
    print(f"calibrated on frames {frames} ({reference[0]:.1f} m, {math.degrees(reference[1]):+.1f} deg of yaw "
          f"by {source}):")
    print(f"    filter.mounting_pitch: {pitch:.4f}   # {math.degrees(pitch):+.2f} deg, "
          f"{'nose down' if pitch >= 0 else 'nose up'}")
    print(f"    filter.mounting_roll: {roll:.4f}    # {math.degrees(roll):+.2f} deg, "
          f"{'left side up' if roll >= 0 else 'left side down'}")
    # Written for camera.base_T_camera: the camera's tilt to the road is what was measured.
    print("    filter.mounting_reference: camera   # for camera.base_T_camera (kept with /tf_static extrinsics)")
    print("    filter.tilt_from_images: 0   # this pitch as is, not re-measured at the engine's start")
    return 0


def mounting_from_images(seq, config) -> tuple[float, float, TravelDirection, float]:
    """The mounting that the direction of travel the images of ``seq`` show puts the camera at:
    ``(pitch, roll, direction, azimuth)``, the angles (rad) for ``camera.base_T_camera`` with
    ``filter.mounting_reference: camera`` (the params lines ``--from-images`` prints, and what ``bevo run
    --tilt-from-images`` runs with), the roll the params' on the bag's rig. ValueError: a camera not
    looking forward, or too few frame pairs with a direction."""
    T_bag = seq.camera.T_base_cam.double().numpy()
    if T_bag[0, 2] < 0.5:  # the optical axis in base_frame: within 60 deg of forward
        raise ValueError("the pitch from the images needs a camera looking forward (its optical axis within 60 deg "
                         "of base_frame's x): the direction of travel is measured ahead of it")
    roll = mounting_in_use(config, T_bag)[1]  # the roll the engine uses on the bag's rig, kept
    direction = travel_direction(seq.images.numpy(), seq.camera.K.double().numpy())  # ValueError: too few pairs
    pitch, azimuth = mounting_pitch_from_travel(direction, T_bag[:3, :3], roll)
    params_chain = np.asarray(config.camera.base_T_camera, dtype=np.float64).reshape(4, 4)
    pitch, roll = mounting_for_extrinsics((pitch, roll), T_bag, params_chain)
    return pitch, roll, direction, azimuth


def _from_images(seq, frames: str, config) -> int:
    """``--from-images``: the pitch from the direction of travel, at the params' roll."""
    pitch, roll, direction, azimuth = mounting_from_images(seq, config)
    print(f"calibrated on frames {frames} from the images' direction of travel ({direction.pairs} frame pairs, "
          f"{direction.pairs_skipped} without one): the optical axis {-math.degrees(direction.elevation):+.2f} "
          f"+- {math.degrees(direction.elevation_sem):.2f} deg below it (+ down); its azimuth from base_frame's x "
          f"{math.degrees(azimuth):+.2f} deg, left + (0 with right extrinsics)")
    print(f"    filter.mounting_pitch: {pitch:.4f}   # {math.degrees(pitch):+.2f} deg, "
          f"{'nose down' if pitch >= 0 else 'nose up'}")
    print(f"    filter.mounting_roll: {roll:.4f}    # {math.degrees(roll):+.2f} deg, the params' "
          "(not observable from the direction of travel)")
    print("    filter.mounting_reference: camera   # for camera.base_T_camera (kept with /tf_static extrinsics)")
    print("    filter.tilt_from_images: 0   # this pitch as is, not re-measured at the engine's start")
    return 0


def _imu_time_offset(seq, frames: str, config, imu_stamps: np.ndarray, gyro: np.ndarray) -> int:
    """``--imu-time-offset``: the IMU's clock against the images' from the rotations between frames."""
    index, rotations = image_rotations(seq.images.numpy(), seq.camera.K.double().numpy())
    result = imu_time_offset(seq.frame_stamps.numpy(), index, rotations, imu_stamps, gyro,
                             seq.camera.T_base_cam.double().numpy()[:3, :3], config.filter.gyro_sampling)  # ValueError
    print(f"calibrated on frames {frames} from the rotations between frames ({result.pairs} frame pairs kept, "
          f"{result.pairs_skipped} without a rotation, without IMU around them or trimmed): the gyro matches the images "
          f"to {math.degrees(result.residual):.3f} deg per axis and pair at")
    now = config.odometry.imu_time_offset
    apart = (result.offset - now) / result.standard_error
    print(f"    odometry.imu_time_offset: {result.offset:.4f}   # s, +- {result.standard_error * 1e3:.1f} ms "
          f"(the params' {now:.4f}: {'off by' if abs(apart) > 2 else 'within'} {abs(apart):.1f} standard errors)")
    if (note := result.gain_note()) is not None:
        print(f"{prog_name('calibrate_mounting')}: note: {note}", file=sys.stderr)
    return 0
