"""``bevo demo`` (`make demo`): the whole BEVO pipeline on a built-in default, no data needed.

1. generate a synthetic bumpy drive with exact ground truth and write it as a rosbag2;
2. train the DUKF's O and Q end to end on its first three quarters (bevo train);
3. run the odometry over the held-out last quarter (bevo run, the node's engine),
   with the learned and with the hand-set default parameters;
4. evaluate (bevo evaluate) and print the metrics table; plots land in out/demo/.
When ../shared/data/kitti exists it also converts the KITTI sample, runs and evaluates it.
Every step is a `bevo` command called exactly as the README shows.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from bevo_ros.commands import new_parser
from bevo_ros.config import REPO_ROOT as REPO, package_file

KITTI = REPO.parent / "shared" / "data" / "kitti"


def step(title: str) -> float:
    print(f"\n=== {title}", flush=True)
    return time.perf_counter()


def call(command: str, argv: list[str]) -> None:
    """Run ``bevo COMMAND ARGV`` in this process (its module's ``main``); stop the demo if it fails."""
    from bevo_ros import cli

    print(f"$ bevo {command} " + " ".join(argv), flush=True)
    rc = cli.command_module(command).main(argv)
    if rc != 0:
        raise SystemExit(f"demo: bevo {command} failed with exit code {rc}")


def metrics_row(label: str, eval_dir: Path) -> str:
    m = json.loads((eval_dir / "metrics.json").read_text())
    t_rel = "n/a" if m.get("t_rel") is None else f"{m['t_rel']:.2f}"
    r_rel = "n/a" if m.get("r_rel") is None else f"{m['r_rel']:.2f}"
    pr = m.get("pitch_roll") or {}
    pitch = pr.get("pitch RMSE vs reference", float("nan"))
    roll = pr.get("roll RMSE vs reference", float("nan"))
    return (f"| {label} | {m['frames']} | {m['path_length']:.1f} | {m['rpe_trans_rmse'] * 100:.1f} | "
            f"{m['rpe_yaw_rmse']:.3f} | {m['drift_percent']:.2f} | {m['ate_rmse']:.2f} | {t_rel} | {r_rel} | "
            f"{pitch:.2f} / {roll:.2f} |")


HEADER = ("| run | frames | path (m) | RPE trans RMSE (cm/frame) | RPE yaw RMSE (deg/frame) | end drift (%) | ATE (m) | "
          "t_rel (%) | r_rel (deg/100 m) | pitch / roll RMSE (deg) |\n|---|---|---|---|---|---|---|---|---|---|")


def main(argv: list[str] | None = None) -> int:
    p = new_parser(__doc__)
    p.add_argument("--out", default="out/demo", help="output directory (default out/demo, in the working directory)")
    p.add_argument("--duration", type=float, default=40.0, help="synthetic drive length, s (default 40)")
    p.add_argument("--epochs", type=int, default=6, help="training epochs (default 6)")
    p.add_argument("--seed", type=int, default=7, help="drive and initialisation seed (default 7)")
    p.add_argument("--no-kitti", action="store_true", help="skip the KITTI sample even if present")
    args = p.parse_args(argv)

    import torch

    torch.set_num_threads(min(2, torch.get_num_threads()))
    from bevo_ros.datasets.rosbag import split_frames, write_drive_bag
    from bevo_ros.datasets.synthetic import make_drive

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    synth_params = str(package_file("params/synthetic.yaml"))

    t = step(f"1/4 synthetic bumpy drive ({args.duration:.0f} s, 10 Hz camera, 100 Hz IMU) -> rosbag2")
    drive = make_drive(seed=args.seed, duration=args.duration, bumps=1.5, render="lazy")
    bag_path = out / "synthetic_bag"
    # with a wheel odometry 1 % long (a tyre's calibration error), for the speed input's row
    write_drive_bag(drive, bag_path, overwrite=True, wheel_odometry_topic="/wheel/odometry", wheel_speed_scale=1.01)
    n = len(drive.frame_stamps)
    (_, cut), _ = split_frames(n, "3/4")
    print(f"wrote {bag_path}: {n} frames, {len(drive.imu_stamps)} IMU messages (rendered and written in "
          f"{time.perf_counter() - t:.1f} s)")

    t = step("2/4 train O and Q end to end on the first three quarters (the paper's pipeline), then fused mode's "
             "numbers")
    # The paper's pipeline: its O/Q as trained. Fused mode (the params' mode): O/Q, the suspension and the
    # vehicle filter's noise, each kept only if the fused engine reads the validation frames clearly better.
    paper_params = out / "synthetic_paper.yaml"
    from bevo_ros.io.files import atomic_write_text

    key = "    learned_params_file: params/learned_default.yaml"
    text = Path(synth_params).read_text()
    if key not in text:
        raise ValueError(f"{synth_params}: no '{key.strip()}' line to make its paper-mode copy from")
    atomic_write_text(paper_params, text.replace(
        key, f"    learned_params_file: {package_file('params/learned_paper.yaml')}\n    odometry.mode: paper", 1))
    learned_paper, learned = out / "learned_paper.yaml", out / "learned.yaml"
    for params, target in ((paper_params, learned_paper), (synth_params, learned)):
        call("train", [str(bag_path), "--out", str(target), "--params", str(params), "--split", "3/4",
                       "--epochs", str(args.epochs), "--seed", str(args.seed)])
    print(f"training took {time.perf_counter() - t:.1f} s")

    t = step(f"3/4 odometry over the held-out last quarter (frames {cut}..{n - 1})")
    rows = []
    # Training fits the paper pipeline's O and Q (the batched KL path), then, for fused mode, the suspension
    # and the vehicle filter's noise; each fused-mode fit is kept only if the engine reads the validation
    # frames (these held-out ones) clearly better. The fused row with this run's file shows what that gave.
    default = str(package_file("params/learned_default.yaml"))
    runs = (("fused", "fused", default, "fused (default params)", []),
            ("fused_learned", "fused", str(learned), "fused, this run's learned file", []),
            ("fused_speed", "fused", default, "fused + wheel speed 1 % long", ["--speed-topic", "/wheel/odometry"]),
            ("learned", "paper", str(learned_paper), "paper, learned O/Q", []),
            ("default", "paper", str(package_file("params/learned_paper.yaml")), "paper, default O/Q", []))
    for label, mode, params_file, title, extra in runs:
        run_dir, eval_dir = out / f"run_{label}", out / f"eval_{label}"
        call("run", [str(bag_path), "--out", str(run_dir), "--params", synth_params, "--learned", params_file,
                     "--first-frame", str(cut), "--mode", mode, "-q"] + extra)
        call("evaluate", ["--gt", str(run_dir / "gt_kitti.txt"), "--est", str(run_dir / "trajectory_kitti.txt"),
                          "--pitch-roll", str(run_dir / "pitch_roll.csv"), "--out", str(eval_dir),
                          "--title", f"synthetic held-out, {title}"])
        rows.append(metrics_row(f"synthetic held-out, {title}", eval_dir))
    print(f"odometry + evaluation took {time.perf_counter() - t:.1f} s")

    if not args.no_kitti and (KITTI / "odometry" / "sequences" / "06").is_dir():
        t = step("4/4 KITTI sample (sequence 06, 51 frames) -> rosbag2 -> odometry -> evaluation")
        kbag = out / "kitti06_bag"
        call("convert", ["--odometry", str(KITTI / "odometry"), "--sequence", "06", "-o", str(kbag),
                         "--overwrite", "-q"])
        for mode, learned_file in (("fused", "learned_default.yaml"), ("paper", "learned_paper.yaml")):
            run_dir, eval_dir = out / f"run_kitti06_{mode}", out / f"eval_kitti06_{mode}"
            call("run", [str(kbag), "--out", str(run_dir), "--mode", mode, "--learned",
                         str(package_file(f"params/{learned_file}")), "-q"])
            call("evaluate", ["--gt", str(run_dir / "gt_kitti.txt"), "--est", str(run_dir / "trajectory_kitti.txt"),
                              "--pitch-roll", str(run_dir / "pitch_roll.csv"), "--out", str(eval_dir),
                              "--title", f"KITTI 06, frames 0-50, {mode}"])
            rows.append(metrics_row(f"KITTI 06 sample, {mode} (params/kitti.yaml)", eval_dir))
        print(f"KITTI took {time.perf_counter() - t:.1f} s")
    else:
        print("\n(4/4 skipped: no KITTI sample at ../shared/data/kitti)")

    table = HEADER + "\n" + "\n".join(rows) + "\n"
    from bevo_ros.io.files import atomic_write_text

    atomic_write_text(out / "summary.md", "# BEVO demo\n\n" + table)
    print("\n" + table)
    print(f"plots: {out}/eval_fused/trajectory.png, frame_errors.png, pitch_roll.png")
    from bevo_ros.datasets.synthetic.aerial_map import localization_demo  # BEVO+ (issue 13): odometry only vs map localisation

    plus = localization_demo(out / "bevo_plus")
    print("\n" + plus["table"] + f"plot: {plus['plot']}")
    atomic_write_text(out / "summary.md", "# BEVO demo\n\n" + table + "\n" + plus["table"])
    print(f"demo finished in {time.perf_counter() - t_start:.0f} s")
    return 0
