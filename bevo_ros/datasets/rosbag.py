"""Recordings as the engine sees them: synthetic drives to rosbag2, bags to tensors, splits.

Shared by ``bevo run`` (bevo_ros.pipeline), ``bevo train``, ``bevo ablation`` and the demo,
so every tool reads a recording the same way.
"""
from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np
import torch

from bevo_ros.io import bag
from bevo_ros.io.static_tf import PARAMETERS_EXTRINSICS, camera_extrinsics, imu_axes
from bevo_ros.config import BevoConfig, ConfigError, camera_model, coerce_setting, extrinsics_problem
from bevo_ros.core.validation import intrinsics_problem
from bevo_ros.core.geometry import CameraModel, rpy_from_rotation
from bevo_ros.evaluation.metrics import rotation_error

PathLike = str | os.PathLike


# --------------------------------------------------------------------------- synthetic -> bag
def write_drive_bag(drive, path: PathLike, storage: str = "sqlite3", overwrite: bool = False,
                    frame_range: tuple[int, int] | None = None, imu_axes: np.ndarray | None = None,
                    wheel_odometry_topic: str | None = None, wheel_speed_scale: float = 1.0,
                    ground_truth: bool = True) -> Path:
    """Write a :class:`bevo_ros.datasets.synthetic.drive.SyntheticDrive` as a rosbag2 with KITTI-like topics.

    Sensor topics carry only what sensors give (raw IMU, images, CameraInfo) plus the rig on
    ``/tf_static`` (base_link -> imu_link, base_link -> camera_optical_frame); ground truth goes to
    ``/ground_truth/odometry`` (base pose in ``odom``, identity at the first written frame) and
    ``/ground_truth/imu`` (gravity-referenced attitude). ``frame_range`` = (first, stop) frames;
    the IMU is cut to the same time span. ``imu_axes``: ``R_base_imu (3, 3)`` of an IMU mounted in
    other axes (e.g. z down): its rates and accelerations are written in them, the rotation on
    ``/tf_static`` (default: the base's axes). ``wheel_odometry_topic``: also a wheel odometry's
    nav_msgs/Odometry there at every IMU sample, its twist the true speed (signed: reversing reads negative) times ``wheel_speed_scale``
    (a wheel's scale error), its pose unset (``bevo calibrate --speed-topic``). ``ground_truth``
    False: no ground-truth topics (a bag as a car records it).
    """
    from bevo_ros.datasets.synthetic.drive import base_poses_4x4

    f0, f1 = frame_range or (0, len(drive.frame_stamps))
    t_lo, t_hi = drive.frame_stamps[f0], drive.frame_stamps[f1 - 1]
    poses = base_poses_4x4(drive)
    poses = np.linalg.inv(poses[f0]) @ poses
    cam = drive.camera
    K = cam.K.double().numpy()
    with bag.BagWriter(path, storage=storage, overwrite=overwrite) as w:
        k = 0
        imu_sel = np.nonzero((drive.imu_stamps >= t_lo - 0.5) & (drive.imu_stamps <= t_hi))[0]
        t_first = float(drive.imu_stamps[imu_sel[0]]) if len(imu_sel) else float(t_lo)
        # the rig, latched: the synthetic IMU is the base frame; the camera is T_base_cam
        T_base_imu = np.eye(4)
        R_imu_base = np.eye(3)
        if imu_axes is not None:
            T_base_imu[:3, :3] = imu_axes
            R_imu_base = np.asarray(imu_axes, dtype=np.float64).T
        w.write_tf_static(t_first, [("base_link", "imu_link", T_base_imu),
                                    ("base_link", "camera_optical_frame", cam.T_base_cam.double().numpy())])
        for i in range(f0, f1):
            s = drive.frame_stamps[i]
            while k < len(imu_sel) and drive.imu_stamps[imu_sel[k]] <= s:
                j = imu_sel[k]
                gyro, accel = drive.gyro[j], drive.accel[j]
                if imu_axes is not None:
                    gyro, accel = R_imu_base @ np.asarray(gyro, np.float64), R_imu_base @ np.asarray(accel, np.float64)
                w.write_imu(float(drive.imu_stamps[j]), gyro, accel, frame_id="imu_link")
                if wheel_odometry_topic:
                    v = drive.imu_velocity_gravity[j]  # the base's forward speed, signed: a wheel's
                    speed = wheel_speed_scale * math.copysign(float(np.linalg.norm(v)),
                                                              float(drive.imu_rotation_gravity[j][:, 0] @ v))
                    w.write(wheel_odometry_topic, bag.ODOMETRY_MSG, bag.odometry_message(
                        float(drive.imu_stamps[j]), np.eye(4), "odom", "base_link", twist=(speed, 0, 0, 0, 0, 0)),
                        float(drive.imu_stamps[j]))
                k += 1
            w.write_camera_info(float(s), K, cam.width, cam.height_px, frame_id="camera_optical_frame")
            w.write_image(float(s), np.asarray(drive.images[i]), frame_id="camera_optical_frame")
            if ground_truth:
                w.write_odometry(float(s), poses[i], frame_id="odom", child_frame_id="base_link")
                pitch, roll = drive.pitch_roll_gravity[i]
                w.write_imu_attitude(float(s), float(roll), float(pitch), float(drive.poses_xy_yaw[i, 2]))
    return Path(path)


