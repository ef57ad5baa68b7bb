"""Static transforms as a tree of rigid poses (``/tf_static``'s content): what bevo_node's
listener (``bevo_ros.ros.tf``) and the offline commands reading a bag's ``/tf_static``
(``bevo_ros.datasets.rosbag``) both look the rig up in. No ROS needed."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from bevo_ros.rotations import matrix_from_quaternion

# The extrinsics' source when /tf_static has no base_frame -> camera frame (the node and `bevo run` say so).
PARAMETERS_EXTRINSICS = "parameters camera.base_T_camera"


def matrix_from_transform(t: Any) -> np.ndarray:
    """geometry_msgs/Transform -> ``(4, 4)`` (pose of the child in the parent)."""
    q, p = t.rotation, t.translation
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion((q.x, q.y, q.z, q.w))
    T[:3, 3] = (p.x, p.y, p.z)
    return T


class StaticTree:
    """The static transforms received so far: ``child -> (parent, T_parent_child)``."""

    def __init__(self) -> None:
        self.edges: dict[str, tuple[str, np.ndarray]] = {}
        self.version = 0  # bumped whenever an edge changes (callers re-read what they derived)

    def add(self, parent: str, child: str, T: np.ndarray) -> None:
        parent, child = parent.lstrip("/"), child.lstrip("/")
        old = self.edges.get(child)
        if old is None or old[0] != parent or not np.allclose(old[1], T, rtol=0, atol=1e-12):
            self.edges[child] = (parent, np.asarray(T, dtype=np.float64))
            self.version += 1

    def add_message(self, msg: Any) -> list[str]:
        """Every transform of a tf2_msgs/TFMessage (rclpy's or rosbags' message: the same fields) but
        those that are no rigid transform (a zero or NaN quaternion: a NaN rotation blamed every IMU
        sample in that frame as non-finite): returned, ``"parent -> child: why"``, and left out."""
        bad = []
        for t in msg.transforms:
            q, p = t.transform.rotation, t.transform.translation
            norm = float(np.linalg.norm([q.x, q.y, q.z, q.w]))
            if not (math.isfinite(norm) and norm > 1e-9 and all(map(math.isfinite, (p.x, p.y, p.z)))):
                bad.append(f"{t.header.frame_id} -> {t.child_frame_id}: quaternion "
                           f"{[q.x, q.y, q.z, q.w]}, translation {[p.x, p.y, p.z]}")
                continue
            self.add(t.header.frame_id, t.child_frame_id, matrix_from_transform(t.transform))
        return bad

    def _to_root(self, frame: str) -> tuple[str, np.ndarray]:
        """``(root, T_root_frame)``: up the tree from ``frame`` (cycle-safe)."""
        T, seen = np.eye(4), {frame}
        while frame in self.edges:
            parent, T_pc = self.edges[frame]
            if parent in seen:
                break
            T = T_pc @ T
            seen.add(parent)
            frame = parent
        return frame, T

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """``T_target_source`` (pose of ``source`` in ``target``), None when not connected."""
        target, source = target.lstrip("/"), source.lstrip("/")
        if target == source:
            return np.eye(4)
        root_s, T_rs = self._to_root(source)
        root_t, T_rt = self._to_root(target)
        if root_s != root_t:
            return None
        return np.linalg.inv(T_rt) @ T_rs


def camera_extrinsics(transforms: Any, base_frame: str, camera_frame: str, fallback) -> tuple[np.ndarray, str]:
    """``(base_T_camera (4, 4), source)``: ``transforms.lookup(base_frame, camera_frame)`` (a
    :class:`StaticTree` or the node's listener; None: not used) when known, else ``fallback``
    (``camera.base_T_camera``). The node's choice and the offline commands' alike."""
    if transforms is not None and camera_frame:
        T = transforms.lookup(base_frame, camera_frame)
        if T is not None:
            return T, f"/tf_static {base_frame} -> {camera_frame}"
    return np.asarray(fallback, dtype=np.float64).reshape(4, 4), PARAMETERS_EXTRINSICS


def imu_axes(transforms: Any, base_frame: str, imu_frame: str) -> np.ndarray | None:
    """Rotation taking vectors from ``imu_frame`` into ``base_frame``'s axes (``transforms`` as in
    :func:`camera_extrinsics`), None for the same frame, no frame or no such transform (the IMU's
    axes are then taken as the base's)."""
    frame = imu_frame.lstrip("/")
    if transforms is None or not frame or frame == base_frame.lstrip("/"):
        return None
    T = transforms.lookup(base_frame, frame)
    return None if T is None else T[:3, :3].copy()
