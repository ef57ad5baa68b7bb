#!/usr/bin/env python3
"""Convert a KITTI sequence (odometry or raw layout) into a rosbag2 for bevo_ros.

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
                          written frame), from poses/NN.txt through the IMU->camera calibration
  /ground_truth/imu       sensor_msgs/Imu carrying the OXTS unit's own roll/pitch/yaw
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

try:
    import bevo_ros  # noqa: F401
except ImportError:  # running from a source checkout without installing
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from bevo_ros import bag, kitti

EPILOG = """\
notes:
  KITTI's synced OXTS stream is only 10 Hz, so /imu/data is 10 Hz here (one IMU message per
  frame, stamped with the OXTS time); the unsynced 100 Hz OXTS data is not used.
  Frame times: odometry times.txt when present (offset to the OXTS clock), otherwise the OXTS
  timestamps; raw layout: image_0X/timestamps.txt.
  Odometry sequence NN maps to its raw drive with the devkit table (00..10); the OXTS directory
  is looked up in --raw-root, or given with --oxts.
  The sample's 2011_09_30 drives have no raw calibration; the 2011_09_26 files describe the same
  rig and are found by the default search (override with --raw-calib).

examples:
  kitti_to_bag.py --odometry ../shared/data/kitti/odometry --sequence 06 -o seq06_bag
  kitti_to_bag.py --odometry DATASET --sequence 06 --first 0 --count 20 --storage mcap -o short
  kitti_to_bag.py --raw RAW/2011_09_30/2011_09_30_drive_0020_sync --camera 0 -o drive20_bag