# --------------------------------------------------------------------------- bag -> tensors
@dataclass
class Recording:
    """A recording as tensors, ready for :func:`bevo_ros.core.sequence.run_sequence` (float64 stamps)
    (:class:`bevo_ros.io.bag.BagContents` is a bag's raw content in numpy; this is the one recording type
    of the datasets: bags via :func:`load_sequence`, synthetic drives via ``SyntheticDrive.to_recording``)."""

    imu_stamps: torch.Tensor  # (N,)
    gyro: torch.Tensor  # (N, 3)
    accel: torch.Tensor  # (N, 3)
    frame_stamps: torch.Tensor  # (F,)
    images: torch.Tensor  # (F, H, W) uint8
    camera: CameraModel
    gt_poses: torch.Tensor | None  # (F, 4, 4) base poses at the frames
    gt_pitch_roll: torch.Tensor | None  # (F, 2) gravity-referenced reference attitude
    name: str = ""
    # the base's (pitch, roll) on the road the engine measured at the recording's start
    # (filter.tilt_from_images: measure_start_tilt); None: the configuration's (mounting_in_use)
    mounting: tuple[float, float] | None = None

    def __len__(self) -> int:
        return int(self.frame_stamps.shape[0])

    def gt_motion(self) -> torch.Tensor:
        """``(F-1, 3)`` ground-truth (dx, dy, dyaw) of the base between consecutive frames."""
        if self.gt_poses is None:
            raise ValueError(f"{self.name}: no ground truth in this recording")
        rel = torch.linalg.inv(self.gt_poses[:-1]) @ self.gt_poses[1:]
        yaw = torch.atan2(rel[:, 1, 0], rel[:, 0, 0])
        return torch.stack([rel[:, 0, 3], rel[:, 1, 3], yaw], dim=-1)

    def mounting_in_use(self, config: BevoConfig) -> tuple[float, float]:
        """The base's (pitch, roll) on the road the engine runs this recording at: the one it measured at the
        start (:attr:`mounting`), else the configuration's for this camera (``config.mounting_in_use``)."""
        from bevo_ros.config import mounting_in_use

        return self.mounting if self.mounting is not None else mounting_in_use(config, self.camera.T_base_cam)

    def frames(self, start: int, stop: int) -> "Recording":
        """Frames ``[start, stop)`` with the IMU from the start of the recording up to the last frame
        (the filter needs its history; the extra IMU only warms it up)."""
        t_hi = self.frame_stamps[stop - 1]
        n = int(torch.searchsorted(self.imu_stamps, t_hi, right=True))
        return Recording(self.imu_stamps[:n], self.gyro[:n], self.accel[:n], self.frame_stamps[start:stop],
                         self.images[start:stop], self.camera,
                         None if self.gt_poses is None else self.gt_poses[start:stop],
                         None if self.gt_pitch_roll is None else self.gt_pitch_roll[start:stop], self.name,
                         self.mounting)  # the engine run on keeps the start's tilt


