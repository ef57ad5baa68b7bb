"""Plausibility checks of the inputs: pure functions and one small state machine, no ROS.

* :func:`imu_problem`: an IMU sample whose accelerometer or gyro reading no car can produce
  (a corrupted message, a driver bug, a saturated or broken sensor) is refused with the reason,
  so it never reaches the attitude filter.
* :func:`intrinsics_problem`: a camera matrix that cannot describe a real pinhole camera for the
  given image size (``fx = 1e-300``, ``cx = 1e30``) is refused with the reason.
* :class:`TimeJumpGuard`: a stamp far from the stream's timeline is held until further messages
  (or the clock) confirm the jump; a lone outlier is dropped instead of resetting the odometry.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

STANDARD_GRAVITY = 9.80665  # m/s^2


# ------------------------------------------------------------------------------------------ IMU
@dataclass(frozen=True)
class ImuLimits:
    """Largest readings an IMU on a car can give (beyond them the sample is corrupt).

    max_acceleration: bound on the specific-force norm, m/s^2. Default 8 g: driving gives < 2 g,
        road shocks on a stiff mount a few g, automotive MEMS ranges are +-8 g or +-16 g.
    max_angular_rate: bound on each gyro axis, rad/s. Default 35 rad/s (~2000 deg/s, the
        largest range of common MEMS gyros; a car turns at < 1 rad/s).
    """

    max_acceleration: float = 8.0 * STANDARD_GRAVITY
    max_angular_rate: float = 35.0


class ImplausibleImuError(ValueError):
    """An IMU sample outside :class:`ImuLimits`; ``reason`` is the drop-counter key."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


def imu_problem(gyro: Sequence[float], accel: Sequence[float], limits: ImuLimits) -> tuple[str, str] | None:
    """``(reason, message)`` when a finite sample ``gyro (3,)`` rad/s, ``accel (3,)`` m/s^2 is
    outside ``limits``, else None."""
    a = math.sqrt(sum(float(v) * float(v) for v in accel))
    if not a <= limits.max_acceleration:  # "not <=": an overflow to inf is refused too
        return ("imu_accel_range", f"|linear_acceleration| = {a:.4g} m/s^2 ({a / STANDARD_GRAVITY:.3g} g) exceeds "
                                   f"filter.max_acceleration = {limits.max_acceleration:.4g} m/s^2")
    w = max(abs(float(v)) for v in gyro)
    if not w <= limits.max_angular_rate:
        return ("imu_gyro_range", f"|angular_velocity| = {w:.4g} rad/s ({math.degrees(w):.4g} deg/s) on one axis "
                                  f"exceeds filter.max_angular_rate = {limits.max_angular_rate:.4g} rad/s")
    return None


# ------------------------------------------------------------------------------------------ camera
# A rectified pinhole image's horizontal field of view between ~2.9 deg (fx = 20 W) and ~168 deg
# (fx = 0.05 W); square-ish pixels; the principal point inside the image.
FX_PER_WIDTH = (0.05, 20.0)
PIXEL_ASPECT = (0.5, 2.0)
MAX_IMAGE_SIDE = 100_000


def intrinsics_problem(K: Any, width: int, height: int) -> str | None:
    """Why the camera matrix ``K (3, 3)`` cannot be a real camera for a ``width x height``
    image, or None when it is plausible (see the module constants for the limits)."""
    try:
        k = [[float(K[r][c]) for c in range(3)] for r in range(3)]
    except (TypeError, ValueError, IndexError):
        return "the camera matrix is not 3x3 numbers"
    w, h = int(width), int(height)
    if not (0 < w <= MAX_IMAGE_SIDE and 0 < h <= MAX_IMAGE_SIDE):
        return f"image size {w}x{h} is not plausible"
    if not all(math.isfinite(v) for row in k for v in row):
        return "the camera matrix has NaN/inf"
    fx, fy, cx, cy = k[0][0], k[1][1], k[0][2], k[1][2]
    if abs(k[1][0]) > 1e-9 or abs(k[2][0]) > 1e-9 or abs(k[2][1]) > 1e-9 or abs(k[2][2] - 1.0) > 1e-9:
        return f"the camera matrix is not [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (rows 2-3: {k[1]}, {k[2]})"
    lo, hi = FX_PER_WIDTH
    if not lo * w <= fx <= hi * w:
        return f"fx = {fx:.6g} px is not within [{lo:g}, {hi:g}] x the width {w} px"
    if not PIXEL_ASPECT[0] <= fy / fx <= PIXEL_ASPECT[1]:
        return f"fy / fx = {fy:.6g} / {fx:.6g} is not within [{PIXEL_ASPECT[0]:g}, {PIXEL_ASPECT[1]:g}]"
    if abs(k[0][1]) > 0.1 * fx:
        return f"skew {k[0][1]:.6g} is more than 0.1 fx"
    if not (0.0 <= cx <= w and 0.0 <= cy <= h):
        return f"principal point ({cx:.6g}, {cy:.6g}) is outside the {w}x{h} image"
    return None


