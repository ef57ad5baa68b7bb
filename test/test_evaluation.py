"""KITTI-standard evaluation against cases computed by hand."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from bevo_ros.commands import evaluate as evaluate_tool
from bevo_ros.datasets import kitti
from bevo_ros.evaluation import metrics as ev
from helpers.env import in_ci

REPO = Path(__file__).resolve().parents[1]


def se3(yaw: float = 0.0, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = t
    return T


def random_rigid(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    T = np.eye(4)
    T[:3, :3] = q * np.sign(np.linalg.det(q))
    T[:3, 3] = rng.normal(size=3) * 50
    return T


def integrate(steps: list[np.ndarray]) -> np.ndarray:
    """Compose relative motions into poses starting at the identity. -> (len(steps) + 1, 4, 4)."""
    poses = [np.eye(4)]
    for step in steps:
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def straight_line(n: int, spacing: float) -> np.ndarray:
    """``n`` poses along the base x axis, ``spacing`` metres apart (z up)."""
    return integrate([se3(0.0, (spacing, 0, 0))] * (n - 1))


def test_last_frame_is_strictly_beyond_the_length():
    dist = np.array([0.0, 50.0, 100.0, 150.0, 200.0])
    assert ev.last_frame_from_segment_length(dist, 0, 100.0) == 3  # 100 is not beyond 100
    assert ev.last_frame_from_segment_length(dist, 1, 100.0) == 4
    assert ev.last_frame_from_segment_length(dist, 2, 100.0) == -1


def test_identical_trajectories_give_zero():
    gt = ev.inv_se3(random_rigid(1)) @ integrate([se3(0.01, (1.0, 0.05, 0.0))] * 1200)
    m = ev.evaluate_trajectories(gt, gt.copy(), convention="base")
    print("\n".join(m.summary_lines()[:6]))
    # Zero up to rounding (acos near 1 turns eps ~1e-16 into ~1e-8 rad).
    assert m.t_rel < 1e-9 and m.r_rel < 1e-6 and m.segments > 0
    assert m.ate_rmse < 1e-9 and m.drift_m < 1e-9 and np.abs(m.rpe_trans).max() < 1e-9


def test_scale_by_one_percent_gives_one_percent():
    """Straight line, poses s = 0.37 m apart, estimate = GT translations x 1.01.

    Rotations are identical, so ``pose_error = [I | -0.01 dt]`` with ``dt`` the GT displacement of
    the segment, and ``t_err = 0.01 |dt| / L``. The devkit's last frame is the first one strictly
    beyond ``L``: ``k_L = floor(L / s) + 1`` steps, ``|dt| = k_L s`` (s is chosen so that no L/s is
    near an integer: no ties for rounding to decide). A start f (multiple of 10) has a segment iff
    ``f + k_L <= N - 1``: ``c_L = floor((N - 1 - k_L) / 10) + 1``. Pooled:
    ``t_rel = sum_L c_L k_L s / L / sum_L c_L`` % = 1.00 % to two decimals.
    """
    n, s = 2500, 0.37  # 924.6 m
    gt = straight_line(n, s)
    world = random_rigid(2)  # KITTI's metric does not care where the world frame is
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    m = ev.evaluate_trajectories(world @ gt, world @ est, convention="base")
    lengths = np.arange(100, 900, 100)
    k = np.floor(lengths / s) + 1
    counts = np.floor((n - 1 - k) / 10) + 1
    hand = float(np.sum(counts * k * s / lengths) / np.sum(counts))
    print(f"scale 1.01: t_rel {m.t_rel:.6f} % (hand: {hand:.6f} %), r_rel {m.r_rel:.2e} deg/100 m, "
          f"{m.segments} segments (hand {int(counts.sum())}), endpoint drift {m.drift_percent:.3f} %")
    assert round(m.t_rel, 2) == 1.00
    assert m.segments == int(counts.sum())
    assert m.t_rel == pytest.approx(hand, rel=1e-9)
    assert m.r_rel < 1e-6
    assert m.drift_percent == pytest.approx(1.0, abs=1e-6)


def test_constant_yaw_rate_bias_gives_the_derived_r_rel():
    """GT: straight line, 1 m per frame, N = 1001 frames. Estimate: the same 1 m steps but each
    step also turns by b = 1e-4 rad (a constant yaw-rate bias).

    Derivation: ``dist[i] = i``, so the devkit's last frame for a segment of length L (integer)
    is ``first + L + 1`` (the first frame *strictly* beyond L). Over ``n = L + 1`` steps the
    estimate turns by ``R_est = Rz(b n)`` while ``R_gt = I``, so
    ``pose_error = inv(delta_est) delta_gt`` has rotation ``Rz(-b n)`` and
    ``rotationError = acos((tr - 1) / 2) = b n`` (b n < pi). Hence
    ``r_err(L) = b (L + 1) / L`` rad/m. A start frame f (multiple of 10) yields a segment iff
    ``f + L + 1 <= N - 1``: ``c_L = floor((N - 2 - L) / 10) + 1`` segments. The pooled mean is
    ``r_rel = 100 * 180/pi * b * sum_L c_L (L + 1) / L / sum_L c_L`` deg/100 m
    = 0.5730 * (1 + ~0.4 %) deg/100 m for b = 1e-4.
    """
    n, b = 1001, 1e-4
    gt = straight_line(n, 1.0)
    est = integrate([se3(b, (1.0, 0, 0))] * (n - 1))
    m = ev.evaluate_trajectories(gt, est, convention="base")
    lengths = np.arange(100, 900, 100)
    counts = np.floor((n - 2 - lengths) / 10) + 1
    hand = 100 * math.degrees(b) * float(np.sum(counts * (lengths + 1) / lengths) / np.sum(counts))
    print(f"yaw bias {b} rad/frame: r_rel {m.r_rel:.6f} deg/100 m (hand {hand:.6f}), t_rel {m.t_rel:.3f} %, "
          f"segments {m.segments} (hand {int(counts.sum())}), RPE yaw {m.rpe_yaw.mean():.6f} deg/frame")
    assert m.segments == int(counts.sum())
    assert m.r_rel == pytest.approx(hand, rel=1e-9)
    assert np.allclose(m.rpe_yaw, math.degrees(b))
    assert m.yaw_drift_deg == pytest.approx(math.degrees(b * (n - 1)), rel=1e-9)


def test_short_sequence_reports_drift_not_t_rel():
    """49 m of path (< 100 m): no KITTI segment; a 2 % scale error shows as 2 % endpoint drift."""
    gt = straight_line(50, 1.0)
    est = gt.copy()
    est[:, :3, 3] *= 1.02
    m = ev.evaluate_trajectories(gt, est, convention="base")
    print("\n".join(m.summary_lines()))
    assert m.t_rel is None and m.r_rel is None and m.segments == 0
    assert m.path_length == pytest.approx(49.0)
    assert m.drift_m == pytest.approx(0.98) and m.drift_percent == pytest.approx(2.0)
    assert "n/a" in m.to_markdown()


def test_rigidly_moved_estimate_has_zero_ate_and_errors():
    gt = integrate([se3(0.02, (1.0, 0.0, 0.01))] * 300)
    est = random_rigid(3) @ gt
    m = ev.evaluate_trajectories(gt, est, convention="base")
    print(f"rigidly moved: ATE {m.ate_rmse:.2e} m, t_rel {m.t_rel:.2e} %, drift {m.drift_m:.2e} m")
    assert m.ate_rmse < 1e-8 and m.t_rel < 1e-8 and m.drift_m < 1e-8
    # A genuine error is not aligned away: shift the second half sideways by 1 m.
    est2 = gt.copy()
    est2[150:, 1, 3] += 1.0
    m2 = ev.evaluate_trajectories(gt, est2, convention="base")
    print(f"half shifted by 1 m: ATE {m2.ate_rmse:.3f} m, max RPE {m2.rpe_trans.max():.3f} m")
    assert 0.3 < m2.ate_rmse < 0.6 and m2.rpe_trans.max() == pytest.approx(1.0, abs=1e-9)


def test_camera_convention_heading():
    """A left turn: in the camera frame (y down) it is a rotation about -y."""
    yaw = 0.1
    R_cam = np.array([[math.cos(yaw), 0, -math.sin(yaw)], [0, 1, 0], [math.sin(yaw), 0, math.cos(yaw)]])
    # Rotation about y by -yaw (left turn, camera z forward, x right).
    assert ev.heading(R_cam, "camera") == pytest.approx(yaw)
    assert ev.heading(se3(yaw)[:3, :3], "base") == pytest.approx(yaw)


def test_cli_writes_report_and_rejects_bad_input(tmp_path, capsys):
    gt = straight_line(120, 1.0)
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    kitti.write_poses(tmp_path / "gt.txt", gt)
    kitti.write_poses(tmp_path / "est.txt", est[:60])
    t = np.arange(60) * 0.1
    pr = np.stack([t, 0.01 + 0.001 * np.sin(t), 0.02 * np.ones(60), 0.01 * np.ones(60), 0.02 * np.ones(60)], axis=1)
    csv_path = tmp_path / "pr.csv"
    csv_path.write_text("stamp,pitch,roll,oxts_pitch,oxts_roll\n" + "\n".join(",".join(map(str, r)) for r in pr) + "\n")
    out = tmp_path / "eval"
    rc = evaluate_tool.main(["--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt"),
                             "--out", str(out), "--pitch-roll", str(csv_path), "--convention", "base"])
    text = capsys.readouterr().out
    print(text)
    assert rc == 0
    assert {p.name for p in out.iterdir()} == {"summary.md", "metrics.json", "trajectory.png", "frame_errors.png",
                                               "pitch_roll.png"}
    assert "endpoint drift: 0.590 m (1.00 % of the path)" in text
    rmse = math.degrees(0.001 * math.sqrt(np.mean(np.sin(t) ** 2)))
    assert f"pitch RMSE vs reference: {rmse:.3f} deg" in text
    assert (out / "trajectory.png").read_bytes()[:4] == b"\x89PNG"

    bad = tmp_path / "bad.txt"
    bad.write_text((tmp_path / "est.txt").read_text().replace("e+00", "e+0x", 1))
    rc = evaluate_tool.main(["--gt", str(tmp_path / "gt.txt"), "--est", str(bad), "--out", str(out)])
    err = capsys.readouterr().err
    print(err)
    assert rc == 2 and "bad.txt:1:" in err
    rc = evaluate_tool.main(["--gt", str(tmp_path / "est.txt"), "--est", str(tmp_path / "gt.txt"), "--out", str(out)])
    assert rc == 2 and "need 120 GT poses" in capsys.readouterr().err
    # a pitch/roll CSV with another row count than the estimate's poses (another run's?) is said, and scored
    # on its own rows (a CSV at another rate is legitimate)
    other = tmp_path / "other.csv"
    other.write_text("\n".join(csv_path.read_text().splitlines()[:41]) + "\n")  # header + 40 rows
    with pytest.warns(UserWarning, match="other.csv: 40 rows, but .*est.txt has 60 poses: not the same run's"):
        rc = evaluate_tool.main(["--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt"), "--out",
                                 str(out), "--pitch-roll", str(other)])
    assert rc == 0


@pytest.mark.kitti
def test_kitti_sequence_06_against_itself_scaled(kitti_root):
    """On a real (looping) sequence the scale error only shows up over chords: t_rel < 1 %."""
    gt = kitti.read_poses(kitti_root / "odometry" / "poses" / "06.txt")
    est = gt.copy()
    est[:, :3, 3] *= 1.01
    m = ev.evaluate_trajectories(gt, est)
    same = ev.evaluate_trajectories(gt, gt)
    print(f"seq 06 ({m.path_length:.0f} m): scale 1.01 -> t_rel {m.t_rel:.3f} %, r_rel {m.r_rel:.2e}; "
          f"identical -> t_rel {same.t_rel:.2e} %, r_rel {same.r_rel:.2e} deg/100 m")
    assert 0.3 < m.t_rel <= 1.0001 and m.r_rel < 1e-6
    assert same.t_rel < 1e-9 and same.r_rel < 1e-6


def test_rpe_and_ate_equal_evo_on_a_hand_computed_case():
    """Our per-frame RPE and SE(3)-aligned ATE against evo (the field's reference implementation)
    and against values worked out by hand. Ground truth: 1 m steps along x. Estimate steps: 1.1 m;
    1 m with a 0.1 rad yaw error; 1 m with 0.2 m sideways; 1 m. Per step (base convention):
    translation errors 0.1, 0, 0.2, 0 m (the yawed step is correct in its own frame), yaw errors
    0, 0.1 rad, 0, 0. ATE case: a unit square of positions and the same square scaled by 1.1 -> the
    rigid alignment keeps the orientation and matches the centres, each corner then misses by
    0.1 x sqrt(0.5) m: RMSE 0.1 sqrt(0.5)."""
    if not in_ci():
        pytest.importorskip("evo", reason="evo (requirements.txt) not installed: make setup")
    from evo.core import metrics as evo_metrics
    from evo.core.trajectory import PosePath3D

    gt = np.stack([se3(t=(float(i), 0.0, 0.0)) for i in range(5)])
    steps = [se3(t=(1.1, 0, 0)), se3(0.1, (1.0, 0, 0)), se3(t=(1.0, 0.2, 0)), se3(t=(1.0, 0, 0))]
    est = [np.eye(4)]
    for d in steps:
        est.append(est[-1] @ d)
    est = np.stack(est)

    rpe_t, rpe_yaw = ev.relative_pose_errors(gt, est, convention="base")
    np.testing.assert_allclose(rpe_t, [0.1, 0.0, 0.2, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.abs(rpe_yaw), [0.0, 0.1, 0.0, 0.0], atol=1e-12)

    def evo_rpe(relation):
        rpe = evo_metrics.RPE(relation, delta=1, delta_unit=evo_metrics.Unit.frames, all_pairs=False)
        rpe.process_data((PosePath3D(poses_se3=list(gt)), PosePath3D(poses_se3=list(est))))
        return np.asarray(rpe.error)

    np.testing.assert_allclose(evo_rpe(evo_metrics.PoseRelation.translation_part), rpe_t, atol=1e-12)
    np.testing.assert_allclose(evo_rpe(evo_metrics.PoseRelation.rotation_angle_rad), np.abs(rpe_yaw), atol=1e-12)

    corners = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1.0, 0.0), (0.0, 1.0, 0.0)]
    square = np.stack([se3(t=c) for c in corners])
    scaled = np.stack([se3(t=tuple(1.1 * v for v in c)) for c in corners])
    ours = ev.evaluate_trajectories(square, scaled, convention="base")
    ref, moved = PosePath3D(poses_se3=list(square)), PosePath3D(poses_se3=list(scaled))
    moved.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, moved))
    evo_ate = ape.get_statistic(evo_metrics.StatisticsType.rmse)
    print(f"\nATE RMSE: ours {ours.ate_rmse:.12f} m, evo {evo_ate:.12f} m, by hand {0.1 * math.sqrt(0.5):.12f} m; "
          f"RPE RMSE ours {ours.rpe_trans_rmse:.6f} m")
    assert ours.ate_rmse == pytest.approx(0.1 * math.sqrt(0.5), abs=1e-12)
    assert evo_ate == pytest.approx(ours.ate_rmse, abs=1e-12)
    np.testing.assert_allclose(ours.aligned_est[:, :3, 3], np.asarray(moved.positions_xyz), atol=1e-12)


def test_demo_rows_read_the_pitch_roll_errors_evaluate_writes(tmp_path):
    """make demo's table takes the attitude errors from metrics.json under the names evaluate gives them."""
    import json

    from bevo_ros.commands.demo import metrics_row
    from bevo_ros.evaluation.metrics import pitch_roll_errors

    t = np.linspace(0.0, 1.0, 11)
    pr = {"stamp": t, "pitch": 0.01 + 0 * t, "roll": -0.02 + 0 * t, "oxts_pitch": 0 * t, "oxts_roll": 0 * t}
    metrics = {"frames": 11, "path_length": 10.0, "rpe_trans_rmse": 0.04, "rpe_yaw_rmse": 0.05, "drift_percent": 1.0,
               "ate_rmse": 0.1, "t_rel": None, "r_rel": None, "pitch_roll": pitch_roll_errors(pr)}
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    row = metrics_row("x", tmp_path)
    assert row.endswith(f"| {math.degrees(0.01):.2f} / {math.degrees(0.02):.2f} |"), row
