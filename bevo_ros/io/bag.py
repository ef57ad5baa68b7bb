"""rosbag2 read/write helpers shared by the commands and datasets (rosbags only, no rclpy).

* :class:`BagWriter` writes sensor_msgs/nav_msgs messages into a new rosbag2 (sqlite3 or mcap)
  atomically: everything goes to a hidden temp directory beside the target, which is renamed
  into place only when the ``with`` block ends without an exception (and removed otherwise).
* :func:`read_recording` loads a whole bag into numpy arrays (:class:`BagContents`: IMU, images,
  camera info, ground truth) for the offline commands and training.
* :func:`iter_messages` / :func:`iter_raw_messages` stream messages in bag-time order.

Stamps: writer methods take ``stamp`` as float seconds, or as an ``int`` / numpy integer meaning
*nanoseconds* (exact; KITTI stamps have 9 decimals, more than a float64 of ~1e9 s can carry).
The bag (receive) time of every message equals its header stamp.
"""
from __future__ import annotations

import contextlib
import math
import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from bevo_ros.io.ros_conversions import (ns_to_seconds, out_of_order, speed_frame, stamp_to_ns,  # noqa: F401 - one place
                                         twist_speed)
from bevo_ros.io.static_tf import StaticTree
from bevo_ros.rotations import matrix_from_quaternion, quaternion_from_matrix, quaternion_from_rpy, rpy_from_matrix

PathLike = str | Path

# Default topic names (the node, the commands and the tests agree on them).
IMU_TOPIC = "/imu/data"
IMAGE_TOPIC = "/camera/image_rect"  # rectified images (image_pipeline naming); bevo_node's default
LEGACY_IMAGE_TOPIC = "/camera/image_raw"  # bags written before issue 11: read_recording falls back to it
CAMERA_INFO_TOPIC = "/camera/camera_info"
GT_ODOMETRY_TOPIC = "/ground_truth/odometry"
GT_IMU_TOPIC = "/ground_truth/imu"

STORAGES = ("sqlite3", "mcap")

IMU_MSG = "sensor_msgs/msg/Imu"
IMAGE_MSG = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_MSG = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_MSG = "sensor_msgs/msg/CameraInfo"
ODOMETRY_MSG = "nav_msgs/msg/Odometry"
TWIST_STAMPED_MSG = "geometry_msgs/msg/TwistStamped"
TF_MSG = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC = "/tf_static"


class BagError(ValueError):
    """A bag that cannot be read or written as asked (message names the bag)."""


