"""The paper's ablation study (Table 3): the variants (w/o O, w/o Q, w/o DUKF, BEVO, w/ GT, fused),
their metrics, the markdown table, notes and plots (``bevo ablation`` runs them over bags)."""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

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
    mounting = torch.tensor(seq.mounting_in_use(config), dtype=torch.float64)  # the engine's, for this camera
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
         ref, gt: np.ndarray, failed: int, pairs: int, loss: float, t0: float, est: np.ndarray | None = None) -> dict:
    """One table row: per-frame ``motion (F-1, 3)`` (array or tensor) and the road attitude ``(F, 2)`` fed to the BEV.
    ``est`` ``(F, 4, 4)``: the poses scored, relative to the first (default: ``motion`` integrated on a plane)."""
    from bevo_ros.evaluation.metrics import evaluate_trajectories

    est = planar_poses(motion) if est is None else est
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
    """The fused engine over ``seq``: the same metrics as the paper rows (no KL loss), scored on the poses it
    publishes (3-D: it climbs with the road, as ``bevo run`` writes them), not on its motions laid on a plane."""
    from bevo_ros.datasets.rosbag import run_engine
    from bevo_ros.pipeline import base_poses

    t0 = time.perf_counter()
    steps = run_engine(seq, config, learned, mode="fused")
    if len(steps) != len(seq):
        raise ValueError(f"{seq.name}: the fused engine dropped {len(seq) - len(steps)} frame(s)")
    motion = np.array([s.motion for s in steps[1:]])
    published = base_poses(steps)
    truth = seq.gt_motion().double().numpy()
    yaw_err = np.abs((motion[:, 2] - truth[:, 2] + math.pi) % (2 * math.pi) - math.pi)
    return _row("fused", learned.process_noise_density, learned.measurement_noise_variance, motion,
                float(np.linalg.norm(motion[:, :2] - truth[:, :2], axis=1).mean()), float(yaw_err.mean()),
                np.array([s.pitch_roll_road for s in steps]), ref, gt, 0, len(steps) - 1, float("nan"), t0,
                est=np.linalg.inv(published[0]) @ published)


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
           "* RPE = per-frame relative pose error (paper rows planar: the estimate keeps a constant elevation, as in "
           "the paper; the fused row on the 3-D poses the engine publishes, as `bevo run` writes them); drift = endpoint position error in % of the GT path; ATE after rigid alignment. KITTI "
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


@dataclass
class AblationOptions:
    """What ``run_ablation`` does: the fields of ``bevo ablation``'s options (see its ``--help``)."""

    params: str                                 # parameters file the config came from (recorded in the report)
    learned: str | None = None                  # learned-parameters YAML (None: the config's); ignored with train
    train: bool = False                         # train O/Q on the recordings first
    fused_learned: str = ""                     # learned-parameters YAML of the fused row
    epochs: int = 10
    lr: float = 0.3
    seed: int = 0
    init: tuple[float, float, float, float] | None = None
    split: str = "3/4"
    eval: str | None = None                     # "all" | "held-out" | None (held-out with train, else all)
    gt_attitude: str = "imu-highpass"
    empirical_o: float = EMPIRICAL_O
    empirical_q: float = EMPIRICAL_Q
    synthetic: float | None = None              # seconds of a synthetic drive written to OUT/synthetic_bag
    synthetic_seed: int = 3
    bumps: float = 2.0
    noise: float = 2.0
    image_scale: float = 1.0
    device: str = "cpu"
    quiet: bool = False


@dataclass
class AblationResult:
    report: dict                                # what OUT/ablation.json holds
    rows_by_bag: dict[str, list[dict]] = field(default_factory=dict)
    learned_src: str = ""
    notes: str = ""                             # the markdown notes (also at the end of OUT/ablation.md)


