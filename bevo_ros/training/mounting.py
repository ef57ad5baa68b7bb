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


def reference_from_speed(seq: Recording, speed_stamps: np.ndarray, speeds: np.ndarray) -> tuple[float, float]:
    """``(distance m, yaw rad)`` over the recording's frames without ground truth: the forward speed
    ``speeds (N,)`` (m/s at ``speed_stamps (N,)`` s: wheel odometry, CAN, GNSS) integrated between the
    first and the last frame, and the gyro's rate about gravity (the stretch's mean accelerometer
    direction) integrated over the same time. The pitch found is as good as the speed's scale: a
    wheel speed 1 % long reads the camera ~0.04 deg more nose-up (KITTI's geometry: ~25 % per deg).
    ValueError when the speed does not cover the frames or the car hardly moves."""
    t0, t1 = (float(v) for v in seq.frame_stamps[[0, -1]])
    t, v = np.asarray(speed_stamps, dtype=np.float64), np.asarray(speeds, dtype=np.float64)
    if len(t) < 2 or t[0] > t0 or t[-1] < t1:
        span = f"{t[0]:.3f}..{t[-1]:.3f} s" if len(t) else "nothing"
        raise ValueError(f"the speed covers {span}, not the calibration frames' {t0:.3f}..{t1:.3f} s")
    distance = _integral(t, v, t0, t1)
    if distance < 1.0:
        raise ValueError(f"the speed gives {distance:.2f} m over the calibration frames: drive forward a few "
                         "metres or more")
    ti = seq.imu_stamps.double().numpy()
    keep = (ti >= t0 - 0.5) & (ti <= t1 + 0.5)
    if keep.sum() < 2:
        raise ValueError("no IMU samples over the calibration frames (the yaw reference)")
    accel = seq.accel.double().numpy()[keep]
    up = accel.mean(axis=0) / np.linalg.norm(accel.mean(axis=0))
    rate = seq.gyro.double().numpy()[keep] @ up
    return distance, _integral(ti[keep], rate, t0, t1)


def calibrate(seq: Recording, spec: BevSpec, roll0: float = 0.0, dpc: DpcConfig | None = None,
              reference: tuple[float, float] | None = None) -> tuple[float, float]:
    """``(pitch, roll)`` in radians: pitch first (at ``roll0``), then roll at that pitch. Where several
    attitudes match the reference ``(distance m, yaw rad)`` over the frames (default: the ground
    truth's, :func:`reference_from_ground_truth`), the one whose BEVs correlate best (the sharpest
    peaks) wins."""
    dist, yaw = reference if reference is not None else reference_from_ground_truth(seq)
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
