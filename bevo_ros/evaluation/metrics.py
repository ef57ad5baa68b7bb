"""Trajectory evaluation: the official KITTI odometry metric, per-frame RPE, ATE, endpoint drift.

The KITTI metric follows the devkit's ``evaluate_odometry.cpp`` exactly (in float64 where the
devkit uses float32):

* ``dist[i]``: cumulative ground-truth path length, ``dist[0] = 0``.
* first frames every ``step_size = 10`` frames; segment lengths 100, 200, ..., 800 m.
* ``last = lastFrameFromSegmentLength``: the first frame ``i >= first`` with
  ``dist[i] > dist[first] + len`` (segments that run off the end are skipped).
* ``pose_error = inv(inv(res[first]) res[last]) @ (inv(gt[first]) gt[last])``;
  ``t_err = |pose_error_t| / len``; ``r_err = acos(clip(0.5 (trace(R) - 1), -1, 1)) / len``.
* The sequence result is the plain mean over all segments (pooled), reported as ``t_rel`` in %
  and ``r_rel`` in deg / 100 m.

A sequence shorter than 100 m has no such segment: ``t_rel``/``r_rel`` are None and the endpoint
drift (in % of the path length) is what it can honestly report.

Poses are ``(F, 4, 4)`` ``T_world_body``; KITTI files hold camera-0 poses (``convention="camera"``:
optical axes, the vertical is -y), bevo_ros base poses use ``convention="base"`` (z up).
"""
from __future__ import annotations

import csv
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from bevo_ros.core.pose import integrate_motions

PathLike = str | Path

KITTI_LENGTHS = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
KITTI_STEP = 10
CONVENTIONS = ("camera", "base")


# ----------------------------------------------------------------------------------------------
# SE(3) helpers
# ----------------------------------------------------------------------------------------------
def _check_poses(poses: np.ndarray, name: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{name} must be (F, 4, 4), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        bad = int(np.nonzero(~np.isfinite(poses).all(axis=(1, 2)))[0][0])
        raise ValueError(f"{name}: pose {bad} is not finite")
    return poses


def inv_se3(T: np.ndarray) -> np.ndarray:
    """Inverse of poses ``(..., 4, 4)``.

    A general matrix inverse, as the devkit's ``Matrix::inv``: KITTI files round R to 7 digits,
    so R^T is not exactly R^-1 and would leave a spurious ~1e-4 rad rotation error.
    """
    return np.linalg.inv(T)


def rotation_error(pose_error: np.ndarray) -> np.ndarray:
    """The devkit's ``rotationError``: angle of ``(..., 4, 4)`` in radians."""
    tr = pose_error[..., 0, 0] + pose_error[..., 1, 1] + pose_error[..., 2, 2]
    return np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0))


def heading(R: np.ndarray, convention: str = "camera") -> np.ndarray:
    """Rotation about the vertical axis (positive = left turn seen from above), radians.

    ``camera``: optical frame, vertical = -y: ``atan2(-R[0, 2], R[2, 2])``.
    ``base``: z up: ``atan2(R[1, 0], R[0, 0])``.
    """
    if convention == "camera":
        return np.arctan2(-R[..., 0, 2], R[..., 2, 2])
    if convention == "base":
        return np.arctan2(R[..., 1, 0], R[..., 0, 0])
    raise ValueError(f"unknown convention {convention!r} (use {CONVENTIONS})")


