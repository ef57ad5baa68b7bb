"""KITTI (odometry or raw layout) -> rosbag2 (``bevo convert``): locate a sequence's images, OXTS,
calibration and poses (:func:`load_source`), then write IMU, images, CameraInfo, /tf_static and the
ground truth in stamp order (:func:`convert`)."""
from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bevo_ros.commands import prog_name
from bevo_ros.io import bag
from bevo_ros.datasets import kitti


IMU_LEAD_S = 0.5  # s of --imu-oxts records written before the first frame (the DUKF's start)
IMU_GAP_PERIODS = 2.5  # --imu-oxts: a step between records longer than this many (median) periods is a gap
INTERPOLATED_IMU = ("bridge", "line", "leave-out")  # ConversionOptions.interpolated_imu


class ConversionError(ValueError):
    """Expected bad input (missing or inconsistent KITTI files, bad options): ``bevo convert`` reports it
    with exit code 2."""


@dataclass
class ConversionOptions:
    """What to convert and how (``bevo convert``'s options, same names): ``odometry`` + ``sequence`` or
    ``raw`` selects the input, ``output`` the bag."""

    output: str | Path
    odometry: str | Path | None = None
    raw: str | Path | None = None
    sequence: str = "06"
    storage: str = "sqlite3"
    overwrite: bool = False
    camera: int = 0
    first: int = 0
    count: int | None = None
    oxts: str | Path | None = None
    oxts_offset: int | None = None
    raw_root: str | Path | None = None
    raw_calib: str | Path | None = None
    poses: str | Path | None = None
    imu_topic: str = bag.IMU_TOPIC
    image_topic: str = bag.IMAGE_TOPIC
    camera_info_topic: str = bag.CAMERA_INFO_TOPIC
    gt_odometry_topic: str = bag.GT_ODOMETRY_TOPIC
    gt_imu_topic: str = bag.GT_IMU_TOPIC
    speed_topic: str = ""  # also the OXTS unit's velocity as a TwistStamped there (a GNSS/INS speed)
    imu_frame: str = "imu_link"
    camera_frame: str = "camera_optical_frame"
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    no_tf_static: bool = False
    gyro_var: float = 1e-4
    accel_var: float = 1e-2
    quiet: bool = False
    # KITTI's interpolated OXTS records on the IMU topic (kitti.interpolated_oxts): "bridge" (their rates
    # and accelerations from the unit's own attitude and velocity change across them, kitti.bridged_imu),
    # "line" (as KITTI wrote them) or "leave-out" (an IMU gap); /ground_truth/imu keeps them as they are
    interpolated_imu: str = "bridge"
    oxts_ground_truth: bool = True  # a raw drive without poses: the OXTS unit's GPS/INS poses
    imu_oxts: str | Path | None = None  # /imu/data from this OXTS directory (the raw extract's 100 Hz one)


@dataclass
class Source:
    """Everything of one sequence, indexed by frame (OXTS record i belongs to frame i)."""

    images: list[Path]
    frame_stamps_ns: np.ndarray  # (F,)
    oxts: kitti.OxtsData  # len F
    P: np.ndarray  # (3, 4) projection of the rectified camera
    camera: int
    poses: np.ndarray | None  # (F, 4, 4) T_world_cam0 (KITTI's poses are camera 0's); NaN rows where no ground truth
    T_base_cam: np.ndarray | None  # (4, 4) the converted camera's extrinsics (/tf_static)
    description: str
    T_base_cam0: np.ndarray | None = None  # (4, 4) camera 0's, the poses' frame: set with T_base_cam
    record_offset: int = 0  # the raw OXTS record of frame 0 (an odometry sequence's start in its drive)
    # the drive's records around the sequence's (oxts = oxts_drive[record_offset:][:F]): a run of
    # interpolated records is judged and bridged with its real ends outside the sequence; None: oxts only
    oxts_drive: kitti.OxtsData | None = None
    date: str = ""  # the recording day (2011_09_30), '' unknown: kitti.day_tilt_note


