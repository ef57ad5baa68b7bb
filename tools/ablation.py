#!/usr/bin/env python3
"""The paper's ablation study (Table 3) on rosbag2 recordings: what the DUKF and its learned
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
import math
import sys
import time
from pathlib import Path

try:
    import bevo_ros  # noqa: F401
except ImportError:  # running from a source checkout without installing
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from bevo_ros.config import REPO_ROOT, ConfigError, atomic_write_text

DEFAULT_PARAMS = REPO_ROOT / "params" / "kitti.yaml"
# "Textbook" values, set from an IMU's white-noise specs as one would without learning: gyro
# 0.005 rad/s per sample at 100 Hz -> angle random-walk density 0.005^2 * 0.01 = 2.5e-7 rad^2/s;
# accelerometer 0.05 m/s^2 -> (0.05 / 9.81)^2 = 2.6e-5 rad^2 per angle. They ignore vibration and
# the vehicle's own acceleration, which is exactly what a hand-tuned filter gets wrong.
EMPIRICAL_O = 2.5e-7
EMPIRICAL_Q = 2.6e-5
VARIANTS = ("w/o O", "w/o Q", "w/o DUKF", "BEVO", "w/ GT", "fused")
GT_MODES = ("imu-highpass", "imu", "road-poses", "zero")

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
  ablation.py --synthetic 30 --params params/synthetic.yaml --train --out out/ablation_synthetic
  kitti_to_bag.py --odometry ../shared/data/kitti/odometry --sequence 06 -o seq06_bag
  ablation.py seq06_bag --train --eval all --out out/ablation_kitti06
  ablation.py seq06_bag --learned params/learned.yaml --out out/ablation_kitti06
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="*", metavar="BAG", help="rosbag2 directories with ground truth")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--params", default=str(DEFAULT_PARAMS), help="ROS parameters file (default params/kitti.yaml)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--learned", help="learned-parameters YAML (default: the one named in --params)")
    src.add_argument("--train", action="store_true", help="train O/Q on the bags first (bevo_ros.training)")
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
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    p.add_argument("--device", default="cpu", help="cpu or cuda (falls back to CPU)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress output from training")
    return p


# --------------------------------------------------------------------------- helpers
def make_synthetic_bag(path: Path, seconds: float, seed: int, bumps: float, noise: float, image_scale: float):
    """A bumpy synthetic drive (gentle curves, no road tilt) written as a rosbag2. -> (path, drive)"""
    from bevo_ros.core.geometry import CameraModel
    from bevo_ros.datasets import write_drive_bag
    from bevo_ros.synthetic import RenderOptions, kitti_like_camera, make_drive

    cam = kitti_like_camera()
    if image_scale != 1.0:
        K = cam.K.clone()
        K[:2] *= image_scale
        cam = CameraModel(K, int(round(cam.width * image_scale)), int(round(cam.height_px * image_scale)),
                          cam.T_base_cam, cam.mount_height)
    drive = make_drive(seed=seed, duration=seconds, bumps=bumps, noise=noise, render="lazy", camera=cam,
                       curvature=0.3, road_tilt=False, speed_variation=0.3, ground_seed=0,
                       render_options=RenderOptions(supersample=1 if image_scale < 1 else 2))
    return write_drive_bag(drive, path, overwrite=True), drive


def reference_attitude(seq, mode, config):
    """``(F, 2)`` [pitch, roll] road-relative reference for "w/ GT" (float64 tensor).

    Modes that lose the static part (road-poses, zero; imu-highpass when the low-pass is on) get the
    configured mounting attitude added, exactly as the engine adds it to the filtered attitude;
    "imu" and the simulator's truth are absolute already."""
    import torch

    from bevo_ros.core.road_tilt import is_enabled, road_relative_attitude
    from bevo_ros.datasets import road_relative_gt

    if not isinstance(mode, str):  # the simulator's own road-relative attitude of these frames
        return torch.as_tensor(mode, dtype=torch.float64)
    mounting = torch.tensor([config.filter.mounting_pitch, config.filter.mounting_roll], dtype=torch.float64)
    if mode == "zero":
        return torch.zeros(len(seq), 2, dtype=torch.float64) + mounting
    if mode == "road-poses":
        return road_relative_gt(seq.gt_poses.double()) + mounting
    if seq.gt_pitch_roll is None:
        raise ValueError(f"{seq.name}: no /ground_truth/imu attitude for --gt-attitude {mode}")
    if mode == "imu":
        return seq.gt_pitch_roll.double().clone()
    dt = torch.diff(seq.frame_stamps.double(), prepend=seq.frame_stamps[:1].double())
    tau = config.filter.road_tilt_time_constant
    highpass = road_relative_attitude(seq.gt_pitch_roll.double()[None], dt[None], tau)[0]
    return highpass + mounting if is_enabled(tau) else highpass  # no low-pass: the static part is still in


