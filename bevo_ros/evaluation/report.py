"""Evaluation output: ``summary.md``, ``metrics.json`` and the PNG plots of a :class:`Metrics`
(trajectories from the top, per-frame errors, pitch/roll against the reference), all written atomically."""
from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np

from bevo_ros.evaluation.metrics import Metrics, PathLike
from bevo_ros.io.files import atomic_write_bytes, atomic_write_text


# ----------------------------------------------------------------------------------------------
def _save_figure(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())


def _top_view(poses: np.ndarray, convention: str) -> tuple[np.ndarray, np.ndarray, str, str]:
    """Horizontal-plane coordinates for a top view (x right, up = forward at the start)."""
    p = poses[:, :3, 3]
    if convention == "camera":
        return p[:, 0], p[:, 2], "x (m)", "z (m)"
    return -p[:, 1], p[:, 0], "-y (m)", "x (m)"


def plot_trajectories(path: PathLike, gt: np.ndarray, est: np.ndarray, metrics: Metrics, title: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 6))
    gx, gy, xl, yl = _top_view(gt, metrics.convention)
    ex, ey, _, _ = _top_view(est, metrics.convention)
    ax.plot(gx, gy, "k-", lw=1.5, label="ground truth")
    ax.plot(ex, ey, "r-", lw=1.2, label="estimate")
    ax.plot(gx[:1], gy[:1], "go", label="start")
    ax.set_xlabel(xl)
    ax.set_ylabel(yl)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend()
    ax.set_title(title or "Top view")
    _save_figure(fig, Path(path))
    plt.close(fig)


def plot_frame_errors(path: PathLike, metrics: Metrics) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    frames = np.arange(1, metrics.frames)
    a1.plot(frames, metrics.rpe_trans, "b-")
    a1.set_ylabel("RPE translation (m)")
    a2.plot(frames, metrics.rpe_yaw, "m-")
    a2.set_ylabel("RPE yaw (deg)")
    a2.set_xlabel("frame")
    for a in (a1, a2):
        a.grid(True, alpha=0.3)
    a1.set_title("Per-frame relative pose error")
    _save_figure(fig, Path(path))
    plt.close(fig)


def plot_pitch_roll(path: PathLike, pr: dict[str, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = pr["stamp"] - pr["stamp"][0]
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    for ax, name in zip(axes, ("pitch", "roll")):
        ax.plot(t, np.degrees(pr[f"oxts_{name}"]), "k-", lw=1.2, label=f"reference {name}")
        ax.plot(t, np.degrees(pr[name]), "r-", lw=1.0, label=f"filtered {name}")
        ax.set_ylabel(f"{name} (deg)")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best")
    axes[-1].set_xlabel("time (s)")
    axes[0].set_title("Filtered attitude vs the reference (OXTS, or a synthetic drive's truth)")
    _save_figure(fig, Path(path))
    plt.close(fig)


def write_report(out_dir: PathLike, gt: np.ndarray, est: np.ndarray, metrics: Metrics,
                 pitch_roll: dict[str, np.ndarray] | None = None, title: str = "Trajectory evaluation") -> list[Path]:
    """Write ``summary.md``, ``metrics.json`` and the PNG plots into ``out_dir``; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "summary.md", out / "metrics.json", out / "trajectory.png", out / "frame_errors.png"]
    atomic_write_text(paths[0], metrics.to_markdown(title))
    atomic_write_text(paths[1], json.dumps(metrics.to_dict(), indent=2, default=_json_default) + "\n")
    plot_trajectories(paths[2], gt, est, metrics, title)
    plot_frame_errors(paths[3], metrics)
    if pitch_roll is not None:
        paths.append(out / "pitch_roll.png")
        plot_pitch_roll(paths[-1], pitch_roll)
    else:  # an earlier report's plot in the same folder would read as this run's
        (out / "pitch_roll.png").unlink(missing_ok=True)
    return paths


def _json_default(obj):
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, float) and math.isnan(obj):
        return None
    raise TypeError(f"not JSON serialisable: {type(obj)}")
