"""ROS message <-> numpy helpers for ``bevo_node`` (rclpy message classes, no node state).

Stamps: ``builtin_interfaces/Time`` -> float seconds as ``sec + nanosec * 1e-9`` (one formula,
:func:`ns_to_seconds`, for the node, the bag reader and the KITTI reader, so they feed the engine
identical floats). Outgoing headers copy the input header's ``Time`` object, never a float round trip.
"""
from __future__ import annotations

import array
import math
from typing import Any

import numpy as np

from bevo_ros.rotations import quaternion_from_rpy, rpy_from_quaternion

# Image encodings the node accepts: name -> (channels, bytes per channel). Everything else is
# rejected with the reason (the engine works on one grey channel).
IMAGE_ENCODINGS = {
    "mono8": (1, 1), "8UC1": (1, 1),
    "mono16": (1, 2), "16UC1": (1, 2),
    "rgb8": (3, 1), "bgr8": (3, 1),
    "rgba8": (4, 1), "bgra8": (4, 1),
}


# Encodings converted to grey with OpenCV (sensor_msgs/image_encodings names -> cv2 code, bytes per
# pixel). ROS names Bayer patterns by their first row, OpenCV by the second: cv_bridge's mapping.
CV2_GRAY_ENCODINGS = {
    "bayer_rggb8": ("COLOR_BayerBG2GRAY", 1), "bayer_bggr8": ("COLOR_BayerRG2GRAY", 1),
    "bayer_gbrg8": ("COLOR_BayerGR2GRAY", 1), "bayer_grbg8": ("COLOR_BayerGB2GRAY", 1),
    "yuv422": ("COLOR_YUV2GRAY_UYVY", 2), "uyvy": ("COLOR_YUV2GRAY_UYVY", 2),
    "yuyv": ("COLOR_YUV2GRAY_YUY2", 2), "yuv422_yuy2": ("COLOR_YUV2GRAY_YUY2", 2),
}


class ImageConversionError(ValueError):
    """An image the node cannot use; ``reason`` is the drop-counter key."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


def ns_to_seconds(ns: np.ndarray | Any) -> np.ndarray:
    """int64 nanoseconds ``(...)`` -> float64 seconds ``(...)``: whole seconds split off first, so
    ``sec + nanosec * 1e-9`` rounds once."""
    ns = np.asarray(ns, dtype=np.int64)
    return (ns // 1_000_000_000).astype(np.float64) + (ns % 1_000_000_000).astype(np.float64) * 1e-9


def out_of_order(stamps_ns: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: stamps not after every stamp before them (a duplicate, or a clock that stepped
    back): such a record cannot be placed in time, while its neighbours are fine."""
    stamps_ns = np.asarray(stamps_ns)
    if len(stamps_ns) < 2:
        return np.zeros(len(stamps_ns), dtype=bool)
    return np.concatenate([[False], stamps_ns[1:] <= np.maximum.accumulate(stamps_ns)[:-1]])


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time``-like (``sec``, ``nanosec``; rclpy or rosbags) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_to_sec(stamp: Any) -> float:
    """``builtin_interfaces/Time`` -> float seconds (:func:`ns_to_seconds`)."""
    return float(ns_to_seconds(stamp_to_ns(stamp)))


def sec_to_stamp(t: float):
    """Float seconds -> ``builtin_interfaces/Time`` (nanosecond rounding; for tests and benchmarks)."""
    from builtin_interfaces.msg import Time

    whole = math.floor(t)
    ns = int(round((t - whole) * 1e9))
    if ns >= 1_000_000_000:
        whole, ns = whole + 1, ns - 1_000_000_000
    return Time(sec=int(whole), nanosec=ns)