def planar_poses(motion) -> np.ndarray:
    """``(P, 3)`` motions -> ``(P + 1, 4, 4)`` poses (z = 0, level) starting at the identity."""
    import torch

    from bevo_ros.core.pose import integrate_motions

    xyyaw = integrate_motions(torch.as_tensor(motion, dtype=torch.float64)).numpy()
    T = np.tile(np.eye(4), (len(xyyaw), 1, 1))
    c, s = np.cos(xyyaw[:, 2]), np.sin(xyyaw[:, 2])
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 0, 3], T[:, 1, 3] = xyyaw[:, 0], xyyaw[:, 1]
    return T


def _num(v, fmt: str) -> str:
    return "n/a" if v is None or not math.isfinite(v) else format(v, fmt)


def _row(variant: str, o, q, motion, trans_err_mean: float, yaw_err_mean: float, road: np.ndarray,
         ref, gt: np.ndarray, failed: int, pairs: int, loss: float, t0: float) -> dict:
    """One table row: per-frame ``motion (F-1, 3)`` (array or tensor) and the road attitude ``(F, 2)`` fed to the BEV."""
    from bevo_ros.evaluation import evaluate_trajectories

    est = planar_poses(motion)
    m = evaluate_trajectories(gt, est, convention="base")
    att = np.degrees(road - ref.numpy())
    return {
        "variant": variant, "O": None if o is None else list(o), "Q": None if q is None else list(q),
        "rpe_trans_mean_m": trans_err_mean, "rpe_yaw_mean_deg": math.degrees(yaw_err_mean),
        "rpe_trans_rmse_m": m.rpe_trans_rmse, "rpe_yaw_rmse_deg": m.rpe_yaw_rmse,
        "drift_percent": m.drift_percent, "drift_m": m.drift_m, "ate_rmse_m": m.ate_rmse,
        "t_rel": m.t_rel, "r_rel": m.r_rel, "path_m": m.path_length,
        "attitude_rmse_deg": [float(v) for v in np.sqrt((att ** 2).mean(axis=0))],
        "failed_pairs": failed, "pairs": pairs, "kl_loss": loss,
        "seconds": time.perf_counter() - t0, "_est": est, "_road": road,
    }


def _fused_row(seq, config, learned, gt: np.ndarray, ref) -> dict:
    """The fused engine over ``seq``: the same metrics as the paper rows (no KL loss)."""
    from bevo_ros.datasets import run_engine

    t0 = time.perf_counter()
    steps = run_engine(seq, config, learned, mode="fused")
    if len(steps) != len(seq):
        raise ValueError(f"{seq.name}: the fused engine dropped {len(seq) - len(steps)} frame(s)")
    motion = np.array([s.motion for s in steps[1:]])
    truth = seq.gt_motion().double().numpy()
    yaw_err = np.abs((motion[:, 2] - truth[:, 2] + math.pi) % (2 * math.pi) - math.pi)
    return _row("fused", learned.process_noise_density, learned.measurement_noise_variance, motion,
                float(np.linalg.norm(motion[:, :2] - truth[:, :2], axis=1).mean()), float(yaw_err.mean()),
                np.array([s.pitch_roll_road for s in steps]), ref, gt, 0, len(steps) - 1, float("nan"), t0)