@dataclass(frozen=True)
class RigSettings:
    """How the offline commands take a bag's rig and calibration: as bevo_node does, with its
    parameters of the same names (a params file's values, :meth:`from_params`).

    ``extrinsics_from_tf``: the camera's extrinsics from the bag's ``/tf_static`` ``base_frame ->
    image frame`` and the IMU's axes from ``base_frame -> IMU frame`` when there (else
    ``camera.base_T_camera`` and the IMU's axes as the base's). ``use_camera_info``,
    ``camera_info_use_p``, ``undistort``: the intrinsics from the bag's first CameraInfo (``P`` or
    ``K``; distorted images undistorted with OpenCV maps, ``bevo_ros.ros.camera``), else the
    ``camera.*`` parameters. ``speed_topic`` (``''`` = none): a vehicle speed the motion filter fuses
    (``io.ros_conversions.forward_speed_from_msg``; ``speed_variance`` where the message has none).
    ``imu_topic``, ``image_topic``, ``camera_info_topic``: the node's (relative: a bag recorded in the
    root namespace has them under ``/``, :meth:`bag_topic`); the commands' ``--imu-topic`` and
    ``--image-topic`` override them (a bag's CameraInfo on another topic was passed over for the
    ``camera.*`` parameters)."""

    base_frame: str = "base_link"
    extrinsics_from_tf: bool = True
    use_camera_info: bool = True
    camera_info_use_p: bool = True
    undistort: str = "auto"
    speed_topic: str = ""
    speed_variance: float = 0.01
    imu_topic: str = "imu/data"
    image_topic: str = "camera/image_rect"
    camera_info_topic: str = "camera/camera_info"

    @classmethod
    def from_params(cls, flat: dict, source: str | None = None) -> "RigSettings":
        """From a params file's flat parameters (``bevo_ros.config.load_config``'s second value), by
        the node's rules (a bool only from a bool; ``base_frame`` not empty; ``undistort`` one of
        its modes)."""
        from bevo_ros.ros.camera import UNDISTORT_MODES

        values = {f.name: coerce_setting(flat.get(f.name, f.default), f.default, f.name, source) for f in fields(cls)}
        where = f" ({source})" if source else ""
        if not values["base_frame"].strip("/ "):
            raise ConfigError(f"base_frame must not be empty{where}")
        if values["undistort"] not in UNDISTORT_MODES:
            raise ConfigError(f"undistort must be one of {', '.join(UNDISTORT_MODES)}, got {values['undistort']!r}{where}")
        if not values["speed_variance"] > 0:
            raise ConfigError(f"speed_variance must be > 0, got {values['speed_variance']!r}{where}")
        return cls(**values)

    @staticmethod
    def bag_topic(name: str) -> str:
        """A node's topic name as a bag recorded in the root namespace holds it (``/`` + relative)."""
        return name if name.startswith("/") else "/" + name

    def read_topics(self) -> dict[str, str]:
        """``bag.read_recording``'s topic arguments: the node's topics in the bag."""
        return {"imu_topic": self.bag_topic(self.imu_topic), "image_topic": self.bag_topic(self.image_topic),
                "camera_info_topic": self.bag_topic(self.camera_info_topic)}


def extrinsics_for_recording(rec: bag.BagContents, config: BevoConfig,
                             rig: RigSettings = RigSettings()) -> tuple[np.ndarray, str]:
    """``(base_T_camera (4, 4), source)``: the bag's ``/tf_static`` ``base_frame -> image frame``
    when it has it (and ``rig.extrinsics_from_tf``), else ``camera.base_T_camera``: bevo_node's
    choice (``bevo_ros.ros.rig``), so that ``bevo run`` equals the node replaying the bag."""
    return camera_extrinsics(rec.static_tf if rig.extrinsics_from_tf else None, rig.base_frame, rec.image_frame_id,
                             config.camera.base_T_camera)


def imu_rotation_for_recording(rec: bag.BagContents, frame_id: str, rig: RigSettings = RigSettings()) -> np.ndarray | None:
    """Rotation taking the IMU's ``frame_id`` axes into ``base_frame``'s (the bag's ``/tf_static``),
    None for the same axes or no such transform (the node then takes the IMU axes as the base's)."""
    return imu_axes(rec.static_tf if rig.extrinsics_from_tf else None, rig.base_frame, frame_id)