# ----------------------------------------------------------------------------------------------
# Small conversions
# ----------------------------------------------------------------------------------------------
@lru_cache(maxsize=1)
def typestore():
    """The rosbags type store of ROS 2 Jazzy (cached)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def to_ns(stamp: float | int) -> int:
    """Float seconds or integer nanoseconds -> integer nanoseconds (see module docstring)."""
    if isinstance(stamp, (bool, np.bool_)):
        raise TypeError("stamp must be float seconds or integer nanoseconds, not bool")
    if isinstance(stamp, (int, np.integer)):
        return int(stamp)
    s = float(stamp)
    if not math.isfinite(s):
        raise ValueError(f"non-finite stamp {stamp!r}")
    whole = math.floor(s)
    return int(whole) * 1_000_000_000 + int(round((s - whole) * 1e9))  # s - whole is exact


def ns_to_sec_nanosec(ns: int) -> tuple[int, int]:
    if ns < 0:
        raise ValueError(f"negative stamp {ns} ns cannot go into builtin_interfaces/Time")
    return ns // 1_000_000_000, ns % 1_000_000_000


def _covariance(value: float | Sequence[float] | np.ndarray | None, n: int, default: float) -> np.ndarray:
    """Scalar variance, per-axis variances ``(n,)`` or a full ``(n, n)`` -> flat row-major."""
    if value is None:
        value = default
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.eye(n) * float(arr)
    elif arr.shape == (n,):
        arr = np.diag(arr)
    elif arr.shape != (n, n):
        raise ValueError(f"covariance must be a scalar, ({n},) or ({n}, {n}); got {arr.shape}")
    return arr.reshape(-1).copy()


# ----------------------------------------------------------------------------------------------
# Message builders (rosbags dataclasses)
# ----------------------------------------------------------------------------------------------
def _header(stamp: float | int, frame_id: str):
    ts = typestore().types
    sec, nanosec = ns_to_sec_nanosec(to_ns(stamp))
    return ts["std_msgs/msg/Header"](stamp=ts["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                     frame_id=frame_id)


def _vector3(v: Sequence[float]):
    x, y, z = (float(a) for a in np.asarray(v, dtype=np.float64).reshape(3))
    return typestore().types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def _quaternion(q: Sequence[float]):
    x, y, z, w = (float(a) for a in np.asarray(q, dtype=np.float64).reshape(4))
    return typestore().types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)


def imu_message(stamp: float | int, gyro: Sequence[float], accel: Sequence[float], frame_id: str,
                orientation: Sequence[float] | None = None, orientation_covariance=None,
                gyro_covariance=None, accel_covariance=None):
    """sensor_msgs/Imu. Without ``orientation``, ``orientation_covariance[0] = -1`` ("no estimate").

    Covariances: scalar variance, ``(3,)`` variances or ``(3, 3)``. Defaults: gyro 1e-4 (rad/s)^2,
    accel 1e-2 (m/s^2)^2 (OXTS RT3000-class noise, rounded up).
    """
    types = typestore().types
    if orientation is None:
        q = (0.0, 0.0, 0.0, 1.0)
        ocov = np.zeros(9)
        ocov[0] = -1.0
    else:
        q = orientation
        ocov = _covariance(orientation_covariance, 3, 1e-6)
    return types[IMU_MSG](
        header=_header(stamp, frame_id),
        orientation=_quaternion(q),
        orientation_covariance=ocov,
        angular_velocity=_vector3(gyro),
        angular_velocity_covariance=_covariance(gyro_covariance, 3, 1e-4),
        linear_acceleration=_vector3(accel),
        linear_acceleration_covariance=_covariance(accel_covariance, 3, 1e-2),
    )


def image_message(stamp: float | int, image: np.ndarray, frame_id: str, encoding: str | None = None):
    """sensor_msgs/Image from ``(H, W)`` uint8 (mono8), ``(H, W)`` uint16 (mono16) or ``(H, W, 3)``
    uint8 (rgb8 unless ``encoding='bgr8'``)."""
    image = np.asarray(image)
    if image.ndim == 2 and image.dtype == np.uint8:
        enc, channels, depth = encoding or "mono8", 1, 1
    elif image.ndim == 2 and image.dtype == np.uint16:
        enc, channels, depth = encoding or "mono16", 1, 2
    elif image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8:
        enc, channels, depth = encoding or "rgb8", 3, 1
    else:
        raise ValueError(f"unsupported image: shape {image.shape}, dtype {image.dtype} "
                         "(need (H, W) uint8/uint16 or (H, W, 3) uint8)")
    from bevo_ros.io.ros_conversions import IMAGE_ENCODINGS

    if IMAGE_ENCODINGS.get(enc) != (channels, depth):
        raise ValueError(f"encoding {enc!r} does not fit an image of shape {image.shape}, dtype {image.dtype}")
    h, w = image.shape[:2]
    data = np.ascontiguousarray(image).astype(image.dtype.newbyteorder("<"), copy=False).view(np.uint8).reshape(-1)
    return typestore().types[IMAGE_MSG](header=_header(stamp, frame_id), height=h, width=w, encoding=enc,
                                        is_bigendian=0, step=w * channels * depth, data=data)


def camera_info_message(stamp: float | int, K: np.ndarray, width: int, height: int, frame_id: str,
                        P: np.ndarray | None = None, D: Sequence[float] | None = None,
                        distortion_model: str = "plumb_bob", R: np.ndarray | None = None):
    """sensor_msgs/CameraInfo; for rectified images D = 0 (plumb_bob), R = I, P = [K | 0]."""
    types = typestore().types
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    P = np.hstack([K, np.zeros((3, 1))]) if P is None else np.asarray(P, dtype=np.float64).reshape(3, 4)
    R = np.eye(3) if R is None else np.asarray(R, dtype=np.float64).reshape(3, 3)
    D = np.zeros(5) if D is None else np.asarray(D, dtype=np.float64).reshape(-1)
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return types[CAMERA_INFO_MSG](header=_header(stamp, frame_id), height=int(height), width=int(width),
                                  distortion_model=distortion_model, d=D.copy(), k=K.reshape(-1).copy(),
                                  r=R.reshape(-1).copy(), p=P.reshape(-1).copy(), binning_x=0, binning_y=0,
                                  roi=roi)


def odometry_message(stamp: float | int, T: np.ndarray, frame_id: str, child_frame_id: str,
                     pose_covariance=None, twist: Sequence[float] | None = None, twist_covariance=None):
    """nav_msgs/Odometry of pose ``T (4, 4)`` (child in frame_id); twist (vx, vy, vz, wx, wy, wz)."""
    types = typestore().types
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"pose must be (4, 4), got {T.shape}")
    t = T[:3, 3]
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=_quaternion(quaternion_from_matrix(T[:3, :3])))
    tw = np.zeros(6) if twist is None else np.asarray(twist, dtype=np.float64).reshape(6)
    twist_msg = types["geometry_msgs/msg/Twist"](linear=_vector3(tw[:3]), angular=_vector3(tw[3:]))
    return types[ODOMETRY_MSG](
        header=_header(stamp, frame_id), child_frame_id=child_frame_id,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=_covariance(pose_covariance, 6, 0.0)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist_msg,
                                                            covariance=_covariance(twist_covariance, 6, 0.0)))


def twist_stamped_message(stamp: float | int, linear: Sequence[float], frame_id: str,
                          angular: Sequence[float] = (0.0, 0.0, 0.0)):
    """geometry_msgs/TwistStamped (m/s, rad/s in ``frame_id``)."""
    types = typestore().types
    return types[TWIST_STAMPED_MSG](header=_header(stamp, frame_id),
                                    twist=types["geometry_msgs/msg/Twist"](linear=_vector3(linear), angular=_vector3(angular)))


def tf_message(stamp: float | int, transforms: Sequence[tuple[str, str, np.ndarray]]):
    """tf2_msgs/TFMessage of ``(parent, child, T_parent_child (4, 4))`` transforms."""
    types = typestore().types
    out = []
    for parent, child, T in transforms:
        T = np.asarray(T, dtype=np.float64).reshape(4, 4)
        out.append(types["geometry_msgs/msg/TransformStamped"](
            header=_header(stamp, parent), child_frame_id=child,
            transform=types["geometry_msgs/msg/Transform"](translation=_vector3(T[:3, 3]),
                                                           rotation=_quaternion(quaternion_from_matrix(T[:3, :3])))))
    return types[TF_MSG](transforms=out)


def offered_qos(latched: bool = False, depth: int = 10):
    """The offered QoS a recorder stores for a topic: reliable, keep-last; ``latched`` = transient
    local (``/tf_static``), so a player can offer it the same way to late subscribers."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    inf = QosTime(sec=2147483647, nsec=4294967295)  # rosbag2's "infinite" duration
    return Qos(history=QosHistory.KEEP_LAST, depth=int(depth), reliability=QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               deadline=inf, lifespan=inf, liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=inf,
               avoid_ros_namespace_conventions=False)