def run_variants(seq, config, learned, gt_mode: str, empirical_o: float, empirical_q: float, device,
                 fused_learned=None) -> list[dict]:
    """Every variant over ``seq`` (frames as given; IMU from the recording start)."""
    import torch

    from bevo_ros.training import make_dukf, sequence_pass

    o_l, q_l = tuple(learned.process_noise_density), tuple(learned.measurement_noise_variance)
    ref = reference_attitude(seq, gt_mode, config)
    gt = seq.gt_poses.double().numpy()
    gt = np.linalg.inv(gt[0]) @ gt
    rows = []
    specs = {
        "w/o O": dict(o=(empirical_o, empirical_o), q=q_l, source="dukf"),
        "w/o Q": dict(o=o_l, q=(empirical_q, empirical_q), source="dukf"),
        "w/o DUKF": dict(o=None, q=None, source="accel"),
        "BEVO": dict(o=o_l, q=q_l, source="dukf"),
        "w/ GT": dict(o=None, q=None, source="given"),
    }
    for name in VARIANTS:
        if name == "fused":
            rows.append(_fused_row(seq, config, fused_learned, gt, ref))
            continue
        sp = specs[name]
        dukf = make_dukf(sp["o"], sp["q"], config.filter.motion_model, device) if sp["o"] is not None else None
        t0 = time.perf_counter()
        with torch.no_grad():
            r = sequence_pass(dukf, seq, config, source=sp["source"], device=device,
                              given_pitch_roll_road=ref if sp["source"] == "given" else None)
        rows.append(_row(name, sp["o"], sp["q"], r.motion, float(r.trans_err.mean()), float(r.yaw_err.mean()),
                         r.pitch_roll_road.numpy(), ref, gt, r.n_failed, r.pairs, r.loss, t0))
    return rows


