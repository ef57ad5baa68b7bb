"""The engine's trajectory in the odometry frame: frame motions composed, and a pose set at a stamp.

A pose set from outside (``set_pose``, as robot_localization's) is the vehicle's pose at the
given stamp, which is rarely a frame's: a node receives it while frames before that stamp may still
wait for their IMU, or after frames past it were processed. So the frames' motions of the last
``memory`` frames are kept, and the pose is set where its stamp falls: the frames after it compose
their motions onto it (the motion of the frame interval holding the stamp in proportion to the time
after it), as if the trajectory had started there. A stamp after the latest frame waits for the
frame that reaches it.
"""
from __future__ import annotations

import bisect
import math
from collections import deque

import numpy as np

from .pose import compose_se2_floats, propagate_covariance_se2_floats

__all__ = ["PlanarTrajectory", "check_pose"]


def check_pose(x: float, y: float, yaw: float, z: float, covariance) -> tuple[tuple[float, float, float], float,
                                                                              np.ndarray]:
    """``((x, y, yaw), z, (3, 3) covariance)`` checked: finite, the covariance of ``(x, y, yaw)``
    symmetric positive semi-definite (None: zeros, an exact pose), yaw wrapped to [-pi, pi).
    ValueError otherwise."""
    values = [float(v) for v in (x, y, yaw, z)]
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"pose must be finite, got x {x!r}, y {y!r}, z {z!r}, yaw {yaw!r}")
    cov = np.zeros((3, 3)) if covariance is None else np.array(covariance, dtype=np.float64)
    if cov.shape != (3, 3) or not np.isfinite(cov).all():
        raise ValueError(f"pose covariance must be a finite (3, 3) array of (x, y, yaw), got shape {cov.shape}")
    tol = 1e-9 * max(float(np.abs(cov).max()), 1e-300)
    if np.abs(cov - cov.T).max() > tol or np.linalg.eigvalsh(0.5 * (cov + cov.T)).min() < -tol:
        raise ValueError("pose covariance must be symmetric positive semi-definite")
    x, y, yaw, z = values
    return (x, y, (yaw + math.pi) % (2 * math.pi) - math.pi), z, 0.5 * (cov + cov.T)


class PlanarTrajectory:
    """``(x, y, yaw)`` and its ``(3, 3)`` covariance in the odometry frame, and a constant ``z``.

    Args:
        memory: frames whose motions are kept for a pose set at an earlier stamp.
    """

    def __init__(self, memory: int = 300) -> None:
        if memory < 1:
            raise ValueError(f"memory must be >= 1 frame, got {memory}")
        self._frames: deque[tuple[float, tuple[float, float, float], np.ndarray]] = deque(maxlen=int(memory))
        self.reset()

    def reset(self) -> None:
        """Back to identity, with no frames and no pose waiting."""
        self.pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.cov = np.zeros((3, 3))
        self.z = 0.0
        self._frames.clear()
        self._waiting: tuple[float, tuple[float, float, float], float, np.ndarray] | None = None

    @property
    def waiting(self) -> float | None:
        """The stamp of a set pose that waits for a frame at or after it, None if none waits."""
        return None if self._waiting is None else self._waiting[0]

    def add(self, stamp: float, motion, motion_cov: np.ndarray) -> None:
        """Compose one frame's body-frame motion ``(dx, dy, dyaw)`` (m, rad; zeros for the first
        frame) with its ``(3, 3)`` covariance; then a set pose whose stamp it reaches takes effect."""
        self._compose(motion, motion_cov)
        self._frames.append((float(stamp), tuple(float(v) for v in motion), np.asarray(motion_cov, dtype=np.float64)))
        if self._waiting is not None and self._waiting[0] <= stamp:
            waiting, self._waiting = self._waiting, None
            self._set_at(*waiting)

    def set_pose(self, pose: tuple[float, float, float], z: float, cov: np.ndarray, stamp: float | None = None) -> str:
        """Set the pose (checked by :func:`check_pose`) at ``stamp`` (s; None: at the latest frame,
        or the first one to come). Returns how: ``"latest"``, ``"at stamp"``, ``"waits"`` (after the
        latest frame: set when a frame reaches it), or ``"oldest"`` (before the frames kept: set at the
        oldest of them). A pose set replaces one that waits."""
        self._waiting = None
        if stamp is None:
            self.pose, self.z, self.cov = pose, z, cov
            return "latest"
        if not self._frames or stamp > self._frames[-1][0]:
            self._waiting = (float(stamp), pose, z, cov)
            return "waits"
        return self._set_at(float(stamp), pose, z, cov)

    def _compose(self, motion, motion_cov: np.ndarray) -> None:
        self.cov = propagate_covariance_se2_floats(self.pose[2], self.cov, motion, motion_cov)
        self.pose = compose_se2_floats(self.pose, motion)

    def _set_at(self, stamp: float, pose: tuple[float, float, float], z: float, cov: np.ndarray) -> str:
        frames = list(self._frames)
        k = bisect.bisect_right([f[0] for f in frames], stamp)  # frames k.. are after the stamp
        self.pose, self.z, self.cov = pose, z, cov
        if k == 0:  # its motion into the oldest kept frame is unknown: set at that frame
            for _, motion, motion_cov in frames[1:]:
                self._compose(motion, motion_cov)
            return "oldest"
        if k < len(frames):
            # the part of frame k's interval after the stamp (its motion as if at a constant rate)
            t0, (t1, motion, motion_cov) = frames[k - 1][0], frames[k]
            share = (t1 - stamp) / (t1 - t0) if t1 > t0 else 1.0
            self._compose([share * m for m in motion], share * motion_cov)
            for _, motion, motion_cov in frames[k + 1:]:
                self._compose(motion, motion_cov)
        return "at stamp"