@dataclass
class TopicQos:
    """What a player needs of a recorded offered QoS (rosbag2 metadata)."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 0  # 0: not recorded


def topic_qos(bag_path: PathLike) -> dict[str, TopicQos]:
    """``{topic: TopicQos}`` from the bag's recorded offered QoS (defaults where none is recorded:
    reliable, volatile). A topic offered transient local by any publisher is replayed latched."""
    from rosbags.interfaces import QosDurability, QosReliability

    reader = _open_reader(bag_path)
    try:
        out: dict[str, TopicQos] = {}
        for conn in reader.connections:
            q = out.setdefault(conn.topic, TopicQos())
            for prof in getattr(conn.ext, "offered_qos_profiles", None) or []:
                q.transient_local |= prof.durability == QosDurability.TRANSIENT_LOCAL
                q.reliable &= prof.reliability != QosReliability.BEST_EFFORT
                q.depth = max(q.depth, int(prof.depth))
            if _is_ros1(conn) and getattr(conn.ext, "latching", 0):
                q.transient_local = True
        return out
    finally:
        reader.close()


# ----------------------------------------------------------------------------------------------
# Writer
# ----------------------------------------------------------------------------------------------
def _storage_plugin(storage: str):
    from rosbags.rosbag2 import StoragePlugin

    if storage not in STORAGES:
        raise ValueError(f"unknown storage {storage!r} (choose from {', '.join(STORAGES)})")
    return StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3


PARTIAL_LOCK = ".lock"
UNLOCKED_PARTIAL_AGE = 60.0  # s: a partial without a lock file (older code) is stale after this


def _lock_partial(tmpdir: Path) -> int:
    """Hold an exclusive flock on ``tmpdir/.lock`` (the kernel releases it when the process dies)."""
    import fcntl

    fd = os.open(tmpdir / PARTIAL_LOCK, os.O_CREAT | os.O_RDWR, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return fd


def _partial_is_stale(partial: Path) -> bool:
    import fcntl
    import time

    lock = partial / PARTIAL_LOCK
    try:
        fd = os.open(lock, os.O_RDWR)
    except FileNotFoundError:  # older code, or a writer between mkdtemp and its lock: by age
        try:
            return time.time() - partial.stat().st_mtime > UNLOCKED_PARTIAL_AGE
        except FileNotFoundError:
            return False
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False  # its writer is alive
    finally:
        os.close(fd)
    return True


def remove_stale_partials(path: PathLike, keep: Path | None = None) -> list[Path]:
    """Remove the ``.<name>.partial-*`` directories of ``path`` left by killed writers; returns them."""
    path = Path(path)
    removed = []
    for partial in sorted(path.parent.glob(f".{path.name}.partial-*")):
        if partial == keep or not partial.is_dir() or not _partial_is_stale(partial):
            continue
        shutil.rmtree(partial, ignore_errors=True)
        removed.append(partial)
    return removed


def _replaceable(path: Path) -> bool:
    """An existing output that ``--overwrite`` may replace: a rosbag2 folder (its ``metadata.yaml``) or
    an empty folder; never a file or a folder of something else (a user's data under a mistyped -o)."""
    if not path.is_dir() or path.is_symlink():
        return False
    return (path / "metadata.yaml").is_file() or not any(path.iterdir())


class BagWriter:
    """Atomic rosbag2 writer (context manager).

    Example::

        with BagWriter("out_bag", storage="mcap") as bag:
            bag.write_imu(t, gyro, accel, "imu_link")

    Everything is written into ``.<name>.partial-XXXX/<name>`` beside ``path``; on success it is
    renamed to ``path`` (replacing an old bag only when ``overwrite``); on an exception (including
    KeyboardInterrupt) the temp directory is removed and ``path`` is untouched. A process killed
    outright (SIGKILL, power loss) cannot clean up: the next writer of the same ``path`` removes
    such stale partials (each writer holds a lock on its own while it lives, so a concurrent
    writer's is kept); ``removed_partials`` lists them.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False (raised by the constructor,
            before any work is done).
    """

    def __init__(self, path: PathLike, storage: str = "sqlite3", overwrite: bool = False):
        self.path = Path(path)
        self.storage = storage
        self.overwrite = overwrite
        self._plugin = _storage_plugin(storage)
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path}: output bag exists (use --overwrite to replace it)")
        if self.path.exists() and not _replaceable(self.path):  # --overwrite replaces a bag, not any folder
            raise FileExistsError(f"{self.path}: exists and is not a rosbag2 folder (no metadata.yaml); --overwrite "
                                  f"replaces only a bag: not replacing it")
        if self.path.parent.exists() and not self.path.parent.is_dir():
            raise FileNotFoundError(f"{self.path.parent}: not a directory (the output bag's parent)")
        self.counts: dict[str, int] = {}
        self._writer = None
        self._tmpdir: Path | None = None
        self._connections: dict[str, Any] = {}
        self._msgtypes: dict[str, str] = {}
        self._lock_fd: int | None = None
        self.removed_partials: list[Path] = []

    # context management ------------------------------------------------------------------
    def __enter__(self) -> "BagWriter":
        from rosbags.rosbag2 import Writer

        try:  # as `bevo run --out` does: `-o bags/kitti06` on a fresh machine
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise FileNotFoundError(f"{self.path.parent}: cannot create the output directory ({exc})") from exc
        self._tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.partial-", dir=self.path.parent))
        try:
            self._lock_fd = _lock_partial(self._tmpdir)
            self.removed_partials = remove_stale_partials(self.path, keep=self._tmpdir)
            self._writer = Writer(self._tmpdir / self.path.name, version=9, storage_plugin=self._plugin)
            self._writer.open()
        except BaseException:
            self._discard()
            raise
        return self

    def _discard(self) -> None:
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                self._writer.close()
                self._commit()
            else:
                try:
                    self._writer.close()
                except Exception:  # the original exception matters, not this one
                    pass
        finally:
            self._discard()

    def _commit(self) -> None:
        assert self._tmpdir is not None
        new = self._tmpdir / self.path.name
        if self.path.exists():
            if not self.overwrite or not _replaceable(self.path):
                raise FileExistsError(f"{self.path}: output appeared while writing (or is no bag); not replacing it")
            trash = self._tmpdir / (self.path.name + ".old")
            os.replace(self.path, trash)  # same filesystem: two renames, never a half bag at path
            try:
                os.replace(new, self.path)
            except BaseException:  # the old bag back where it was before the partial is discarded
                os.replace(trash, self.path)
                raise
            return
        os.replace(new, self.path)

    # writing --------------------------------------------------------------------------------
    def write(self, topic: str, msgtype: str, msg: Any, stamp: float | int) -> None:
        """Serialize ``msg`` (a rosbags message of ``msgtype``) to ``topic`` at bag time ``stamp``."""
        if self._writer is None or self._tmpdir is None:
            raise RuntimeError("BagWriter must be used as a context manager ('with BagWriter(...) as bag:')")
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=typestore(),
                                               offered_qos_profiles=[offered_qos(topic == TF_STATIC_TOPIC,
                                                                                 1 if topic == TF_STATIC_TOPIC else 10)])
            self._connections[topic] = conn
            self._msgtypes[topic] = msgtype
        elif self._msgtypes[topic] != msgtype:
            raise BagError(f"{self.path}: topic {topic} already has type {self._msgtypes[topic]}, not {msgtype}")
        self._writer.write(conn, to_ns(stamp), typestore().serialize_cdr(msg, msgtype))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def write_imu(self, stamp: float | int, gyro: Sequence[float], accel: Sequence[float], frame_id: str = "imu_link",
                  topic: str = IMU_TOPIC, **kwargs) -> None:
        """Rates (rad/s) and specific force (m/s^2) only; see :func:`imu_message` for kwargs."""
        self.write(topic, IMU_MSG, imu_message(stamp, gyro, accel, frame_id, **kwargs), stamp)

    def write_imu_attitude(self, stamp: float | int, roll: float, pitch: float, yaw: float,
                           gyro: Sequence[float] = (0.0, 0.0, 0.0), accel: Sequence[float] = (0.0, 0.0, 0.0),
                           frame_id: str = "imu_link", topic: str = GT_IMU_TOPIC,
                           orientation_covariance=None, **kwargs) -> None:
        """An Imu message whose orientation is ``Rz(yaw) Ry(pitch) Rx(roll)`` (e.g. the OXTS attitude)."""
        msg = imu_message(stamp, gyro, accel, frame_id, orientation=quaternion_from_rpy(roll, pitch, yaw),
                          orientation_covariance=orientation_covariance, **kwargs)
        self.write(topic, IMU_MSG, msg, stamp)

    def write_image(self, stamp: float | int, image: np.ndarray, frame_id: str = "camera_optical_frame",
                    topic: str = IMAGE_TOPIC, encoding: str | None = None) -> None:
        self.write(topic, IMAGE_MSG, image_message(stamp, image, frame_id, encoding), stamp)

    def write_camera_info(self, stamp: float | int, K: np.ndarray, width: int, height: int,
                          frame_id: str = "camera_optical_frame", topic: str = CAMERA_INFO_TOPIC, **kwargs) -> None:
        self.write(topic, CAMERA_INFO_MSG, camera_info_message(stamp, K, width, height, frame_id, **kwargs), stamp)

    def write_tf_static(self, stamp: float | int, transforms: Sequence[tuple[str, str, np.ndarray]],
                        topic: str = TF_STATIC_TOPIC) -> None:
        """The rig's static transforms ``(parent, child, T_parent_child)``, latched (transient local
        offered QoS recorded in the metadata, as a recording of tf2_ros's static broadcaster)."""
        self.write(topic, TF_MSG, tf_message(stamp, transforms), stamp)

    def write_odometry(self, stamp: float | int, T: np.ndarray, frame_id: str = "odom",
                       child_frame_id: str = "base_link", topic: str = GT_ODOMETRY_TOPIC, **kwargs) -> None:
        self.write(topic, ODOMETRY_MSG, odometry_message(stamp, T, frame_id, child_frame_id, **kwargs), stamp)