def calibration_for_recording(rec: bag.BagContents, config: BevoConfig, rig: RigSettings = RigSettings()):
    """The images' calibration (``bevo_ros.ros.camera.Calibration``: ``K``, size, undistortion maps
    or None) as bevo_node takes it: the bag's first CameraInfo (with ``use_camera_info``), else the
    ``camera.*`` parameters (the node's fallback). A CameraInfo it cannot use is an error that says
    why (the node would wait for a usable one, then fall back to the parameters)."""
    from bevo_ros.ros.camera import CalibrationError, calibration_from_camera_info, calibration_from_parameters

    if rig.use_camera_info and rec.camera_info is not None:
        try:
            calib = calibration_from_camera_info(rec.camera_info, rig.camera_info_use_p, rig.undistort, rec.image_topic,
                                                 source=f"CameraInfo on {rec.camera_info_topic}")
            problem = intrinsics_problem(calib.K, calib.width, calib.height)  # the node's check of a CameraInfo
            if problem is not None:
                raise CalibrationError(problem)
        except CalibrationError as exc:
            raise ConfigError(f"{rec.path}: its CameraInfo on {rec.camera_info_topic} is unusable: {exc} (or set "
                              "use_camera_info: false and the camera.* parameters)") from None
        return calib
    if not config.camera.has_intrinsics():
        raise ConfigError(f"{rec.path}: no CameraInfo{' read' if rig.use_camera_info else ' (use_camera_info false)'} and "
                          "the camera intrinsics are not set (camera.fx, fy, cx, cy, width, height_px)")
    return calibration_from_parameters(config.camera)


def camera_for_recording(rec: bag.BagContents, config: BevoConfig, rig: RigSettings = RigSettings(),
                         calibration=None) -> CameraModel:
    """The engine's camera for a bag: intrinsics as :func:`calibration_for_recording` (or the
    ``calibration`` given), extrinsics as :func:`extrinsics_for_recording`. By default
    (``camera_info_use_p``) ``P[:3, :3]``, the rectified camera matrix, as bevo_node: the images
    are rectified, and for them K and P can differ."""
    T, source = extrinsics_for_recording(rec, config, rig)
    if source != PARAMETERS_EXTRINSICS and (problem := extrinsics_problem(T)) is not None:
        raise ConfigError(f"{rec.path}: camera extrinsics from {source} unusable: {problem}")
    calib = calibration if calibration is not None else calibration_for_recording(rec, config, rig)
    settings = replace(config.camera, base_T_camera=T.reshape(-1).tolist())
    return camera_model(settings, K=calib.K, width=calib.width, height_px=calib.height)


# How far the parameters' camera may be from a bag's before they are taken as another camera. KITTI's
# raw calibrations of one rig differ by ~1 deg of camera pitch and centimetres from day to day (what
# filter.mounting_reference: camera re-derives the mounting for); beyond these it is another rig.
ANOTHER_RIG_M, ANOTHER_RIG_DEG = 0.10, 3.0
# When the parameters' camera is the one the BEV is projected with: ~25 % of scale per degree of pitch.
USED_CAMERA_M, USED_CAMERA_DEG = 0.05, 0.25
USED_FOCAL_REL, USED_CENTRE_PX = 0.01, 5.0  # camera.fx/fy relative, camera.cx/cy in px


def _rotation_deg(A: np.ndarray, B: np.ndarray) -> float:
    """Angle of the rotation between two poses' rotations, degrees."""
    return float(np.degrees(rotation_error(A[:3, :3].T @ B[:3, :3])))


