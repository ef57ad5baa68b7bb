"""``bevo convert``: a KITTI sequence (odometry or raw layout) -> a rosbag2 for bevo_ros (bevo_ros.datasets.kitti_bag).

Topics (names are options):
  /imu/data               sensor_msgs/Imu: the OXTS rates and accelerations only
                          (orientation_covariance[0] = -1: no ground truth leaks in)
  /camera/image_rect      sensor_msgs/Image, mono8 (cameras 0/1) or rgb8 (cameras 2/3): KITTI's
                          images are rectified (image_pipeline naming)
  /camera/camera_info     sensor_msgs/CameraInfo, rectified: D = 0 (plumb_bob), R = I, P from calib
  /tf_static              tf2_msgs/TFMessage, latched (transient local offered QoS in the metadata):
                          base_link -> imu_link (identity: KITTI's base is the OXTS IMU) and
                          base_link -> camera_optical_frame (the raw calibration chain)
  /ground_truth/odometry  nav_msgs/Odometry of base_link (the IMU) in odom (= base at the first
                          written frame), from poses/NN.txt through the IMU->camera calibration;
                          a raw drive without --poses: the OXTS unit's GPS/INS poses at the image
                          stamps (--no-oxts-ground-truth leaves it out)
  /ground_truth/imu       sensor_msgs/Imu carrying the OXTS unit's own roll/pitch/yaw
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bevo_ros.commands import new_parser, prog_name
from bevo_ros.datasets import kitti
from bevo_ros.io import bag
from bevo_ros.datasets.kitti_bag import INTERPOLATED_IMU, ConversionError, ConversionOptions, convert, load_source

EPILOG = """\
notes:
  KITTI's synced OXTS stream is only 10 Hz, so /imu/data is 10 Hz here (one IMU message per
  frame, stamped with the OXTS time); --imu-oxts takes it from the raw extract's unsynced 100 Hz
  OXTS of the same drive instead (the paper's IMU rate).
  Frame times: odometry times.txt when present (placed on the OXTS clock by the records' median
  offset: a synced record is the packet nearest the trigger, ms away), otherwise the OXTS
  timestamps; raw layout: image_0X/timestamps.txt.
  Odometry sequence NN maps to its raw drive with the devkit table (00..10); the OXTS directory
  is looked up in --raw-root, or given with --oxts.
  OXTS records that KITTI's synchronisation filled in by linear interpolation over lost packets
  (all six IMU channels exactly on the line through their neighbours; e.g. drive 0020's records
  1-11, the sample's start) are reported, and bridged by the unit's own attitude and velocity change
  across them (which hold the lost packets' integrals; --interpolated-imu line|leave-out otherwise).
  Calibration: the odometry layout's camera matrix is calib.txt's; the rig's extrinsics come from
  the raw calibration of the drive's day, else the nearest other day found (the sample's 2011_09_30
  drives have none: 2011_09_26's describe the same rig; override with --raw-calib). A raw drive's
  camera matrix (P_rect_0X) must be its own day's (the day from the drive folder's name): another
  day's only with --raw-calib, and never one whose S_rect_0X is not the images' size.

examples:
  bevo convert --odometry ../shared/data/kitti/odometry --sequence 06 -o seq06_bag
  bevo convert --odometry DATASET --sequence 06 --first 0 --count 20 --storage mcap -o short
  bevo convert --raw RAW/2011_10_03/2011_10_03_drive_0042_sync --poses DATASET/poses/01.txt -o drive42_bag
  bevo convert --raw RAW/2011_09_26/2011_09_26_drive_0009_sync -o drive09_bag   # ground truth: the OXTS's poses
  bevo convert --raw RAW/2011_09_26/2011_09_26_drive_0009_sync --imu-oxts EXTRACT/2011_09_26/2011_09_26_drive_0009_extract/oxts -o drive09_100hz
  bevo convert --render-oxts RAW/2011_09_30/2011_09_30_drive_0027_sync/oxts --first 0 --count 160 -o real_imu_bag
  bevo convert --render-oxts RAW/2011_09_30/2011_09_30_drive_0020_sync/oxts --vertical-curves -o drive20_hills_bag
"""


def _dir_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def build_parser() -> argparse.ArgumentParser:
    p = new_parser(__doc__, EPILOG)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--odometry", metavar="DIR", help="KITTI odometry root (holds sequences/ and poses/)")
    src.add_argument("--raw", metavar="DIR", help="a raw drive directory <date>/<date>_drive_NNNN_sync")
    src.add_argument("--render-oxts", metavar="DIR",
                     help="a raw drive's oxts directory: its real IMU and motion with a rendered synthetic camera "
                          "(exact ground truth; bevo_ros.datasets.synthetic.oxts_drive; run with params/synthetic.yaml)")
    p.add_argument("--vertical-curves", action="store_true",
                   help="with --render-oxts: the images show the road ahead bent by the drive's own slope further "
                        "along (its crests and sags; drive_from_oxts' vertical_curves)")
    p.add_argument("--sequence", default="06", help="odometry sequence number (default 06)")
    p.add_argument("-o", "--output", required=True, help="output bag directory (must not exist, see --overwrite)")
    p.add_argument("--storage", choices=bag.STORAGES, default="sqlite3", help="rosbag2 storage plugin (default sqlite3)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    p.add_argument("--camera", type=int, choices=(0, 1, 2, 3), default=0,
                   help="camera: 0/1 grey left/right (mono8), 2/3 colour (rgb8); default 0")
    p.add_argument("--first", type=int, default=0, help="first frame to convert (default 0)")
    p.add_argument("--count", type=int, default=None, help="number of frames to convert (default: all)")
    p.add_argument("--oxts", metavar="DIR", help="raw OXTS directory (overrides the lookup)")
    p.add_argument("--imu-oxts", metavar="DIR",
                   help="the IMU topic from this OXTS directory instead of the synced records: the raw extract's "
                        "unsynced 100 Hz oxts/ of the same drive (the synced records still give the frame times, "
                        "the ground truth and the ground-truth attitude); from 0.5 s before the first frame")
    p.add_argument("--oxts-offset", type=int, default=None, metavar="N",
                   help="raw frame of odometry frame 0 (default: from the devkit mapping)")
    p.add_argument("--raw-root", metavar="DIR", help="raw data root holding <date>/<drive>_sync (default: "
                   "raw/ beside or above the odometry root)")
    p.add_argument("--raw-calib", metavar="DIR", help="directory with calib_{imu_to_velo,velo_to_cam,cam_to_cam}.txt "
                   "(default: searched from the drive upwards, preferring the drive's date)")
    p.add_argument("--poses", metavar="FILE", help="ground-truth camera poses (default: <odometry>/poses/NN.txt; a raw "
                   "drive: the OXTS unit's GPS/INS poses at the image stamps, as the devkit's convertOxtsToPose)")
    p.add_argument("--no-oxts-ground-truth", dest="oxts_ground_truth", action="store_false",
                   help="a raw drive without --poses: no ground truth (default: the OXTS unit's GPS/INS poses)")
    p.add_argument("--imu-topic", default=bag.IMU_TOPIC)
    p.add_argument("--image-topic", default=bag.IMAGE_TOPIC)
    p.add_argument("--camera-info-topic", default=bag.CAMERA_INFO_TOPIC)
    p.add_argument("--gt-odometry-topic", default=bag.GT_ODOMETRY_TOPIC)
    p.add_argument("--gt-imu-topic", default=bag.GT_IMU_TOPIC)
    p.add_argument("--speed-topic", default="", metavar="TOPIC",
                   help="also write the OXTS unit's velocity (vf, vl, vu) there as geometry_msgs/TwistStamped in the "
                        "base frame: a GNSS/INS speed for `bevo calibrate --speed-topic` (default: not written)")
    p.add_argument("--imu-frame", default="imu_link", help="frame id of the IMU messages (default imu_link)")
    p.add_argument("--camera-frame", default="camera_optical_frame", help="frame id of the images")
    p.add_argument("--odom-frame", default="odom", help="frame id of the ground-truth odometry")
    p.add_argument("--base-frame", default="base_link", help="child frame id of the ground-truth odometry")
    p.add_argument("--no-tf-static", action="store_true",
                   help="do not write /tf_static (base -> IMU identity, base -> camera optical frame)")
    p.add_argument("--gyro-var", type=float, default=1e-4, help="angular_velocity variance, (rad/s)^2")
    p.add_argument("--accel-var", type=float, default=1e-2, help="linear_acceleration variance, (m/s^2)^2")
    p.add_argument("--interpolated-imu", choices=INTERPOLATED_IMU, default="bridge",
                   help="the OXTS records KITTI's synchronisation interpolated over lost packets, on the IMU topic: "
                        "bridge (default: their rates and accelerations from the unit's own attitude and velocity "
                        "change across them, which hold the lost packets' integrals), line (as KITTI wrote them: "
                        "the line between the real records) or "
                        "leave-out (an IMU gap); the ground-truth IMU topic keeps them as they are")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or notes")
    return p


def _render_oxts(args) -> int:
    """``--render-oxts``: the drive of :func:`~bevo_ros.datasets.synthetic.oxts_drive.drive_from_oxts`
    (frames ``--first``, ``--count``) written by the synthetic drives' bag writer."""
    from bevo_ros.datasets.kitti import read_oxts
    from bevo_ros.datasets.rosbag import write_drive_bag
    from bevo_ros.datasets.synthetic.oxts_drive import drive_from_oxts

    out = Path(args.output)
    try:
        if out.exists() and not args.overwrite:
            raise FileExistsError(f"{out}: output bag exists (use --overwrite to replace it)")
        drive = drive_from_oxts(read_oxts(args.render_oxts), render="lazy", vertical_curves=args.vertical_curves)
        n = drive.num_frames
        stop = n if args.count is None else args.first + args.count
        if not (0 <= args.first and args.first + 2 <= stop <= n):
            raise ValueError(f"--first {args.first} --count {args.count}: the drive has {n} frames (need >= 2 in range)")
        write_drive_bag(drive, out, storage=args.storage, overwrite=args.overwrite, frame_range=(args.first, stop),
                        wheel_odometry_topic=args.speed_topic or None)
    except KeyboardInterrupt:
        print(f"{prog_name('kitti_to_bag')}: interrupted; no bag written", file=sys.stderr)
        return 130
    except (FileNotFoundError, FileExistsError, ValueError) as exc:
        print(f"{prog_name('kitti_to_bag')}: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out} ({args.storage}): {args.render_oxts}'s IMU and motion, rendered camera, frames "
          f"{args.first}..{stop - 1} of {n}, {drive.frame_stamps[stop - 1] - drive.frame_stamps[args.first]:.3f} s, "
          f"size {_dir_size(out) / 1e6:.2f} MB")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.render_oxts:
        if args.imu_oxts:
            print(f"{prog_name('kitti_to_bag')}: error: --imu-oxts applies to a drive's real images (--render-oxts "
                  "renders its frames at the given OXTS records)", file=sys.stderr)
            return 2
        return _render_oxts(args)
    if args.vertical_curves:
        print(f"{prog_name('kitti_to_bag')}: error: --vertical-curves applies to --render-oxts only (real images "
              "show their road as it is)", file=sys.stderr)
        return 2
    out = Path(args.output)
    try:
        if out.exists() and not args.overwrite:
            raise ConversionError(f"{out}: output bag exists (use --overwrite to replace it)")
        opts = ConversionOptions(**{k: v for k, v in vars(args).items() if k not in ("render_oxts", "vertical_curves")})
        src = load_source(opts)
        counts = convert(src, opts)
    except KeyboardInterrupt:
        print(f"{prog_name('kitti_to_bag')}: interrupted; no bag written", file=sys.stderr)
        return 130
    except (ConversionError, FileNotFoundError, FileExistsError, ValueError) as exc:
        print(f"{prog_name('kitti_to_bag')}: error: {exc}", file=sys.stderr)
        return 2
    first, last = src.frame_stamps_ns[args.first], src.frame_stamps_ns[args.first + counts.get(args.image_topic, 1) - 1]
    print(f"wrote {out} ({args.storage}) from {src.description}, frames {args.first}.."
          f"{args.first + counts.get(args.image_topic, 0) - 1}")
    width = max(len(t) for t in counts)
    for topic, c in sorted(counts.items()):
        print(f"  {topic:<{width}}  {c:6d} msgs")
    print(f"  duration {(last - first) * 1e-9:.3f} s, size {_dir_size(out) / 1e6:.2f} MB")
    if (note := kitti.day_tilt_note(src.date, str(out))) is not None:  # even with --quiet: the scale hangs on it
        print(f"{prog_name('kitti_to_bag')}: warning: {note}", file=sys.stderr)
    return 0
