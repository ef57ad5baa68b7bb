"""Mounting calibration: the rig's static pitch/roll on the road (filter.mounting_pitch /
mounting_roll) from a calibration drive (``bevo calibrate``).

pitch: bisection until the distance travelled in the BEV matches the reference's;
roll:  bisection until the summed BEV yaw matches the reference's (a roll error shears the BEV).
Both use a constant attitude (no filter), so the result is the rig's, not the road's. The
reference is the ground truth (:func:`reference_from_ground_truth`), or, for a car without one, its
own speed (wheel odometry, CAN, GNSS) with the yaw from the gyro (:func:`reference_from_speed`).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from bevo_ros.core.geometry import BevSpec
from bevo_ros.core.motion import vehicle_motion_from_registration
from bevo_ros.core.phase_correlation import DpcConfig
from bevo_ros.core.sequence import project_frames, register_consecutive
from bevo_ros.datasets.rosbag import Recording


def constant_attitude_motion(seq: Recording, spec: BevSpec, pitch: float, roll: float,
                             dpc: DpcConfig | None = None) -> tuple[torch.Tensor, float]:
    """``(F-1, 3)`` BEV motion with a constant road-relative attitude, and the mean peak quality
    (``dpc``: the settings' phase correlation, the engine's defaults when None)."""
    pr = torch.tensor([[pitch, roll]], dtype=torch.float32).repeat(len(seq), 1)
    with torch.no_grad():
        bev, mask = project_frames(seq.images, seq.camera.to(dtype=torch.float32), pr, spec)
        reg = register_consecutive(bev, mask, dpc or DpcConfig())
        motion = vehicle_motion_from_registration(reg.angle.double(), reg.shift.double(), spec)
        return motion, float(reg.quality.mean())


def find_roots(f, lo: float, hi: float, steps: int = 12, iters: int = 12) -> list[float]:
    """Every root of ``f`` on [lo, hi]: a coarse scan brackets sign changes, bisection refines.

    Far from the truth the BEV decorrelates and ``f`` stops being monotonic, hence the scan.
    """
    grid = [lo + (hi - lo) * i / steps for i in range(steps + 1)]
    values = [f(x) for x in grid]
    roots = []
    for a, b, fa, fb in zip(grid, grid[1:], values, values[1:]):
        if (fa > 0) == (fb > 0):
            continue
        for _ in range(iters):
            mid = 0.5 * (a + b)
            fm = f(mid)
            if (fm > 0) == (fa > 0):
                a, fa = mid, fm
            else:
                b = mid
        roots.append(0.5 * (a + b))
    if not roots:
        raise ValueError(f"no attitude in [{math.degrees(lo):.1f}, {math.degrees(hi):.1f}] deg matches the reference")
    return roots


def reference_from_ground_truth(seq: Recording) -> tuple[float, float]:
    """``(distance m, yaw rad)`` over the recording's frames from its ground truth: the sums of the
    per-frame forward motion and yaw."""
    gt = seq.gt_motion()
    return float(gt[:, 0].sum()), float(gt[:, 2].sum())


def _integral(t: np.ndarray, v: np.ndarray, t0: float, t1: float) -> float:
    """``v(t)`` (samples, linear between them) integrated over ``[t0, t1]``."""
    inside = (t > t0) & (t < t1)
    ts = np.concatenate([[t0], t[inside], [t1]])
    vs = np.interp(ts, t, v)
    return float(np.sum(0.5 * (vs[1:] + vs[:-1]) * np.diff(ts)))


def _check_sampling(t: np.ndarray, t0: float, t1: float, what: str, max_gap: float) -> None:
    """ValueError unless the samples ``t`` cover ``[t0, t1]`` with no gap longer than ``max_gap`` s."""
    if len(t) < 2 or t[0] > t0 + 1e-9 or t[-1] < t1 - 1e-9:
        span = f"{t[0]:.3f}..{t[-1]:.3f} s" if len(t) else "nothing"
        unset = " (header stamps unset?)" if len(t) and t[-1] < 1.0 else ""
        raise ValueError(f"{what} covers {span}{unset}, not the calibration frames' {t0:.3f}..{t1:.3f} s")
    lo, hi = np.searchsorted(t, t0, side="right") - 1, np.searchsorted(t, t1, side="left")
    gaps = np.diff(t[lo:hi + 1])
    if gaps.size and gaps.max() > max_gap:
        k = int(np.argmax(gaps))
        raise ValueError(f"{what} has a gap of {gaps[k]:.2f} s at {t[lo + k]:.3f} s within the calibration frames "
                         f"(at most {max_gap:g} s)")


class SpeedReference(NamedTuple):
    """:func:`reference_from_speed`'s result: the reference and how the yaw was taken."""

    distance: float  # m
    yaw: float  # rad
    gyro_bias: float  # rad/s about gravity, taken off (0 without a rest)
    rest_seconds: float  # the rest the bias was read over