def _shipped_params_with_camera(T: np.ndarray) -> list[str]:
    """The package's params/*.yaml whose camera.base_T_camera is ``T`` (to the centimetre and a
    tenth of a degree): a hint which one was written for the bag's rig. Read only when warning."""
    from bevo_ros.config import load_params_file, package_file

    names = []
    for path in sorted(package_file("params").glob("*.yaml")):
        try:
            flat = load_params_file(path)
        except (ConfigError, OSError):
            continue
        value = flat.get("camera.base_T_camera")
        if isinstance(value, list) and len(value) == 16:
            P = np.asarray(value, dtype=np.float64).reshape(4, 4)
            if np.linalg.norm(P[:3, 3] - T[:3, 3]) < 0.01 and _rotation_deg(P, T) < 0.1:
                names.append(f"params/{path.name}")
    return names


def rig_disagreements(rec: bag.BagContents, config: BevoConfig, rig: RigSettings = RigSettings(),
                      calibration=None) -> list[str]:
    """Where the parameters the engine uses for a bag disagree with what the bag says, one message
    each (parameter, both values, which is used); [] when they agree. Cheap: the bag's CameraInfo
    and /tf_static only, no image.

    * ``use_camera_info: false`` with a CameraInfo in the bag: ``camera.fx/fy/cx/cy/width/height_px``
      are used; named where they differ from the bag's (1 % focal length, 5 px, any size).
    * ``extrinsics_from_tf: false`` with the camera on /tf_static: ``camera.base_T_camera`` is used;
      named beyond 5 cm or 0.25 deg (a quarter degree of pitch is ~6 % of the BEV's scale).
    * /tf_static's camera used, more than 10 cm or 3 deg from ``camera.base_T_camera`` (another rig:
      one rig's calibrations differ by ~1 deg and centimetres): ``filter.mounting_*`` and
      ``camera.mount_height`` were calibrated for the parameters' rig and are used with the bag's
      (``mounting_reference: camera`` re-derives the mounting through ``camera.base_T_camera``, which
      then describes another camera). E.g. a ``bevo convert --render-oxts`` bag (its level camera
      0.31 m left of KITTI's) with params/kitti.yaml: mounting +1.07 / -1.26 deg instead of 0, 21.7 %
      drift instead of 3.5 % (drive 0027, 160 frames); the KITTI sample with params/synthetic.yaml:
      mounting 0 instead of +1.55 / -1.01 deg, 35.6 % instead of 1.72 %."""
    out: list[str] = []
    cam = config.camera
    calib = calibration if calibration is not None else calibration_for_recording(rec, config, rig)
    if rec.camera_info is not None and not (rig.use_camera_info and calib.source.startswith("CameraInfo")):
        from bevo_ros.ros.camera import CalibrationError, calibration_from_camera_info

        try:
            bag_calib = calibration_from_camera_info(rec.camera_info, rig.camera_info_use_p, "off", rec.image_topic)
        except CalibrationError:
            bag_calib = None
        if bag_calib is not None:
            K, B = calib.K, bag_calib.K
            checks = [("camera.fx", K[0, 0], B[0, 0], USED_FOCAL_REL * B[0, 0]),
                      ("camera.fy", K[1, 1], B[1, 1], USED_FOCAL_REL * B[1, 1]),
                      ("camera.cx", K[0, 2], B[0, 2], USED_CENTRE_PX), ("camera.cy", K[1, 2], B[1, 2], USED_CENTRE_PX),
                      ("camera.width", calib.width, bag_calib.width, 0), ("camera.height_px", calib.height,
                                                                          bag_calib.height, 0)]
            differ = [f"{name} {float(mine):g} (bag {float(theirs):g})" for name, mine, theirs, tol in checks
                      if abs(float(mine) - float(theirs)) > tol]
            if differ:
                out.append(f"{', '.join(differ)}: the camera.* parameters differ from the bag's CameraInfo on "
                           f"{rec.camera_info_topic}; the parameters' are used (use_camera_info: false)")
    params_T = np.asarray(cam.base_T_camera, dtype=np.float64).reshape(4, 4)
    bag_T, source = camera_extrinsics(rec.static_tf, rig.base_frame, rec.image_frame_id, params_T)
    if source == PARAMETERS_EXTRINSICS:
        return out  # the bag says nothing about its camera's pose
    metres = float(np.linalg.norm(bag_T[:3, 3] - params_T[:3, 3]))
    degrees = _rotation_deg(bag_T, params_T)
    where = (f"camera.base_T_camera puts the camera at {np.round(params_T[:3, 3], 3).tolist()} m, the bag's {source} "
             f"at {np.round(bag_T[:3, 3], 3).tolist()} m ({metres:.2f} m and {degrees:.2f} deg apart)")
    hint = _shipped_params_with_camera(bag_T)
    hint = f"; {' and '.join(hint)} describe{'s' if len(hint) == 1 else ''} the bag's camera" if hint else ""
    if not rig.extrinsics_from_tf:
        if metres > USED_CAMERA_M or degrees > USED_CAMERA_DEG:
            out.append(f"{where}: the parameters' is used (extrinsics_from_tf: false){hint}")
        return out
    if metres <= ANOTHER_RIG_M and degrees <= ANOTHER_RIG_DEG:
        return out
    from bevo_ros.config import mounting_in_use

    f = config.filter
    given = (float(f.mounting_pitch), float(f.mounting_roll))
    used = mounting_in_use(config, bag_T)

    def deg(pair: tuple[float, float]) -> str:
        return f"{np.degrees(pair[0]):+.2f} / {np.degrees(pair[1]):+.2f} deg"

    mounting = (f"filter.mounting_pitch / mounting_roll {deg(given)}" +
                (f", re-derived through camera.base_T_camera (mounting_reference: camera) to {deg(used)} for the "
                 "bag's camera, are used" if f.mounting_reference == "camera" else " are used as given"))
    out.append(f"{where}: another rig than the parameters were written for? The bag's camera is used; {mounting}, "
               f"and camera.mount_height {cam.mount_height:g} m: calibrated for the parameters' rig, not measured "
               f"for the bag's (bevo calibrate BAG measures its mounting){hint}")
    return out


