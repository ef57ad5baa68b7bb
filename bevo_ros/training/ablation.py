"""The paper's ablation study (Table 3): the variants (w/o O, w/o Q, w/o DUKF, BEVO, w/ GT, fused),
their metrics, the markdown table, notes and plots (``bevo ablation`` runs them over bags)."""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np


# "Textbook" values, set from an IMU's white-noise specs as one would without learning: gyro
# 0.005 rad/s per sample at 100 Hz -> angle random-walk density 0.005^2 * 0.01 = 2.5e-7 rad^2/s;
# accelerometer 0.05 m/s^2 -> (0.05 / 9.81)^2 = 2.6e-5 rad^2 per angle. They ignore vibration and
# the vehicle's own acceleration, which is exactly what a hand-tuned filter gets wrong.
EMPIRICAL_O = 2.5e-7
EMPIRICAL_Q = 2.6e-5
VARIANTS = ("w/o O", "w/o Q", "w/o DUKF", "BEVO", "w/ GT", "fused")
GT_MODES = ("imu-highpass", "imu", "road-poses", "zero")


def make_synthetic_bag(path: Path, seconds: float, seed: int, bumps: float, noise: float, image_scale: float):
    """A bumpy synthetic drive (gentle curves, no road tilt) written as a rosbag2. -> (path, drive)"""
    from bevo_ros.core.geometry import CameraModel
    from bevo_ros.datasets.rosbag import write_drive_bag
    from bevo_ros.datasets.synthetic.drive import RenderOptions, kitti_like_camera, make_drive

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
    from bevo_ros.datasets.rosbag import road_relative_gt

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
    from bevo_ros.evaluation.metrics import evaluate_trajectories

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
    from bevo_ros.datasets.rosbag import run_engine

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

    from bevo_ros.training.trainer import make_dukf, sequence_pass

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

    from bevo_ros.io.files import atomic_write_bytes

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
