#!/usr/bin/env python3
"""Calibrate the rig's static attitude on the road (filter.mounting_pitch / mounting_roll).

The BEV's metric scale hangs on the camera's pitch relative to the road (~25 % per degree at
KITTI's geometry) and a roll error biases every yaw estimate. The road-tilt low-pass removes
every constant from the filtered attitude, so the static tilt of the IMU/camera rig on the road
is a calibration, like the camera height. This tool measures it on a short stretch of a bag with
ground truth (a "calibration drive"):

  pitch: bisection until the distance travelled in the BEV matches the ground truth;
  roll:  bisection until the summed BEV yaw matches the ground truth's (a roll error shears the BEV).

Both use a constant attitude (no filter), so the result is the rig's, not the road's.
Prints the two YAML lines for params/*.yaml.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

try:
    import bevo_ros  # noqa: F401
except ImportError:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch

from bevo_ros.config import REPO_ROOT, ConfigError, bev_spec, load_config
from bevo_ros.core.geometry import BevSpec
from bevo_ros.core.phase_correlation import DpcConfig
from bevo_ros.core.sequence import register_consecutive, project_frames
from bevo_ros.core.motion import vehicle_motion_from_registration
from bevo_ros.datasets import Recording, load_sequence


def constant_attitude_motion(seq: Recording, spec: BevSpec, pitch: float, roll: float) -> tuple[torch.Tensor, float]:
    """``(F-1, 3)`` BEV motion with a constant road-relative attitude, and the mean peak quality."""
    pr = torch.tensor([[pitch, roll]], dtype=torch.float32).repeat(len(seq), 1)
    with torch.no_grad():
        bev, mask = project_frames(seq.images, seq.camera.to(dtype=torch.float32), pr, spec)
        reg = register_consecutive(bev, mask, DpcConfig())
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


def calibrate(seq: Recording, spec: BevSpec, roll0: float = 0.0) -> tuple[float, float]:
    """``(pitch, roll)`` in radians: pitch first (at ``roll0``), then roll at that pitch. Where several
    attitudes match the ground truth, the one whose BEVs correlate best (the sharpest peaks) wins."""
    gt = seq.gt_motion()
    dist, yaw = float(gt[:, 0].sum()), float(gt[:, 2].sum())
    span = math.radians(3)
    pitches = find_roots(lambda p: float(constant_attitude_motion(seq, spec, p, roll0)[0][:, 0].sum()) - dist,
                         -span, span)
    pitch = max(pitches, key=lambda p: constant_attitude_motion(seq, spec, p, roll0)[1])
    rolls = find_roots(lambda r: float(constant_attitude_motion(seq, spec, pitch, r)[0][:, 2].sum()) - yaw,
                       -span, span)
    roll = max(rolls, key=lambda r: constant_attitude_motion(seq, spec, pitch, r)[1])
    return pitch, roll


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", help="rosbag2 with images, IMU, CameraInfo and /ground_truth/odometry")
    p.add_argument("--params", default=str(REPO_ROOT / "params" / "kitti.yaml"), help="parameters file")
    p.add_argument("--frames", default="0:11", help="frame range START:STOP of the calibration drive (default 0:11)")
    args = p.parse_args(argv)
    try:
        config, _ = load_config(args.params)
        seq = load_sequence(args.bag, config)
        start, stop = (int(v) for v in args.frames.split(":"))
        if not 0 <= start < stop - 1 < len(seq):
            raise ValueError(f"--frames {args.frames}: need at least 2 frames within 0..{len(seq)}")
        seq = seq.frames(start, stop)
    except (ConfigError, ValueError, FileNotFoundError) as exc:
        print(f"calibrate_mounting: error: {exc}", file=sys.stderr)
        return 2
    spec = bev_spec(config)
    try:
        pitch, roll = calibrate(seq, spec)
    except ValueError as exc:
        print(f"calibrate_mounting: error: {exc}", file=sys.stderr)
        return 1
    print(f"calibrated on frames {args.frames} ({float(seq.gt_motion()[:, 0].sum()):.1f} m):")
    print(f"    filter.mounting_pitch: {pitch:.4f}   # {math.degrees(pitch):+.2f} deg, nose down")
    print(f"    filter.mounting_roll: {roll:.4f}    # {math.degrees(roll):+.2f} deg, left side up")
    return 0


if __name__ == "__main__":
    sys.exit(main())