def gt_at(stamps: np.ndarray, gt_stamps: np.ndarray, gt_poses: np.ndarray) -> np.ndarray:
    """GT poses at ``stamps``: exact matches (the usual case) else nearest within 5 ms."""
    idx = np.clip(np.searchsorted(gt_stamps, stamps), 1, len(gt_stamps) - 1)
    left_closer = np.abs(gt_stamps[idx - 1] - stamps) <= np.abs(gt_stamps[idx] - stamps)
    idx = np.where(left_closer, idx - 1, idx)
    off = np.abs(gt_stamps[idx] - stamps) > 5e-3
    if off.any():
        if off.all():
            raise ValueError("ground truth is not stamped at the image stamps (more than 5 ms apart)")
        have = np.flatnonzero(~off)
        raise ValueError(f"ground truth covers only {len(have)} of the {len(stamps)} frames (frames {have[0]}..{have[-1]} "
                         f"of this run have one at their stamps): convert or run only those frames (e.g. bevo convert "
                         f"--first/--count, bevo run --first-frame) to score them")
    return gt_poses[idx]


def load_sequence(bag_path: PathLike, config: BevoConfig, require_gt: bool = True,
                  rig: RigSettings = RigSettings()) -> Recording:
    """Read a bag written by ``bevo convert`` or :func:`write_drive_bag` into a :class:`Recording`.

    Frames before the first IMU sample are dropped (the filter has nothing to say about them). The
    rig and calibration as bevo_node takes them (:class:`RigSettings`): the camera from the bag's
    CameraInfo and ``/tf_static`` when there (distorted images undistorted), the IMU's vectors
    rotated into ``base_frame``'s axes.
    """
    rec = bag.read_recording(bag_path, **rig.read_topics())
    if rec.images is None or len(rec.frame_stamps_ns) < 2:
        raise ValueError(f"{bag_path}: needs at least 2 images")
    if len(rec.imu_stamps_ns) == 0:  # every message left out (read_recording warned why)
        raise ValueError(f"{bag_path}: no usable IMU sample (each one not finite or out of order)")
    calib = calibration_for_recording(rec, config, rig)
    camera = camera_for_recording(rec, config, rig, calib)
    for problem in rig_disagreements(rec, config, rig, calib):  # as bevo run warns: training, calibration, ablation
        warnings.warn(f"{bag_path}: {problem}", UserWarning, stacklevel=2)
    if len(rec.images) and (problem := calib.size_problem(rec.images[0])) is not None:  # the node drops each (bad_image_size)
        raise ValueError(f"{bag_path}: an image {problem}")
    if calib.maps is not None:  # distorted images: undistorted as the node does, in place
        for i in range(len(rec.images)):
            rec.images[i] = calib.rectify(rec.images[i])
    ids = np.asarray(rec.imu_frame_ids, dtype=object)
    for frame in dict.fromkeys(rec.imu_frame_ids):  # each IMU frame's samples, as the node rotates each message
        R = imu_rotation_for_recording(rec, frame, rig)
        if R is not None:
            rows = ids == frame
            rec.gyro[rows], rec.accel[rows] = rec.gyro[rows] @ R.T, rec.accel[rows] @ R.T
    fs = rec.frame_stamps
    keep = fs >= rec.imu_stamps[0]
    gt = gt_pr = None
    if rec.gt_poses is not None:
        gt = torch.from_numpy(gt_at(fs[keep], rec.gt_stamps, rec.gt_poses))
    elif require_gt:
        raise ValueError(f"{bag_path}: no /ground_truth/odometry messages (needed for training/evaluation)")
    if rec.gt_pitch is not None:
        gt_pr = torch.from_numpy(np.stack([np.interp(fs[keep], rec.gt_att_stamps, rec.gt_pitch),
                                           np.interp(fs[keep], rec.gt_att_stamps, rec.gt_roll)], axis=-1))
    return Recording(
        imu_stamps=torch.from_numpy(rec.imu_stamps),
        gyro=torch.from_numpy(rec.gyro),
        accel=torch.from_numpy(rec.accel),
        frame_stamps=torch.from_numpy(fs[keep]),
        images=torch.from_numpy(rec.images[keep]),
        camera=camera,
        gt_poses=gt,
        gt_pitch_roll=gt_pr,
        name=Path(bag_path).resolve().name,  # the bag directory's own name, also for '.' or 'bag/'
    )