def run_ablation(bags: list[str | Path], config, options: AblationOptions, out: str | Path,
                 log: Callable[[str], None] = print, warn: Callable[[str], None] = print,
                 rig=None) -> AblationResult:
    """The whole study: (optional synthetic drive,) load the bags, (train or load O/Q,) every variant per bag;
    writes OUT/ablation.md, OUT/ablation.json and OUT/<bag>_ablation.png. Progress goes to ``log``,
    a diverged training's message to ``warn``. ``rig``: how the bags' rig and calibration are taken
    (``RigSettings``, the params' node settings of the same names). Raises ``ValueError`` (and the loaders' errors) on bad input."""
    from bevo_ros.datasets.rosbag import RigSettings, load_sequence, split_frames, with_start_tilt
    from bevo_ros.io.files import atomic_write_text
    from bevo_ros.io.learned_params import load_learned_params, save_learned_params
    from bevo_ros.training.trainer import TrainOptions, resolve_device, train

    o = options
    if not bags and o.synthetic is None:
        raise ValueError("give at least one BAG or --synthetic SECONDS")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    device = resolve_device(o.device, log)
    bag_paths = [Path(b) for b in bags]
    gt_modes = {}
    if o.synthetic is not None:
        t0 = time.perf_counter()
        syn, drive = make_synthetic_bag(out / "synthetic_bag", o.synthetic, o.synthetic_seed, o.bumps,
                                        o.noise, o.image_scale)
        log(f"wrote {syn} ({o.synthetic:.0f} s drive, seed {o.synthetic_seed}, bumps {o.bumps}, "
            f"noise {o.noise}) in {time.perf_counter() - t0:.1f} s")
        bag_paths.append(syn)
        gt_modes[str(syn)] = np.asarray(drive.pitch_roll_road, dtype=np.float64)  # exact, per frame
    seqs = [load_sequence(b, config, rig=rig or RigSettings()) for b in bag_paths]
    fused_learned = load_learned_params(o.fused_learned)
    # the trained rows at the tilt the engine measures at each bag's start (the fused row's, when it runs the bag whole)
    with_start_tilt(seqs, config, fused_learned, log, mode="fused")
    eval_mode = o.eval or ("held-out" if o.train else "all")
    if o.train:
        topts = TrainOptions(epochs=o.epochs, lr=o.lr, split=o.split, seed=o.seed,
                             init=tuple(o.init) if o.init else None, device=str(device))
        result = train(seqs, config, topts, checkpoint=out / "learned.yaml.ckpt.yaml", progress=not o.quiet)
        learned = result.learned
        save_learned_params(learned, out / "learned.yaml")
        learned_src = (f"trained here on the first {'three quarters' if o.split == '3/4' else '20 %'} of "
                       f"each bag ({result.epochs_run} epochs, status {result.status}, best epoch "
                       f"{result.best_epoch}; {out / 'learned.yaml'})")
        if result.status == "diverged":
            warn(result.message)
    else:
        from bevo_ros.config import shipped_learned_for_mode

        # the paper's rows run the paper's pipeline: the params' shipped fused file swapped for the paper's
        # (as bevo run --mode paper does); a file given with --learned, or a user's own, as it is
        path = o.learned or shipped_learned_for_mode(config.learned_params_file, "paper")
        learned = load_learned_params(path)
        learned_src = f"from {path}"
    log(f"learned O = {list(learned.process_noise_density)}, Q = {list(learned.measurement_noise_variance)}")

    md = ["# BEVO ablation (paper Table 3)", "",
          f"Parameters: {o.params}. Frames evaluated: {eval_mode}. Every variant runs the engine's BEV "
          "projection and phase correlation; only the attitude fed to the BEV differs.", ""]
    report: dict = {"params": str(o.params), "eval": eval_mode, "learned": {
        "process_noise_density": list(learned.process_noise_density),
        "measurement_noise_variance": list(learned.measurement_noise_variance), "source": learned_src},
        "bags": {}}
    rows_by_bag = {}
    names: list[str] = []  # each bag's key in the report and its plot's name: two bags' folders may share a name
    for s in seqs:
        name, k = s.name, 2
        while name in names:
            name, k = f"{s.name}_{k}", k + 1
        names.append(name)
    for b, s, name in zip(bag_paths, seqs, names):
        if eval_mode == "held-out":
            _, (c, d) = split_frames(len(s), o.split)
        else:
            c, d = 0, len(s)
        part = s.frames(c, d)
        if c:  # the fused row's engine starts at the part, and measures the tilt there: every row at it
            with_start_tilt([part], config, fused_learned, log, mode="fused")
        mode = gt_modes.get(str(b), o.gt_attitude)
        if not isinstance(mode, str):
            if len(mode) != len(s):
                raise ValueError(f"{name}: {len(s)} frames in the bag but {len(mode)} in the drive")
            mode = mode[c:d]
        t0 = time.perf_counter()
        label = mode if isinstance(mode, str) else "simulator (exact road-relative attitude)"
        rows = run_variants(part, config, learned, mode, o.empirical_o, o.empirical_q, device,
                            fused_learned=fused_learned)
        frames = f"frames {c}..{d - 1} of {len(s)}" + (" (held out from training)" if eval_mode == "held-out" else "")
        md.append(table_markdown(name, rows, frames, label))
        gt = part.gt_poses.double().numpy()
        gt = np.linalg.inv(gt[0]) @ gt
        ref = reference_attitude(part, mode, config).numpy()
        png = out / f"{name}_ablation.png".replace(" ", "_")
        plot_bag(png, name, gt, rows, ref)
        md.append(f"![{name}]({png.name})\n")
        rows_by_bag[name] = rows
        report["bags"][name] = {"frames": [c, d], "gt_attitude": label, "plot": png.name,
                                  "rows": [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]}
        log(f"{name}: {len(rows)} variants over {d - c} frames in {time.perf_counter() - t0:.1f} s")
        log(table_markdown(name, rows, frames, label))
    text = notes(rows_by_bag, learned_src, o.empirical_o, o.empirical_q)
    md.append(text)
    atomic_write_text(out / "ablation.md", "\n".join(md))
    atomic_write_text(out / "ablation.json", json.dumps(report, indent=2, default=float) + "\n")
    return AblationResult(report, rows_by_bag, learned_src, text)
