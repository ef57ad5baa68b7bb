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
import json
import sys
import time
from pathlib import Path


import numpy as np

from bevo_ros.commands import add_threads_option, set_threads
from bevo_ros.config import REPO_ROOT, ConfigError
from bevo_ros.io.files import atomic_write_text
from bevo_ros.training.ablation import (EMPIRICAL_O, EMPIRICAL_Q, GT_MODES, make_synthetic_bag, notes, plot_bag,
                                        reference_attitude, run_variants, table_markdown)

DEFAULT_PARAMS = REPO_ROOT / "params" / "kitti.yaml"

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
    p = argparse.ArgumentParser(description=__doc__, epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="*", metavar="BAG", help="rosbag2 directories with ground truth")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--params", default=str(DEFAULT_PARAMS), help="ROS parameters file (default params/kitti.yaml)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--learned", help="learned-parameters YAML (default: the one named in --params)")
    src.add_argument("--train", action="store_true", help="train O/Q on the bags first (bevo_ros.training.trainer)")
    p.add_argument("--fused-learned", default=str(REPO_ROOT / "params" / "learned_default.yaml"),
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
    from bevo_ros.config import load_config
    from bevo_ros.datasets.rosbag import load_sequence, split_frames
    from bevo_ros.io import bag
    from bevo_ros.io.learned_params import load_learned_params, save_learned_params
    from bevo_ros.training.trainer import TrainingDiverged, TrainOptions, resolve_device, train

    set_threads(args.threads)
    out = Path(args.out)
    t_start = time.perf_counter()
    try:
        if not args.bags and args.synthetic is None:
            raise ValueError("give at least one BAG or --synthetic SECONDS")
        out.mkdir(parents=True, exist_ok=True)
        config, _ = load_config(args.params)
        device = resolve_device(args.device, print)
        bag_paths = [Path(b) for b in args.bags]
        gt_modes = {}
        if args.synthetic is not None:
            t0 = time.perf_counter()
            syn, drive = make_synthetic_bag(out / "synthetic_bag", args.synthetic, args.synthetic_seed, args.bumps,
                                            args.noise, args.image_scale)
            print(f"wrote {syn} ({args.synthetic:.0f} s drive, seed {args.synthetic_seed}, bumps {args.bumps}, "
                  f"noise {args.noise}) in {time.perf_counter() - t0:.1f} s")
            bag_paths.append(syn)
            gt_modes[str(syn)] = np.asarray(drive.pitch_roll_road, dtype=np.float64)  # exact, per frame
        seqs = []
        for b in bag_paths:
            s = load_sequence(b, config)
            s.name = b.resolve().name
            seqs.append(s)
        eval_mode = args.eval or ("held-out" if args.train else "all")
        if args.train:
            options = TrainOptions(epochs=args.epochs, lr=args.lr, split=args.split, seed=args.seed,
                                   init=tuple(args.init) if args.init else None, device=str(device))
            result = train(seqs, config, options, checkpoint=out / "learned.yaml.ckpt.yaml", progress=not args.quiet)
            learned = result.learned
            save_learned_params(learned, out / "learned.yaml")
            learned_src = (f"trained here on the first {'three quarters' if args.split == '3/4' else '20 %'} of "
                           f"each bag ({result.epochs_run} epochs, status {result.status}, best epoch "
                           f"{result.best_epoch}; {out / 'learned.yaml'})")
            if result.status == "diverged":
                print(f"ablation: warning: {result.message}", file=sys.stderr)
        else:
            path = args.learned or config.learned_params_file
            learned = load_learned_params(path)
            learned_src = f"from {path}"
        print(f"learned O = {list(learned.process_noise_density)}, Q = {list(learned.measurement_noise_variance)}")
        fused_learned = load_learned_params(args.fused_learned)

        md = ["# BEVO ablation (paper Table 3)", "",
              f"Parameters: {args.params}. Frames evaluated: {eval_mode}. Every variant runs the engine's BEV "
              "projection and phase correlation; only the attitude fed to the BEV differs.", ""]
        report: dict = {"params": str(args.params), "eval": eval_mode, "learned": {
            "process_noise_density": list(learned.process_noise_density),
            "measurement_noise_variance": list(learned.measurement_noise_variance), "source": learned_src},
            "bags": {}}
        rows_by_bag = {}
        for b, s in zip(bag_paths, seqs):
            if eval_mode == "held-out":
                _, (c, d) = split_frames(len(s), args.split)
            else:
                c, d = 0, len(s)
            part = s.frames(c, d)
            mode = gt_modes.get(str(b), args.gt_attitude)
            if not isinstance(mode, str):
                if len(mode) != len(s):
                    raise ValueError(f"{s.name}: {len(s)} frames in the bag but {len(mode)} in the drive")
                mode = mode[c:d]
            t0 = time.perf_counter()
            label = mode if isinstance(mode, str) else "simulator (exact road-relative attitude)"
            rows = run_variants(part, config, learned, mode, args.empirical_O, args.empirical_Q, device,
                                fused_learned=fused_learned)
            frames = f"frames {c}..{d - 1} of {len(s)}" + (" (held out from training)" if eval_mode == "held-out" else "")
            md.append(table_markdown(s.name, rows, frames, label))
            gt = part.gt_poses.double().numpy()
            gt = np.linalg.inv(gt[0]) @ gt
            ref = reference_attitude(part, mode, config).numpy()
            png = out / f"{s.name}_ablation.png"
            plot_bag(png, s.name, gt, rows, ref)
            md.append(f"![{s.name}]({png.name})\n")
            rows_by_bag[s.name] = rows
            report["bags"][s.name] = {"frames": [c, d], "gt_attitude": label, "plot": png.name,
                                      "rows": [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]}
            print(f"{s.name}: {len(rows)} variants over {d - c} frames in {time.perf_counter() - t0:.1f} s")
            print(table_markdown(s.name, rows, frames, label))
        md.append(notes(rows_by_bag, learned_src, args.empirical_O, args.empirical_Q))
        atomic_write_text(out / "ablation.md", "\n".join(md))
        atomic_write_text(out / "ablation.json", json.dumps(report, indent=2, default=float) + "\n")
    except (ConfigError, bag.BagError, FileNotFoundError, ValueError, TrainingDiverged) as exc:
        print(f"ablation: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("ablation: interrupted", file=sys.stderr)
        return 130
    print(notes(rows_by_bag, learned_src, args.empirical_O, args.empirical_Q))
    print(f"wrote {out / 'ablation.md'}, {out / 'ablation.json'} and the plots in {time.perf_counter() - t_start:.0f} s")
    return 0