# ----------------------------------------------------------------------------------------------
# Locating the inputs
# ----------------------------------------------------------------------------------------------
def _check_image_names(images: list[Path]) -> None:
    """Names must be consecutive frame numbers from 0, or frames and stamps cannot be paired."""
    for i, p in enumerate(images):
        if not p.stem.isdigit() or int(p.stem) != i:
            raise ConversionError(f"{p}: expected frame {i} here; image numbers must be consecutive from 0 "
                            f"(a missing or extra image would misalign the timestamps)")


def _find_oxts(opts: ConversionOptions, date: str, drive: str, odometry_root: Path) -> Path:
    if opts.oxts:
        return Path(opts.oxts)
    roots = [Path(opts.raw_root)] if opts.raw_root else [odometry_root / "raw", odometry_root.parent / "raw",
                                                         odometry_root.parent.parent / "raw"]
    tried = []
    for root in roots:
        cand = root / date / f"{drive}_sync" / "oxts"
        tried.append(str(cand))
        if cand.is_dir():
            return cand
    # Odometry sequence 03's raw drive is not among the raw downloads: a user looks for it in vain.
    unpublished = (" This raw drive (odometry sequence 03) is not among KITTI's raw downloads: the sequence has no IMU"
                   if drive == kitti.ODOMETRY_TO_RAW["03"][0] else "")
    raise ConversionError(f"no OXTS directory for raw drive {drive}; looked in: {', '.join(tried)} "
                          f"(give --raw-root or --oxts).{unpublished}")


def _raw_calib_dir(opts: ConversionOptions, near: Path, date: str, intrinsics: bool = False) -> Path:
    """The raw calibration directory for a ``date`` drive: ``--raw-calib``, else the day's own,
    else (extrinsics only: the IMU-to-velodyne chain is one rig's) the nearest other day's.

    ``intrinsics``: the caller takes the camera matrix (``P_rect``) from it too, which KITTI
    calibrated anew each day (fx 707-722 px: percents of scale): another day's is refused unless
    given explicitly with ``--raw-calib``."""
    if opts.raw_calib:
        d = Path(opts.raw_calib)
        if not d.is_dir():
            raise ConversionError(f"{d}: --raw-calib directory not found")
        if date and not _days_own(d, near, date):  # said even with --quiet: the scale of everything hangs on it
            print(f"warning: the raw calibration in {d} is for another day than this {date} drive "
                  + ("(its camera matrix too)" if intrinsics else "(its extrinsics)"), file=sys.stderr)
        return d
    found = kitti.find_raw_calib_dir(near, date)
    files = "calib_imu_to_velo.txt, calib_velo_to_cam.txt, calib_cam_to_cam.txt"
    if found is None:
        raise ConversionError(f"no raw calibration ({files}) found near {near}; give --raw-calib DIR")
    if date and not _days_own(found, near, date):
        if intrinsics:
            raise ConversionError(
                f"no raw calibration of {date} ({files}, all three) near {near}: found {found.name}'s, but a raw "
                f"drive's camera matrix (P_rect) is calibrated each day (and each day's rectified image size "
                f"differs) and another day's mis-scales the odometry by percents; give --raw-calib DIR with "
                f"{date}'s files")
        if not opts.quiet:
            print(f"note: using the raw calibration in {found} for a {date} drive (extrinsics only: the same rig; "
                  f"the camera matrix comes from calib.txt)", file=sys.stderr)
    return found


def _days_own(calib_dir: Path, near: Path, date: str) -> bool:
    """A calibration folder is the drive's own day's when named as the day (KITTI's ``RAW/<day>/``) or
    when it is the drive's folder or the folder holding it, whatever their names."""
    near = Path(near).resolve()
    return calib_dir.name == date or Path(calib_dir).resolve() in (near, near.parent)


def _drive_date(drive_dir: Path) -> str:
    """A raw drive's day: from its folder's name (``2011_09_30_drive_0020_sync``), else its parent's
    (``RAW/2011_09_30/...``); absolute, so ``--raw .`` has one too."""
    drive_dir = drive_dir.resolve()
    m = re.match(r"(\d{4}_\d{2}_\d{2})_drive", drive_dir.name)
    return m.group(1) if m else drive_dir.parent.name