SPEED_MAX_GAP = 1.5  # s between speed samples (a 1 Hz GNSS speed passes; a steady stretch is linear enough)
IMU_MAX_GAP = 0.5  # s between IMU samples
REST_SPEED = 0.05  # m/s: the car is at rest, the gyro reads its bias
REST_MIN = 1.0  # s of rest before the bias is taken
REVERSAL_RATIO = 0.9  # net distance / distance travelled below which the stretch drove both ways


def reference_from_speed(seq: Recording, speed_stamps: np.ndarray, speeds: np.ndarray) -> SpeedReference:
    """``(distance m, yaw rad, ...)`` over the recording's frames without ground truth: the speed
    ``speeds (N,)`` (m/s at ``speed_stamps (N,)`` s: wheel odometry, CAN, GNSS; signed, or unsigned on a drive forward) integrated
    between the first and the last frame, and the gyro's rate about gravity (the stretch's mean
    accelerometer direction) integrated over the same time, less its bias read where the speed says the
    car stood (at least REST_MIN s anywhere in the recording before the last frame: start the recording at
    rest; a bias b left in reads as a roll error of ~b / (0.3 v)). The pitch found is as good as the
    speed's scale: a wheel speed 1 % long reads the camera ~0.04 deg less nose-down (KITTI's geometry).
    ValueError when the speed or the IMU does not cover the frames, the car hardly moves or changes
    direction, or the accelerometer does not read gravity."""
    t0, t1 = (float(v) for v in seq.frame_stamps[[0, -1]])
    t, v = np.asarray(speed_stamps, dtype=np.float64), np.asarray(speeds, dtype=np.float64)
    _check_sampling(t, t0, t1, "the speed", SPEED_MAX_GAP)
    distance = _integral(t, v, t0, t1)  # signed (a speed in base_frame): a stretch in reverse counts back
    travelled = _integral(t, np.abs(v), t0, t1)
    if travelled < 1.0:
        raise ValueError(f"the speed gives {travelled:.2f} m over the calibration frames: drive a few metres or "
                         "more")
    if abs(distance) < REVERSAL_RATIO * travelled:  # forth and back: the BEV's errors add over the whole path
        raise ValueError(f"the speed changes direction over the calibration frames ({distance:+.2f} m net of "
                         f"{travelled:.2f} m travelled): choose frames driving one way")
    ti = seq.imu_stamps.double().numpy()
    gyro, accel = seq.gyro.double().numpy(), seq.accel.double().numpy()
    _check_sampling(ti, t0, t1, "the IMU", IMU_MAX_GAP)
    stretch = (ti >= t0) & (ti <= t1)
    g = np.linalg.norm(accel[stretch].mean(axis=0))
    if not 7.0 < g < 12.5:
        raise ValueError(f"the accelerometer's mean over the calibration frames is {g:.2f} m/s^2, not gravity "
                         "(the IMU topic must carry the specific force, gravity included)")
    up = accel[stretch].mean(axis=0) / g
    rate = gyro @ up
    covered = (ti >= t[0]) & (ti <= t[-1])
    rest = covered & (np.abs(np.interp(ti, t, v)) < REST_SPEED) & (ti <= t1)
    dt = np.diff(ti, prepend=ti[0])
    rest_seconds = float(dt[rest].sum())
    bias = float(rate[rest].mean()) if rest_seconds >= REST_MIN else 0.0
    return SpeedReference(distance, _integral(ti, rate - bias, t0, t1), bias, rest_seconds if bias else 0.0)


def calibrate(seq: Recording, spec: BevSpec, roll0: float = 0.0, dpc: DpcConfig | None = None,
              reference: tuple[float, float] | None = None) -> tuple[float, float]:
    """``(pitch, roll)`` in radians: pitch first (at ``roll0``), then roll at that pitch. Where several
    attitudes match the reference ``(distance m, yaw rad)`` over the frames (default: the ground
    truth's, :func:`reference_from_ground_truth`), the one whose BEVs correlate best (the sharpest
    peaks) wins."""
    dist, yaw = (reference if reference is not None else reference_from_ground_truth(seq))[:2]
    span = math.radians(3)
    def solve(f, name: str, context: str) -> list[float]:
        try:
            return find_roots(f, -span, span)
        except ValueError as exc:  # the attitude is held constant: over bumps or in a bend no one attitude fits
            raise ValueError(f"{name}: {exc} ({context}); use a straight, smooth stretch of a few seconds at a "
                             "steady speed (--frames)") from None

    pitches = solve(lambda p: float(constant_attitude_motion(seq, spec, p, roll0, dpc)[0][:, 0].sum()) - dist,
                    "pitch", f"distance {dist:.1f} m")
    pitch = max(pitches, key=lambda p: constant_attitude_motion(seq, spec, p, roll0, dpc)[1])
    rolls = solve(lambda r: float(constant_attitude_motion(seq, spec, pitch, r, dpc)[0][:, 2].sum()) - yaw,
                  "roll", f"yaw {math.degrees(yaw):+.1f} deg")
    roll = max(rolls, key=lambda r: constant_attitude_motion(seq, spec, pitch, r, dpc)[1])
    return pitch, roll
