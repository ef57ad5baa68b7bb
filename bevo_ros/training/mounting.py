"""Mounting calibration: the rig's static pitch/roll on the road (filter.mounting_pitch /
mounting_roll) from a calibration drive with ground truth (``bevo calibrate``).

pitch: bisection until the distance travelled in the BEV matches the ground truth;
roll:  bisection until the summed BEV yaw matches the ground truth's (a roll error shears the BEV).
Both use a constant attitude (no filter), so the result is the rig's, not the road's.
"""
from __future__ import annotations

import math

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
        raise ValueError(f"no attitude in [{math.degrees(lo):.1f}, {math.degrees(hi):.1f}] deg matches the ground truth")
    return roots


def calibrate(seq: Recording, spec: BevSpec, roll0: float = 0.0, dpc: DpcConfig | None = None) -> tuple[float, float]:
    """``(pitch, roll)`` in radians: pitch first (at ``roll0``), then roll at that pitch. Where several
    attitudes match the ground truth, the one whose BEVs correlate best (the sharpest peaks) wins."""
    gt = seq.gt_motion()
    dist, yaw = float(gt[:, 0].sum()), float(gt[:, 2].sum())
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