def _check_rectified_size(cam_calib: dict, key: str, path: Path, image: Path) -> None:
    """A calibration's ``S_rect_0X`` (its rectified image size) must be the images' size."""
    if key not in cam_calib or cam_calib[key].size != 2:
        return  # older files have no S_rect: nothing to check
    w, h = (int(round(v)) for v in cam_calib[key])
    img = _load_image(image, colour=False)
    if (img.shape[1], img.shape[0]) != (w, h):
        raise ConversionError(f"{path}: {key} is {w}x{h} but the images are {img.shape[1]}x{img.shape[0]} "
                              f"({image}): that calibration is not this camera's; give --raw-calib DIR with the "
                              f"drive's own day")


def odometry_source(opts: ConversionOptions) -> Source:
    root = Path(opts.odometry)
    seq = f"{int(opts.sequence):02d}" if str(opts.sequence).isdigit() else str(opts.sequence)
    seq_dir = root / "sequences" / seq
    if not seq_dir.is_dir():
        hint = ""
        if (root / f"image_{opts.camera}").is_dir() or root.name == "sequences" or (root / "dataset").is_dir():
            hint = " (--odometry takes the folder that holds sequences/ and poses/, e.g. .../dataset)"
        raise ConversionError(f"{seq_dir}: sequence directory not found{hint}")
    images = kitti.list_images(seq_dir / f"image_{opts.camera}")
    _check_image_names(images)
    calib = kitti.read_odometry_calib(seq_dir / "calib.txt")
    key = f"P{opts.camera}"
    if key not in calib:
        raise ConversionError(f"{seq_dir / 'calib.txt'}: no '{key}:' line for camera {opts.camera}")

    if seq in kitti.ODOMETRY_TO_RAW:
        date, drive, start, end = kitti.raw_drive_for_sequence(seq)
    elif opts.oxts:
        date, drive, start, end = "", "", 0, None
    else:
        raise ConversionError(f"sequence {seq} has no raw drive (only 00..10 do): give --oxts DIR")
    if opts.oxts_offset is not None:
        start = opts.oxts_offset
    oxts_dir = _find_oxts(opts, date, drive, root)
    oxts = kitti.read_oxts(oxts_dir, increasing=False)  # a record out of order is judged where converted
    n = len(images)
    last = start + n - 1
    if end is not None and last > end:
        raise ConversionError(f"{seq_dir / f'image_{opts.camera}'}: {n} images but sequence {seq} maps to raw frames "
                        f"{start}..{end} ({end - start + 1} frames)")
    if last >= len(oxts):
        raise ConversionError(f"{oxts_dir}: {len(oxts)} OXTS records, but {n} images starting at raw frame {start} "
                        f"need {last + 1}")
    oxts_drive, oxts = oxts, oxts.slice(start, start + n)

    times_txt = seq_dir / "times.txt"
    if times_txt.is_file():
        times = kitti.read_times(times_txt)
        if len(times) < n:
            raise ConversionError(f"{times_txt}: {len(times)} times but {n} images in {seq_dir / f'image_{opts.camera}'}")
        times = times[:n]  # a partial download (the first n images) comes with the sequence's whole times.txt
        # times.txt counts from the sequence start: put it on the OXTS clock where the records say it is.
        # A synced record is the unit's packet nearest the camera's trigger, 3-13 ms RMS away (0016-0027):
        # their median offset, not record 0's alone (which shifted every frame against the IMU by its own).
        camera_ns = np.round((times - times[0]) * 1e9).astype(np.int64)
        stamps = camera_ns + np.int64(np.median(oxts.stamps_ns - camera_ns))
    else:
        stamps = oxts.stamps_ns.copy()

    poses, T_base_cam = None, None
    poses_txt = Path(opts.poses) if opts.poses else root / "poses" / f"{seq}.txt"
    if poses_txt.is_file():
        all_poses = kitti.read_poses(poses_txt)
        if len(all_poses) < n:
            raise ConversionError(f"{poses_txt}: {len(all_poses)} poses but {n} images")
        poses = all_poses[:n]
    elif opts.poses:
        raise ConversionError(f"{poses_txt}: --poses file not found")
    calib_date = date or oxts_dir.parent.parent.name
    T_base_cam0 = None
    if poses is not None or kitti.find_raw_calib_dir(oxts_dir.parent, calib_date) is not None or opts.raw_calib:
        # the rig's extrinsics: ground truth in the base frame (the poses are camera 0's), and /tf_static
        calib_dir = _raw_calib_dir(opts, oxts_dir.parent, calib_date)
        T_base_cam = kitti.invert_rigid(kitti.imu_to_camera_extrinsics(calib_dir, opts.camera))
        T_base_cam0 = kitti.invert_rigid(kitti.imu_to_camera_extrinsics(calib_dir, 0))
    elif not opts.quiet:  # no ground truth to put in the base frame: the bag goes without the rig
        print(f"note: no raw calibration found near {oxts_dir.parent} (--raw-calib DIR): the bag has no /tf_static, "
              f"and bevo run / bevo_node take the camera's extrinsics from their parameters (camera.base_T_camera)",
              file=sys.stderr)
    return Source(images, stamps, oxts, calib[key], opts.camera, poses, T_base_cam,
                  f"odometry sequence {seq} (raw {drive or oxts_dir}, from raw frame {start})", T_base_cam0, start,
                  oxts_drive, date=calib_date)