# ----------------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------------
def _open_reader(bag_path: PathLike):
    from rosbags.highlevel import AnyReader

    path = Path(bag_path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: bag not found")
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        path = path.parent  # accept the storage file of a bag directory too
    if path.is_dir() and not (path / "metadata.yaml").is_file():  # rosbags would name the folder as the file
        raise BagError(f"{path}: not a rosbag2 folder (it has no metadata.yaml)")
    try:
        reader = AnyReader([path], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags raises its own error classes for broken bags
        raise BagError(f"{path}: cannot open as a rosbag2 ({exc})") from None
    return reader


def bag_topics(bag_path: PathLike) -> dict[str, tuple[str, int]]:
    """{topic: (msgtype, message count)} of a bag."""
    reader = _open_reader(bag_path)
    try:
        return {name: (info.msgtype or "", int(info.msgcount)) for name, info in reader.topics.items()}
    finally:
        reader.close()


def bag_time_range(bag_path: PathLike) -> tuple[int, int]:
    """``(first, last)`` bag time of any message, ns; ``(0, 0)`` for an empty bag."""
    reader = _open_reader(bag_path)
    try:
        if reader.message_count == 0:
            return 0, 0
        return int(reader.start_time), int(reader.end_time)
    finally:
        reader.close()


@dataclass
class RawMessage:
    """One message as stored: CDR bytes (ROS 1 bags are converted), bag time in ns."""

    topic: str
    msgtype: str
    stamp_ns: int
    data: bytes


def _read(bag_path: PathLike, topics: Sequence[str] | None, start_ns: int | None, stop_ns: int | None):
    """``(reader, connection, bag time ns, raw bytes)`` in bag-time order; the reader closes at the end."""
    reader = _open_reader(bag_path)
    try:
        conns = _select_connections(reader, bag_path, topics)
        if conns:
            for conn, t_ns, raw in reader.messages(connections=conns, start=start_ns, stop=stop_ns):
                yield reader, conn, int(t_ns), raw
    finally:
        reader.close()


def iter_raw_messages(bag_path: PathLike, topics: Sequence[str] | None = None, start_ns: int | None = None,
                      stop_ns: int | None = None) -> Iterator[RawMessage]:
    """Serialized messages in bag-time order (ties: storage order), optionally filtered by topic."""
    for reader, conn, t_ns, raw in _read(bag_path, topics, start_ns, stop_ns):
        data = bytes(raw)
        if _is_ros1(conn):
            data = bytes(reader.typestore.ros1_to_cdr(data, conn.msgtype))
        yield RawMessage(conn.topic, conn.msgtype, t_ns, data)


def _is_ros1(conn) -> bool:
    return type(conn.ext).__name__ == "ConnectionExtRosbag1"


def _select_connections(reader, bag_path: PathLike, topics: Sequence[str] | None) -> list:
    if topics is None:
        return list(reader.connections)
    available = {c.topic for c in reader.connections}
    missing = [t for t in topics if t not in available]
    if missing:
        raise BagError(f"{bag_path}: no topic {', '.join(missing)} (the bag has: {', '.join(sorted(available)) or 'none'})")
    return [c for c in reader.connections if c.topic in set(topics)]


def iter_messages(bag_path: PathLike, topics: Sequence[str] | None = None, start_ns: int | None = None,
                  stop_ns: int | None = None) -> Iterator[tuple[str, int, Any]]:
    """``(topic, bag time ns, deserialized rosbags message)`` in bag-time order."""
    for reader, conn, t_ns, raw in _read(bag_path, topics, start_ns, stop_ns):
        yield conn.topic, t_ns, reader.deserialize(raw, conn.msgtype)


# A vehicle's forward speed: wheel odometry (nav_msgs/Odometry, its twist), a CAN or GNSS speed as a twist.
SPEED_MSGS = (ODOMETRY_MSG, TWIST_STAMPED_MSG, "geometry_msgs/msg/TwistWithCovarianceStamped")


def read_speed(bag_path: PathLike, topic: str, base_frame: str = "base_link") -> tuple[np.ndarray, np.ndarray, bool]:
    """The speed on ``topic`` (one of :data:`SPEED_MSGS`), read as the node and ``bevo run`` read it
    (:func:`~bevo_ros.io.ros_conversions.forward_speed_from_msg`): a twist in ``base_frame`` gives its
    ``linear.x``, signed (reversing reads negative); one in another frame (a GNSS driver's east/north
    velocity) its horizontal speed, unsigned -> ``(stamps (N,) s, speeds (N,) m/s, signed)`` by header
    stamp. The covariance is not read. BagError when the topic is missing, of another type, empty, not
    finite, or mixes twists in ``base_frame`` with twists in other frames (signed with unsigned speeds)."""
    path = Path(bag_path)
    topics = bag_topics(path)
    if topic not in topics:
        raise BagError(f"{path}: no topic {topic} (the bag has: {', '.join(sorted(topics)) or 'none'})")
    if topics[topic][0] not in SPEED_MSGS:
        raise BagError(f"{path}: topic {topic} carries {topics[topic][0] or 'an unknown type'}, not a speed "
                       f"({' or '.join(SPEED_MSGS)})")
    stamps, speeds, frames = [], [], set()
    for _, _, msg in iter_messages(path, [topic]):
        speed, signed = twist_speed(msg, base_frame)
        if not math.isfinite(speed):
            raise BagError(f"{path}: topic {topic} holds a speed that is not finite ({speed!r} m/s at "
                           f"{stamp_to_ns(msg.header.stamp) * 1e-9:.6f} s)")
        stamps.append(stamp_to_ns(msg.header.stamp))
        speeds.append(speed)
        frames.add((speed_frame(msg), signed))
    if not stamps:
        raise BagError(f"{path}: topic {topic} has no messages")
    if len({signed for _, signed in frames}) > 1:
        others = sorted(f"'{f}'" for f, signed in frames if not signed)
        raise BagError(f"{path}: topic {topic} mixes twists in base_frame '{base_frame}' with twists in "
                       f"{', '.join(others)}: its speeds would mix signed and unsigned")
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    signed = next(iter(frames))[1]
    return ns_to_seconds(np.asarray(stamps, dtype=np.int64)[order]), np.asarray(speeds, dtype=np.float64)[order], signed


def decode_image(msg: Any) -> np.ndarray:
    """sensor_msgs/Image or CompressedImage (as read from a bag) -> uint8 grey ``(H, W)``: the node's conversion
    (:func:`bevo_ros.ros_conversions.image_to_gray`), so a bag gives the engine the very grey levels
    bevo_node gives it. Raises :class:`BagError` for an encoding or layout it cannot use."""
    from bevo_ros.io.ros_conversions import ImageConversionError, image_to_gray

    try:
        return image_to_gray(msg)
    except ImageConversionError as exc:
        raise BagError(str(exc)) from None


@dataclass
class BagContents:
    """A bag's raw contents in numpy arrays (what :func:`read_recording` returns; the tensors the
    engine and training run on are :class:`bevo_ros.datasets.rosbag.Recording`). Stamps are header
    stamps: float64 seconds, plus the exact int64 nanoseconds in the ``*_ns`` twins.

    Attributes:
        imu_stamps: ``(N,)``; gyro, accel: ``(N, 3)`` float64 (rad/s, m/s^2).
        frame_stamps: ``(F,)``; images: ``(F, H, W)`` uint8 (grey), or None if not loaded.
        camera_info: the first sensor_msgs/CameraInfo message as read (rosbags), or None;
            camera_info_topic: its topic.
        image_topic: the topic the images were read from (``/camera/image_raw`` for old bags without
            ``/camera/image_rect``).
        gt_stamps: ``(G,)``; gt_poses: ``(G, 4, 4)`` base poses in ``gt_frame_id``, or None.
        gt_att_stamps, gt_roll, gt_pitch, gt_yaw: ``(A,)`` attitude of the ground-truth Imu, or None.
        static_tf: the transforms of every ``/tf_static`` message (the rig, as bevo_node reads it).
        imu_frame_id, image_frame_id: the last non-empty ``frame_id``; imu_frame_ids: each IMU sample's.
    """

    path: Path
    imu_stamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    frame_stamps_ns: np.ndarray
    images: np.ndarray | None
    image_encoding: str = ""
    imu_frame_id: str = ""
    image_frame_id: str = ""
    camera_info: Any = None
    camera_info_topic: str = ""
    image_topic: str = ""
    gt_stamps_ns: np.ndarray | None = None
    gt_poses: np.ndarray | None = None
    gt_frame_id: str = ""
    gt_child_frame_id: str = ""
    gt_att_stamps_ns: np.ndarray | None = None
    gt_roll: np.ndarray | None = None
    gt_pitch: np.ndarray | None = None
    gt_yaw: np.ndarray | None = None
    topics: dict[str, tuple[str, int]] = field(default_factory=dict)
    static_tf: StaticTree = field(default_factory=StaticTree)
    imu_frame_ids: list[str] = field(default_factory=list)  # per IMU sample

    @property
    def imu_stamps(self) -> np.ndarray:
        return ns_to_seconds(self.imu_stamps_ns)

    @property
    def frame_stamps(self) -> np.ndarray:
        return ns_to_seconds(self.frame_stamps_ns)

    @property
    def gt_stamps(self) -> np.ndarray | None:
        return None if self.gt_stamps_ns is None else ns_to_seconds(self.gt_stamps_ns)

    @property
    def gt_att_stamps(self) -> np.ndarray | None:
        return None if self.gt_att_stamps_ns is None else ns_to_seconds(self.gt_att_stamps_ns)


# What each topic role of read_recording must carry.
EXPECTED_TYPES = {"imu": (IMU_MSG,), "image": (IMAGE_MSG, COMPRESSED_IMAGE_MSG), "camera_info": (CAMERA_INFO_MSG,),
                  "gt_odometry": (ODOMETRY_MSG,), "gt_imu": (IMU_MSG,)}


def read_recording(bag_path: PathLike, imu_topic: str = IMU_TOPIC, image_topic: str = IMAGE_TOPIC,
                   camera_info_topic: str = CAMERA_INFO_TOPIC, gt_odometry_topic: str = GT_ODOMETRY_TOPIC,
                   gt_imu_topic: str = GT_IMU_TOPIC, load_images: bool = True,
                   required: Sequence[str] = ("imu", "image")) -> BagContents:
    """Load a recording. Topics listed in ``required`` (``imu``, ``image``, ``camera_info``,
    ``gt_odometry``, ``gt_imu``) must exist; the others are read when present.

    Raises:
        FileNotFoundError: no bag at ``bag_path``.
        BagError: unreadable bag, a required topic missing, images of different sizes or an
            unsupported encoding (the message names the bag, topic and message index).
    """
    names = {"imu": imu_topic, "image": image_topic, "camera_info": camera_info_topic,
             "gt_odometry": gt_odometry_topic, "gt_imu": gt_imu_topic}
    unknown = set(required) - set(names)
    if unknown:
        raise ValueError(f"unknown required topic keys {sorted(unknown)} (use {sorted(names)})")
    path = Path(bag_path)
    topics = bag_topics(path)
    if image_topic == IMAGE_TOPIC and image_topic not in topics and LEGACY_IMAGE_TOPIC in topics:
        names["image"] = image_topic = LEGACY_IMAGE_TOPIC
    missing = [names[k] for k in required if names[k] not in topics]
    if missing:
        raise BagError(f"{path}: required topic(s) {', '.join(missing)} missing "
                       f"(the bag has: {', '.join(sorted(topics)) or 'none'})")
    empty = [names[k] for k in required if topics[names[k]][1] == 0]  # recorded, but not one message
    if empty:
        raise BagError(f"{path}: required topic(s) {', '.join(empty)} hold no message")
    for key, types in EXPECTED_TYPES.items():  # `--imu-topic /camera/image_rect` and the like
        topic = names[key]
        if topic in topics and topics[topic][0] not in types:
            raise BagError(f"{path}: topic {topic} carries {topics[topic][0] or 'an unknown type'}, not "
                           f"{' or '.join(types)} (the {key.replace('_', ' ')} topic)")
    wanted = [t for t in names.values() if t in topics]
    if TF_STATIC_TOPIC in topics and topics[TF_STATIC_TOPIC][0] == TF_MSG:
        wanted.append(TF_STATIC_TOPIC)

    imu_t, gyro, accel = [], [], []
    frame_t, images = [], []
    gt_t, gt_T = [], []
    att_t, att = [], []
    rec = BagContents(path, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64),
                    None, topics=topics)
    rec.image_topic = image_topic
    shape = None
    for topic, _, msg in iter_messages(path, wanted):
        if topic == imu_topic:
            imu_t.append(stamp_to_ns(msg.header.stamp))
            gyro.append((msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z))
            accel.append((msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z))
            rec.imu_frame_ids.append(msg.header.frame_id)
            rec.imu_frame_id = msg.header.frame_id or rec.imu_frame_id
        elif topic == image_topic:
            frame_t.append(stamp_to_ns(msg.header.stamp))
            rec.image_frame_id = msg.header.frame_id or rec.image_frame_id  # an empty one keeps the last (the node's rig)
            rec.image_encoding = getattr(msg, "encoding", None) or getattr(msg, "format", "")  # CompressedImage: format
            if load_images:
                try:
                    img = decode_image(msg)
                except BagError as exc:
                    raise BagError(f"{path}: {topic} message {len(frame_t) - 1}: {exc}") from None
                if shape is None:
                    shape = img.shape
                elif img.shape != shape:
                    raise BagError(f"{path}: {topic} message {len(frame_t) - 1} is {img.shape[1]}x{img.shape[0]}, "
                                   f"the first was {shape[1]}x{shape[0]}")
                images.append(img)
        elif topic == camera_info_topic and rec.camera_info is None:
            rec.camera_info, rec.camera_info_topic = msg, topic
        elif topic == gt_odometry_topic:
            p = msg.pose.pose
            T = np.full((4, 4), np.nan)  # a pose without a rotation: left out below
            with contextlib.suppress(ValueError):
                T[:3, :3] = matrix_from_quaternion((p.orientation.x, p.orientation.y, p.orientation.z,
                                                    p.orientation.w))
            T[:3, 3], T[3] = (p.position.x, p.position.y, p.position.z), (0.0, 0.0, 0.0, 1.0)
            gt_t.append(stamp_to_ns(msg.header.stamp))
            gt_T.append(T)
            rec.gt_frame_id, rec.gt_child_frame_id = msg.header.frame_id, msg.child_frame_id
        elif topic == TF_STATIC_TOPIC:
            for what in rec.static_tf.add_message(msg):
                warnings.warn(f"{path}: /tf_static transform left out, no rigid transform: {what}", UserWarning,
                              stacklevel=2)
        elif topic == gt_imu_topic:
            if msg.orientation_covariance[0] == -1.0:
                continue  # no attitude in this message
            q = msg.orientation
            att_t.append(stamp_to_ns(msg.header.stamp))
            try:
                att.append(rpy_from_matrix(matrix_from_quaternion((q.x, q.y, q.z, q.w))))
            except ValueError:
                att.append((math.nan, math.nan, math.nan))  # left out below

    gyro_a, accel_a = (np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in (gyro, accel))
    keep = _usable(path, imu_topic, imu_t, np.isfinite(gyro_a).all(1) & np.isfinite(accel_a).all(1))
    rec.imu_stamps_ns, rec.gyro, rec.accel = np.asarray(imu_t, dtype=np.int64)[keep], gyro_a[keep], accel_a[keep]
    rec.imu_frame_ids = [f for f, k in zip(rec.imu_frame_ids, keep) if k]
    keep = _usable(path, image_topic, frame_t)
    rec.frame_stamps_ns = np.asarray(frame_t, dtype=np.int64)[keep]
    if load_images:
        rec.images = np.stack([im for im, k in zip(images, keep) if k]) if keep.any() else np.zeros((0, 0, 0), np.uint8)
    if gt_T:
        poses = np.stack(gt_T)
        keep = _usable(path, gt_odometry_topic, gt_t, np.isfinite(poses).all(axis=(1, 2)))
        if keep.any():
            rec.gt_stamps_ns, rec.gt_poses = np.asarray(gt_t, np.int64)[keep], poses[keep]
    if att:
        a = np.asarray(att, dtype=np.float64)
        keep = _usable(path, gt_imu_topic, att_t, np.isfinite(a).all(1))
        if keep.any():
            a = a[keep]
            rec.gt_att_stamps_ns = np.asarray(att_t, np.int64)[keep]
            rec.gt_roll, rec.gt_pitch, rec.gt_yaw = a[:, 0], a[:, 1], a[:, 2]
    return rec


def _usable(path: Path, topic: str, stamps_ns: list[int], valid: np.ndarray | None = None) -> np.ndarray:
    """``(N,)`` bool: the messages of ``topic`` to keep. Left out, with one warning that counts them:
    those whose values are not ``valid`` (not finite, a zero quaternion) and those whose header stamp
    is not after every earlier kept one (a duplicate, or a clock that stepped back: bevo_node drops
    such a message too, counted in /diagnostics, so offline runs and training see what it sees)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    keep = np.ones(len(stamps), dtype=bool) if valid is None else np.asarray(valid, dtype=bool).copy()
    invalid = int((~keep).sum())
    ordered = np.flatnonzero(keep)
    keep[ordered[out_of_order(stamps[ordered])]] = False
    disordered = int((~keep).sum()) - invalid
    if invalid or disordered:
        first = int(np.flatnonzero(~keep)[0])
        warnings.warn(f"{path}: {topic}: {invalid + disordered} of {len(stamps)} messages left out ({invalid} with "
                      f"values not finite or no rotation, {disordered} with a stamp not after an earlier one; the "
                      f"first is message {first})", UserWarning, stacklevel=3)
    return keep