def split_frames(n: int, split: str) -> tuple[tuple[int, int], tuple[int, int]]:
    """Frame ranges ``(train, validation)`` for the paper's splits.

    ``"3/4"``: first three quarters train, last quarter validates. ``"20%"``: the first 20 %
    trains, the rest validates (the paper's generalisation study). Ranges share no pair.
    """
    if split in ("3/4", "0.75", "three-quarters"):
        cut = int(round(0.75 * n))
    elif split in ("20%", "0.2", "first20"):
        cut = int(round(0.2 * n))
    else:
        raise ValueError(f"unknown split {split!r}: use '3/4' or '20%'")
    cut = min(max(cut, 2), n - 2)
    return (0, cut), (cut, n)


def road_relative_gt(poses: torch.Tensor) -> torch.Tensor:
    """Roll/pitch of ground-truth base poses ``(F, 4, 4)`` as ``(F, 2)`` [pitch, roll].

    The poses are relative to the first frame's base (as bags store them), so this is the attitude
    relative to the road only when the first frame sits level on it (``w/ GT`` ablation on KITTI).
    """
    roll, pitch, _ = rpy_from_rotation(poses[:, :3, :3])
    return torch.stack([pitch, roll], dim=-1)


def stamp_order(imu_stamps, frame_stamps, image_first: bool = False,
                trailing: bool = True, by_stamp: bool = False) -> Iterator[tuple[str, int]]:
    """The order the node receives a recording in: ``("imu", i)`` and ``("image", k)`` events,
    each image after the first IMU sample at or after its stamp (a camera's latency), IMU first on
    equal stamps (``image_first``: the image first); ``by_stamp``: each image before the IMU
    samples stamped after it (a bag played by stamp: KITTI frames on the camera clock beside the
    10 Hz OXTS); ``trailing``: frames after the last IMU sample too. The one feeding order of the
    offline engine runs and the tests."""
    frames = [float(t) for t in frame_stamps]
    k = 0
    for i, s in enumerate(float(t) for t in imu_stamps):
        while by_stamp and k < len(frames) and (frames[k] < s or (image_first and frames[k] == s)):
            yield "image", k
            k += 1
        if not image_first:
            yield "imu", i
        while k < len(frames) and frames[k] <= s:
            yield "image", k
            k += 1
        if image_first:
            yield "imu", i
    if trailing:
        for k in range(k, len(frames)):
            yield "image", k