def raw_source(opts: ConversionOptions) -> Source:
    drive_dir = Path(opts.raw).resolve()  # `--raw .` has a name (the day, the source's description)
    if not drive_dir.is_dir():
        raise ConversionError(f"{drive_dir}: raw drive directory not found")
    cam_dir = drive_dir / f"image_{opts.camera:02d}"
    if not cam_dir.is_dir():
        drives = sorted(p.name for p in drive_dir.iterdir() if p.is_dir() and p.name.endswith("_sync"))
        if drives:
            raise ConversionError(f"{cam_dir}: not found: --raw takes one drive's folder, e.g. {drive_dir / drives[0]}")
    images = kitti.list_images(cam_dir / "data")
    _check_image_names(images)
    stamps = kitti.read_timestamps_ns(cam_dir / "timestamps.txt")
    if len(stamps) != len(images):
        raise ConversionError(f"{cam_dir / 'timestamps.txt'}: {len(stamps)} timestamps but {len(images)} images in "
                        f"{cam_dir / 'data'}")
    oxts_dir = Path(opts.oxts) if opts.oxts else drive_dir / "oxts"
    oxts = kitti.read_oxts(oxts_dir, increasing=False)  # a record out of order is judged where converted
    if len(oxts) != len(images):
        raise ConversionError(f"{oxts_dir}: {len(oxts)} OXTS records but {len(images)} images in {cam_dir / 'data'} "
                        "(synced data pairs them one to one)")
    date = _drive_date(drive_dir)
    calib_dir = _raw_calib_dir(opts, drive_dir, date, intrinsics=True)
    cam_calib_path = calib_dir / "calib_cam_to_cam.txt"
    cam_calib = kitti.read_raw_calib(cam_calib_path)
    key = f"P_rect_{opts.camera:02d}"
    if key not in cam_calib or cam_calib[key].size != 12:
        raise ConversionError(f"{cam_calib_path}: no valid '{key}:' line")
    _check_rectified_size(cam_calib, f"S_rect_{opts.camera:02d}", cam_calib_path, images[0])
    T_base_cam = kitti.invert_rigid(kitti.imu_to_camera_extrinsics(calib_dir, opts.camera))
    T_base_cam0 = kitti.invert_rigid(kitti.imu_to_camera_extrinsics(calib_dir, 0))  # the poses' camera

    poses = None
    if opts.poses:
        all_poses = kitti.read_poses(opts.poses)
        drive = drive_dir.name.removesuffix("_sync")
        offset = opts.oxts_offset
        if offset is None:
            offset = next((s for d, s, _ in kitti.ODOMETRY_TO_RAW.values() if d == drive), 0)
        if not 0 <= offset < len(images):
            raise ConversionError(f"{opts.poses}: its first pose is frame {offset} (--oxts-offset or the devkit's table "
                                  f"for {drive}), but the drive has {len(images)} frames")
        poses = np.full((len(images), 4, 4), np.nan)
        lo, hi = offset, min(len(images), offset + len(all_poses))
        poses[lo:hi] = all_poses[: hi - lo]
    elif opts.oxts_ground_truth:
        # Most raw drives have no odometry sequence: the unit's own GPS/INS poses, at the images' stamps
        # (camera 0's poses, as an odometry sequence's are)
        poses = kitti.oxts_poses(oxts, stamps) @ T_base_cam0
        if not opts.quiet:
            print(f"{prog_name('kitti_to_bag')}: note: ground truth from the OXTS unit's GPS/INS poses at the image "
                  f"stamps (the devkit's convertOxtsToPose; --poses for an odometry sequence's, --no-oxts-ground-truth "
                  f"for none)", file=sys.stderr)
    return Source(images, stamps, oxts, cam_calib[key].reshape(3, 4), opts.camera, poses,
                  T_base_cam, f"raw drive {drive_dir.name}", T_base_cam0, date=date)