def wrap(angle: np.ndarray) -> np.ndarray:
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def trajectory_distances(poses: np.ndarray) -> np.ndarray:
    """``(F,)`` cumulative path length of the translations, ``dist[0] = 0``."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def last_frame_from_segment_length(dist: np.ndarray, first: int, length: float) -> int:
    """First frame ``i >= first`` with ``dist[i] > dist[first] + length``; -1 when none (devkit)."""
    i = int(np.searchsorted(dist, dist[first] + length, side="right"))
    # dist is non-decreasing, so searchsorted(side="right") is the first index strictly beyond.
    return i if i < len(dist) else -1


# ----------------------------------------------------------------------------------------------
# Metrics
# ----------------------------------------------------------------------------------------------
@dataclass
class SegmentErrors:
    """One row per evaluated KITTI segment."""

    first_frame: np.ndarray  # (S,) int
    length: np.ndarray  # (S,) m
    t_err: np.ndarray  # (S,) translation error / length (fraction)
    r_err: np.ndarray  # (S,) rotation error / length (rad/m)


def kitti_segment_errors(gt: np.ndarray, est: np.ndarray, lengths=KITTI_LENGTHS,
                         step_size: int = KITTI_STEP) -> SegmentErrors:
    """The devkit's ``calcSequenceErrors`` (see module docstring)."""
    dist = trajectory_distances(gt)
    firsts, lens, t_errs, r_errs = [], [], [], []
    for first in range(0, len(gt), step_size):
        for length in lengths:
            last = last_frame_from_segment_length(dist, first, length)
            if last == -1:
                continue
            delta_gt = inv_se3(gt[first]) @ gt[last]
            delta_est = inv_se3(est[first]) @ est[last]
            err = inv_se3(delta_est) @ delta_gt
            firsts.append(first)
            lens.append(length)
            t_errs.append(np.linalg.norm(err[:3, 3]) / length)
            r_errs.append(float(rotation_error(err)) / length)
    return SegmentErrors(np.asarray(firsts, dtype=np.int64), np.asarray(lens, dtype=np.float64),
                         np.asarray(t_errs, dtype=np.float64), np.asarray(r_errs, dtype=np.float64))


def kitti_metrics(gt: np.ndarray, est: np.ndarray) -> tuple[float | None, float | None, SegmentErrors]:
    """``(t_rel %, r_rel deg/100 m, segments)``; the rates are None when no segment fits."""
    seg = kitti_segment_errors(_check_poses(gt, "gt"), _check_poses(est, "est"))
    if seg.t_err.size == 0:
        return None, None, seg
    return float(seg.t_err.mean() * 100.0), float(np.degrees(seg.r_err.mean()) * 100.0), seg


def relative_pose_errors(gt: np.ndarray, est: np.ndarray, convention: str = "camera") -> tuple[np.ndarray, np.ndarray]:
    """Per-frame RPE: ``(F-1,)`` translation error (m) and heading error (rad) of each step."""
    d_gt = inv_se3(gt[:-1]) @ gt[1:]
    d_est = inv_se3(est[:-1]) @ est[1:]
    err = inv_se3(d_est) @ d_gt
    return np.linalg.norm(err[:, :3, 3], axis=1), wrap(heading(d_est[:, :3, :3], convention)
                                                       - heading(d_gt[:, :3, :3], convention))