# ----------------------------------------------------------------------------------------- inputs
def imu_to_arrays(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """sensor_msgs/Imu -> ``gyro (3,)`` rad/s, ``accel (3,)`` m/s^2 (float64, unchecked)."""
    w, a = msg.angular_velocity, msg.linear_acceleration
    return np.array([w.x, w.y, w.z], dtype=np.float64), np.array([a.x, a.y, a.z], dtype=np.float64)


def image_to_gray(msg: Any) -> np.ndarray:
    """sensor_msgs/Image -> ``(H, W)`` uint8 grey.

    mono8/8UC1 are used as they are (zero-copy view when the rows are unpadded); rgb8/bgr8 (and
    rgba8/bgra8) are converted with the ITU-R BT.601 luma weights in float32 (``bag.decode_image``
    is this function, so bags and the node give the engine identical grey levels); mono16/16UC1
    are scaled to 8 bits by /257 (65535 -> 255).

    Raises:
        ImageConversionError: unsupported encoding (reason ``bad_encoding``) or a data/step size
            inconsistent with width x height (reason ``bad_image``).
    """
    if hasattr(msg, "format"):  # sensor_msgs/CompressedImage
        return compressed_to_gray(msg)
    enc = msg.encoding
    if enc in CV2_GRAY_ENCODINGS:
        return _cv2_to_gray(msg)
    if enc not in IMAGE_ENCODINGS:
        raise ImageConversionError(
            "bad_encoding",
            f"unsupported image encoding '{enc}' (supported: {', '.join([*IMAGE_ENCODINGS, *CV2_GRAY_ENCODINGS])})")
    channels, depth = IMAGE_ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ImageConversionError("bad_image", f"empty image {w}x{h}")
    data = np.frombuffer(msg.data, dtype=np.uint8)
    row = w * channels * depth
    if step < row or data.size < step * h:
        raise ImageConversionError(
            "bad_image", f"image {w}x{h} {enc}: step {step} and data size {data.size} do not match "
                         f"(need step >= {row} and size >= {step * h})")
    rows = data[: step * h].reshape(h, step)[:, :row]
    if depth == 2:
        dt = np.dtype(">u2" if msg.is_bigendian else "<u2")
        img16 = np.ascontiguousarray(rows).view(dt).reshape(h, w)
        return np.round(img16.astype(np.float32) / 257.0).astype(np.uint8)
    if channels == 1:
        return rows if rows.flags.c_contiguous else np.ascontiguousarray(rows)
    img = rows.reshape(h, w, channels).astype(np.float32)
    if enc.startswith("rgb"):
        r, g, b = img[..., 0], img[..., 1], img[..., 2]
    else:
        b, g, r = img[..., 0], img[..., 1], img[..., 2]
    gray = 0.299 * r + 0.587 * g + 0.114 * b
    return np.clip(np.round(gray), 0, 255).astype(np.uint8)


def _rows(msg: Any, row_bytes: int) -> np.ndarray:
    """``(H, row_bytes)`` uint8 view of an Image's pixel rows (step padding dropped)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ImageConversionError("bad_image", f"empty image {w}x{h}")
    data = np.frombuffer(msg.data, dtype=np.uint8)
    if step < row_bytes or data.size < step * h:
        raise ImageConversionError(
            "bad_image", f"image {w}x{h} {msg.encoding}: step {step} and data size {data.size} do not match "
                         f"(need step >= {row_bytes} and size >= {step * h})")
    return data[: step * h].reshape(h, step)[:, :row_bytes]


def _cv2_to_gray(msg: Any) -> np.ndarray:
    """Bayer (demosaiced) and packed YUV 4:2:2 images -> grey with OpenCV's conversion codes."""
    import cv2

    code, bpp = CV2_GRAY_ENCODINGS[msg.encoding]
    w = int(msg.width)
    if bpp == 2 and w % 2:
        raise ImageConversionError("bad_image", f"{msg.encoding} image width {w} is odd (4:2:2 pairs pixels)")
    rows = np.ascontiguousarray(_rows(msg, w * bpp))
    src = rows.reshape(int(msg.height), w, bpp) if bpp == 2 else rows
    return cv2.cvtColor(src, getattr(cv2, code))


def compressed_to_gray(msg: Any) -> np.ndarray:
    """sensor_msgs/CompressedImage (jpeg, png, ...) -> ``(H, W)`` uint8 grey, via ``cv2.imdecode``."""
    import cv2

    data = np.frombuffer(msg.data, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None
    if img is None:
        raise ImageConversionError("bad_compressed",
                                   f"compressed image ({msg.format or 'no format'}, {data.size} bytes) cannot be "
                                   "decoded by OpenCV")
    return img


def gray_to_image_msg(img: np.ndarray, header: Any = None, encoding: str = "mono8"):
    """``(H, W)`` uint8 (or ``(H, W, 3)`` for rgb8/bgr8) -> sensor_msgs/Image."""
    from sensor_msgs.msg import Image

    img = np.ascontiguousarray(img)
    msg = Image()
    if header is not None:
        msg.header = header
    msg.height, msg.width = int(img.shape[0]), int(img.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = int(img.strides[0])
    msg.data = array.array("B", img.tobytes())
    return msg


def camera_info_intrinsics(msg: Any, use_p: bool = True) -> tuple[np.ndarray, int, int]:
    """sensor_msgs/CameraInfo -> ``(K (3, 3), width, height)``.

    ``use_p``: take the rectified camera matrix ``P[:3, :3]`` (right for rectified images, as the
    engine expects) when P is set; otherwise ``K``.
    """
    P = np.asarray(msg.p, dtype=np.float64).reshape(3, 4)
    K = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    M = P[:, :3] if use_p and P[0, 0] > 0 and P[1, 1] > 0 else K
    if not (np.all(np.isfinite(M)) and M[0, 0] > 0 and M[1, 1] > 0):
        raise ValueError("CameraInfo has no valid camera matrix (fx, fy must be > 0)")
    if int(msg.width) <= 0 or int(msg.height) <= 0:
        raise ValueError(f"CameraInfo has an invalid image size {msg.width}x{msg.height}")
    return M.copy(), int(msg.width), int(msg.height)


def yaw_from_quaternion_msg(q: Any) -> float:
    """A geometry_msgs/Quaternion's yaw, taken at its direction (any norm: ``z: 1, w: 1`` is 90 deg).
    ValueError for a quaternion that is no rotation (zero, not finite: an orientation left out)."""
    norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    if not (math.isfinite(norm) and norm > 1e-9):
        raise ValueError(f"orientation is no rotation ({q.x}, {q.y}, {q.z}, {q.w})")
    return rpy_from_quaternion(q.x / norm, q.y / norm, q.z / norm, q.w / norm)[2]


def planar_pose_from_msg(msg: Any) -> tuple[float, float, float, float, list[list[float]]]:
    """geometry_msgs/PoseWithCovarianceStamped -> ``(x, y, z, yaw, (3, 3) covariance of (x, y, yaw))``,
    the quaternion taken at its direction (:func:`yaw_from_quaternion_msg`). ValueError for a position
    that is not finite or a quaternion that is no rotation (zero, not finite)."""
    p, q, cov = msg.pose.pose.position, msg.pose.pose.orientation, msg.pose.covariance
    yaw = yaw_from_quaternion_msg(q)
    if not all(math.isfinite(v) for v in (p.x, p.y, p.z)):
        raise ValueError(f"position is not finite ({p.x}, {p.y}, {p.z})")
    planar = [[float(cov[6 * r + c]) for c in (0, 1, 5)] for r in (0, 1, 5)]  # the 6x6's x, y, yaw rows
    return float(p.x), float(p.y), float(p.z), yaw, planar


def speed_frame(msg: Any) -> str:
    """The frame a speed message's twist is in: an Odometry's ``child_frame_id``, else its header's."""
    return (msg.child_frame_id if hasattr(msg, "child_frame_id") else msg.header.frame_id).lstrip("/")


def twist_speed(msg: Any, base_frame: str) -> tuple[float, bool]:
    """A speed message's ``(speed m/s, signed)`` (:func:`forward_speed_from_msg`'s rule, no variance, no check)."""
    twist = msg.twist.twist if hasattr(msg.twist, "twist") else msg.twist  # Odometry / *WithCovariance*
    vx, vy = float(twist.linear.x), float(twist.linear.y)
    signed = speed_frame(msg) == base_frame.lstrip("/")
    return (vx if signed else math.hypot(vx, vy)), signed


def forward_speed_from_msg(msg: Any, base_frame: str, default_variance: float) -> tuple[float, float, bool]:
    """A vehicle's speed message -> ``(speed m/s, variance (m/s)^2, signed)``, the arguments of
    :meth:`~bevo_ros.core.odometry.BevoOdometry.add_speed`: nav_msgs/Odometry (wheel odometry),
    geometry_msgs/TwistStamped (CAN, GNSS) or TwistWithCovarianceStamped, as rclpy or rosbags gives it.

    A twist in ``base_frame`` (an Odometry's ``child_frame_id``, a twist's ``header.frame_id``) gives
    its ``linear.x``, signed (reversing reads negative); one in another frame (a GNSS driver's
    east/north velocity) its horizontal speed ``hypot(linear.x, linear.y)``, unsigned (the engine
    takes the direction of travel from the images). The variance
    is the twist covariance's ``linear.x`` entry when it has one above 0, else ``default_variance``.
    ValueError when the speed or the variance is not finite."""
    speed, signed = twist_speed(msg, base_frame)
    cov = float(msg.twist.covariance[0]) if hasattr(msg.twist, "covariance") else 0.0
    variance = cov if cov > 0 else float(default_variance)
    if not (math.isfinite(speed) and math.isfinite(variance) and variance > 0):
        raise ValueError(f"speed {speed!r} with variance {variance!r}: not a finite speed with a variance > 0")
    return speed, variance, signed


# ---------------------------------------------------------------------------------------- outputs
def odometry_msg(step: Any, stamp: Any, frame_id: str, child_frame_id: str):
    """engine ``OdometryStep`` -> nav_msgs/Odometry with the given header stamp (a Time)."""
    from nav_msgs.msg import Odometry

    msg = Odometry()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    p = msg.pose.pose.position
    p.x, p.y, p.z = (float(v) for v in step.position)
    q = msg.pose.pose.orientation
    q.x, q.y, q.z, q.w = quaternion_from_rpy(*(float(v) for v in step.rpy))
    msg.pose.covariance = np.ascontiguousarray(step.pose_covariance, dtype=np.float64).reshape(36)
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    lin.x, lin.y, lin.z = (float(v) for v in step.twist_linear)
    ang.x, ang.y, ang.z = (float(v) for v in step.twist_angular)
    msg.twist.covariance = np.ascontiguousarray(step.twist_covariance, dtype=np.float64).reshape(36)
    return msg


def pose_stamped_from_odometry(odom: Any):
    from geometry_msgs.msg import PoseStamped

    ps = PoseStamped()
    ps.header = odom.header
    ps.pose = odom.pose.pose
    return ps


def transform_from_odometry(odom: Any):
    """nav_msgs/Odometry -> geometry_msgs/TransformStamped ``frame_id -> child_frame_id``."""
    from geometry_msgs.msg import TransformStamped

    t = TransformStamped()
    t.header = odom.header
    t.child_frame_id = odom.child_frame_id
    p, q = odom.pose.pose.position, odom.pose.pose.orientation
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = p.x, p.y, p.z
    t.transform.rotation = q
    return t


def bev_to_mono8(bev: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """BEV float ``(S, S)`` in [0, 1] -> uint8; pixels outside ``mask`` are black."""
    img = np.nan_to_num(np.asarray(bev, dtype=np.float32), nan=0.0)
    if mask is not None:
        img = img * (np.asarray(mask, dtype=np.float32) > 0.5)
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)


def heatmap_to_mono8(heat: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A correlation surface (any real values) -> uint8 ``size`` (rows, cols), normalised to its
    max (nearest-neighbour resampling, so the peak stays one visible block)."""
    h = np.nan_to_num(np.asarray(heat, dtype=np.float32), nan=0.0)
    h = h - h.min()
    peak = float(h.max())
    if peak > 0:
        h = h / peak
    rows = (np.arange(size[0]) * h.shape[0] // size[0]).clip(0, h.shape[0] - 1)
    cols = (np.arange(size[1]) * h.shape[1] // size[1]).clip(0, h.shape[1] - 1)
    return np.round(h[np.ix_(rows, cols)] * 255.0).astype(np.uint8)


__all__ = [
    "IMAGE_ENCODINGS", "CV2_GRAY_ENCODINGS", "ImageConversionError", "compressed_to_gray", "stamp_to_sec", "stamp_to_ns", "ns_to_seconds", "sec_to_stamp",
    "out_of_order",
    "imu_to_arrays", "image_to_gray", "gray_to_image_msg", "camera_info_intrinsics",
    "odometry_msg", "pose_stamped_from_odometry",
    "transform_from_odometry", "bev_to_mono8", "heatmap_to_mono8",
]