def feed_engine(odo, imu_stamps, gyro, accel, frame_stamps, image, image_first: bool = False,
                trailing: bool = True, by_stamp: bool = False,
                speeds: Sequence[tuple] = (), until: Callable[[], bool] | None = None) -> list:
    """Feed ``odo`` (a ``BevoOdometry``) in :func:`stamp_order`, then flush; ``image(k)`` gives frame
    ``k``; ``speeds``, ``add_speed``'s arguments ``(stamp, m/s, variance[, signed])`` in stamp order,
    each before the first IMU sample or image stamped at or after it. ``until``: checked before each
    input; once true the feeding stops there, unflushed. Returns every ``OdometryStep``."""
    steps, n = [], 0
    for kind, j in stamp_order(imu_stamps, frame_stamps, image_first, trailing, by_stamp):
        if until is not None and until():
            return steps
        stamp = float(imu_stamps[j] if kind == "imu" else frame_stamps[j])
        while n < len(speeds) and speeds[n][0] <= stamp:
            odo.add_speed(*speeds[n])
            n += 1
        if kind == "imu":
            steps += odo.add_imu(stamp, gyro[j], accel[j])
        else:
            steps += odo.add_image(stamp, image(j))
    return steps + odo.flush()


def _engine(sequence: Recording, config: BevoConfig, learned, mode: str | None):
    """``build_odometry`` for ``sequence``'s camera, ``mode`` overriding ``odometry.mode``."""
    import dataclasses

    from bevo_ros.config import build_odometry

    if mode is not None:
        config = dataclasses.replace(config, odometry=dataclasses.replace(config.odometry, mode=mode))
    return build_odometry(config, learned, camera=sequence.camera)


def measure_start_tilt(sequence: Recording, config: BevoConfig, learned, mode: str | None = None):
    """The base's ``(pitch, roll)`` on the road that the engine (``build_odometry``, ``filter.tilt_from_images``)
    measures at ``sequence``'s start, and its :class:`~bevo_ros.core.start_tilt.TiltMeasurement`: fed as
    :func:`run_engine` feeds it until the hold releases (or the recording ends: flushed, as ``bevo run`` at a
    bag's end). For the code that runs the core without the engine (the training's loss, the ablation's
    given-attitude rows), so that it works at the tilt the engine does. ``mode`` overrides ``odometry.mode`` (the
    fused engine takes the suspension's pitch out of the pairs, the paper's does not). None with the measurement off."""
    odo = _engine(sequence, config, learned, mode)
    if not odo.holding:
        return None
    feed_engine(odo, sequence.imu_stamps.tolist(), sequence.gyro.tolist(), sequence.accel.tolist(),
                sequence.frame_stamps.tolist(), lambda k: sequence.images[k].numpy(), until=lambda: not odo.holding)
    return tuple(map(float, odo.mounting_attitude)), odo.tilt_measurement


def with_start_tilt(sequences: list[Recording], config: BevoConfig, learned, log=print, mode: str | None = None) -> None:
    """Each recording's :attr:`Recording.mounting` set to what :func:`measure_start_tilt` gives (nothing with
    ``filter.tilt_from_images: 0``), each said in one line through ``log``."""
    for s in sequences:
        found = measure_start_tilt(s, config, learned, mode)
        if found is not None:
            s.mounting = found[0] if found[1].measured else None
            log(f"{s.name or 'recording'}: {found[1].describe()}")


def run_engine(sequence: Recording, config: BevoConfig, learned, mode: str | None = None) -> list:
    """The node's engine (``build_odometry``) fed a :class:`Recording` in stamp order (IMU first on
    equal stamps), then flushed. Returns every ``OdometryStep``; ``mode`` overrides ``odometry.mode``."""
    odo = _engine(sequence, config, learned, mode)
    return feed_engine(odo, sequence.imu_stamps.tolist(), sequence.gyro.tolist(), sequence.accel.tolist(),
                       sequence.frame_stamps.tolist(), lambda k: sequence.images[k].numpy())