# ----------------------------------------------------------------------------------------------
# Conversion
# ----------------------------------------------------------------------------------------------
def _load_image(path: Path, colour: bool) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ConversionError(f"{path}: cannot read image")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        if not colour:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    elif colour:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    return img


def _ranges(indices: np.ndarray) -> str:
    """``[1, 2, 3, 7]`` -> ``'1-3, 7'``."""
    runs, start = [], None
    for k, i in enumerate(indices):
        if start is None:
            start = i
        if k + 1 == len(indices) or indices[k + 1] != i + 1:
            runs.append(f"{start}-{i}" if i > start else f"{i}")
            start = None
    return ", ".join(runs)


def convert(src: Source, opts: ConversionOptions) -> dict[str, int]:
    """Write frames ``[first, first + count)`` of ``src`` into ``opts.output``; returns message counts."""
    from tqdm import tqdm

    n = len(src.images)
    first = opts.first
    if not 0 <= first < n:
        raise ConversionError(f"--first {first} is outside the {n} frames of {src.description}")
    stop = n if opts.count is None else min(n, first + opts.count)
    if opts.count is not None and opts.count < 1:
        raise ConversionError("--count must be >= 1")
    if src.poses is not None:
        have = np.flatnonzero(np.isfinite(src.poses).all(axis=(1, 2)))
        if not len(have) or have[-1] < first or have[0] >= stop:
            raise ConversionError(f"the ground truth (--poses) covers frames {_ranges(have) or 'none'} of "
                                  f"{src.description}, none of the frames {first}..{stop - 1} converted")
        if first == 0 and opts.count is None and (have[0] > 0 or have[-1] < n - 1):
            # A raw drive runs past its odometry sequence (0020: 1104 frames, 1101 poses; 0028's poses
            # start at frame 1100): by default the frames the ground truth covers, so that every frame
            # the odometry gives is scored (bevo run writes gt_kitti.txt only for a full cover).
            first, stop = int(have[0]), int(have[-1]) + 1
            if not opts.quiet:
                print(f"{prog_name('kitti_to_bag')}: note: frames {first}..{stop - 1} of {src.description}, those with "
                      f"ground truth (--first/--count convert others)", file=sys.stderr)
    colour = src.camera >= 2
    K = src.P[:, :3]

    gt = None
    if src.poses is not None and src.T_base_cam0 is not None:
        sel = src.poses[first:stop]
        valid = np.isfinite(sel).all(axis=(1, 2))
        if valid.any():
            # odom = the base frame at the first frame with ground truth: the GT starts at identity
            # like the estimate does.
            gt = np.full_like(sel, np.nan)
            gt[valid] = kitti.base_poses(sel[valid], src.T_base_cam0)

    # Records KITTI's synchronisation interpolated over lost packets are no measurement: they are
    # bridged by the unit's own attitude and velocity change across them (kitti.bridged_imu; the line
    # KITTI wrote turned the sample's heading 1.5 deg too far), unless asked otherwise, and reported.
    # Judged and bridged over the drive's records, so that a run across the sequence's ends has its real ends.
    drive, offset = (src.oxts, 0) if src.oxts_drive is None else (src.oxts_drive, src.record_offset)
    in_source = slice(offset, offset + len(src.oxts))
    interpolated_drive = kitti.interpolated_oxts(drive)
    interpolated = interpolated_drive[in_source]
    gyro_out, accel_out = src.oxts.gyro, src.oxts.accel
    bridged: list[tuple[int, int]] = []
    if opts.interpolated_imu == "bridge" and opts.imu_oxts is None:
        gyro_out, accel_out, bridged = kitti.bridged_imu(drive, interpolated_drive)
        gyro_out, accel_out = gyro_out[in_source], accel_out[in_source]
    found = np.flatnonzero(interpolated[first:stop]) + first
    if len(found) and not opts.quiet and opts.imu_oxts is None:  # with --imu-oxts they are not the IMU topic
        kept = np.setdiff1d(found, [i - offset for a, b in bridged for i in range(a, b)])
        where = {"leave-out": f"left out of {opts.imu_topic} (kept on {opts.gt_imu_topic})",
                 "line": f"written to {opts.imu_topic} as KITTI wrote them",
                 "bridge": (f"bridged on {opts.imu_topic} by the unit's own attitude and velocity change across them "
                            f"(as KITTI wrote them on {opts.gt_imu_topic}; --interpolated-imu line|leave-out)"
                            + (f"; {_ranges(kept + src.record_offset)} not (no real record, or one misstamped, at "
                               f"an end, or over {math.degrees(kitti.BRIDGE_MAX_ANGLE):.0f} deg of turn): as KITTI "
                               "wrote them" if len(kept) else ""))}[opts.interpolated_imu]
        print(f"{prog_name('kitti_to_bag')}: {len(found)} OXTS record(s) {_ranges(found + src.record_offset)} are KITTI's linear "
              f"interpolation over lost packets (all six IMU channels exactly on the line through their "
              f"neighbours): {where}",
              file=sys.stderr)

    # An OXTS record stamped at or before an earlier one cannot be placed in time: left out (both IMU
    # topics), said; the drive's others are written (a whole drive refused for one stamp before).
    disordered = np.zeros(n, dtype=bool)
    disordered[first:stop] = kitti.misstamped(src.oxts.stamps_ns[first:stop])
    if disordered.any():
        topics = opts.gt_imu_topic if opts.imu_oxts is not None else f"{opts.imu_topic} and {opts.gt_imu_topic}"
        print(f"{prog_name('kitti_to_bag')}: warning: {int(disordered.sum())} OXTS record(s) "
              f"{_ranges(np.flatnonzero(disordered) + src.record_offset)} stamped out of order with the others "
              f"(oxts/timestamps.txt): left out of {topics}", file=sys.stderr)
    imu_stream, imu_records = _imu_stream(src, opts, first, stop, ~disordered & ~interpolated)

    # Every message as (stamp, rank, kind, index): same-stamp ties keep the IMU before the image,
    # so a consumer has the IMU sample of a frame when the frame arrives.
    events = []
    for i in range(first, stop):
        if not disordered[i]:
            events.append((int(src.oxts.stamps_ns[i]), 0, "imu", i))
        events.append((int(src.frame_stamps_ns[i]), 2, "image", i))
    events += [(int(imu_stream.stamps_ns[j]), 0, "imu_stream", j) for j in imu_records]
    events.sort()

    size = None
    with bag.BagWriter(opts.output, storage=opts.storage, overwrite=opts.overwrite) as writer:
        for partial in writer.removed_partials:  # left by a killed earlier run
            print(f"{prog_name('kitti_to_bag')}: removed {partial}, the partial output of an interrupted run",
                  file=sys.stderr)
        if src.T_base_cam is not None and events and not opts.no_tf_static:
            # the rig on /tf_static (latched): base = the OXTS IMU (KITTI's convention), and the camera
            writer.write_tf_static(events[0][0], [(opts.base_frame, opts.imu_frame, np.eye(4)),
                                                  (opts.base_frame, opts.camera_frame, src.T_base_cam)])
        for stamp, _, kind, i in tqdm(events, desc="kitti_to_bag", unit="msg", disable=opts.quiet, file=sys.stderr):
            if kind == "imu_stream":  # --imu-oxts: the IMU's own records, not the synced ones
                writer.write_imu(stamp, imu_stream.gyro[i], imu_stream.accel[i], opts.imu_frame, topic=opts.imu_topic,
                                 gyro_covariance=opts.gyro_var, accel_covariance=opts.accel_var)
                continue
            if kind == "imu":
                gyro, accel = src.oxts.gyro[i], src.oxts.accel[i]
                if imu_stream is None and not (opts.interpolated_imu == "leave-out" and interpolated[i]):
                    writer.write_imu(stamp, gyro_out[i], accel_out[i], opts.imu_frame, topic=opts.imu_topic,
                                     gyro_covariance=opts.gyro_var, accel_covariance=opts.accel_var)
                writer.write_imu_attitude(stamp, src.oxts.roll[i], src.oxts.pitch[i], src.oxts.yaw[i], gyro=gyro,
                                          accel=accel, frame_id=opts.imu_frame, topic=opts.gt_imu_topic,
                                          orientation_covariance=np.radians(0.03) ** 2,
                                          gyro_covariance=opts.gyro_var, accel_covariance=opts.accel_var)
                if opts.speed_topic:  # the unit's forward / left / up velocity, in the base frame
                    v = [float(src.oxts.field(k)[i]) for k in ("vf", "vl", "vu")]
                    writer.write(opts.speed_topic, bag.TWIST_STAMPED_MSG,
                                 bag.twist_stamped_message(stamp, v, opts.base_frame), stamp)
                continue
            img = _load_image(src.images[i], colour)
            if size is None:
                size = img.shape[:2]
            elif img.shape[:2] != size:
                raise ConversionError(f"{src.images[i]}: image is {img.shape[1]}x{img.shape[0]}, "
                                f"the first was {size[1]}x{size[0]}")
            writer.write_camera_info(stamp, K, img.shape[1], img.shape[0], opts.camera_frame,
                                     topic=opts.camera_info_topic, P=src.P)
            writer.write_image(stamp, img, opts.camera_frame, topic=opts.image_topic)
            if gt is not None and np.isfinite(gt[i - first]).all():
                writer.write_odometry(stamp, gt[i - first], opts.odom_frame, opts.base_frame,
                                      topic=opts.gt_odometry_topic,
                                      pose_covariance=[0.01] * 3 + [np.radians(0.1) ** 2] * 3)
        counts = dict(writer.counts)
    return counts