def umeyama_alignment(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (no scale) ``R, t`` minimising ``sum |R source_i + t - target_i|^2``. ``(N, 3)`` x2.

    Umeyama (1991) with the scale fixed to 1, i.e. Kabsch on centred points with the reflection
    guard.
    """
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    cov = (target - mu_t).T @ (source - mu_s) / len(source)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    return R, mu_t - R @ mu_s


@dataclass
class Metrics:
    """Everything :func:`evaluate_trajectories` measures.

    Attributes:
        frames: number of poses; path_length: GT path length (m).
        t_rel: KITTI translational error (%), None below 100 m. r_rel: deg / 100 m, or None.
        segments: number of KITTI segments; per_length: {length m: (t %, r deg/100 m, count)}.
        rpe_trans: ``(F-1,)`` m; rpe_yaw: ``(F-1,)`` deg (per-frame step errors).
        ate_rmse, ate_max: after rigid SE(3) alignment of the positions (m).
        drift_m, drift_percent: endpoint position error relative to the start pose, and in % of
            the GT path length; yaw_drift_deg: endpoint heading error.
        aligned_est: ``(F, 4, 4)`` the estimate after the ATE alignment.
    """

    frames: int
    path_length: float
    t_rel: float | None
    r_rel: float | None
    segments: int
    per_length: dict[int, tuple[float, float, int]]
    rpe_trans: np.ndarray
    rpe_yaw: np.ndarray
    ate_rmse: float
    ate_max: float
    drift_m: float
    drift_percent: float | None
    yaw_drift_deg: float
    aligned_est: np.ndarray = field(repr=False)
    convention: str = "camera"
    pitch_roll: dict[str, float] | None = None

    @property
    def rpe_trans_rmse(self) -> float:
        return float(np.sqrt(np.mean(self.rpe_trans ** 2))) if self.rpe_trans.size else 0.0

    @property
    def rpe_yaw_rmse(self) -> float:
        return float(np.sqrt(np.mean(self.rpe_yaw ** 2))) if self.rpe_yaw.size else 0.0

    def summary_rows(self) -> list[tuple[str, str]]:
        """(metric, value) rows for the Markdown table and the console."""
        rows = [("frames", f"{self.frames}"), ("GT path length", f"{self.path_length:.2f} m")]
        if self.t_rel is None:
            rows.append(("KITTI t_rel / r_rel", "n/a (path < 100 m: no KITTI segment; see endpoint drift)"))
        else:
            rows.append(("KITTI t_rel", f"{self.t_rel:.2f} % ({self.segments} segments)"))
            rows.append(("KITTI r_rel", f"{self.r_rel:.3f} deg/100 m"))
        drift = "n/a" if self.drift_percent is None else f"{self.drift_percent:.2f} %"
        rows += [
            ("endpoint drift", f"{self.drift_m:.3f} m ({drift} of the path)"),
            ("endpoint yaw drift", f"{self.yaw_drift_deg:+.3f} deg"),
            ("ATE RMSE (SE(3)-aligned)", f"{self.ate_rmse:.3f} m (max {self.ate_max:.3f} m)"),
            ("RPE translation RMSE", f"{self.rpe_trans_rmse:.4f} m/frame"),
            ("RPE yaw RMSE", f"{self.rpe_yaw_rmse:.4f} deg/frame"),
        ]
        for length, (t, r, n) in sorted(self.per_length.items()):
            rows.append((f"KITTI {length} m segments", f"t {t:.2f} %, r {r:.3f} deg/100 m (n={n})"))
        if self.pitch_roll:
            for key, value in self.pitch_roll.items():
                rows.append((key, f"{value:.3f} deg"))
        return rows

    def summary_lines(self) -> list[str]:
        return [f"{k}: {v}" for k, v in self.summary_rows()]

    def to_markdown(self, title: str = "Trajectory evaluation") -> str:
        lines = [f"# {title}", "", "| metric | value |", "|---|---|"]
        lines += [f"| {k} | {v} |" for k, v in self.summary_rows()]
        lines += ["", "KITTI metric: official devkit definition (segments of 100..800 m starting every 10th "
                  "frame, pooled mean). Endpoint drift is relative to the start pose."]
        return "\n".join(lines) + "\n"

    def to_dict(self) -> dict:
        d = {k: v for k, v in asdict(self).items() if k not in ("rpe_trans", "rpe_yaw", "aligned_est")}
        d["per_length"] = {str(k): list(v) for k, v in self.per_length.items()}
        d["rpe_trans_rmse"], d["rpe_yaw_rmse"] = self.rpe_trans_rmse, self.rpe_yaw_rmse
        return d


def evaluate_trajectories(gt: np.ndarray, est: np.ndarray, convention: str = "camera") -> Metrics:
    """All metrics of an estimate against ground truth.

    Args:
        gt, est: ``(F, 4, 4)`` poses of the same frames (``T_world_body``; any world frames).
        convention: ``"camera"`` (KITTI camera-0 poses, vertical = -y) or ``"base"`` (z up);
            only the heading-based numbers (yaw RPE, yaw drift) depend on it.
    """
    gt, est = _check_poses(gt, "gt"), _check_poses(est, "est")
    if gt.shape != est.shape:
        raise ValueError(f"gt has {len(gt)} poses but est has {len(est)}")
    if len(gt) < 2:
        raise ValueError("need at least 2 poses")
    if convention not in CONVENTIONS:
        raise ValueError(f"unknown convention {convention!r} (use {CONVENTIONS})")
    t_rel, r_rel, seg = kitti_metrics(gt, est)
    per_length = {}
    for length in np.unique(seg.length):
        m = seg.length == length
        per_length[int(length)] = (float(seg.t_err[m].mean() * 100), float(np.degrees(seg.r_err[m].mean()) * 100),
                                   int(m.sum()))
    rpe_t, rpe_yaw = relative_pose_errors(gt, est, convention)

    R, t = umeyama_alignment(est[:, :3, 3], gt[:, :3, 3])
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = R, t
    aligned = A @ est
    ate = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1)

    path = float(trajectory_distances(gt)[-1])
    end_gt = inv_se3(gt[0]) @ gt[-1]
    end_est = inv_se3(est[0]) @ est[-1]
    drift = float(np.linalg.norm(end_est[:3, 3] - end_gt[:3, 3]))
    yaw_drift = float(np.degrees(wrap(heading(end_est[:3, :3], convention) - heading(end_gt[:3, :3], convention))))
    return Metrics(
        frames=len(gt), path_length=path, t_rel=t_rel, r_rel=r_rel, segments=int(seg.t_err.size),
        per_length=per_length, rpe_trans=rpe_t, rpe_yaw=np.degrees(rpe_yaw),
        ate_rmse=float(np.sqrt(np.mean(ate ** 2))), ate_max=float(ate.max()), drift_m=drift,
        drift_percent=(drift / path * 100.0) if path > 0 else None, yaw_drift_deg=yaw_drift,
        aligned_est=aligned, convention=convention)


# ----------------------------------------------------------------------------------------------
# Pitch/roll CSV
# ----------------------------------------------------------------------------------------------
PITCH_ROLL_COLUMNS = ("stamp", "pitch", "roll", "oxts_pitch", "oxts_roll")


def read_pitch_roll_csv(path: PathLike) -> dict[str, np.ndarray]:
    """CSV with a header naming ``stamp, pitch, roll, oxts_pitch, oxts_roll`` (radians; any
    column order, extra columns ignored) -> {column: (N,) float64}. ``oxts_*`` hold the bag's
    reference attitude (``/ground_truth/imu``: the OXTS unit's on KITTI, the truth on a synthetic drive)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: pitch/roll CSV not found")
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise ValueError(f"{path}: empty file") from None
        missing = [c for c in PITCH_ROLL_COLUMNS if c not in header]
        if missing:
            raise ValueError(f"{path}:1: header lacks column(s) {', '.join(missing)} (has {', '.join(header)})")
        idx = [header.index(c) for c in PITCH_ROLL_COLUMNS]
        rows = []
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            try:
                rows.append([float(row[i]) for i in idx])
            except (ValueError, IndexError):
                raise ValueError(f"{path}:{lineno}: cannot parse {','.join(row)[:80]!r}") from None
    if not rows:
        raise ValueError(f"{path}: no data rows")
    data = np.asarray(rows, dtype=np.float64)
    return {c: data[:, i] for i, c in enumerate(PITCH_ROLL_COLUMNS)}


def pitch_roll_errors(pr: dict[str, np.ndarray]) -> dict[str, float]:
    """RMSE (deg) of the filtered pitch/roll against the reference attitude (the CSV's ``oxts_*``), ignoring NaN rows."""
    out = {}
    for name in ("pitch", "roll"):
        d = np.degrees(pr[name] - pr[f"oxts_{name}"])
        d = d[np.isfinite(d)]
        if d.size:
            out[f"{name} RMSE vs reference"] = float(np.sqrt(np.mean(d ** 2)))
    return out


def motion_scores(est: np.ndarray, gt: np.ndarray, attitude: np.ndarray | None = None,
                  true_attitude: np.ndarray | None = None) -> dict[str, float]:
    """Issue 9's figures of a drive from its per-frame planar motions (the engine's ``OdometryStep.motion``).

    Args:
        est, gt: ``(F-1, 3)`` ``(dx, dy, dyaw)`` per frame pair (m, rad), estimated and true.
        attitude, true_attitude: optional ``(F, 2)`` road-relative ``(pitch, roll)`` per frame (rad).

    Returns:
        ``trans_pct`` per-frame translation RMSE in % of the mean motion, ``yaw`` per-frame yaw RMSE
        (deg), ``drift`` endpoint position error in % of the path, ``scale`` forward scale error (%),
        and with the attitudes ``pitch`` / ``roll`` RMS errors (deg).
    """
    est, gt = np.asarray(est, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    dist = np.linalg.norm(gt[:, :2], axis=1)
    err = np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)
    end_e, end_g = (integrate_motions(torch.as_tensor(m))[-1].numpy() for m in (est, gt))
    out = {"trans_pct": float(np.sqrt(np.mean(err**2)) / dist.mean() * 100),
           "yaw": float(np.degrees(np.sqrt(np.mean((est[:, 2] - gt[:, 2]) ** 2)))),
           "drift": float(np.linalg.norm(end_e[:2] - end_g[:2]) / dist.sum() * 100),
           "scale": float((est[:, 0].sum() / gt[:, 0].sum() - 1) * 100)}
    if attitude is not None and true_attitude is not None:
        rms = np.degrees(np.sqrt(np.mean((np.asarray(attitude) - np.asarray(true_attitude)) ** 2, axis=0)))
        out["pitch"], out["roll"] = float(rms[0]), float(rms[1])
    return out
