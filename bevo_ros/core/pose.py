"""SE(2) odometry composition and 6-DoF pose matrices (z held constant)."""
from __future__ import annotations

import math

import numpy as np
import torch

from .geometry import rotation_from_rpy, wrap_angle

Tensor = torch.Tensor


def compose_se2(pose: Tensor, motion: Tensor) -> Tensor:
    """Apply a body-frame increment. ``pose (..., 3)`` x, y, yaw; ``motion (..., 3)`` dx, dy, dyaw."""
    x, y, yaw = pose.unbind(-1)
    dx, dy, dyaw = motion.unbind(-1)
    c, s = torch.cos(yaw), torch.sin(yaw)
    return torch.stack([x + c * dx - s * dy, y + s * dx + c * dy, wrap_angle(yaw + dyaw)], dim=-1)


def integrate_motions(motions: Tensor, start: Tensor | None = None) -> Tensor:
    """Chain increments ``(T, 3)`` into poses ``(T + 1, 3)`` starting at ``start`` (identity)."""
    pose = torch.zeros(3, dtype=motions.dtype, device=motions.device) if start is None else start
    poses = [pose]
    for m in motions:
        pose = compose_se2(pose, m)
        poses.append(pose)
    return torch.stack(poses)


def propagate_covariance_se2(pose: Tensor, cov: Tensor, motion: Tensor, motion_cov: Tensor) -> Tensor:
    """First-order covariance of ``compose_se2(pose, motion)``. ``(3,)``, ``(3, 3)`` -> ``(3, 3)``."""
    yaw = pose[..., 2]
    dx, dy = motion[..., 0], motion[..., 1]
    c, s = torch.cos(yaw), torch.sin(yaw)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    j_pose = torch.stack([one, zero, -s * dx - c * dy, zero, one, c * dx - s * dy, zero, zero, one], -1)
    j_motion = torch.stack([c, -s, zero, s, c, zero, zero, zero, one], -1)
    j_pose = j_pose.reshape(*yaw.shape, 3, 3)
    j_motion = j_motion.reshape(*yaw.shape, 3, 3)
    out = j_pose @ cov @ j_pose.transpose(-1, -2) + j_motion @ motion_cov @ j_motion.transpose(-1, -2)
    return 0.5 * (out + out.transpose(-1, -2))


def compose_se2_floats(pose: tuple[float, float, float], motion) -> tuple[float, float, float]:
    """:func:`compose_se2` on plain floats (the engine's per-frame pose: ~30 tensor operations on
    3 numbers are most of its cost); equal to float64 rounding."""
    x, y, yaw = pose
    dx, dy, dyaw = (float(v) for v in motion)
    c, s = math.cos(yaw), math.sin(yaw)
    return x + c * dx - s * dy, y + s * dx + c * dy, (yaw + dyaw + math.pi) % (2 * math.pi) - math.pi


def propagate_covariance_se2_floats(yaw: float, cov: np.ndarray, motion, motion_cov: np.ndarray) -> np.ndarray:
    """:func:`propagate_covariance_se2` for one pose in float64 numpy: the pose's ``yaw``, ``(3, 3)``
    covariance, ``(3,)`` motion and its ``(3, 3)`` covariance -> ``(3, 3)``."""
    dx, dy = float(motion[0]), float(motion[1])
    c, s = math.cos(yaw), math.sin(yaw)
    j_pose = np.array([[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]])
    j_motion = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = j_pose @ cov @ j_pose.T + j_motion @ motion_cov @ j_motion.T
    return 0.5 * (out + out.T)


def pose_matrix(position: Tensor, rpy: Tensor) -> Tensor:
    """``(..., 3)`` position and roll/pitch/yaw -> homogeneous ``(..., 4, 4)``."""
    rot = rotation_from_rpy(rpy[..., 0], rpy[..., 1], rpy[..., 2])
    top = torch.cat([rot, position[..., :, None]], dim=-1)
    bottom = torch.zeros(*position.shape[:-1], 1, 4, dtype=position.dtype, device=position.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)
