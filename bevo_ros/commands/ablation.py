"""``bevo ablation``: the paper's ablation study (Table 3) on rosbag2 recordings: what the DUKF and its learned
noise parameters are worth to the odometry.

Five variants, each run with the engine's own BEV projection and phase correlation:

  w/o O     O set to a textbook value (--empirical-O), the learned Q kept
  w/o Q     the learned O kept, Q set to a textbook value (--empirical-Q)
  w/o DUKF  raw accelerometer pitch/roll (no filter), then the same road-tilt low-pass
  BEVO      the learned O and Q
  w/ GT     the ground-truth road-relative attitude fed to the BEV (--gt-attitude)
  fused     odometry.mode fused (the default engine: acceleration-aware attitude, gyro yaw, motion
            filter with gates), with --fused-learned; the five rows above are the paper's pipeline

Metrics per variant: per-frame relative pose error (mean translation m, mean |yaw| deg), endpoint
drift (% of the path), ATE RMSE (m, after rigid alignment), KITTI t_rel/r_rel when the path is at
least 100 m, the road-relative pitch/roll RMSE against the reference attitude, and the number of
frame pairs whose BEV had no valid pixel (registration impossible: zero motion is used).
Writes OUT/ablation.md (tables + notes), OUT/ablation.json and OUT/<bag>_ablation.png (top view
of every variant's trajectory, and the road pitch/roll each fed to the BEV).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from bevo_ros.commands import (DEFAULT_PARAMS, add_threads_option, bag_errors, guarded, new_parser, prog_name,
                               set_threads)
from bevo_ros.config import package_file
# make_synthetic_bag and reference_attitude are re-exported: tests reach them through the command module.
from bevo_ros.training.ablation import (EMPIRICAL_O, EMPIRICAL_Q, GT_MODES, AblationOptions,  # noqa: F401
                                        make_synthetic_bag, reference_attitude, run_ablation)

EPILOG = """\
reference attitude for "w/ GT" (--gt-attitude):
  imu-highpass  the bag's /ground_truth/imu attitude (KITTI: the OXTS unit's own roll/pitch)
                minus its low-pass with filter.road_tilt_time_constant, plus filter.mounting_*,
                i.e. the very road-tilt separation BEVO applies to the DUKF output, fed a
                near-perfect attitude (default)
  imu           the /ground_truth/imu attitude as is: the exact road-relative attitude on a level
                road (synthetic drives without road tilt); on KITTI it contains slope and camber
  road-poses    roll/pitch of the ground-truth poses, i.e. relative to the FIRST frame's attitude
                (the bags' odom frame is the base at the first frame), plus filter.mounting_*
  zero          a level vehicle on a flat road (filter.mounting_* only)
  (--synthetic drives use the simulator's exact road-relative attitude.)

examples:
  bevo ablation --synthetic 30 --params params/synthetic.yaml --train --out out/ablation_synthetic
  bevo convert --odometry ../shared/data/kitti/odometry --sequence 06 -o seq06_bag
  bevo ablation seq06_bag --train --eval all --out out/ablation_kitti06
  bevo ablation seq06_bag --learned params/learned.yaml --out out/ablation_kitti06
"""


def build_parser() -> argparse.ArgumentParser:
    p = new_parser(__doc__, EPILOG)
    p.add_argument("bags", nargs="*", metavar="BAG", help="rosbag2 directories with ground truth")
    p.add_argument("--out", required=True, help="output directory")
    # default None: --synthetic alone takes the synthetic rig's file (KITTI's mounting on it is another rig)
    p.add_argument("--params", default=None, help="ROS parameters file (default params/kitti.yaml; with --synthetic "
                                                  "and no BAG params/synthetic.yaml, the synthetic drive's rig)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--learned", help="learned-parameters YAML (default: the one named in --params)")
    src.add_argument("--train", action="store_true", help="train O/Q on the bags first (bevo_ros.training.trainer)")
    p.add_argument("--fused-learned", default=str(package_file("params/learned_default.yaml")),
                   help="learned-parameters YAML of the fused row (default params/learned_default.yaml)")
    p.add_argument("--epochs", type=int, default=10, help="with --train: epochs (default 10)")
    p.add_argument("--lr", type=float, default=0.3, help="with --train: Adam learning rate (default 0.3)")
    p.add_argument("--seed", type=int, default=0, help="with --train: seed of the initial O/Q (default 0)")
    p.add_argument("--init", type=float, nargs=4, metavar=("O1", "O2", "Q1", "Q2"), help="with --train: initial O/Q")
    p.add_argument("--split", default="3/4", choices=["3/4", "20%"], help="with --train: train/validation split")
    p.add_argument("--eval", choices=["all", "held-out"], default=None,
                   help="frames evaluated: all, or the split's held-out part (default: held-out with --train, "
                        "else all)")
    p.add_argument("--gt-attitude", choices=GT_MODES, default="imu-highpass", help="reference for w/ GT")
    p.add_argument("--empirical-O", type=float, default=EMPIRICAL_O, help=f"w/o O value, rad^2/s (default {EMPIRICAL_O})")
    p.add_argument("--empirical-Q", type=float, default=EMPIRICAL_Q, help=f"w/o Q value, rad^2 (default {EMPIRICAL_Q})")
    p.add_argument("--synthetic", type=float, metavar="SECONDS",
                   help="also generate a synthetic bumpy drive of this length into OUT/synthetic_bag")
    p.add_argument("--synthetic-seed", type=int, default=3, help="seed of that drive (default 3)")
    p.add_argument("--bumps", type=float, default=2.0, help="its road-relative pitch/roll scale (default 2)")
    p.add_argument("--noise", type=float, default=2.0, help="its IMU noise scale incl. vibration (default 2)")
    p.add_argument("--image-scale", type=float, default=1.0, help="its image size relative to KITTI (default 1)")
    add_threads_option(p)
    p.add_argument("--device", default="cpu", help="cpu or cuda (falls back to CPU)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress output from training")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from bevo_ros.training.trainer import TrainingDiverged

    set_threads(args.threads)
    return guarded("ablation", lambda: _ablation(args), bag_errors(TrainingDiverged))


def _ablation(args: argparse.Namespace) -> int:
    from bevo_ros.config import load_config
    from bevo_ros.datasets.rosbag import RigSettings

    out = Path(args.out)
    t_start = time.perf_counter()
    if not args.bags and args.synthetic is None:
        raise ValueError("give at least one BAG or --synthetic SECONDS")
    if args.params is None:
        args.params = str(package_file("params/synthetic.yaml") if not args.bags else DEFAULT_PARAMS)
    out.mkdir(parents=True, exist_ok=True)
    config, flat = load_config(args.params)
    options = AblationOptions(
        params=args.params, learned=args.learned, train=args.train, fused_learned=args.fused_learned,
        epochs=args.epochs, lr=args.lr, seed=args.seed, init=tuple(args.init) if args.init else None,
        split=args.split, eval=args.eval, gt_attitude=args.gt_attitude, empirical_o=args.empirical_O,
        empirical_q=args.empirical_Q, synthetic=args.synthetic, synthetic_seed=args.synthetic_seed,
        bumps=args.bumps, noise=args.noise, image_scale=args.image_scale, device=args.device, quiet=args.quiet)
    result = run_ablation(args.bags, config, options, out,
                          warn=lambda msg: print(f"{prog_name('ablation')}: warning: {msg}", file=sys.stderr),
                          rig=RigSettings.from_params(flat, str(args.params)))
    print(result.notes)
    print(f"wrote {out / 'ablation.md'}, {out / 'ablation.json'} and the plots in {time.perf_counter() - t_start:.0f} s")
    return 0