def _imu_stream(src: Source, opts: ConversionOptions, first: int, stop: int,
                real: np.ndarray) -> tuple[kitti.OxtsData | None, list[int]]:
    """``--imu-oxts``: the OXTS directory whose records are the IMU topic (the raw extract's unsynced
    100 Hz ``oxts``, on the synced records' clock) and its records to write: from IMU_LEAD_S before the
    first frame to the first record at or after the last one. Records whose stamps cannot be placed
    in time (:func:`kitti.misstamped`) are left out, gaps longer than IMU_GAP_PERIODS periods (lost
    packets, which the extract leaves out where the synced records were interpolated) listed, and
    said; so is a stream that does not hold the synced records ``real`` (``(F,)`` bool: neither
    misstamped nor interpolated), which are its packets. ``(None, [])`` without the option.
    ConversionError when the records kept do not cover the frames (another drive's, another clock)."""
    if opts.imu_oxts is None:
        return None, []
    say = prog_name("kitti_to_bag")
    path = Path(opts.imu_oxts)
    try:
        stream = kitti.read_oxts(path, increasing=False)
    except (OSError, ValueError) as exc:
        raise ConversionError(f"--imu-oxts: {exc}") from None
    t0, t1 = int(src.frame_stamps_ns[first]), int(src.frame_stamps_ns[stop - 1])
    t = stream.stamps_ns
    bad = kitti.misstamped(t)
    good = np.flatnonzero(~bad)
    if not len(good) or t[good[0]] > t0 or t[good[-1]] < t1:
        span = f"{t[good[0]] * 1e-9:.3f}..{t[good[-1]] * 1e-9:.3f} s" if len(good) else "no records"
        raise ConversionError(f"--imu-oxts {path}: its records ({span}) do not cover the frames converted "
                              f"({t0 * 1e-9:.3f}..{t1 * 1e-9:.3f} s): not this drive's OXTS, or another clock")
    last = t[good[np.searchsorted(t[good], t1)]]  # the first record at or after the last frame
    lead = t0 - int(IMU_LEAD_S * 1e9)
    keep = good[(t[good] >= lead) & (t[good] <= last)]
    window = np.flatnonzero(bad)
    window = window[(window > keep[0]) & (window < keep[-1])]  # by record number, not by the bad stamps
    if len(window):
        print(f"{say}: warning: {len(window)} record(s) of --imu-oxts {_ranges(window)} stamped out of order with "
              f"the others: left out of {opts.imu_topic}", file=sys.stderr)
    dt = np.diff(t[keep]) * 1e-9
    period = float(np.median(dt)) if len(dt) else 0.0
    gaps = np.flatnonzero(dt > IMU_GAP_PERIODS * period)
    if len(gaps):
        worst = gaps[np.argmax(dt[gaps])]
        print(f"{say}: warning: --imu-oxts has {len(gaps)} gap(s) over {IMU_GAP_PERIODS:g} periods (lost packets) "
              f"over the frames, the longest {dt[worst]:.3f} s after record {keep[worst]}: the engine bridges gaps up to "
              f"filter.max_imu_gap (0.5 s by default) and restarts its attitude past one", file=sys.stderr)
    synced = src.oxts.stamps_ns[first:stop][real[first:stop]]
    held = np.isin(synced, t[keep])
    if len(synced) and held.mean() < 0.5:
        print(f"{say}: warning: only {int(held.sum())} of the {len(synced)} synced OXTS records are among --imu-oxts's "
              f"(KITTI's synced records are the unit's packets nearest each frame): another drive's, or shifted?",
              file=sys.stderr)
    if not opts.quiet:
        print(f"{say}: note: {opts.imu_topic} from {path} ({len(keep)} records, {1.0 / max(period, 1e-9):.0f} Hz); "
              f"the synced records give {opts.gt_imu_topic} and the ground truth", file=sys.stderr)
    return stream, keep.tolist()


