"""Rotations in numpy and floats, for messages, bags, datasets and synthetic drives: the one place.

Conventions (REP-103): quaternions in ROS's order ``(x, y, z, w)``; roll, pitch, yaw as
``R = Rz(yaw) Ry(pitch) Rx(roll)`` (SciPy's intrinsic ``"ZYX"``). Closed forms, not SciPy's
:class:`~scipy.spatial.transform.Rotation` (the tests' reference): they run per message in the nodes
(SciPy's ``from_euler`` takes ~0.1 ms a call, the closed form ~1 us) and per sample in the synthetic
drives, which must stay bit for bit what they were. The engine's differentiable tensor forms are
:mod:`bevo_ros.core.geometry`'s (``rotation_from_rpy``, ...).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation ``(3, 3)`` -> unit quaternion ``(4,)`` ``(x, y, z, w)`` with ``w >= 0`` (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def matrix_from_quaternion(q: Sequence[float]) -> np.ndarray:
    """Quaternion ``(x, y, z, w)`` (normalised here) -> rotation ``(3, 3)``. ValueError for a zero or
    non-finite one (no rotation)."""
    q = np.asarray(q, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not (math.isfinite(norm) and norm > 1e-9):
        raise ValueError(f"quaternion {tuple(q.tolist())} is no rotation (zero or not finite)")
    x, y, z, w = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` -> ``(x, y, z, w)``."""
    cr, sr = math.cos(roll * 0.5), math.sin(roll * 0.5)
    cp, sp = math.cos(pitch * 0.5), math.sin(pitch * 0.5)
    cy, sy = math.cos(yaw * 0.5), math.sin(yaw * 0.5)
    return (sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def rpy_from_matrix(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of ``Rz(yaw) Ry(pitch) Rx(roll)`` ``(3, 3)`` -> ``(roll, pitch, yaw)``, pitch in [-pi/2, pi/2]."""
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    return math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])


def rpy_from_quaternion(x: float, y: float, z: float, w: float) -> tuple[float, float, float]:
    """Inverse of :func:`quaternion_from_rpy` (a unit quaternion)."""
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


# ------------------------------------------------------------------ vectorised, written out
def rotation_x(angle: np.ndarray) -> np.ndarray:
    """Rotations about x. ``(...,)`` -> ``(..., 3, 3)``."""
    c, s, o, z = np.cos(angle), np.sin(angle), np.ones_like(angle), np.zeros_like(angle)
    return np.stack([o, z, z, z, c, -s, z, s, c], -1).reshape(*np.shape(angle), 3, 3)


def rotation_y(angle: np.ndarray) -> np.ndarray:
    """Rotations about y. ``(...,)`` -> ``(..., 3, 3)``."""
    c, s, o, z = np.cos(angle), np.sin(angle), np.ones_like(angle), np.zeros_like(angle)
    return np.stack([c, z, s, z, o, z, -s, z, c], -1).reshape(*np.shape(angle), 3, 3)


def rotation_z(angle: np.ndarray) -> np.ndarray:
    """Rotations about z. ``(...,)`` -> ``(..., 3, 3)``."""
    c, s, o, z = np.cos(angle), np.sin(angle), np.ones_like(angle), np.zeros_like(angle)
    return np.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(*np.shape(angle), 3, 3)


def rpy_from_matrices(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(roll, pitch, yaw)`` of ``Rz Ry Rx`` rotations ``(..., 3, 3)`` -> 3 x ``(...,)``; at pitch +-pi/2
    (gimbal lock) the split of roll and yaw is atan2's, with no warning."""
    return (np.arctan2(R[..., 2, 1], R[..., 2, 2]), np.arcsin(np.clip(-R[..., 2, 0], -1, 1)),
            np.arctan2(R[..., 1, 0], R[..., 0, 0]))


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Axis times angle of rotations ``(..., 3, 3)`` with angles below pi -> ``(..., 3)``."""
    w = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = np.linalg.norm(w, axis=-1)
    angle = np.arctan2(sin, 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0))
    return w * np.where(sin > 1e-12, angle / np.maximum(sin, 1e-300), 1.0)[..., None]


__all__ = ["quaternion_from_matrix", "matrix_from_quaternion", "quaternion_from_rpy", "rpy_from_matrix",
           "rpy_from_quaternion", "rotation_x", "rotation_y", "rotation_z", "rpy_from_matrices", "rotation_vector"]