"""


class UserError(Exception):
    """Expected bad input: reported on stderr with exit code 2."""


@dataclass
class Source:
    """Everything of one sequence, indexed by frame (OXTS record i belongs to frame i)."""

    images: list[Path]
    frame_stamps_ns: np.ndarray  # (F,)
    oxts: kitti.OxtsData  # len F
    P: np.ndarray  # (3, 4) projection of the rectified camera
    camera: int
    poses: np.ndarray | None  # (F, 4, 4) T_world_cam; NaN rows where no ground truth
    T_base_cam: np.ndarray | None  # (4, 4)
    description: str


# ----------------------------------------------------------------------------------------------
# Locating the inputs
# ----------------------------------------------------------------------------------------------
def _check_image_names(images: list[Path]) -> None:
    """Names must be consecutive frame numbers from 0, or frames and stamps cannot be paired."""
    for i, p in enumerate(images):
        if not p.stem.isdigit() or int(p.stem) != i:
            raise UserError(f"{p}: expected frame {i} here; image numbers must be consecutive from 0 "
                            f"(a missing or extra image would misalign the timestamps)")


def _find_oxts(args, date: str, drive: str, odometry_root: Path) -> Path:
    if args.oxts:
        return Path(args.oxts)
    roots = [Path(args.raw_root)] if args.raw_root else [odometry_root / "raw", odometry_root.parent / "raw",
                                                         odometry_root.parent.parent / "raw"]
    tried = []
    for root in roots:
        cand = root / date / f"{drive}_sync" / "oxts"
        tried.append(str(cand))
        if cand.is_dir():
            return cand
    raise UserError(f"no OXTS directory for raw drive {drive}; looked in: {', '.join(tried)} "
                    "(give --raw-root or --oxts)")


def _raw_calib_dir(args, near: Path, date: str) -> Path:
    if args.raw_calib:
        d = Path(args.raw_calib)
        if not d.is_dir():
            raise UserError(f"{d}: --raw-calib directory not found")
        return d
    found = kitti.find_raw_calib_dir(near, date)
    if found is None:
        raise UserError(f"no raw calibration (calib_imu_to_velo.txt, calib_velo_to_cam.txt, calib_cam_to_cam.txt) "
                        f"found near {near}; give --raw-calib DIR")
    if found.name != date and not args.quiet:
        print(f"note: using the raw calibration in {found} for a {date} drive (same rig)", file=sys.stderr)
    return found


def odometry_source(args) -> Source:
    root = Path(args.odometry)
    seq = f"{int(args.sequence):02d}" if str(args.sequence).isdigit() else str(args.sequence)
    seq_dir = root / "sequences" / seq
    if not seq_dir.is_dir():
        raise UserError(f"{seq_dir}: sequence directory not found")
    images = kitti.list_images(seq_dir / f"image_{args.camera}")
    _check_image_names(images)
    calib = kitti.read_odometry_calib(seq_dir / "calib.txt")
    key = f"P{args.camera}"
    if key not in calib:
        raise UserError(f"{seq_dir / 'calib.txt'}: no '{key}:' line for camera {args.camera}")

    if seq in kitti.ODOMETRY_TO_RAW:
        date, drive, start, end = kitti.raw_drive_for_sequence(seq)
    elif args.oxts:
        date, drive, start, end = "", "", 0, None
    else:
        raise UserError(f"sequence {seq} has no raw drive (only 00..10 do): give --oxts DIR")
    if args.oxts_offset is not None:
        start = args.oxts_offset
    oxts_dir = _find_oxts(args, date, drive, root)
    oxts = kitti.read_oxts(oxts_dir)
    n = len(images)
    last = start + n - 1
    if end is not None and last > end:
        raise UserError(f"{seq_dir / f'image_{args.camera}'}: {n} images but sequence {seq} maps to raw frames "
                        f"{start}..{end} ({end - start + 1} frames)")
    if last >= len(oxts):
        raise UserError(f"{oxts_dir}: {len(oxts)} OXTS records, but {n} images starting at raw frame {start} "
                        f"need {last + 1}")
    oxts = oxts.slice(start, start + n)

    times_txt = seq_dir / "times.txt"
    if times_txt.is_file():
        times = kitti.read_times(times_txt)
        if len(times) != n:
            raise UserError(f"{times_txt}: {len(times)} times but {n} images in {seq_dir / f'image_{args.camera}'}")
        # times.txt counts from the sequence start: put it on the OXTS clock of frame 0.
        stamps = oxts.stamps_ns[0] + np.round((times - times[0]) * 1e9).astype(np.int64)
    else:
        stamps = oxts.stamps_ns.copy()

    poses, T_base_cam = None, None
    poses_txt = Path(args.poses) if args.poses else root / "poses" / f"{seq}.txt"
    if poses_txt.is_file():
        all_poses = kitti.read_poses(poses_txt)
        if len(all_poses) < n:
            raise UserError(f"{poses_txt}: {len(all_poses)} poses but {n} images")
        poses = all_poses[:n]
    elif args.poses:
        raise UserError(f"{poses_txt}: --poses file not found")
    calib_date = date or oxts_dir.parent.parent.name
    if poses is not None or kitti.find_raw_calib_dir(oxts_dir.parent, calib_date) is not None or args.raw_calib:
        # the rig's extrinsics: ground truth in the base frame, and /tf_static
        T_base_cam = kitti.invert_rigid(kitti.imu_to_camera_extrinsics(
            _raw_calib_dir(args, oxts_dir.parent, calib_date), args.camera))
    return Source(images, stamps, oxts, calib[key], args.camera, poses, T_base_cam,
                  f"odometry sequence {seq} (raw {drive or oxts_dir}, from raw frame {start})")


def raw_source(args) -> Source:
    drive_dir = Path(args.raw)
    if not drive_dir.is_dir():
        raise UserError(f"{drive_dir}: raw drive directory not found")
    cam_dir = drive_dir / f"image_{args.camera:02d}"
    images = kitti.list_images(cam_dir / "data")
    _check_image_names(images)
    stamps = kitti.read_timestamps_ns(cam_dir / "timestamps.txt")
    if len(stamps) != len(images):
        raise UserError(f"{cam_dir / 'timestamps.txt'}: {len(stamps)} timestamps but {len(images)} images in "
                        f"{cam_dir / 'data'}")
    oxts_dir = Path(args.oxts) if args.oxts else drive_dir / "oxts"
    oxts = kitti.read_oxts(oxts_dir)
    if len(oxts) != len(images):
        raise UserError(f"{oxts_dir}: {len(oxts)} OXTS records but {len(images)} images in {cam_dir / 'data'} "
                        "(synced data pairs them one to one)")
    date = drive_dir.parent.name
    calib_dir = _raw_calib_dir(args, drive_dir, date)
    cam_calib_path = calib_dir / "calib_cam_to_cam.txt"
    cam_calib = kitti.read_raw_calib(cam_calib_path)
    key = f"P_rect_{args.camera:02d}"
    if key not in cam_calib or cam_calib[key].size != 12:
        raise UserError(f"{cam_calib_path}: no valid '{key}:' line")
    T_base_cam = kitti.invert_rigid(kitti.imu_to_camera_extrinsics(calib_dir, args.camera))

    poses = None
    if args.poses:
        all_poses = kitti.read_poses(args.poses)
        drive = drive_dir.name.removesuffix("_sync")
        offset = args.oxts_offset
        if offset is None:
            offset = next((s for d, s, _ in kitti.ODOMETRY_TO_RAW.values() if d == drive), 0)
        poses = np.full((len(images), 4, 4), np.nan)
        lo, hi = offset, min(len(images), offset + len(all_poses))
        poses[lo:hi] = all_poses[: hi - lo]
    return Source(images, stamps, oxts, cam_calib[key].reshape(3, 4), args.camera, poses,
                  T_base_cam, f"raw drive {drive_dir.name}")


# ----------------------------------------------------------------------------------------------
# Conversion
# ----------------------------------------------------------------------------------------------
def _load_image(path: Path, colour: bool) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise UserError(f"{path}: cannot read image")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        if not colour:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    elif colour:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    return img


def convert(src: Source, args) -> dict[str, int]:
    """Write frames ``[first, first + count)`` of ``src`` into ``args.output``; returns message counts."""
    from tqdm import tqdm

    n = len(src.images)
    first = args.first
    if not 0 <= first < n:
        raise UserError(f"--first {first} is outside the {n} frames of {src.description}")
    stop = n if args.count is None else min(n, first + args.count)
    if args.count is not None and args.count < 1:
        raise UserError("--count must be >= 1")
    colour = src.camera >= 2
    K = src.P[:, :3]

    gt = None
    if src.poses is not None and src.T_base_cam is not None:
        sel = src.poses[first:stop]
        valid = np.isfinite(sel).all(axis=(1, 2))
        if valid.any():
            # odom = the base frame at the first frame with ground truth: the GT starts at identity
            # like the estimate does.
            gt = np.full_like(sel, np.nan)
            gt[valid] = kitti.base_poses(sel[valid], src.T_base_cam)

    # Every message as (stamp, rank, kind, index): same-stamp ties keep the IMU before the image,
    # so a consumer has the IMU sample of a frame when the frame arrives.
    events = []
    for i in range(first, stop):
        events.append((int(src.oxts.stamps_ns[i]), 0, "imu", i))
        events.append((int(src.frame_stamps_ns[i]), 2, "image", i))
    events.sort()

    size = None
    with bag.BagWriter(args.output, storage=args.storage, overwrite=args.overwrite) as writer:
        for partial in writer.removed_partials:  # left by a killed earlier run
            print(f"kitti_to_bag: removed {partial}, the partial output of an interrupted run", file=sys.stderr)
        if src.T_base_cam is not None and events and not args.no_tf_static:
            # the rig on /tf_static (latched): base = the OXTS IMU (KITTI's convention), and the camera
            writer.write_tf_static(events[0][0], [(args.base_frame, args.imu_frame, np.eye(4)),
                                                  (args.base_frame, args.camera_frame, src.T_base_cam)])
        for stamp, _, kind, i in tqdm(events, desc="kitti_to_bag", unit="msg", disable=args.quiet, file=sys.stderr):
            if kind == "imu":
                gyro, accel = src.oxts.gyro[i], src.oxts.accel[i]
                writer.write_imu(stamp, gyro, accel, args.imu_frame, topic=args.imu_topic,
                                 gyro_covariance=args.gyro_var, accel_covariance=args.accel_var)
                writer.write_imu_attitude(stamp, src.oxts.roll[i], src.oxts.pitch[i], src.oxts.yaw[i], gyro=gyro,
                                          accel=accel, frame_id=args.imu_frame, topic=args.gt_imu_topic,
                                          orientation_covariance=np.radians(0.03) ** 2,
                                          gyro_covariance=args.gyro_var, accel_covariance=args.accel_var)
                continue
            img = _load_image(src.images[i], colour)
            if size is None:
                size = img.shape[:2]
            elif img.shape[:2] != size:
                raise UserError(f"{src.images[i]}: image is {img.shape[1]}x{img.shape[0]}, "
                                f"the first was {size[1]}x{size[0]}")
            writer.write_camera_info(stamp, K, img.shape[1], img.shape[0], args.camera_frame,
                                     topic=args.camera_info_topic, P=src.P)
            writer.write_image(stamp, img, args.camera_frame, topic=args.image_topic)
            if gt is not None and np.isfinite(gt[i - first]).all():
                writer.write_odometry(stamp, gt[i - first], args.odom_frame, args.base_frame,
                                      topic=args.gt_odometry_topic,
                                      pose_covariance=[0.01] * 3 + [np.radians(0.1) ** 2] * 3)
        counts = dict(writer.counts)
    return counts


def _dir_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="kitti_to_bag.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--odometry", metavar="DIR", help="KITTI odometry root (holds sequences/ and poses/)")
    src.add_argument("--raw", metavar="DIR", help="a raw drive directory <date>/<date>_drive_NNNN_sync")
    p.add_argument("--sequence", default="06", help="odometry sequence number (default 06)")
    p.add_argument("-o", "--output", required=True, help="output bag directory (must not exist, see --overwrite)")
    p.add_argument("--storage", choices=bag.STORAGES, default="sqlite3", help="rosbag2 storage plugin (default sqlite3)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    p.add_argument("--camera", type=int, choices=(0, 1, 2, 3), default=0,
                   help="camera: 0/1 grey left/right (mono8), 2/3 colour (rgb8); default 0")
    p.add_argument("--first", type=int, default=0, help="first frame to convert (default 0)")
    p.add_argument("--count", type=int, default=None, help="number of frames to convert (default: all)")
    p.add_argument("--oxts", metavar="DIR", help="raw OXTS directory (overrides the lookup)")
    p.add_argument("--oxts-offset", type=int, default=None, metavar="N",
                   help="raw frame of odometry frame 0 (default: from the devkit mapping)")
    p.add_argument("--raw-root", metavar="DIR", help="raw data root holding <date>/<drive>_sync (default: "
                   "raw/ beside or above the odometry root)")
    p.add_argument("--raw-calib", metavar="DIR", help="directory with calib_{imu_to_velo,velo_to_cam,cam_to_cam}.txt "
                   "(default: searched from the drive upwards, preferring the drive's date)")
    p.add_argument("--poses", metavar="FILE", help="ground-truth camera poses (default: <odometry>/poses/NN.txt)")
    p.add_argument("--imu-topic", default=bag.IMU_TOPIC)
    p.add_argument("--image-topic", default=bag.IMAGE_TOPIC)
    p.add_argument("--camera-info-topic", default=bag.CAMERA_INFO_TOPIC)
    p.add_argument("--gt-odometry-topic", default=bag.GT_ODOMETRY_TOPIC)
    p.add_argument("--gt-imu-topic", default=bag.GT_IMU_TOPIC)
    p.add_argument("--imu-frame", default="imu_link", help="frame id of the IMU messages (default imu_link)")
    p.add_argument("--camera-frame", default="camera_optical_frame", help="frame id of the images")
    p.add_argument("--odom-frame", default="odom", help="frame id of the ground-truth odometry")
    p.add_argument("--base-frame", default="base_link", help="child frame id of the ground-truth odometry")
    p.add_argument("--no-tf-static", action="store_true",
                   help="do not write /tf_static (base -> IMU identity, base -> camera optical frame)")
    p.add_argument("--gyro-var", type=float, default=1e-4, help="angular_velocity variance, (rad/s)^2")
    p.add_argument("--accel-var", type=float, default=1e-2, help="linear_acceleration variance, (m/s^2)^2")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or notes")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    out = Path(args.output)
    try:
        if out.exists() and not args.overwrite:
            raise UserError(f"{out}: output bag exists (use --overwrite to replace it)")
        src = odometry_source(args) if args.odometry else raw_source(args)
        counts = convert(src, args)
    except KeyboardInterrupt:
        print("kitti_to_bag: interrupted; no bag written", file=sys.stderr)
        return 130
    except (UserError, FileNotFoundError, FileExistsError, ValueError) as exc:
        print(f"kitti_to_bag: error: {exc}", file=sys.stderr)
        return 2
    first, last = src.frame_stamps_ns[args.first], src.frame_stamps_ns[args.first + counts.get(args.image_topic, 1) - 1]
    print(f"wrote {out} ({args.storage}) from {src.description}, frames {args.first}.."
          f"{args.first + counts.get(args.image_topic, 0) - 1}")
    width = max(len(t) for t in counts)
    for topic, c in sorted(counts.items()):
        print(f"  {topic:<{width}}  {c:6d} msgs")
    print(f"  duration {(last - first) * 1e-9:.3f} s, size {_dir_size(out) / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