def load_source(opts: ConversionOptions) -> Source:
    """The odometry sequence (``opts.odometry``) or raw drive (``opts.raw``) to convert."""
    if (opts.odometry is None) == (opts.raw is None):
        raise ConversionError("give exactly one of an odometry root (with a sequence) or a raw drive")
    for name in ("gyro_var", "accel_var"):  # a negative covariance in every IMU message
        if not getattr(opts, name) >= 0:
            raise ConversionError(f"--{name.replace('_', '-')} {getattr(opts, name)}: a variance must be >= 0")
    if opts.interpolated_imu not in INTERPOLATED_IMU:
        raise ConversionError(f"--interpolated-imu {opts.interpolated_imu!r}: choose one of {', '.join(INTERPOLATED_IMU)}")
    if opts.imu_oxts is not None and opts.interpolated_imu != "bridge":
        raise ConversionError("--interpolated-imu applies to the synced records; with --imu-oxts they are not the IMU "
                              "topic (the extract has no interpolated records: lost packets are gaps)")
    if opts.oxts_offset is not None and opts.oxts_offset < 0:  # a negative slice left no OXTS record (IndexError)
        raise ConversionError(f"--oxts-offset {opts.oxts_offset}: must be >= 0 (the OXTS record of the first image)")
    return odometry_source(opts) if opts.odometry is not None else raw_source(opts)
