#!/usr/bin/env python3
"""Evaluate an estimated trajectory against KITTI ground truth.

Both files are in the KITTI odometry format: one pose per line, the 3x4 matrix [R | t] row-major
(12 numbers), camera-0 poses T_world_cam. Reports the official KITTI metric (t_rel in %, r_rel in
deg/100 m over 100..800 m segments), per-frame RPE, ATE after rigid SE(3) alignment, and the
endpoint drift in % of the path length (the only honest number below 100 m of path, where
KITTI's t_rel does not exist).

Writes into --out: summary.md, metrics.json, trajectory.png, frame_errors.png and, with
--pitch-roll, pitch_roll.png (all written atomically).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

try:
    import bevo_ros  # noqa: F401
except ImportError:  # running from a source checkout without installing
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bevo_ros import evaluation, kitti

EPILOG = """\
The ground truth may be longer than the estimate (e.g. the full poses/06.txt for a run over its
first frames): frames --first .. --first + len(est) - 1 of it are used.
--pitch-roll takes a CSV with a header naming stamp, pitch, roll, oxts_pitch, oxts_roll (radians).

example:
  evaluate.py --gt ../shared/data/kitti/odometry/poses/06.txt --est out/06.txt --out out/eval06
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--gt", required=True, help="ground-truth poses (KITTI format)")
    p.add_argument("--est", required=True, help="estimated poses (KITTI format)")
    p.add_argument("--out", required=True, help="output directory (created if needed)")
    p.add_argument("--pitch-roll", metavar="CSV", help="filtered vs OXTS pitch/roll CSV to plot and score")
    p.add_argument("--first", type=int, default=0, help="ground-truth frame of the first estimated pose (default 0)")
    p.add_argument("--convention", choices=evaluation.CONVENTIONS, default="camera",
                   help="pose frame: camera (KITTI camera-0, default) or base (z up)")
    p.add_argument("--title", default="", help="title of the summary and plots")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        gt = kitti.read_poses(args.gt)
        est = kitti.read_poses(args.est)
        if args.first < 0 or args.first + len(est) > len(gt):
            raise ValueError(f"{args.est}: {len(est)} poses from GT frame {args.first} need "
                             f"{args.first + len(est)} GT poses, {args.gt} has {len(gt)}")
        if len(gt) != len(est) or args.first:
            print(f"note: using GT frames {args.first}..{args.first + len(est) - 1} of {len(gt)}", file=sys.stderr)
        gt = gt[args.first: args.first + len(est)]
        pr = evaluation.read_pitch_roll_csv(args.pitch_roll) if args.pitch_roll else None
        metrics = evaluation.evaluate_trajectories(gt, est, args.convention)
        if pr is not None:
            metrics.pitch_roll = evaluation.pitch_roll_errors(pr)
        title = args.title or f"{Path(args.est).name} vs {Path(args.gt).name}"
        paths = evaluation.write_report(args.out, gt, est, metrics, pr, title)
    except (FileNotFoundError, ValueError) as exc:
        print(f"evaluate: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("evaluate: interrupted", file=sys.stderr)
        return 130
    for line in metrics.summary_lines():
        print(line)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