# ------------------------------------------------------------------------------------------ stamps
@dataclass
class StampVerdict:
    """What to do with one message (see :meth:`TimeJumpGuard.check`).

    accept: process the message now.
    outliers: held items found to be lone outliers: drop them (count them).
    jump: ``"back"`` or ``"forward"`` when a time jump was confirmed by this message; then
        ``release`` holds every item of the new timeline, this one included, in arrival order,
        to process now (after a reset for a jump back) and ``accept`` is False.
    """

    accept: bool
    outliers: list = field(default_factory=list)
    jump: str | None = None
    jump_size: float = 0.0
    release: list = field(default_factory=list)


class TimeJumpGuard:
    """Separates lone outlier stamps from real time jumps (a bag restarted, a clock stepped).

    One guard per input stream (streams may lag each other when the consumer is behind). A stamp
    within ``[ref - max_back, ref + max_forward]`` of the timeline ``ref`` (the newest accepted
    stamp of the stream) is accepted. Any other is held: once ``confirmations`` held
    messages agree with each other (each within the same window of the previous), the jump is
    confirmed and they are released; a message back on the old timeline first makes the held
    ones lone outliers (dropped). (With ROS time from /clock, the node's clock-jump handler is
    the other confirmation.)
    Like robot_localization's reset on a time jump, but a single wild stamp resets nothing.
    Nothing is lost on a real jump: the held messages are released, not dropped.

    Args:
        max_back: seconds a stamp may be before the timeline (smaller steps back are for the
            consumer to reorder or drop).
        max_forward: seconds a stamp may be after the timeline.
        confirmations: messages on a new timeline needed to accept it (>= 1; 1 = no guard).
    """

    def __init__(self, max_back: float, max_forward: float, confirmations: int = 3) -> None:
        self.max_back, self.max_forward = float(max_back), float(max_forward)
        self.confirmations = max(1, int(confirmations))
        self.ref: float | None = None
        self.held: list[tuple[float, Any]] = []

    def reset(self) -> list:
        """Forget the timeline (e.g. the ROS clock jumped); returns the held items (dropped)."""
        held = [item for _, item in self.held]
        self.ref, self.held = None, []
        return held

    def rebase(self, ref: float) -> tuple[list, list]:
        """Move to the timeline ``ref`` another stream's guard confirmed (the consumer reset):
        returns ``(release, outliers)``, the held items on it and off it."""
        release = [(t, it) for t, it in self.held if self._near(t, ref)]
        outliers = [it for t, it in self.held if not self._near(t, ref)]
        self.ref, self.held = max([ref] + [t for t, _ in release]), []
        return [it for _, it in release], outliers

    def _near(self, t: float, ref: float) -> bool:
        return ref - self.max_back <= t <= ref + self.max_forward

    def check(self, t: float, item: Any = None) -> StampVerdict:
        """Classify the message stamped ``t`` (``item`` is returned in outliers/release)."""
        if self.ref is None or self._near(t, self.ref):
            outliers = [it for _, it in self.held]
            self.held = []
            self.ref = t if self.ref is None else max(self.ref, t)
            return StampVerdict(True, outliers)
        outliers = []
        if self.held and not self._near(t, self.held[-1][0]):
            outliers = [it for _, it in self.held]  # a different wild stamp: the earlier ones were lone
            self.held = []
        self.held.append((t, item))
        if len(self.held) < self.confirmations:
            return StampVerdict(False, outliers)
        first = self.held[0][0]
        jump = "back" if first < self.ref else "forward"
        size = abs(first - self.ref)
        release = [it for _, it in self.held]
        self.ref, self.held = max(s for s, _ in self.held), []
        return StampVerdict(False, outliers, jump, size, release)


__all__ = ["ImuLimits", "ImplausibleImuError", "imu_problem", "intrinsics_problem", "STANDARD_GRAVITY",
           "StampVerdict", "TimeJumpGuard"]
