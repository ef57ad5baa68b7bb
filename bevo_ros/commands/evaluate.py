"""``bevo evaluate``: an estimated trajectory against KITTI ground truth.

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

from bevo_ros.commands import guarded, new_parser
from bevo_ros.evaluation.metrics import CONVENTIONS
from bevo_ros.pipeline import evaluate_files

EPILOG = """\
The ground truth may be longer than the estimate (e.g. the full poses/06.txt for a run over its
first frames): frames --first .. --first + len(est) - 1 of it are used.
--pitch-roll takes a CSV with a header naming stamp, pitch, roll, oxts_pitch, oxts_roll (radians).

example:
  bevo evaluate --gt ../shared/data/kitti/odometry/poses/06.txt --est out/06.txt --out out/eval06
"""


def build_parser() -> argparse.ArgumentParser:
    p = new_parser(__doc__, EPILOG)
    p.add_argument("--gt", required=True, help="ground-truth poses (KITTI format)")
    p.add_argument("--est", required=True, help="estimated poses (KITTI format)")
    p.add_argument("--out", required=True, help="output directory (created if needed)")
    p.add_argument("--pitch-roll", metavar="CSV", help="filtered vs reference (OXTS) pitch/roll CSV to plot and score")
    p.add_argument("--first", type=int, default=0, help="ground-truth frame of the first estimated pose (default 0)")
    p.add_argument("--convention", choices=CONVENTIONS, default="camera",
                   help="pose frame: camera (KITTI camera-0, default) or base (z up)")
    p.add_argument("--title", default="", help="title of the summary and plots")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return guarded("evaluate", lambda: _evaluate(args), (FileNotFoundError, ValueError))


def _evaluate(args: argparse.Namespace) -> int:
    metrics, paths = evaluate_files(args.gt, args.est, args.out, args.pitch_roll, args.first, args.convention,
                                    args.title)
    for line in metrics.summary_lines():
        print(line)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0