def table_markdown(name: str, rows: list[dict], frames: str, gt_mode: str) -> str:
    path = rows[0]["path_m"]
    kitti = "t_rel (%) / r_rel (deg/100 m)"
    lines = [f"## {name}", "", f"{frames}; GT path {path:.1f} m; w/ GT reference: {gt_mode}.", "",
             f"| variant | O (rad^2/s) | Q (rad^2) | RPE trans mean (m) | RPE yaw mean (deg) | drift (%) | "
             f"ATE RMSE (m) | {kitti} | road pitch/roll RMSE vs ref (deg) | failed pairs |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        o = "-" if r["O"] is None else "/".join(f"{v:.2g}" for v in r["O"])
        q = "-" if r["Q"] is None else "/".join(f"{v:.2g}" for v in r["Q"])
        tr = "n/a (< 100 m)" if r["t_rel"] is None else f"{r['t_rel']:.2f} / {r['r_rel']:.2f}"
        att = "/".join(f"{v:.2f}" for v in r["attitude_rmse_deg"])
        bold = "**" if r["variant"] == "BEVO" else ""
        lines.append(f"| {bold}{r['variant']}{bold} | {o} | {q} | {_num(r['rpe_trans_mean_m'], '.4f')} | "
                     f"{_num(r['rpe_yaw_mean_deg'], '.4f')} | {_num(r['drift_percent'], '.2f')} | "
                     f"{_num(r['ate_rmse_m'], '.3f')} | {tr} | {att} | {r['failed_pairs']}/{r['pairs']} |")
    return "\n".join(lines) + "\n"


def plot_bag(path: Path, name: str, gt: np.ndarray, rows: list[dict], ref: np.ndarray) -> None:
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bevo_ros.evaluation import atomic_write_bytes

    fig, axes = plt.subplots(1, 3, figsize=(16, 5.2), gridspec_kw={"width_ratios": [1.3, 1, 1]})
    ax = axes[0]
    ax.plot(-gt[:, 1, 3], gt[:, 0, 3], "k-", lw=2.2, label="ground truth")
    colours = {"w/o O": "tab:orange", "w/o Q": "tab:purple", "w/o DUKF": "tab:red", "BEVO": "tab:blue",
               "w/ GT": "tab:green", "fused": "tab:cyan"}
    for r in rows:
        e = r["_est"]
        ax.plot(-e[:, 1, 3], e[:, 0, 3], "-", color=colours[r["variant"]], lw=1.2,
                label=f"{r['variant']} (ATE {_num(r['ate_rmse_m'], '.2f')} m)")
    ax.plot([0], [0], "ko")
    ax.set_xlabel("-y (m)")
    ax.set_ylabel("x (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{name}: top view (start at the origin)")
    for k, (ax, label) in enumerate(zip(axes[1:], ("pitch", "roll"))):
        ax.plot(np.degrees(ref[:, k]), "k-", lw=2.0, label="reference")
        for r in rows:
            if r["variant"] != "w/ GT":
                ax.plot(np.degrees(r["_road"][:, k]), "-", color=colours[r["variant"]], lw=1.0, label=r["variant"])
        ax.set_xlabel("frame")
        ax.set_ylabel(f"road-relative {label} fed to the BEV (deg)")
        ax.grid(True, alpha=0.3)
        ax.set_title(label)
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def notes(rows_by_bag: dict[str, list[dict]], learned_src: str, empirical_o: float, empirical_q: float) -> str:
    out = ["## Notes", "",
           f"* Learned O/Q: {learned_src}. w/o O uses O = {empirical_o:.3g} rad^2/s and w/o Q uses Q = "
           f"{empirical_q:.3g} rad^2: textbook values from an IMU's white-noise specs (gyro 0.005 rad/s per "
           "sample at 100 Hz, accelerometer 0.05 m/s^2), blind to vibration and to the vehicle's own acceleration.",
           "* Only the ratio O/Q shapes the filtered attitude (scaling both leaves the mean unchanged), so "
           "w/o O and w/o Q each move that ratio: w/o O towards gyro integration, w/o Q towards the raw "
           "accelerometer.",
           "* RPE = per-frame relative pose error (planar: the estimate keeps a constant elevation, as in the "
           "paper); drift = endpoint position error in % of the GT path; ATE after rigid alignment. KITTI "
           "t_rel/r_rel need >= 100 m of path (the official segments of 100..800 m); shorter recordings show n/a.",
           "* Failed pairs: the BEV of a frame had no valid pixel (the attitude tilted the camera's view off "
           "the BEV's ground patch); such pairs get zero motion, as the node would drop the frame."]
    for name, rows in rows_by_bag.items():
        by = {r["variant"]: r for r in rows}
        b, g, a = by["BEVO"], by["w/ GT"], by["w/o DUKF"]
        verdict = []
        verdict.append(f"w/ GT {'beats' if g['rpe_trans_mean_m'] < a['rpe_trans_mean_m'] else 'does NOT beat'} "
                       f"w/o DUKF in translation RPE ({g['rpe_trans_mean_m']:.4f} vs {a['rpe_trans_mean_m']:.4f} m)")
        verdict.append(f"BEVO vs w/ GT: {b['rpe_trans_mean_m']:.4f} vs {g['rpe_trans_mean_m']:.4f} m, "
                       f"{b['rpe_yaw_mean_deg']:.4f} vs {g['rpe_yaw_mean_deg']:.4f} deg per frame")
        best = min(rows, key=lambda r: r["rpe_trans_mean_m"])
        verdict.append(f"lowest translation RPE: {best['variant']}")
        if rows[0]["path_m"] < 100:
            verdict.append(f"path {rows[0]['path_m']:.1f} m < 100 m: no KITTI t_rel/r_rel")
        out.append(f"* {name}: " + "; ".join(verdict) + ".")
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import torch

    from bevo_ros import bag
    from bevo_ros.config import load_config, load_learned_params, save_learned_params
    from bevo_ros.datasets import load_sequence, split_frames
    from bevo_ros.training import TrainingDiverged, TrainOptions, resolve_device, train

    if args.threads > 0:
        torch.set_num_threads(args.threads)
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


if __name__ == "__main__":
    sys.exit(main())
